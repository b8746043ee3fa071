//! One connected area of a layer, [`Region`]: an outer loop (the paper's Ce) and its
//! holes (Ci); its area, bounds and containment, its normalised form (outer loop
//! counter-clockwise, holes clockwise), and the check that a region supplied by a user
//! or a slicer is a sound polygon with holes ([`Region::validate`], [`RegionError`]).
//! Not the algebra of areas (see `booleans.rs`, `offset/`).

use super::{
    dedup_loop, first_crossing, loop_bounds, point_in_loop, signed_area, signed_area2, Tolerances,
};
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Bounding box (min, max) of several regions (infinite and inverted when empty).
pub fn bounds_of(regions: &[Region]) -> (DVec2, DVec2) {
    let mut lo = DVec2::splat(f64::INFINITY);
    let mut hi = DVec2::splat(f64::NEG_INFINITY);
    for r in regions {
        let (a, b) = r.bounds();
        lo = lo.min(a);
        hi = hi.max(b);
    }
    (lo, hi)
}

/// One connected area of a layer: an outer loop (the paper's external boundary Ce)
/// and zero or more holes (internal boundaries Ci).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Region {
    pub outer: Vec<DVec2>,
    #[serde(default)]
    pub holes: Vec<Vec<DVec2>>,
}

/// What is wrong with a region, naming the loop and where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegionError {
    #[error("{loop_name} has {count} distinct vertices; a loop needs at least 3")]
    TooFewVertices { loop_name: String, count: usize },
    #[error("{loop_name} vertex {index} is not a finite number")]
    NotFinite { loop_name: String, index: usize },
    #[error("{loop_name} encloses no area (|area| = {area_mm2:.3e} mm²)")]
    Degenerate { loop_name: String, area_mm2: f64 },
    #[error("{first} edge {first_edge} crosses {second} edge {second_edge} near ({x:.4}, {y:.4})")]
    SelfIntersecting {
        first: String,
        first_edge: usize,
        second: String,
        second_edge: usize,
        x: f64,
        y: f64,
    },
    #[error("{loop_name} is not inside the outer loop (vertex {index} at ({x:.4}, {y:.4}) lies outside)")]
    HoleOutside {
        loop_name: String,
        index: usize,
        x: f64,
        y: f64,
    },
    #[error("{inner} lies inside {outer}; nested holes are separate islands, give them as their own region")]
    NestedHoles { inner: String, outer: String },
}

impl Region {
    pub fn new(outer: Vec<DVec2>, holes: Vec<Vec<DVec2>>) -> Self {
        Region { outer, holes }
    }

    fn loop_name(i: usize) -> String {
        if i == 0 {
            "outer loop".to_string()
        } else {
            format!("hole {}", i - 1)
        }
    }

    /// All loops, outer first.
    pub fn loops(&self) -> impl Iterator<Item = &Vec<DVec2>> {
        std::iter::once(&self.outer).chain(self.holes.iter())
    }

    /// Net area, mm² (outer minus holes).
    pub fn area(&self) -> f64 {
        signed_area(&self.outer).abs()
            - self.holes.iter().map(|h| signed_area(h).abs()).sum::<f64>()
    }

    /// Axis-aligned bounding box (min, max).
    pub fn bounds(&self) -> (DVec2, DVec2) {
        loop_bounds(&self.outer)
    }

    /// Is `p` inside the material (inside outer, outside every hole)?
    pub fn contains(&self, p: DVec2) -> bool {
        point_in_loop(p, &self.outer) && !self.holes.iter().any(|h| point_in_loop(p, h))
    }

    /// A copy with duplicate points removed, the outer loop counter-clockwise and holes clockwise.
    pub fn normalised(&self, tol: &Tolerances) -> Region {
        let fix = |l: &[DVec2], ccw: bool| {
            let mut l = dedup_loop(l, tol.point_eq_mm);
            if (signed_area2(&l) > 0.0) != ccw {
                l.reverse();
            }
            l
        };
        Region {
            outer: fix(&self.outer, true),
            holes: self.holes.iter().map(|h| fix(h, false)).collect(),
        }
    }

