//! Where a part sits in the machine: the machine frame, the build volume, and the
//! placement of a job's part in it.
//!
//! The **machine frame** has its origin where the machine homes (a `Home` move takes
//! the nozzle to (0, 0, 0)), X and Y across the bed and Z up from the bed's surface.
//! The **build volume** is the box from that origin to `build_volume_mm` (edod.toml
//! `[machine]`). Planning works in the part's own coordinates (the job's polygon, or
//! the mesh file's); a [`Placement`] is the translation, in whole micrometres, from
//! those to the machine frame, chosen by the job's `geometry.placement`
//! ([`PlacementMode`]):
//!
//! - `centre` (the default): the part's XY bounding box centred on the bed and its
//!   lowest point on the bed, as a slicer places an object it loads;
//! - `{ at = [x, y] }`: the bounding box's XY centre at (x, y) of the bed, the lowest
//!   point on the bed;
//! - `keep`: the part's coordinates are the machine's (the part was placed in CAD).
//!
//! [`place`] refuses a part that does not fit, naming the axis and by how much, and
//! [`BuildVolume::check`] refuses any move whose target lies outside the volume, as
//! Klipper refuses a move beyond an axis's limits: on a real machine such a move runs
//! the nozzle into the bed or an axis into its end stop.
//!
//! Whole micrometres, so a placed move's position is exactly its unplaced position
//! (already rounded to µm) plus the offset: placing changes no planned geometry.

use super::Job;
use crate::machine::{Move, MoveKind, PositionUm};
use crate::pipeline::ProcessSettings;
use glam::DVec3;
use serde::Serialize;

/// How a job's part is put on the bed (`geometry.placement`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum PlacementMode {
    /// XY bounding box centred on the bed, lowest point on the bed.
    #[default]
    Centre,
    /// XY bounding box centred at this point of the bed (mm), lowest point on the bed.
    At([f64; 2]),
    /// The part's coordinates are machine coordinates.
    Keep,
}

/// The machine's build volume: from the origin to `size_mm` on each axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildVolume {
    size_mm: [f64; 3],
}

/// The largest build volume side, mm (positions are `i32` micrometres).
pub const MAX_BUILD_SIDE_MM: f64 = 2000.0;

/// How far (µm) a move may lie beyond the volume's faces: the rounding of a road's
/// vertices to whole micrometres.
const MOVE_SLACK_UM: i64 = 1;

const AXES: [char; 3] = ['x', 'y', 'z'];

impl BuildVolume {
    /// A build volume of `size_mm` (X, Y, Z); each side positive, finite and at most
    /// [`MAX_BUILD_SIDE_MM`].
    pub fn new(size_mm: [f64; 3]) -> Result<BuildVolume, String> {
        for (axis, v) in AXES.iter().zip(size_mm) {
            if !(v.is_finite() && v > 0.0 && v <= MAX_BUILD_SIDE_MM) {
                return Err(format!(
                    "{axis} side {v} mm: each side must be positive and at most {MAX_BUILD_SIDE_MM} mm"
                ));
            }
        }
        Ok(BuildVolume { size_mm })
    }

    /// X, Y and Z sides, mm.
    pub fn size_mm(&self) -> [f64; 3] {
        self.size_mm
    }

    /// Whether `p` (mm, machine frame) lies inside the volume.
    pub fn contains_mm(&self, p: [f64; 3]) -> bool {
        p.iter()
            .zip(self.size_mm)
            .all(|(&v, side)| (0.0..=side).contains(&v))
    }

