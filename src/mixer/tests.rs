use super::*;

/// Today's plug-flow chamber of the pipeline, as it was before mixer models: the
/// reference the plug model must match number for number.
fn reference_plug(chamber: &mut VecDeque<(f64, Vec<f64>)>, v: f64, c: &[f64]) -> Vec<f64> {
    chamber.push_back((v, c.to_vec()));
    let mut need = v;
    let mut out = vec![0.0; c.len()];
    while need > 1e-12 {
        let Some(front) = chamber.front_mut() else {
            break;
        };
        let take = front.0.min(need);
        for (o, x) in out.iter_mut().zip(&front.1) {
            *o += take * x;
        }
        front.0 -= take;
        need -= take;
        if front.0 <= 1e-12 {
            chamber.pop_front();
        }
    }
    out.iter().map(|x| x / v).collect()
}

fn opts(model: &str, volume_nl: f64, peclet: Option<f64>) -> MixerOptions {
    MixerOptions::new(model, volume_nl, peclet).unwrap()
}

/// Per-material volume in the chamber, nl.
fn held(m: &Mixer, n: usize) -> Vec<f64> {
    let mut out = vec![0.0; n];
    for (v, c) in m.contents() {
        for (o, x) in out.iter_mut().zip(&c) {
            *o += v * x;
        }
    }
    out
}

/// The step response from pure A to pure B in pushes of `dv`: the mean of B in the
/// outflow over each push, up to `until` nl.
fn step_response(o: &MixerOptions, dv: f64, until: f64) -> Vec<f64> {
    let mut m = Mixer::new(o, &[1.0, 0.0]);
    let n = (until / dv).round() as usize;
    (0..n)
        .map(|_| m.push(dv, &[0.0, 1.0]).unwrap()[1])
        .collect()
}

/// Mean and variance of the residence volume from a step response of pushes of `dv`:
/// mean = ∫(1 − F), E[v²] = 2∫v(1 − F) (midpoints).
fn moments(f: &[f64], dv: f64) -> (f64, f64) {
    let mut mean = 0.0;
    let mut second = 0.0;
    for (i, x) in f.iter().enumerate() {
        let mid = (i as f64 + 0.5) * dv;
        mean += (1.0 - x) * dv;
        second += 2.0 * mid * (1.0 - x) * dv;
    }
    (mean, second - mean * mean)
}

#[test]
fn plug_flow_is_the_planners_lead_number_for_number() {
    let o = MixerOptions::plug(1234.5);
    let mut m = Mixer::new(&o, &[0.3, 0.7]);
    let mut reference = VecDeque::from([(1234.5, vec![0.3, 0.7])]);
    let mut seed = 7u64;
    for _ in 0..500 {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let v = 1.0 + (seed >> 40) as f64 / (1u64 << 24) as f64 * 300.0;
        let a = (seed >> 20 & 0xffff) as f64 / 65535.0;
        let c = [a, 1.0 - a];
        assert_eq!(m.push(v, &c), Some(reference_plug(&mut reference, v, &c)));
    }
    // hil-sim's cases: 1000 nl of B push out the initial A.
    let mut m = Mixer::new(&MixerOptions::plug(1000.0), &[1.0, 0.0]);
    for _ in 0..10 {
        assert_eq!(m.push(100.0, &[0.0, 1.0]), Some(vec![1.0, 0.0]));
    }
    assert_eq!(m.push(100.0, &[0.0, 1.0]), Some(vec![0.0, 1.0]));
    let mut m = Mixer::new(&MixerOptions::plug(100.0), &[1.0, 0.0]);
    assert_eq!(m.push(200.0, &[0.0, 1.0]), Some(vec![0.5, 0.5]));
    assert_eq!(m.push(0.0, &[0.0, 1.0]), None);
    // No chamber: what goes in comes out at once.
    let mut m = Mixer::new(&MixerOptions::plug(0.0), &[1.0, 0.0]);
    assert!(m.is_empty());
    assert_eq!(m.push(5.0, &[0.25, 0.75]), Some(vec![0.25, 0.75]));
}

#[test]
fn a_well_mixed_chamber_washes_out_exponentially() {
    let volume = 800.0;
    let o = opts("mixed", volume, None);
    assert_eq!(o.residence_moments(), (800.0, 640_000.0));
    let mut m = Mixer::new(&o, &[1.0, 0.0]);
    let mut at = 0.0;
    for k in 0..200 {
        let dv = 10.0 + (k % 7) as f64 * 13.0;
        let out = m.push(dv, &[0.0, 1.0]).unwrap();
        // Mean of e^(−v/V) over [at, at + dv].
        let a = volume / dv * ((-at / volume).exp() - (-(at + dv) / volume).exp());
        assert!((out[0] - a).abs() < 1e-12, "{k}: {} vs {a}", out[0]);
        assert!((out[0] + out[1] - 1.0).abs() < 1e-12);
        at += dv;
    }
}

