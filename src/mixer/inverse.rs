//! The feed-forward inverse of a mixing chamber: the compositions to command, segment by
//! segment, so that what leaves the nozzle follows a designed stream as closely as the
//! machine allows.
//!
//! The designed stream is a sequence of segments (volume, composition), one per
//! extrusion move; each is commanded one composition (a move carries one ratio). The
//! commanded compositions minimise the volume-weighted squared difference between the
//! predicted nozzle-exit composition and the design, subject to every commanded
//! composition being a mix the syringes can push: fractions in [0, 1] summing to 1 (no
//! syringe pulled back to steer the mix). The difference is measured on a grid of
//! cells of V/[`CELLS_PER_VOLUME`] over the layer's stream and V beyond it (where the
//! last designed composition is the target and is what is pushed: the next layer is not
//! known), from the chamber's state before the layer.
//!
//! The problem is a bounded least-squares deconvolution; it is solved by accelerated
//! projected gradient (FISTA) from the mixing lead's commands, with the chamber's own
//! model as the forward operator (the chamber is linear and, on a uniform grid,
//! time-invariant, so its adjoint is the same chamber run over the reversed stream).
//! The result is not exact: the caller predicts what it gives with the exact model.

use super::{Mixer, MixerOptions};

/// Grid cells per chamber volume V.
pub const CELLS_PER_VOLUME: f64 = 32.0;

/// Most grid cells a layer's inverse is computed on (the cells grow beyond this).
const MAX_CELLS: usize = 50_000;

/// Gradient steps.
const ITERATIONS: usize = 150;

/// The commanded composition per segment of `designed` (volume nl, composition), from
/// `lead` (one per segment, the starting point), for a chamber `options` in the state
/// `chamber`.
pub fn feed_forward(
    options: &MixerOptions,
    chamber: &Mixer,
    designed: &[(f64, &[f64])],
    lead: Vec<Vec<f64>>,
) -> Vec<Vec<f64>> {
    let Some(problem) = Problem::new(options, chamber, designed) else {
        return lead;
    };
    let mut x: Vec<Vec<f64>> = lead.into_iter().map(|u| project(&u)).collect();
    let mut z = x.clone();
    let mut t = 1.0f64;
    for _ in 0..ITERATIONS {
        let g = problem.gradient(&z);
        let next: Vec<Vec<f64>> = z
            .iter()
            .zip(&g)
            .map(|(u, gu)| project(&u.iter().zip(gu).map(|(a, b)| a - b).collect::<Vec<_>>()))
            .collect();
        let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
        let beta = (t - 1.0) / t_next;
        z = next
            .iter()
            .zip(&x)
            .map(|(n, o)| n.iter().zip(o).map(|(a, b)| a + beta * (a - b)).collect())
            .collect();
        x = next;
        t = t_next;
    }
    x
}

/// The least-squares problem on the grid.
struct Problem<'d> {
    options: MixerOptions,
    cell_nl: f64,
    /// Per cell: the segments overlapping it (index, volume of the overlap).
    overlaps: Vec<Vec<(usize, f64)>>,
    /// Segment volumes.
    volumes: Vec<f64>,
    /// Per cell: designed composition (the target).
    target: Vec<Vec<f64>>,
    /// Per cell: what leaves the nozzle from the chamber's content and the fixed
    /// inflow beyond the layer, with nothing commanded in the layer.
    free: Vec<Vec<f64>>,
    designed: &'d [(f64, &'d [f64])],
}

