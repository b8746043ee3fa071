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
//! projected gradient (FISTA) from the mixing lead's commands. The chamber is linear
//! and, on a uniform grid, time-invariant, so its response is a recursive filter run
//! once per gradient (`filter`: the plug delay and the tank chain's exact step, weights
//! computed once, O(cells × tanks) and no allocation per cell) and its adjoint is the
//! same filter over the reversed stream. The iterations stop when no command moves by
//! more than [`SolveOptions::tolerance`] (default one step of a move's fixed-point ratio,
//! 1/65535), or after [`SolveOptions::max_iterations`]. The result is not exact: the
//! caller predicts what it gives with the exact model.

mod filter;

use super::{Mixer, MixerOptions};
use filter::CellFilter;

/// Grid cells per chamber volume V.
pub const CELLS_PER_VOLUME: f64 = 32.0;

/// Most grid cells a layer's inverse is computed on (the cells grow beyond this).
const MAX_CELLS: usize = 50_000;

/// When the projected-gradient iterations stop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveOptions {
    /// Most gradient steps (default 150).
    pub max_iterations: usize,
    /// Stop once no command's fraction moves by more than this in a step (default
    /// 1/65535, one step of a move's fixed-point ratio).
    pub tolerance: f64,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            max_iterations: 150,
            tolerance: 1.0 / 65535.0,
        }
    }
}

/// The commands chosen and how the solve went.
#[derive(Clone, Debug, PartialEq)]
pub struct Solution {
    /// The commanded composition per segment.
    pub commands: Vec<Vec<f64>>,
    /// Gradient steps taken.
    pub iterations: usize,
    /// ½·Σ cells |exit − target|²·cell volume (nl) at the commands (on the grid).
    pub objective: f64,
}

/// The commanded composition per segment of `designed` (volume nl, composition), from
/// `lead` (one per segment, the starting point), for a chamber `options` in the state
/// `chamber`.
pub fn feed_forward(
    options: &MixerOptions,
    chamber: &Mixer,
    designed: &[(f64, &[f64])],
    lead: Vec<Vec<f64>>,
) -> Vec<Vec<f64>> {
    solve(options, chamber, designed, lead, &SolveOptions::default()).commands
}

/// [`feed_forward`] with its stopping rule given, and how the solve went.
pub fn solve(
    options: &MixerOptions,
    chamber: &Mixer,
    designed: &[(f64, &[f64])],
    lead: Vec<Vec<f64>>,
    stop: &SolveOptions,
) -> Solution {
    let Some(mut problem) = Problem::new(options, chamber, designed) else {
        return Solution {
            commands: lead,
            iterations: 0,
            objective: 0.0,
        };
    };
    let n = problem.components;
    let mut x: Vec<f64> = lead.iter().flat_map(|u| project(u)).collect();
    if x.len() != designed.len() * n {
        x = designed.iter().flat_map(|s| project(s.1)).collect();
    }
    let mut z = x.clone();
    let mut next = x.clone();
    let mut g = vec![0.0; x.len()];
    let (mut t, mut iterations) = (1.0f64, 0);
    while iterations < stop.max_iterations {
        iterations += 1;
        problem.gradient(&z, &mut g);
        let mut moved = 0.0f64;
        for ((nx, zc), gc) in next.chunks_mut(n).zip(z.chunks(n)).zip(g.chunks(n)) {
            for ((a, b), c) in nx.iter_mut().zip(zc).zip(gc) {
                *a = b - c;
            }
            project_in_place(nx);
        }
        let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
        let beta = (t - 1.0) / t_next;
        for ((zc, a), b) in z.iter_mut().zip(&next).zip(&x) {
            *zc = a + beta * (a - b);
            moved = moved.max((a - b).abs());
        }
        std::mem::swap(&mut x, &mut next);
        t = t_next;
        if moved <= stop.tolerance {
            break;
        }
    }
    let objective = problem.objective(&x);
    Solution {
        commands: x.chunks(n).map(<[f64]>::to_vec).collect(),
        iterations,
        objective,
    }
}

/// The least-squares problem on the grid. Cell arrays are per component (`[k][cell]`),
/// commands per segment (`[segment · n + k]`).
struct Problem {
    components: usize,
    cell_nl: f64,
    filter: CellFilter,
    /// Per cell: the segments overlapping it (index, overlap over the cell's volume),
    /// in `overlap_list[overlap_start[c]..overlap_start[c + 1]]`.
    overlap_start: Vec<usize>,
    overlap_list: Vec<(usize, f64)>,
    /// Per segment: 1 / its volume in cells.
    inverse_cells: Vec<f64>,
    /// Designed composition (the target) less what leaves the nozzle from the chamber's
    /// content and the fixed inflow beyond the layer with nothing commanded in it.
    wanted: Vec<Vec<f64>>,
    /// Scratch: inflow, exit and back-propagated residual of one component, the
    /// filter's tanks.
    inflow: Vec<f64>,
    exit: Vec<f64>,
    back: Vec<f64>,
    tanks: Vec<f64>,
}

