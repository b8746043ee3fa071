//! Clipping closed loops and open polylines to the area of [`Shapes`] (through i_overlay),
//! with the pieces of a cut loop stitched back where the clipper split them at its seam:
//! a loop cut by a neighbouring contour becomes the non-continuous segments of the
//! paper's Fig. 4(a). [`ClipArea`] indexes the area's boundary so loops clear of it are
//! taken whole or dropped without the clipper. Not booleans between areas (`booleans.rs`).

use super::i_overlay_integration::clip_lines;
use super::{boundary_index, contains, loop_length, polyline_length, Path, SegmentIndex, Shapes};
use glam::DVec2;

/// The parts of closed loop `l` strictly inside `by` (or on its boundary when
/// `boundary_included`): the whole loop as one closed path when nothing cuts it, else
/// the open pieces, with the piece through the loop's start vertex joined up.
pub fn clip_loop(l: &[DVec2], by: &Shapes, boundary_included: bool, eps_mm: f64) -> Vec<Path> {
    clip_ring(l, by, false, boundary_included, eps_mm)
}

/// [`clip_loop`] by any clip rule (`invert` keeps the parts outside `by`; see
/// [`clip_lines`] for `boundary_included`).
fn clip_ring(
    l: &[DVec2],
    by: &Shapes,
    invert: bool,
    boundary_included: bool,
    eps_mm: f64,
) -> Vec<Path> {
    if l.len() < 2 || (by.is_empty() && !invert) {
        return Vec::new();
    }
    if by.is_empty() {
        return vec![Path {
            points: l.to_vec(),
            closed: true,
        }];
    }
    let mut ring = l.to_vec();
    ring.push(l[0]);
    let pieces: Vec<Vec<DVec2>> = clip_lines(ring, by, invert, boundary_included);
    stitch_loop_pieces(pieces, loop_length(l), eps_mm)
}

/// An area many loops are clipped to (the inside of some shapes, or their outside),
/// with its boundary indexed: a loop that keeps clear of the boundary lies wholly in
/// or wholly out of the area, and is kept whole or dropped without running the clipper
/// (which would return such a loop whole).
pub struct ClipArea<'a> {
    shapes: &'a Shapes,
    /// The area is the outside of `shapes`.
    outside: bool,
    boundary: SegmentIndex,
    clear_mm: f64,
}

impl<'a> ClipArea<'a> {
    /// The inside of `shapes`. `clear_mm`: how far a loop must stay from the boundary
    /// to be taken whole.
    pub fn inside(shapes: &'a Shapes, clear_mm: f64) -> Self {
        Self::new(shapes, false, clear_mm)
    }

    /// The outside of `shapes`.
    pub fn outside(shapes: &'a Shapes, clear_mm: f64) -> Self {
        Self::new(shapes, true, clear_mm)
    }

    fn new(shapes: &'a Shapes, outside: bool, clear_mm: f64) -> Self {
        ClipArea {
            shapes,
            outside,
            boundary: boundary_index(shapes),
            clear_mm,
        }
    }

    /// The shapes whose inside (or outside) the area is.
    pub fn shapes(&self) -> &Shapes {
        self.shapes
    }

    /// [`clip_loop`] against this area.
    pub fn clip_loop(&self, l: &[DVec2], boundary_included: bool, eps_mm: f64) -> Vec<Path> {
        // With `invert`, i_overlay's `boundary_included` means the opposite: lines on
        // the boundary count as outside the shapes, so as inside the area, when false.
        let (invert, boundary_included) = (self.outside, boundary_included != self.outside);
        let n = l.len();
        let clear = n >= 3 && self.boundary.clear_of_loop(l, self.clear_mm);
        if !clear {
            return clip_ring(l, self.shapes, invert, boundary_included, eps_mm);
        }
        if contains(self.shapes, l[0]) != self.outside {
            vec![Path {
                points: l.to_vec(),
                closed: true,
            }]
        } else {
            Vec::new()
        }
    }
}

/// The parts of open polyline `line` inside `by`.
pub fn clip_polyline(line: &[DVec2], by: &Shapes, boundary_included: bool) -> Vec<Path> {
    if line.len() < 2 || by.is_empty() {
        return Vec::new();
    }
    let pieces: Vec<Vec<DVec2>> = clip_lines(line.to_vec(), by, false, boundary_included);
    pieces
        .into_iter()
        .filter(|p| p.len() >= 2)
        .map(|points| Path {
            points,
            closed: false,
        })
        .collect()
}