    /// Refuse a move whose target lies outside the volume (the move index, its kind, its
    /// target and the axis in the message).
    pub fn check(&self, m: &Move) -> Result<(), String> {
        let (kind, to) = match &m.kind {
            MoveKind::Travel { to, .. } => ("travel", to),
            MoveKind::Extrude { to, .. } => ("extrusion", to),
            _ => return Ok(()),
        };
        let at = [to.x_um, to.y_um, to.z_um];
        for ((axis, v), side) in AXES.iter().zip(at).zip(self.size_mm) {
            let side_um = (side * 1000.0).round() as i64;
            let v = i64::from(v);
            if v < -MOVE_SLACK_UM || v > side_um + MOVE_SLACK_UM {
                return Err(format!(
                    "move {} ({kind} to {:.3}, {:.3}, {:.3} mm) leaves the build volume: {axis} = {:.3} mm is outside 0 to {side} mm",
                    m.index,
                    f64::from(to.x_um) / 1000.0,
                    f64::from(to.y_um) / 1000.0,
                    f64::from(to.z_um) / 1000.0,
                    v as f64 / 1000.0,
                ));
            }
        }
        Ok(())
    }
}

/// The translation from the part's coordinates to the machine frame, whole µm.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize)]
pub struct Placement {
    /// X, Y, Z offset, µm.
    pub offset_um: [i32; 3],
}

impl Placement {
    /// The offset, mm.
    pub fn offset_mm(&self) -> [f64; 3] {
        self.offset_um.map(|v| f64::from(v) / 1000.0)
    }

    /// A point of the machine's bed (mm) in the part's coordinates.
    pub fn bed_to_part_xy(&self, xy_mm: [f64; 2]) -> [f64; 2] {
        let o = self.offset_mm();
        [xy_mm[0] - o[0], xy_mm[1] - o[1]]
    }

    /// Move `m`'s target, or a layer mark's height, into the machine frame (saturating:
    /// a target that would not fit in `i32` µm is left at the limit, where
    /// [`BuildVolume::check`] refuses it).
    pub fn apply(&self, m: &mut Move) {
        let [dx, dy, dz] = self.offset_um;
        match &mut m.kind {
            MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => {
                *to = PositionUm {
                    x_um: to.x_um.saturating_add(dx),
                    y_um: to.y_um.saturating_add(dy),
                    z_um: to.z_um.saturating_add(dz),
                };
            }
            MoveKind::LayerMark { z_um, .. } => *z_um = z_um.saturating_add(dz),
            _ => {}
        }
    }

    /// Put `moves` on the machine: each one placed ([`Placement::apply`]), then checked
    /// to lie inside `volume` ([`BuildVolume::check`]); the first outside is the error.
    pub fn put_on_machine(&self, moves: &mut [Move], volume: &BuildVolume) -> Result<(), String> {
        for m in moves {
            self.apply(m);
            volume.check(m)?;
        }
        Ok(())
    }
}

/// Put a part whose bounding box (its own coordinates, mm) is `min`..`max` into
/// `volume` as `mode` says; an error (naming the axis, the part's extent and the
/// volume's) when it does not fit.
pub fn place(
    mode: PlacementMode,
    min: DVec3,
    max: DVec3,
    volume: &BuildVolume,
) -> Result<Placement, String> {
    let (lo, hi) = (min.to_array(), max.to_array());
    if lo.iter().chain(&hi).any(|v| !v.is_finite()) || lo.iter().zip(&hi).any(|(a, b)| a > b) {
        return Err(format!(
            "the part's bounds {lo:?} to {hi:?} mm are not a box"
        ));
    }
    let size = volume.size_mm();
    let offset_mm: [f64; 3] = match mode {
        PlacementMode::Keep => [0.0; 3],
        PlacementMode::Centre | PlacementMode::At(_) => {
            let [cx, cy] = match mode {
                PlacementMode::At(at) => at,
                _ => [size[0] / 2.0, size[1] / 2.0],
            };
            if !(cx.is_finite() && cy.is_finite()) {
                return Err(format!(
                    "geometry.placement.at = [{cx}, {cy}]: not a point of the bed"
                ));
            }
            [
                cx - 0.5 * (lo[0] + hi[0]),
                cy - 0.5 * (lo[1] + hi[1]),
                -lo[2],
            ]
        }
    };
    let offset_um = offset_mm.map(|v| (v * 1000.0).round().clamp(-2e9, 2e9) as i32);
    let placement = Placement { offset_um };
    let o = placement.offset_mm();
    // A part larger than the volume: say by how much, whatever the placement.
    for k in 0..3 {
        let extent = hi[k] - lo[k];
        if extent > size[k] + 1e-3 {
            return Err(format!(
                "the part is {:.1} × {:.1} × {:.1} mm (x × y × z), larger than the build volume {} × {} × {} mm: {:.1} mm too {} along {}",
                hi[0] - lo[0],
                hi[1] - lo[1],
                hi[2] - lo[2],
                size[0],
                size[1],
                size[2],
                extent - size[k],
                ["wide", "deep", "tall"][k],
                AXES[k]
            ));
        }
    }
    for k in 0..3 {
        let (a, b) = (lo[k] + o[k], hi[k] + o[k]);
        if a < -1e-3 || b > size[k] + 1e-3 {
            let how = match mode {
                PlacementMode::Keep => "geometry.placement = \"keep\"".to_string(),
                PlacementMode::At([x, y]) => format!("geometry.placement.at = [{x}, {y}]"),
                PlacementMode::Centre => "geometry.placement = \"centre\"".to_string(),
            };
            return Err(format!(
                "{how}: the part spans {} = {a:.3} to {b:.3} mm on the machine, outside the build volume's 0 to {} mm",
                AXES[k], size[k]
            ));
        }
    }
    Ok(placement)
}