impl<'d> Problem<'d> {
    fn new(
        options: &MixerOptions,
        chamber: &Mixer,
        designed: &'d [(f64, &'d [f64])],
    ) -> Option<Self> {
        let total: f64 = designed.iter().map(|s| s.0).sum();
        let last = designed.last()?.1;
        if !(options.volume_nl > 0.0 && total > 0.0) {
            return None;
        }
        let span = total + options.volume_nl;
        let cell_nl = (options.volume_nl / CELLS_PER_VOLUME).max(span / MAX_CELLS as f64);
        let cells = (span / cell_nl).ceil() as usize;
        let overlaps = cell_overlaps(designed, cell_nl, cells);
        let target = (0..cells)
            .map(|c| {
                let mut acc = vec![0.0; last.len()];
                let mut got = 0.0;
                for &(j, v) in &overlaps[c] {
                    add(&mut acc, v, designed[j].1);
                    got += v;
                }
                add(&mut acc, cell_nl - got, last);
                acc.iter().map(|a| a / cell_nl).collect()
            })
            .collect();
        // The free response: the chamber's content washing out, and beyond the layer
        // the last designed composition pushed in.
        let mut free_chamber = chamber.clone();
        let free = (0..cells)
            .map(|c| {
                let got: f64 = overlaps[c].iter().map(|o| o.1).sum();
                let inflow: Vec<f64> = last.iter().map(|x| x * (cell_nl - got) / cell_nl).collect();
                free_chamber
                    .push(cell_nl, &inflow)
                    .unwrap_or_else(|| vec![0.0; last.len()])
            })
            .collect();
        Some(Problem {
            options: *options,
            cell_nl,
            overlaps,
            volumes: designed.iter().map(|s| s.0).collect(),
            target,
            free,
            designed,
        })
    }

    /// The gradient of ½·Σ cells |exit − target|²·cell over segment commands `u`, per
    /// unit of each segment's volume.
    fn gradient(&self, u: &[Vec<f64>]) -> Vec<Vec<f64>> {
        let n = self.target.first().map_or(0, Vec::len);
        let inflow: Vec<Vec<f64>> = self
            .overlaps
            .iter()
            .map(|cell| {
                let mut acc = vec![0.0; n];
                for &(j, v) in cell {
                    add(&mut acc, v / self.cell_nl, &u[j]);
                }
                acc
            })
            .collect();
        let exit = self.chamber_response(inflow.iter());
        let residual: Vec<Vec<f64>> = exit
            .iter()
            .zip(&self.free)
            .zip(&self.target)
            .map(|((e, f), t)| {
                e.iter()
                    .zip(f)
                    .zip(t)
                    .map(|((e, f), t)| e + f - t)
                    .collect()
            })
            .collect();
        let mut back = self.chamber_response(residual.iter().rev());
        back.reverse();
        let mut g = vec![vec![0.0; n]; self.designed.len()];
        for (cell, b) in self.overlaps.iter().zip(&back) {
            for &(j, v) in cell {
                add(&mut g[j], v / self.volumes[j], b);
            }
        }
        g
    }

    /// What leaves an empty chamber (all content 0) for one inflow per cell, in order.
    fn chamber_response<'a>(&self, inflow: impl Iterator<Item = &'a Vec<f64>>) -> Vec<Vec<f64>> {
        let n = self.target.first().map_or(0, Vec::len);
        let mut m = Mixer::new(&self.options, &vec![0.0; n]);
        inflow
            .map(|c| m.push(self.cell_nl, c).unwrap_or_else(|| vec![0.0; n]))
            .collect()
    }
}

/// Per grid cell of `cell_nl`, the segments that overlap it and by how much.
fn cell_overlaps(designed: &[(f64, &[f64])], cell_nl: f64, cells: usize) -> Vec<Vec<(usize, f64)>> {
    let mut out = vec![Vec::new(); cells];
    let mut start = 0.0;
    for (j, (v, _)) in designed.iter().enumerate() {
        let end = start + v;
        let first = ((start / cell_nl).floor() as usize).min(cells.saturating_sub(1));
        let mut c = first;
        while c < cells && (c as f64) * cell_nl < end {
            let a = start.max(c as f64 * cell_nl);
            let b = end.min((c + 1) as f64 * cell_nl);
            if b > a {
                out[c].push((j, b - a));
            }
            c += 1;
        }
        start = end;
    }
    out
}

fn add(acc: &mut [f64], weight: f64, c: &[f64]) {
    for (a, x) in acc.iter_mut().zip(c) {
        *a += weight * x;
    }
}

