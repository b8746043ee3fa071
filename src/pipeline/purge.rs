//! How much a purge pad pushes. Under plug flow the chamber holds exactly what went in
//! last, so V_dead commanded with the layer's first V_dead of design leaves the chamber
//! holding that. A well-mixed or dispersing chamber washes out gradually: the pad pushes
//! the layer's first designed composition until every part of the chamber (and so what
//! leaves the nozzle) is within the purge tolerance of it, as the model predicts.

use crate::mixer::{Mixer, MixerOptions};

/// The longest washout, in chamber volumes (e^(−20) ≈ 2·10⁻⁹ of a well-mixed
/// chamber's difference is left: any tolerance above that is reached before).
pub const MAX_WASHOUT_VOLUMES: f64 = 20.0;

/// Steps per chamber volume the washout is searched in (the purge volume is a whole
/// number of these).
const STEPS_PER_VOLUME: f64 = 32.0;

/// Whether every part of `chamber` is within `tolerance` of `composition` (largest
/// per-material difference).
pub fn holds(chamber: &Mixer, composition: &[f64], tolerance: f64) -> bool {
    chamber
        .contents()
        .iter()
        .filter(|(v, _)| *v > 0.0)
        .all(|(_, c)| crate::material::max_fraction_difference(c, composition) <= tolerance)
}

/// The volume (nl) of `composition` to push into `chamber` (a chamber `options`) so
/// that it holds `composition` within `tolerance`: 0 when it already does, at most
/// [`MAX_WASHOUT_VOLUMES`] chamber volumes.
pub fn washout_nl(
    chamber: &Mixer,
    options: &MixerOptions,
    composition: &[f64],
    tolerance: f64,
) -> f64 {
    if options.volume_nl <= 0.0 || holds(chamber, composition, tolerance) {
        return 0.0;
    }
    let step = options.volume_nl / STEPS_PER_VOLUME;
    let steps = (MAX_WASHOUT_VOLUMES * STEPS_PER_VOLUME) as usize;
    let mut m = chamber.clone();
    for k in 1..=steps {
        m.push(step, composition);
        if holds(&m, composition, tolerance) {
            return k as f64 * step;
        }
    }
    steps as f64 * step
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A well-mixed chamber full of A, purged with B to within 0.02: e^(−v/V) ≤ 0.02,
    /// v = V·ln 50 ≈ 3.91 V, rounded up to a step of V/32; after it, what leaves the
    /// nozzle is within the tolerance.
    #[test]
    fn a_well_mixed_chamber_is_washed_out_for_its_exponential() {
        let o = MixerOptions::new("mixed", 1000.0, None).unwrap();
        let m = Mixer::new(&o, &[1.0, 0.0]);
        let v = washout_nl(&m, &o, &[0.0, 1.0], 0.02);
        let exact = 1000.0 * 50f64.ln();
        assert!(v >= exact && v < exact + 1000.0 / 32.0, "{v} vs {exact}");
        let mut after = m.clone();
        after.push(v, &[0.0, 1.0]);
        let exit = after.push(1e-6, &[0.0, 1.0]).unwrap();
        assert!((exit[1] - 1.0).abs() <= 0.02, "{exit:?}");
        // Already holding it: no purge; a plug chamber needs exactly V.
        assert_eq!(washout_nl(&after, &o, &[0.0, 1.0], 0.02), 0.0);
        let p = MixerOptions::plug(1000.0);
        assert_eq!(
            washout_nl(&Mixer::new(&p, &[1.0, 0.0]), &p, &[0.0, 1.0], 0.02),
            1000.0
        );
        // A tolerance of 0 stops at the cap.
        assert_eq!(washout_nl(&m, &o, &[0.0, 1.0], 0.0), 20_000.0);
    }

    /// A dispersing chamber washes out in less than a well-mixed one of the same volume
    /// and more than a plug one; the exit after the purge is within the tolerance.
    #[test]
    fn a_dispersing_chamber_washes_out_between_plug_and_mixed() {
        let o = MixerOptions::new("dispersion", 1000.0, Some(10.0)).unwrap();
        let m = Mixer::new(&o, &[0.2, 0.8]);
        let v = washout_nl(&m, &o, &[0.9, 0.1], 0.01);
        assert!(v > 1000.0 && v < 1000.0 * 100f64.ln(), "{v}");
        let mut after = m.clone();
        after.push(v, &[0.9, 0.1]);
        let exit = after.push(1e-6, &[0.9, 0.1]).unwrap();
        assert!((exit[0] - 0.9).abs() <= 0.01, "{exit:?}");
        let mut short = m.clone();
        short.push(v - 1000.0 / 32.0, &[0.9, 0.1]);
        assert!(!holds(&short, &[0.9, 0.1], 0.01));
    }
}
