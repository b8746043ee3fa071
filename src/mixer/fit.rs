//! Calibration: the mixer model and its numbers from a measured step response.
//!
//! # The record
//!
//! A step-response record is text, one sample per line: the volume pushed since the
//! inflow was switched from one material to another (nl), then the measured fraction of
//! the new material at the nozzle exit (0 to 1), separated by spaces, a tab or a comma.
//! Blank lines and lines starting with `#` are skipped. A lab measures it by switching
//! the syringes from plain to dyed material (or to a conducting one) at a steady flow
//! and reading the colour (conductivity) at the nozzle, normalised to 0 before the
//! step and 1 long after, against the volume pushed since the switch.
//!
//! # The fit
//!
//! Least squares of the model's step response to the samples: for plug flow and the
//! well-mixed chamber over V, for the dispersion model over V and Pe (a grid in log Pe,
//! then refined; V by golden-section search for each Pe). The simplest model whose
//! residual is within 10 % of the best is chosen (plug flow and a well-mixed tank are
//! the limits of the dispersion model, which always fits at least as well).

use super::{MixerError, MixerModel, MixerOptions};

/// One sample: volume pushed since the step (nl) and the new material's fraction.
pub type Sample = (f64, f64);

/// A record that does not parse, naming the line.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct RecordError {
    pub line: usize,
    pub message: String,
}

/// Parse a step-response record (format in the module doc).
pub fn parse_record(text: &str) -> Result<Vec<Sample>, RecordError> {
    let mut out = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |message: String| RecordError {
            line: n + 1,
            message,
        };
        let fields: Vec<&str> = line
            .split(|c: char| c == ',' || c.is_whitespace())
            .filter(|f| !f.is_empty())
            .collect();
        let [v, f] = fields[..] else {
            return Err(bad(format!(
                "expected two numbers (pushed nl, fraction), got {line:?}"
            )));
        };
        let num = |t: &str| {
            t.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad(format!("{t:?} is not a number")))
        };
        let (v, f) = (num(v)?, num(f)?);
        if v < 0.0 {
            return Err(bad(format!("pushed volume {v} nl is negative")));
        }
        out.push((v, f));
    }
    if out.len() < 3 {
        return Err(RecordError {
            line: text.lines().count(),
            message: format!("{} samples; a fit needs at least 3", out.len()),
        });
    }
    Ok(out)
}

/// The fitted chamber and how well it fits.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    pub options: MixerOptions,
    /// Root-mean-square residual of the samples.
    pub rms: f64,
}

/// The model's step response: the new material's fraction at the nozzle exit after
/// `pushed_nl` (exact for the plug section and tank chain of [`super::Mixer`]).
pub fn step_response(options: &MixerOptions, pushed_nl: f64) -> f64 {
    let (plug, n, tanks) = options.layout();
    let v = pushed_nl - plug;
    if v < 0.0 {
        return 0.0;
    }
    if n == 0 || tanks <= 0.0 {
        return if v > 0.0 { 1.0 } else { 0.5 };
    }
    // Erlang CDF: 1 − e^(−x)·Σ_{k<n} x^k/k!.
    let x = v / (tanks / n as f64);
    let mut term = (-x).exp();
    let mut sum = 0.0;
    for k in 0..n {
        if k > 0 {
            term *= x / k as f64;
        }
        sum += term;
    }
    (1.0 - sum).clamp(0.0, 1.0)
}

/// Fit `model` (or the best of the three: `None`) to `samples`.
pub fn fit(samples: &[Sample], model: Option<MixerModel>) -> Result<Fit, MixerError> {
    let top = samples.iter().map(|s| s.0).fold(0.0, f64::max);
    if top.is_nan() || top <= 0.0 {
        return Err(MixerError::new(
            "volume_nl",
            "the record pushes no volume".into(),
        ));
    }
    let fits = match model {
        Some(m) => vec![fit_model(samples, m, top)],
        None => [MixerModel::Plug, MixerModel::Mixed, MixerModel::Dispersion]
            .iter()
            .map(|&m| fit_model(samples, m, top))
            .collect(),
    };
    let best = fits.iter().map(|f| f.rms).fold(f64::INFINITY, f64::min);
    let chosen = fits
        .into_iter()
        .find(|f| f.rms <= best * 1.1 + 1e-12)
        .ok_or_else(|| MixerError::new("model", "no model fits the record".into()))?;
    chosen.options.validate()?;
    Ok(chosen)
}