    /// Check the region is a sound polygon with holes: enough vertices, finite,
    /// non-degenerate, no edge crossing any other, holes inside the outer loop and
    /// not inside each other. Call on a normalised region.
    pub fn validate(&self, tol: &Tolerances) -> Result<(), RegionError> {
        for (li, l) in self.loops().enumerate() {
            if let Some(index) = l.iter().position(|p| !p.is_finite()) {
                return Err(RegionError::NotFinite {
                    loop_name: Self::loop_name(li),
                    index,
                });
            }
            let distinct = dedup_loop(l, tol.point_eq_mm).len();
            if distinct < 3 {
                return Err(RegionError::TooFewVertices {
                    loop_name: Self::loop_name(li),
                    count: distinct,
                });
            }
        }
        let loops: Vec<&[DVec2]> = self.loops().map(|l| l.as_slice()).collect();
        if let Some(c) = first_crossing(&loops) {
            return Err(RegionError::SelfIntersecting {
                first: Self::loop_name(c.first.0),
                first_edge: c.first.1,
                second: Self::loop_name(c.second.0),
                second_edge: c.second.1,
                x: c.at.x,
                y: c.at.y,
            });
        }
        for (li, l) in self.loops().enumerate() {
            let a = signed_area(l).abs();
            if a < tol.min_loop_area_mm2 {
                return Err(RegionError::Degenerate {
                    loop_name: Self::loop_name(li),
                    area_mm2: a,
                });
            }
        }
        // No crossings: each hole is entirely inside or entirely outside the outer loop
        // (and each other), so one vertex decides.
        for (hi, h) in self.holes.iter().enumerate() {
            if !point_in_loop(h[0], &self.outer) {
                return Err(RegionError::HoleOutside {
                    loop_name: Self::loop_name(hi + 1),
                    index: 0,
                    x: h[0].x,
                    y: h[0].y,
                });
            }
            for (hj, g) in self.holes.iter().enumerate() {
                if hi != hj && point_in_loop(h[0], g) {
                    return Err(RegionError::NestedHoles {
                        inner: Self::loop_name(hi + 1),
                        outer: Self::loop_name(hj + 1),
                    });
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(c: DVec2, h: f64) -> Vec<DVec2> {
        vec![
            c + DVec2::new(-h, -h),
            c + DVec2::new(h, -h),
            c + DVec2::new(h, h),
            c + DVec2::new(-h, h),
        ]
    }

    #[test]
    fn area_and_orientation() {
        let r = Region::new(square(DVec2::ZERO, 2.0), vec![square(DVec2::ZERO, 1.0)]);
        let n = r.normalised(&Tolerances::default());
        assert!(signed_area(&n.outer) > 0.0);
        assert!(signed_area(&n.holes[0]) < 0.0);
        assert!((n.area() - 12.0).abs() < 1e-12);
        assert!(n.validate(&Tolerances::default()).is_ok());
        assert!(n.contains(DVec2::new(1.5, 0.0)));
        assert!(!n.contains(DVec2::new(0.5, 0.0)));
    }

    #[test]
    fn bowtie_is_self_intersecting() {
        let r = Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(1.0, 1.0),
                DVec2::new(1.0, 0.0),
                DVec2::new(0.0, 1.0),
            ],
            vec![],
        );
        let e = r.validate(&Tolerances::default()).unwrap_err();
        assert!(matches!(e, RegionError::SelfIntersecting { .. }), "{e}");
    }

    #[test]
    fn hole_outside_and_crossing_are_refused() {
        let tol = Tolerances::default();
        let outside = Region::new(
            square(DVec2::ZERO, 1.0),
            vec![square(DVec2::new(5.0, 0.0), 0.5)],
        );
        assert!(matches!(
            outside.normalised(&tol).validate(&tol),
            Err(RegionError::HoleOutside { .. })
        ));
        let crossing = Region::new(
            square(DVec2::ZERO, 1.0),
            vec![square(DVec2::new(1.0, 0.0), 0.5)],
        );
        assert!(matches!(
            crossing.normalised(&tol).validate(&tol),
            Err(RegionError::SelfIntersecting { .. })
        ));
    }

    #[test]
    fn degenerate_and_nan() {
        let tol = Tolerances::default();
        let line = Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(1.0, 0.0),
                DVec2::new(2.0, 0.0),
            ],
            vec![],
        );
        assert!(matches!(
            line.validate(&tol),
            Err(RegionError::Degenerate { .. })
        ));
        let nan = Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(f64::NAN, 0.0),
                DVec2::new(2.0, 1.0),
            ],
            vec![],
        );
        assert!(matches!(
            nan.validate(&tol),
            Err(RegionError::NotFinite { index: 1, .. })
        ));
    }
}
