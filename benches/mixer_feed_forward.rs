//! Cost of the mixer's feed-forward (issue 34): the tooth crown's layers (all four)
//! turned into moves through a mixing chamber with the feed-forward on and off, and
//! the same layers planned (`plan_layers`) for scale. The feed-forward's cost per layer
//! is (on − off) / layers. Figures and how they were taken: `benches/README.md`.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::job::Job;
use edo::mixer::MixerModel;
use edo::pipeline::{layer_moves, ProcessSettings, StreamState};
use edo::plan::{plan_layers, LayerPlan};
use std::hint::black_box;

const CROWN: &str = include_str!("../config/examples/tooth-crown.toml");

/// The crown's layers, planned.
fn crown() -> (Job, Vec<LayerPlan>) {
    let job = Job::from_toml(CROWN, "tooth-crown.toml").expect("the bundled crown");
    let stack = job.extruded_layers().expect("the crown's layers");
    let slices = job.layer_slices(0, stack);
    let layers = plan_layers(&slices, &job.plan, None).expect("the crown plans");
    (job, layers)
}

/// Every layer to moves in order, as edod streams them.
fn all_layers(layers: &[LayerPlan], s: &ProcessSettings) -> usize {
    let mut state = StreamState::new();
    let mut next = 0;
    for l in layers {
        let out = layer_moves(l, s, 1, next, &mut state).expect("moves");
        next = out.next_index;
    }
    next as usize
}

fn bench(c: &mut Criterion) {
    let (job, layers) = crown();
    let slices = job.layer_slices(0, job.extruded_layers().expect("layers"));
    c.bench_function("mixer/crown_plan_layers", |b| {
        b.iter(|| plan_layers(black_box(&slices), &job.plan, None).expect("plans"))
    });
    for (name, model, volume_ul, peclet) in [
        ("mixed_250nl", MixerModel::Mixed, 0.25, None),
        ("mixed_1000nl", MixerModel::Mixed, 1.0, None),
        (
            "dispersion_1000nl_pe40",
            MixerModel::Dispersion,
            1.0,
            Some(40.0),
        ),
    ] {
        for feed_forward in [false, true] {
            let mut s = ProcessSettings::for_nozzle(job.plan.nozzle_mm);
            s.v_dead_ul = volume_ul;
            s.mixer_model = model;
            s.mixer_peclet = peclet;
            s.mixer_feed_forward = feed_forward;
            let moves = all_layers(&layers, &s);
            eprintln!(
                "crown {name}: {} layers, {moves} moves, feed-forward {feed_forward}",
                layers.len()
            );
            let id = format!(
                "mixer/crown_moves_{name}_ff_{}",
                if feed_forward { "on" } else { "off" }
            );
            c.bench_function(&id, |b| b.iter(|| all_layers(black_box(&layers), &s)));
        }
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);
