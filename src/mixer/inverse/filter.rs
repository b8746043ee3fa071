//! The chamber as a recursive filter on a uniform grid of cells: what leaves the nozzle
//! over each cell for one (cell-averaged) inflow per cell, from an empty chamber, in
//! O(cells × tanks × Poisson taps) with no allocation per cell. Exactly what
//! [`Mixer::push`] gives cell by cell, up to rounding: the plug section is a delay of a
//! whole number of cells and a fraction, so each cell's inflow to the tanks is two
//! constant pieces, and each piece advances the tanks by the chain's exact solution with
//! Poisson weights computed once.

use super::super::MixerOptions;

/// Poisson weights below this (past the peak) are dropped.
const NEGLIGIBLE: f64 = 1e-18;

/// One constant piece of a cell's inflow to the tanks: the fraction of the cell it
/// spans, and the chain's weights e^(−x)·x^m/m! for x = its volume over a tank's.
#[derive(Clone, Debug)]
struct Piece {
    fraction: f64,
    weights: Vec<f64>,
}

/// The chamber's response on a grid of `cell_nl` cells.
#[derive(Clone, Debug)]
pub(super) struct CellFilter {
    /// The plug section's delay in whole cells (the fraction of a cell beyond is the
    /// first piece's).
    delay_cells: usize,
    tanks: usize,
    /// A tank's volume over a cell's.
    tank_cells: f64,
    /// The pieces: the earlier cell's (the delay's fraction), then the later one's.
    pieces: [Piece; 2],
}

impl CellFilter {
    pub(super) fn new(options: &MixerOptions, cell_nl: f64) -> Self {
        let (plug_nl, tanks, tanks_nl) = options.layout();
        let delay = plug_nl / cell_nl;
        let delay_cells = delay.floor() as usize;
        let delay_fraction = delay - delay_cells as f64;
        let tank_nl = if tanks > 0 {
            tanks_nl / tanks as f64
        } else {
            0.0
        };
        let piece = |fraction: f64| Piece {
            fraction,
            weights: if tanks > 0 {
                poisson_weights(fraction * cell_nl / tank_nl, tanks)
            } else {
                Vec::new()
            },
        };
        CellFilter {
            delay_cells,
            tanks,
            tank_cells: if tanks > 0 { tank_nl / cell_nl } else { 0.0 },
            pieces: [piece(delay_fraction), piece(1.0 - delay_fraction)],
        }
    }

    /// `out[c]`: what leaves over cell c for `input` (one component), from an empty
    /// chamber; `state` is scratch (the tanks).
    pub(super) fn apply(&self, input: &[f64], out: &mut [f64], state: &mut Vec<f64>) {
        state.clear();
        state.resize(self.tanks, 0.0);
        let at = |c: isize| -> f64 {
            if c < 0 {
                0.0
            } else {
                input.get(c as usize).copied().unwrap_or(0.0)
            }
        };
        for (c, o) in out.iter_mut().enumerate() {
            let later = c as isize - self.delay_cells as isize;
            let inflows = [at(later - 1), at(later)];
            let mut left = 0.0;
            for (piece, u) in self.pieces.iter().zip(inflows) {
                if piece.fraction <= 0.0 {
                    continue;
                }
                left += if self.tanks == 0 {
                    piece.fraction * u
                } else {
                    self.advance(state, &piece.weights, piece.fraction, u)
                };
            }
            *o = left;
        }
    }

    /// Advance the tanks by a constant inflow `u` over `fraction` of a cell; what left
    /// the last tank, as a fraction of a cell times its composition.
    fn advance(&self, state: &mut [f64], weights: &[f64], fraction: f64, u: f64) -> f64 {
        let mut before = 0.0;
        let mut after = 0.0;
        // In place from the last tank back: tank i needs the deviations of tanks ≤ i.
        for i in (0..state.len()).rev() {
            let lo = (i + 1).saturating_sub(weights.len());
            let mut sum = 0.0;
            for j in lo..=i {
                sum += (state[j] - u) * weights[i - j];
            }
            before += state[i] - u;
            after += sum;
            state[i] = u + sum;
        }
        fraction * u + self.tank_cells * (before - after)
    }
}

/// e^(−x)·x^m/m! for m < n, the negligible tail past the peak dropped.
fn poisson_weights(x: f64, n: usize) -> Vec<f64> {
    let mut weights = Vec::with_capacity(n);
    let mut w = (-x).exp();
    for m in 0..n {
        if m > 0 {
            w *= x / m as f64;
        }
        if m as f64 > x && w < NEGLIGIBLE {
            break;
        }
        weights.push(w);
    }
    weights
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mixer::Mixer;

    /// The filter gives what the chamber gives pushed cell by cell, for every model
    /// and grids finer and coarser than the tanks and the plug section.
    #[test]
    fn the_filter_is_the_chamber_cell_by_cell() {
        let mut seed = 11u64;
        let input: Vec<f64> = (0..700)
            .map(|_| {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (seed >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect();
        for (model, pe) in [
            ("plug", None),
            ("mixed", None),
            ("dispersion", Some(0.5)),
            ("dispersion", Some(10.0)),
            ("dispersion", Some(40.0)),
            ("dispersion", Some(3000.0)),
        ] {
            let o = MixerOptions::new(model, 1000.0, pe).unwrap();
            for cell_nl in [1000.0 / 32.0, 7.3, 113.0, 2500.0] {
                let filter = CellFilter::new(&o, cell_nl);
                let mut out = vec![0.0; input.len()];
                filter.apply(&input, &mut out, &mut Vec::new());
                let mut m = Mixer::new(&o, &[0.0]);
                for (c, (u, f)) in input.iter().zip(&out).enumerate() {
                    let want = m.push(cell_nl, &[*u]).unwrap()[0];
                    assert!(
                        (want - f).abs() < 1e-12,
                        "{model} {pe:?} cell {cell_nl}: cell {c} {f} vs {want}"
                    );
                }
            }
        }
    }
}
