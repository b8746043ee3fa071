//! What the mixing chamber makes of a layer's roads: the predicted nozzle-exit
//! composition over each road against its design, and the roads where the design asks
//! for a change faster than the chamber can make.

use serde::{Deserialize, Serialize};

use crate::toolpath::ToolPath;

/// Most mixer-limited roads listed per layer (the worst; all are counted).
pub const MAX_LISTED: usize = 20;

/// A road whose predicted nozzle-exit composition misses its design by more than
/// `mixer_tolerance`: the design changes there faster than the mixing chamber can.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MixerLimit {
    /// The road (index in the layer's paths, in building order).
    pub path: u32,
    /// Where it starts (x, y in the part's coordinates), mm.
    pub at_mm: [f64; 2],
    /// The designed change from the road built before it (largest fraction difference).
    pub step: f64,
    /// Largest fraction difference between the composition predicted to leave the
    /// nozzle over the road (volume-weighted) and the road's design.
    pub error: f64,
}

/// Per road: volume pushed and the volume-weighted exit composition so far.
#[derive(Clone, Debug, Default)]
pub struct RoadExits {
    roads: Vec<(f64, Vec<f64>)>,
}

impl RoadExits {
    /// `volume_nl` of `exit` left the nozzle on road `path`.
    pub fn add(&mut self, path: u32, volume_nl: f64, exit: &[f64]) {
        let i = path as usize;
        if self.roads.len() <= i {
            self.roads.resize(i + 1, (0.0, Vec::new()));
        }
        let r = &mut self.roads[i];
        if r.1.len() < exit.len() {
            r.1.resize(exit.len(), 0.0);
        }
        r.0 += volume_nl;
        for (a, x) in r.1.iter_mut().zip(exit) {
            *a += volume_nl * x;
        }
    }

    /// Per road error against `paths`' designs: (volume-weighted mean, max, the roads
    /// over `tolerance` worst first (at most [`MAX_LISTED`]), how many there are).
    pub fn summarise(
        &self,
        paths: &[ToolPath],
        tolerance: f64,
    ) -> (f64, f64, Vec<MixerLimit>, usize) {
        let (mut sum, mut volume, mut max) = (0.0, 0.0, 0.0f64);
        let mut limited = Vec::new();
        let mut before: Option<&[f64]> = None;
        for (i, (p, (v, acc))) in paths.iter().zip(&self.roads).enumerate() {
            if *v <= 0.0 {
                continue;
            }
            let exit: Vec<f64> = acc.iter().map(|a| a / v).collect();
            let err = crate::material::max_fraction_difference(&p.composition, &exit);
            sum += err * v;
            volume += v;
            max = max.max(err);
            if err > tolerance {
                let start = p.points.first().copied().unwrap_or_default();
                limited.push(MixerLimit {
                    path: i as u32,
                    at_mm: [start.x, start.y],
                    step: before.map_or(0.0, |b| {
                        crate::material::max_fraction_difference(b, &p.composition)
                    }),
                    error: err,
                });
            }
            before = Some(&p.composition);
        }
        let count = limited.len();
        limited.sort_by(|a, b| b.error.total_cmp(&a.error).then(a.path.cmp(&b.path)));
        limited.truncate(MAX_LISTED);
        let mean = if volume > 0.0 { sum / volume } else { 0.0 };
        (mean, max, limited, count)
    }
}
