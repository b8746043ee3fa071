//! Planar geometry shared by every planning stage: closed loops and open polylines,
//! layer regions (an outer loop plus holes, the paper's Ce and Ci) and the checks that a
//! region supplied by a user or a slicer is sound before the EDO method touches it, a
//! spatial index over segments, and polygons with holes with their algebra (equal
//! distance offsets, booleans, clipping).
//!
//! Conventions: millimetres, `f64`; a loop is closed implicitly (last vertex joins the
//! first, never repeated); a [`Region`]'s outer loop is counter-clockwise and its holes
//! clockwise once normalised with [`Region::normalised`].
//!
//! One concern per file; every public item is re-exported here, as `crate::geom::X`:
//!
//! - `tolerances.rs`: [`Tolerances`], the shared geometric tolerances.
//! - `edges.rs`: the edges of open and closed paths ([`edges`]), which vertex follows
//!   which.
//! - `loops.rs`: measures of one loop or polyline: bounds, signed area (orientation),
//!   length, centroid, point in loop.
//! - `distance.rs`: exact point, segment and loop distances.
//! - `crossings.rs`: segment intersection, and the sweep finding crossing edges of loops.
//! - `simplify.rs`: dropping vertices: duplicates, Douglas–Peucker, greedy chords, spikes.
//! - `region.rs`: [`Region`] and its validation ([`RegionError`]).
//! - `segment_index.rs`: [`SegmentIndex`], a grid over segments for distance queries.
//! - `path.rs`: [`Path`], a road centreline, open or closed.
//! - `shapes.rs`: [`Shapes`], polygons with holes, and what needs no overlay on them.
//! - `booleans.rs`: difference, intersection and union of shapes.
//! - `clip.rs`: loops and polylines clipped to shapes ([`ClipArea`]).
//! - `offset/`: the equal distance offset engine (direct offset with a certificate, the
//!   outline as fallback): `raw.rs`, `swallowtail.rs`, `spike.rs`.
//! - `clearance.rs`: [`keep_clear_of`], roads trimmed to a clearance from a contour.
//! - `i_overlay_integration.rs`: the adapter to i_overlay, the only file in the crate that
//!   calls it (the slicer's even-odd union goes through it too).

mod booleans;
mod clearance;
mod clip;
mod crossings;
mod distance;
mod edges;
pub(crate) mod i_overlay_integration;
mod loops;
mod offset;
mod path;
mod region;
mod segment_index;
mod shapes;
mod simplify;
mod tolerances;

pub use booleans::{difference, intersection, nested_difference, union};
pub use clearance::keep_clear_of;
pub use clip::{clip_loop, clip_polyline, ClipArea};
pub use crossings::{
    crossing_point, crossings, first_crossing, segment_intersection_point, segments_intersect,
    sweep_rank, Crossing,
};
pub use distance::{
    point_loop_distance, point_segment_distance, point_segment_distance2, segment_segment_distance,
    sqrt_within,
};
pub use edges::{
    edge_count, edge_ends, edges, loop_edge, loop_edges, neighbours, next_in_loop, prev_in_loop,
};
pub use loops::{
    centroid, loop_bounds, loop_length, point_in_loop, polyline_length, signed_area, signed_area2,
};
pub use offset::{offset, offset_indexed};
pub use path::Path;
pub use region::{bounds_of, Region, RegionError};
pub use segment_index::{NearSegments, SegmentIndex};
pub use shapes::{area, boundary_index, circle, clip_to_box, contains, from_loops, loops, Shapes};
pub use simplify::{dedup_loop, remove_spikes, simplify_loop, simplify_loop_greedy};
pub use tolerances::Tolerances;