fn fit_model(samples: &[Sample], model: MixerModel, top: f64) -> Fit {
    let with = |v: f64, pe: Option<f64>| MixerOptions {
        model,
        volume_nl: v,
        peclet: pe,
    };
    let best_volume = |pe: Option<f64>| {
        let v = golden(|v| sse(samples, &with(v, pe)), top * 1e-4, top);
        (v, sse(samples, &with(v, pe)))
    };
    let (volume, peclet) = if model == MixerModel::Dispersion {
        // A grid in log Pe from 0.01 to 10^4, then refined around the best.
        let grid: Vec<f64> = (0..=42)
            .map(|k| 10f64.powf(-2.0 + k as f64 / 7.0))
            .collect();
        let (mut at, mut err) = (grid[0], f64::INFINITY);
        for &pe in &grid {
            let e = best_volume(Some(pe)).1;
            if e < err {
                (at, err) = (pe, e);
            }
        }
        let step = 10f64.powf(1.0 / 7.0);
        let log_pe = golden(
            |l| best_volume(Some(l.exp())).1,
            (at / step).ln(),
            (at * step).ln(),
        );
        let pe = log_pe.exp();
        (best_volume(Some(pe)).0, Some(pe))
    } else {
        (best_volume(None).0, None)
    };
    let options = with(volume, peclet);
    Fit {
        rms: (sse(samples, &options) / samples.len() as f64).sqrt(),
        options,
    }
}

/// Sum of squared residuals of `samples` against the model's step response.
fn sse(samples: &[Sample], options: &MixerOptions) -> f64 {
    samples
        .iter()
        .map(|&(v, f)| (step_response(options, v) - f).powi(2))
        .sum()
}

/// The minimum of `f` over [a, b] by golden-section search (scanned first on a coarse
/// grid so that a step-shaped objective is bracketed).
fn golden(f: impl Fn(f64) -> f64, a: f64, b: f64) -> f64 {
    const SCAN: usize = 64;
    let at = |k: usize| a + (b - a) * k as f64 / SCAN as f64;
    let best = (0..=SCAN)
        .min_by(|&i, &j| f(at(i)).total_cmp(&f(at(j))))
        .unwrap_or(0);
    let (mut lo, mut hi) = (at(best.saturating_sub(1)), at((best + 1).min(SCAN)));
    let r = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..80 {
        let (c, d) = (hi - r * (hi - lo), lo + r * (hi - lo));
        if f(c) <= f(d) {
            hi = d;
        } else {
            lo = c;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mixer::Mixer;

    /// A step-response record of the chamber `o`, measured every `dv` nl up to 4 V
    /// with seeded uniform noise of ± `noise` (each sample: the exit over the last push,
    /// at its middle).
    fn record(o: &MixerOptions, dv: f64, noise: f64, seed: u64) -> Vec<Sample> {
        let mut m = Mixer::new(o, &[1.0, 0.0]);
        let mut s = seed;
        let n = (4.0 * o.volume_nl / dv) as usize;
        (0..n)
            .map(|k| {
                let f = m.push(dv, &[0.0, 1.0]).unwrap_or_default()[1];
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let u = (s >> 11) as f64 / (1u64 << 53) as f64;
                ((k as f64 + 0.5) * dv, f + noise * (2.0 * u - 1.0))
            })
            .collect()
    }

    #[test]
    fn the_step_response_is_the_chambers() {
        for o in [
            MixerOptions::new("mixed", 800.0, None).unwrap(),
            MixerOptions::new("dispersion", 800.0, Some(7.0)).unwrap(),
            MixerOptions::new("dispersion", 800.0, Some(300.0)).unwrap(),
        ] {
            for (v, f) in record(&o, 0.5, 0.0, 1) {
                assert!((step_response(&o, v) - f).abs() < 2e-3, "{o:?} at {v}");
            }
        }
    }

    #[test]
    fn fits_recover_known_chambers_within_5_percent() {
        for (model, volume, pe, seed) in [
            ("plug", 1500.0, None, 3),
            ("mixed", 800.0, None, 4),
            ("dispersion", 1000.0, Some(10.0), 5),
            ("dispersion", 2500.0, Some(40.0), 6),
            ("dispersion", 600.0, Some(2.0), 7),
        ] {
            let truth = MixerOptions::new(model, volume, pe).unwrap();
            let samples = record(&truth, volume / 100.0, 0.02, seed);
            let got = fit(&samples, None).unwrap();
            let o = got.options;
            assert_eq!(o.model, truth.model, "{truth:?}: {got:?}");
            assert!(
                (o.volume_nl / volume - 1.0).abs() < 0.05,
                "{truth:?}: {got:?}"
            );
            if let (Some(a), Some(b)) = (o.peclet, pe) {
                assert!((a / b - 1.0).abs() < 0.05, "{truth:?}: {got:?}");
            }
            assert!(got.rms < 0.04, "{got:?}");
        }
    }

    #[test]
    fn bad_records_are_refused_naming_the_line() {
        assert_eq!(parse_record("# step\n0 0\n10, 0.1\n").unwrap_err().line, 3);
        assert_eq!(parse_record("0 0\n5 x\n10 1\n").unwrap_err().line, 2);
        assert_eq!(parse_record("0 0\n-5 0.2\n10 1\n").unwrap_err().line, 2);
        assert_eq!(parse_record("0 0 1\n").unwrap_err().line, 1);
        assert_eq!(
            parse_record("# a\n\n0\t0\n10,0.5\n20 1\n").unwrap(),
            vec![(0.0, 0.0), (10.0, 0.5), (20.0, 1.0)]
        );
        assert!(fit(&[(0.0, 0.0), (0.0, 1.0), (0.0, 0.5)], None).is_err());
    }
}