/// Join clipped pieces of one loop back together where they meet end to start, and
/// recognise the unclipped loop.
fn stitch_loop_pieces(mut pieces: Vec<Vec<DVec2>>, loop_len: f64, eps: f64) -> Vec<Path> {
    pieces.retain(|p| p.len() >= 2);
    // Join pieces whose end meets another's start (the clipper may split at the seam).
    let mut joined = true;
    while joined && pieces.len() > 1 {
        joined = false;
        'outer: for i in 0..pieces.len() {
            for j in 0..pieces.len() {
                if i == j {
                    continue;
                }
                let (ei, sj) = (pieces[i][pieces[i].len() - 1], pieces[j][0]);
                if ei.distance(sj) <= eps {
                    let tail = pieces.remove(j);
                    let i = if j < i { i - 1 } else { i };
                    pieces[i].extend_from_slice(&tail[1..]);
                    joined = true;
                    break 'outer;
                }
            }
        }
    }
    pieces
        .into_iter()
        .map(|mut points| {
            let n = points.len();
            let closes = n > 3 && points[0].distance(points[n - 1]) <= eps;
            let len = polyline_length(&points);
            if closes && (len - loop_len).abs() <= (loop_len * 1e-6).max(eps * 10.0) {
                points.pop();
                Path {
                    points,
                    closed: true,
                }
            } else {
                Path {
                    points,
                    closed: false,
                }
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{difference, from_loops};

    fn square(h: f64) -> Vec<DVec2> {
        vec![
            DVec2::new(-h, -h),
            DVec2::new(h, -h),
            DVec2::new(h, h),
            DVec2::new(-h, h),
        ]
    }

    #[test]
    fn clipping_a_loop_keeps_it_closed_or_cuts_it() {
        let by = from_loops(&[square(5.0)]);
        let inside = clip_loop(&square(2.0), &by, false, 1e-6);
        assert_eq!(inside.len(), 1);
        assert!(inside[0].closed);
        assert!((inside[0].length_mm() - 16.0).abs() < 1e-6);
        // A loop straddling the right edge keeps its left part as one open piece.
        let shifted: Vec<DVec2> = square(2.0)
            .iter()
            .map(|p| *p + DVec2::new(4.0, 0.0))
            .collect();
        let cut = clip_loop(&shifted, &by, false, 1e-6);
        assert_eq!(cut.len(), 1, "{cut:?}");
        assert!(!cut[0].closed);
        assert!(
            (cut[0].length_mm() - 10.0).abs() < 1e-6,
            "{}",
            cut[0].length_mm()
        );
    }

    #[test]
    fn clip_area_takes_clear_loops_whole_like_the_clipper() {
        let ring = difference(&from_loops(&[square(5.0)]), &from_loops(&[square(1.0)]));
        let area = ClipArea::inside(&ring, 1e-3);
        let shift = |l: Vec<DVec2>, d: DVec2| -> Vec<DVec2> { l.iter().map(|p| *p + d).collect() };
        let probes = [
            square(3.0),                              // inside, around the hole
            shift(square(0.5), DVec2::new(3.0, 3.0)), // inside, away from the hole
            square(0.5),                              // in the hole
            shift(square(0.5), DVec2::new(9.0, 0.0)), // outside
            shift(square(2.0), DVec2::new(4.0, 0.0)), // cut by the outer edge
            square(1.0),                              // on the hole's edge
        ];
        for l in &probes {
            assert_eq!(
                area.clip_loop(l, false, 1e-6),
                clip_loop(l, &ring, false, 1e-6),
                "{l:?}"
            );
        }
        // Inside the outer square, the ring is the outside of the hole.
        let hole = from_loops(&[square(1.0)]);
        let outside_hole = ClipArea::outside(&hole, 1e-3);
        for l in probes
            .iter()
            .filter(|l| l.iter().all(|p| p.abs().max_element() < 5.0))
        {
            let (got, want) = (
                outside_hole.clip_loop(l, false, 1e-6),
                clip_loop(l, &ring, false, 1e-6),
            );
            assert_eq!(got.len(), want.len(), "{l:?}");
            for (g, w) in got.iter().zip(&want) {
                assert_eq!(g.closed, w.closed);
                assert!((g.length_mm() - w.length_mm()).abs() < 1e-6, "{l:?}");
            }
        }
    }
}