/// The nearest composition a machine can push: fractions ≥ 0 summing to 1 (Euclidean
/// projection onto the simplex).
pub fn project(u: &[f64]) -> Vec<f64> {
    if u.is_empty() {
        return Vec::new();
    }
    let mut sorted: Vec<f64> = u
        .iter()
        .map(|x| if x.is_finite() { *x } else { 0.0 })
        .collect();
    sorted.sort_by(|a, b| b.total_cmp(a));
    let mut sum = 0.0;
    let mut theta = 0.0;
    for (k, s) in sorted.iter().enumerate() {
        sum += s;
        let t = (sum - 1.0) / (k + 1) as f64;
        if s - t > 0.0 {
            theta = t;
        }
    }
    u.iter()
        .map(|x| {
            if x.is_finite() {
                (x - theta).max(0.0)
            } else {
                0.0
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exit composition per segment for commands `u`, from `chamber`.
    fn exit(chamber: &Mixer, designed: &[(f64, &[f64])], u: &[Vec<f64>]) -> Vec<Vec<f64>> {
        let mut m = chamber.clone();
        designed
            .iter()
            .zip(u)
            .map(|((v, _), c)| m.push(*v, c).unwrap())
            .collect()
    }

    /// Volume-weighted mean and max of the largest fraction difference.
    fn error(designed: &[(f64, &[f64])], exit: &[Vec<f64>]) -> (f64, f64) {
        let (mut sum, mut vol, mut max) = (0.0, 0.0, 0.0f64);
        for ((v, d), e) in designed.iter().zip(exit) {
            let err = crate::material::max_fraction_difference(d, e);
            sum += v * err;
            vol += v;
            max = max.max(err);
        }
        (sum / vol, max)
    }

    #[test]
    fn projection_gives_a_pushable_mix() {
        assert_eq!(project(&[0.3, 0.7]), vec![0.3, 0.7]);
        assert_eq!(project(&[1.4, -0.2]), vec![1.0, 0.0]);
        let p = project(&[0.9, 0.9, -1.0]);
        assert!((p[0] - 0.5).abs() < 1e-12 && (p[1] - 0.5).abs() < 1e-12 && p[2] == 0.0);
        let p = project(&[f64::NAN, 0.2]);
        assert!(p.iter().all(|x| (0.0..=1.0).contains(x)));
    }

    #[test]
    fn the_inverse_follows_a_slow_gradient_a_pure_delay_cannot() {
        // A ramp from 20 % to 80 % B over 3 V and back, in segments of V/50, through a
        // well-mixed chamber: the lead (a delay of V) rounds the ramp's corners; the
        // inverse overshoots the command there (within what the syringes can push).
        let volume = 1000.0;
        let o = MixerOptions::new("mixed", volume, None).unwrap();
        let comps: Vec<[f64; 2]> = (0..400)
            .map(|k| {
                let s = (k as f64 / 150.0).min(1.0) * (1.0 - ((k as f64 - 250.0) / 150.0).max(0.0));
                [0.8 - s * 0.6, 0.2 + s * 0.6]
            })
            .collect();
        let designed: Vec<(f64, &[f64])> = comps.iter().map(|c| (20.0, &c[..])).collect();
        let chamber = Mixer::new(&o, designed[0].1);
        let lead: Vec<Vec<f64>> = (0..designed.len())
            .map(|k| designed[(k + 50).min(designed.len() - 1)].1.to_vec())
            .collect();
        let before = error(&designed, &exit(&chamber, &designed, &lead));
        let u = feed_forward(&o, &chamber, &designed, lead);
        for c in &u {
            assert!(c.iter().all(|x| (0.0..=1.0).contains(x)), "{c:?}");
            assert!((c.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        }
        let after = error(&designed, &exit(&chamber, &designed, &u));
        assert!(
            after.0 < 0.25 * before.0,
            "lead {before:?}, inverse {after:?}"
        );

        assert!(after.1 < 0.01, "lead {before:?}, inverse {after:?}");
    }
}