impl Problem {
    fn new(options: &MixerOptions, chamber: &Mixer, designed: &[(f64, &[f64])]) -> Option<Self> {
        let total: f64 = designed.iter().map(|s| s.0).sum();
        let last = designed.last()?.1;
        if !(options.volume_nl > 0.0 && total > 0.0) {
            return None;
        }
        let span = total + options.volume_nl;
        let cell_nl = (options.volume_nl / CELLS_PER_VOLUME).max(span / MAX_CELLS as f64);
        let cells = (span / cell_nl).ceil() as usize;
        let overlaps = cell_overlaps(designed, cell_nl, cells);
        let n = last.len();
        let wanted = wanted(chamber, designed, &overlaps, cell_nl);
        let mut overlap_start = Vec::with_capacity(cells + 1);
        let mut overlap_list = Vec::new();
        for cell in &overlaps {
            overlap_start.push(overlap_list.len());
            overlap_list.extend(cell.iter().map(|&(j, v)| (j, v / cell_nl)));
        }
        overlap_start.push(overlap_list.len());
        Some(Problem {
            components: n,
            cell_nl,
            filter: CellFilter::new(options, cell_nl),
            overlap_start,
            overlap_list,
            inverse_cells: designed.iter().map(|s| cell_nl / s.0).collect(),
            wanted,
            inflow: vec![0.0; cells],
            exit: vec![0.0; cells],
            back: vec![0.0; cells],
            tanks: Vec::new(),
        })
    }

    fn cells(&self) -> usize {
        self.overlap_start.len() - 1
    }

    /// The overlaps of cell `c`: (segment, overlap over the cell's volume).
    fn overlaps(&self, c: usize) -> &[(usize, f64)] {
        &self.overlap_list[self.overlap_start[c]..self.overlap_start[c + 1]]
    }

    /// Component `k` of the commands `u`, cell by cell, into `self.inflow`; the residual
    /// exit − wanted into `self.exit`.
    fn residual(&mut self, u: &[f64], k: usize) {
        let n = self.components;
        for c in 0..self.cells() {
            let mut acc = 0.0;
            for &(j, w) in self.overlaps(c) {
                acc += w * u[j * n + k];
            }
            self.inflow[c] = acc;
        }
        self.filter
            .apply(&self.inflow, &mut self.exit, &mut self.tanks);
        for (e, w) in self.exit.iter_mut().zip(&self.wanted[k]) {
            *e -= w;
        }
    }

    /// The gradient of ½·Σ cells |exit − target|² over segment commands `u`, per cell of
    /// each segment's volume, into `g`.
    fn gradient(&mut self, u: &[f64], g: &mut [f64]) {
        let n = self.components;
        g.iter_mut().for_each(|x| *x = 0.0);
        for k in 0..n {
            self.residual(u, k);
            // The adjoint: the same filter over the reversed residual.
            self.exit.reverse();
            self.filter
                .apply(&self.exit, &mut self.back, &mut self.tanks);
            self.back.reverse();
            for c in 0..self.cells() {
                let b = self.back[c];
                let (from, to) = (self.overlap_start[c], self.overlap_start[c + 1]);
                for &(j, w) in &self.overlap_list[from..to] {
                    g[j * n + k] += w * self.inverse_cells[j] * b;
                }
            }
        }
    }

    /// ½·Σ cells |exit − target|²·cell volume (nl) at `u`.
    fn objective(&mut self, u: &[f64]) -> f64 {
        let mut sum = 0.0;
        for k in 0..self.components {
            self.residual(u, k);
            sum += self.exit.iter().map(|r| r * r).sum::<f64>();
        }
        0.5 * sum * self.cell_nl
    }
}

/// Per component and cell: the designed composition less the free response (the
/// chamber's content washing out, and beyond the layer the last designed composition
/// pushed in).
fn wanted(
    chamber: &Mixer,
    designed: &[(f64, &[f64])],
    overlaps: &[Vec<(usize, f64)>],
    cell_nl: f64,
) -> Vec<Vec<f64>> {
    let last = designed.last().map_or(&[][..], |s| s.1);
    let n = last.len();
    let mut free_chamber = chamber.clone();
    let mut out = vec![vec![0.0; overlaps.len()]; n];
    for (c, cell) in overlaps.iter().enumerate() {
        let mut target = vec![0.0; n];
        let mut got = 0.0;
        for &(j, v) in cell {
            add(&mut target, v / cell_nl, designed[j].1);
            got += v;
        }
        let rest = (cell_nl - got) / cell_nl;
        add(&mut target, rest, last);
        let inflow: Vec<f64> = last.iter().map(|x| x * rest).collect();
        let free = free_chamber
            .push(cell_nl, &inflow)
            .unwrap_or_else(|| vec![0.0; n]);
        for k in 0..n {
            out[k][c] = target[k] - free[k];
        }
    }
    out
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
    let mut out = u.to_vec();
    project_in_place(&mut out);
    out
}

/// [`project`] in place (a non-finite fraction counts as 0).
fn project_in_place(u: &mut [f64]) {
    for x in u.iter_mut() {
        if !x.is_finite() {
            *x = 0.0;
        }
    }
    let mut sorted = [0.0f64; crate::machine::MAX_SYRINGES];
    let theta = if u.len() <= sorted.len() {
        let sorted = &mut sorted[..u.len()];
        sorted.copy_from_slice(u);
        simplex_shift(sorted)
    } else {
        simplex_shift(&mut u.to_vec())
    };
    for x in u.iter_mut() {
        *x = (*x - theta).max(0.0);
    }
}

/// The shift θ of the projection onto the simplex: Σ max(u − θ, 0) = 1 (`sorted` is
/// scratch holding u).
fn simplex_shift(sorted: &mut [f64]) -> f64 {
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
    theta
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
