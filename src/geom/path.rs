//! [`Path`], a road centreline as the planner produces it: an open polyline or a closed
//! loop, with its length and the flattening of a loop thinner than a road into one
//! side of it. Not a toolpath (no widths or composition: see
//! [`crate::toolpath::ToolPath`]).

use super::{edges, signed_area};
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// A road centreline: an open polyline, or a closed loop (last vertex joins the first).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Path {
    pub points: Vec<DVec2>,
    pub closed: bool,
}

impl Path {
    pub fn length_mm(&self) -> f64 {
        self.edges().map(|(a, b)| a.distance(b)).sum()
    }

    /// The road's edges in order (see [`edges`]).
    pub fn edges(&self) -> impl Iterator<Item = (DVec2, DVec2)> + '_ {
        edges(&self.points, self.closed)
    }

    /// A loop round less than a line's area is both sides of that line to the printer
    /// (a road out and straight back, a needle of material): a closed road whose mean
    /// width, twice its area over its length, is under `width_mm` becomes the open road
    /// from one of its tips to the other along one side (the two sides lie within
    /// twice that width of each other). Any other road is returned as it is.
    pub fn flattened_if_thinner_than(self, width_mm: f64) -> Path {
        let n = self.points.len();
        if !self.closed || n < 3 {
            return self;
        }
        let length = self.length_mm();
        let area = signed_area(&self.points).abs();
        if !(length > 0.0 && 2.0 * area < width_mm * length) {
            return self;
        }
        // The tips: the vertex farthest from the first, and the one farthest from it
        // (the two ends of the line for a loop this thin).
        let farthest = |from: DVec2| {
            (0..n)
                .max_by(|&a, &b| {
                    from.distance_squared(self.points[a])
                        .total_cmp(&from.distance_squared(self.points[b]))
                })
                .unwrap_or(0)
        };
        let i = farthest(self.points[0]);
        let j = farthest(self.points[i]);
        let steps = (j + n - i) % n;
        Path {
            points: (0..=steps).map(|k| self.points[(i + k) % n]).collect(),
            closed: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(h: f64) -> Vec<DVec2> {
        vec![
            DVec2::new(-h, -h),
            DVec2::new(h, -h),
            DVec2::new(h, h),
            DVec2::new(-h, h),
        ]
    }

    #[test]
    fn loops_round_a_line_are_printed_once_along_it() {
        let v = |x: f64, y: f64| DVec2::new(x, y);
        // A femur layer 110 contour piece: 0.39 mm out and back, 3 um apart.
        let sliver = Path {
            points: vec![
                v(-36.8034, 17.6064),
                v(-36.8044, 17.6088),
                v(-36.6469, 17.2519),
            ],
            closed: true,
        };
        let line = sliver.clone().flattened_if_thinner_than(0.025);
        assert!(!line.closed);
        assert_eq!(line.points.len(), 3);
        // From one tip to the other, never turning back.
        let (first, last) = (line.points[0], line.points[2]);
        assert!((first.distance(last) - 0.3903).abs() < 1e-3, "{line:?}");
        let (u, w) = (line.points[1] - first, last - line.points[1]);
        assert!(u.dot(w) > 0.0, "{line:?}");
        // A thin loop of many vertices: one side of it, tip to tip.
        let mut thin: Vec<DVec2> = (0..=10).map(|i| v(i as f64 * 0.1, 0.0)).collect();
        thin.extend((1..10).rev().map(|i| v(i as f64 * 0.1, 0.01)));
        let line = Path {
            points: thin.clone(),
            closed: true,
        }
        .flattened_if_thinner_than(0.025);
        assert!(!line.closed);
        assert!(
            (line.length_mm() - 1.0).abs() < 0.01,
            "{}",
            line.length_mm()
        );
        // Wider than the limit, or open: unchanged.
        let kept = Path {
            points: thin.iter().map(|p| v(p.x, p.y * 4.0)).collect(),
            closed: true,
        };
        assert_eq!(kept.clone().flattened_if_thinner_than(0.025), kept);
        let open = Path {
            points: thin,
            closed: false,
        };
        assert_eq!(open.clone().flattened_if_thinner_than(0.025), open);
        let ring = Path {
            points: square(1.0),
            closed: true,
        };
        assert_eq!(ring.clone().flattened_if_thinner_than(0.025), ring);
    }
}