/// Where a job's part (bounding box `bounds`, in its own coordinates) goes on this
/// machine: `geometry.placement` in its build volume ([`place`]). The job's purge pad
/// (`toolpath.purge_xy_mm`, a point of the bed, and `purge_pad_mm` from there along +x
/// and +y) must lie on the bed too.
/// An error names what does not fit and by how much.
pub fn place_part(
    job: &Job,
    bounds: (DVec3, DVec3),
    volume: &BuildVolume,
) -> Result<Placement, String> {
    let placement = place(job.placement, bounds.0, bounds.1, volume)?;
    if let Some([x, y]) = job.toolpath.purge_xy_mm {
        let side = job.toolpath.purge_pad_mm;
        if !(volume.contains_mm([x, y, 0.0]) && volume.contains_mm([x + side, y + side, 0.0])) {
            let [sx, sy, _] = volume.size_mm();
            return Err(format!(
                "toolpath.purge_xy_mm = [{x}, {y}]: the {side} mm purge pad from there is not on the bed (0 to {sx} × 0 to {sy} mm)"
            ));
        }
    }
    Ok(placement)
}

/// The process settings of a job placed by `placement`: the purge position, a point
/// of the bed, in the part's coordinates the planner works in (the moves are placed
/// afterwards, which puts the purge pad back where the job asked).
pub fn placed_settings(settings: &ProcessSettings, placement: &Placement) -> ProcessSettings {
    let mut s = settings.clone();
    s.purge_xy_mm = settings.purge_xy_mm.map(|xy| placement.bed_to_part_xy(xy));
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volume() -> BuildVolume {
        BuildVolume::new([200.0, 200.0, 150.0]).unwrap()
    }

    #[test]
    fn centre_puts_the_part_mid_bed_and_on_it() {
        // The paper's annulus: x, y from -30 to 30, z from 0 to 0.4.
        let p = place(
            PlacementMode::Centre,
            DVec3::new(-30.0, -30.0, 0.0),
            DVec3::new(30.0, 30.0, 0.4),
            &volume(),
        )
        .unwrap();
        assert_eq!(p.offset_um, [100_000, 100_000, 0]);
        // A mesh below the bed is lifted onto it, off-centre in XY is centred.
        let p = place(
            PlacementMode::Centre,
            DVec3::new(10.0, -5.0, -77.25),
            DVec3::new(50.0, 15.0, 12.75),
            &volume(),
        )
        .unwrap();
        assert_eq!(p.offset_um, [70_000, 95_000, 77_250]);
        let p = place(
            PlacementMode::At([40.0, 160.0]),
            DVec3::new(10.0, -5.0, 3.0),
            DVec3::new(50.0, 15.0, 12.0),
            &volume(),
        )
        .unwrap();
        assert_eq!(p.offset_um, [10_000, 155_000, -3_000]);
    }

    #[test]
    fn parts_that_do_not_fit_are_refused_naming_the_axis() {
        // The femur: 466 mm tall in a 150 mm volume.
        let e = place(
            PlacementMode::Centre,
            DVec3::new(-25.0, -30.0, 0.0),
            DVec3::new(25.0, 30.0, 466.0),
            &volume(),
        )
        .unwrap_err();
        assert!(e.contains("316.0 mm too tall along z"), "{e}");
        // Kept where the mesh is: below the bed.
        let e = place(
            PlacementMode::Keep,
            DVec3::new(20.0, 20.0, -77.0),
            DVec3::new(60.0, 60.0, 12.0),
            &volume(),
        )
        .unwrap_err();
        assert!(e.contains("\"keep\"") && e.contains("z = -77.000"), "{e}");
        // Centred at a point too near the bed's edge.
        let e = place(
            PlacementMode::At([190.0, 100.0]),
            DVec3::new(-30.0, -30.0, 0.0),
            DVec3::new(30.0, 30.0, 1.0),
            &volume(),
        )
        .unwrap_err();
        assert!(e.contains("x = 160.000 to 220.000"), "{e}");
        assert!(place(
            PlacementMode::At([f64::NAN, 1.0]),
            DVec3::ZERO,
            DVec3::ONE,
            &volume()
        )
        .is_err());
        assert!(place(
            PlacementMode::Centre,
            DVec3::ZERO,
            DVec3::new(1.0, f64::INFINITY, 1.0),
            &volume()
        )
        .is_err());
    }

    #[test]
    fn moves_are_translated_exactly_and_checked_against_the_volume() {
        let p = Placement {
            offset_um: [100_000, 100_000, 0],
        };
        let mut m = Move {
            job_id: 1,
            index: 7,
            kind: MoveKind::Travel {
                to: PositionUm {
                    x_um: -30_000,
                    y_um: 1_234,
                    z_um: 400,
                },
                feed_um_s: 50_000,
            },
        };
        assert!(volume().check(&m).is_err());
        p.apply(&mut m);
        let MoveKind::Travel { to, .. } = m.kind else {
            unreachable!()
        };
        assert_eq!((to.x_um, to.y_um, to.z_um), (70_000, 101_234, 400));
        assert!(volume().check(&m).is_ok());
        let high = Move {
            kind: MoveKind::Travel {
                to: PositionUm {
                    z_um: 150_002,
                    ..to
                },
                feed_um_s: 1,
            },
            ..m
        };
        let e = volume().check(&high).unwrap_err();
        assert!(e.contains("move 7") && e.contains("z = 150.002"), "{e}");
        // A layer's moves put on the machine: placed, and the first outside refused.
        let mut layer = [high.clone(), m.clone()];
        layer[0].kind = m.kind.clone();
        layer[1].index = 8;
        let back = Placement {
            offset_um: [-100_000, 0, 0],
        };
        let e = back.put_on_machine(&mut layer, &volume()).unwrap_err();
        assert!(e.contains("move 7") && e.contains("x = -30.000"), "{e}");
        let mut layer = [m.clone()];
        Placement::default()
            .put_on_machine(&mut layer, &volume())
            .unwrap();
        assert_eq!(layer[0], m);
        assert!(BuildVolume::new([200.0, 0.0, 150.0]).is_err());
        assert!(BuildVolume::new([200.0, 200.0, f64::NAN]).is_err());
        assert!(BuildVolume::new([3000.0, 200.0, 150.0]).is_err());
        assert_eq!(p.bed_to_part_xy([190.0, 10.0]), [90.0, -90.0]);
        // A layer mark's height goes with the moves (a mesh lifted onto the bed).
        let lifted = Placement {
            offset_um: [0, 0, 77_250],
        };
        let mut mark = Move {
            kind: MoveKind::LayerMark {
                layer: 3,
                z_um: -76_850,
            },
            ..m
        };
        lifted.apply(&mut mark);
        assert!(matches!(
            mark.kind,
            MoveKind::LayerMark {
                layer: 3,
                z_um: 400
            }
        ));
    }
}