#[test]
fn dispersion_has_the_closed_closed_models_mean_and_variance() {
    let volume = 1000.0;
    for pe in [0.2, 2.0, 8.0, 40.0, 400.0] {
        let o = opts("dispersion", volume, Some(pe));
        let s2 = 2.0 / pe - 2.0 / (pe * pe) * (1.0 - (-pe).exp());
        let (mean, var) = o.residence_moments();
        assert!((var - s2 * volume * volume).abs() < 1e-6 * volume * volume);
        let f = step_response(&o, 1.0, 25.0 * volume);
        let (m, v) = moments(&f, 1.0);
        assert!((m - mean).abs() < 1e-6 * volume, "Pe {pe}: mean {m}");
        assert!(
            (v - var).abs() < 1e-3 * volume * volume * s2.max(0.01),
            "Pe {pe}: variance {v}, closed form {var}"
        );
    }
    // Large Pe tends to plug flow, small to one well-mixed tank.
    assert!(dispersion_variance(1e6) < 3e-6);
    assert!((dispersion_variance(1e-6) - 1.0).abs() < 1e-6);
}

#[test]
fn how_a_volume_is_split_into_pushes_does_not_matter() {
    let o = opts("dispersion", 500.0, Some(12.0));
    let mut one = Mixer::new(&o, &[1.0, 0.0, 0.0]);
    let mut many = one.clone();
    let c = [0.2, 0.5, 0.3];
    let whole = one.push(90.0, &c).unwrap();
    let mut sum = [0.0; 3];
    for _ in 0..9 {
        for (s, x) in sum.iter_mut().zip(many.push(10.0, &c).unwrap()) {
            *s += 10.0 * x;
        }
    }
    for (w, s) in whole.iter().zip(sum) {
        assert!((w * 90.0 - s).abs() < 1e-9);
    }
    for ((_, a), (_, b)) in one.contents().iter().zip(many.contents()) {
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-12));
    }
}

#[test]
fn bad_settings_are_refused_naming_the_key() {
    for (model, v, pe, key) in [
        ("plug", -1.0, None, "volume_nl"),
        ("mixed", f64::NAN, None, "volume_nl"),
        ("mixed", f64::INFINITY, None, "volume_nl"),
        ("dispersion", 100.0, Some(0.0), "peclet"),
        ("dispersion", 100.0, Some(-3.0), "peclet"),
        ("dispersion", 100.0, Some(f64::NAN), "peclet"),
        ("dispersion", 100.0, None, "peclet"),
        ("plug", 100.0, Some(5.0), "peclet"),
        ("turbulent", 100.0, None, "model"),
    ] {
        let e = MixerOptions::new(model, v, pe).unwrap_err();
        assert_eq!(e.key, key, "{model} {v} {pe:?}: {e}");
        assert!(e.to_string().starts_with(key));
    }
}

proptest::proptest! {
    /// What goes in comes out or stays in the chamber.
    #[test]
    fn mass_is_conserved(
        model in 0usize..3,
        volume in 0.0f64..5000.0,
        pe in 0.05f64..500.0,
        pushes in proptest::collection::vec((0.0f64..2000.0, 0.0f64..1.0), 1..60),
    ) {
        let o = match model {
            0 => opts("plug", volume, None),
            1 => opts("mixed", volume, None),
            _ => opts("dispersion", volume, Some(pe)),
        };
        let mut m = Mixer::new(&o, &[0.5, 0.5]);
        let before = held(&m, 2);
        let total: f64 = m.contents().iter().map(|c| c.0).sum();
        proptest::prop_assert!((total - volume).abs() < 1e-9 * volume.max(1.0));
        let (mut pushed, mut left) = ([0.0; 2], [0.0; 2]);
        for (v, a) in pushes {
            let c = [a, 1.0 - a];
            if let Some(out) = m.push(v, &c) {
                for k in 0..2 {
                    pushed[k] += v * c[k];
                    left[k] += v * out[k];
                }
            }
        }
        let after = held(&m, 2);
        for k in 0..2 {
            let balance = before[k] + pushed[k] - left[k] - after[k];
            let scale = 1.0 + pushed[k] + before[k];
            proptest::prop_assert!(balance.abs() < 1e-9 * scale, "material {}: {}", k, balance);
        }
    }
}
