//! The pipeline on the example jobs: planned layers become a valid, contiguous move stream
//! whose per-syringe volumes equal the plan's.

use edo::edo::plan_layers;
use edo::job::Job;
use edo::machine::MoveKind;
use edo::pipeline::{layer_moves, ProcessSettings, StreamState};

fn job(name: &str) -> Job {
    let path = format!("{}/config/examples/{name}.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap();
    Job::from_toml(&text, &path).unwrap()
}

#[test]
fn example_jobs_become_exact_move_streams() {
    for name in ["paper-annulus", "tooth-crown", "fibers", "non-star"] {
        let job = job(name);
        let slices = job.layer_slices();
        let layers = plan_layers(&slices[..slices.len().min(2)], &job.design, &job.plan).unwrap();
        let settings = ProcessSettings::for_nozzle(job.plan.nozzle_mm);
        let mut state = StreamState::new();
        let mut index = 0;
        let n = job.materials.len();
        let mut sums = vec![0u64; n];
        let mut marks = 0;
        for layer in &layers {
            let out = layer_moves(layer, &settings, 7, index, &mut state).unwrap();
            assert!(out.stats.paths > 0, "{name}");
            for m in &out.moves {
                assert_eq!(m.index, index, "{name}: indices contiguous");
                assert_eq!(m.job_id, 7);
                m.validate(n).unwrap();
                index += 1;
                match &m.kind {
                    MoveKind::Extrude { volumes_nl, .. } => {
                        assert_eq!(volumes_nl.len(), n);
                        for (s, v) in sums.iter_mut().zip(volumes_nl) {
                            *s += u64::from(*v);
                        }
                    }
                    MoveKind::LayerMark { .. } => marks += 1,
                    _ => {}
                }
            }
            assert_eq!(out.next_index, index);
            // Every retract is primed back before the next extrusion.
            let mut retracted = false;
            for m in &out.moves {
                match &m.kind {
                    MoveKind::Retract { .. } => {
                        assert!(!retracted);
                        retracted = true
                    }
                    MoveKind::Prime { .. } => retracted = false,
                    MoveKind::Extrude { .. } => {
                        assert!(!retracted, "{name}: extrude while retracted")
                    }
                    _ => {}
                }
            }
        }
        assert_eq!(marks, layers.len());
        assert_eq!(sums, state.commanded_nl(), "{name}");
        for (c, p) in state.commanded_nl().iter().zip(state.planned_nl()) {
            assert!((*c as f64 - p).abs() <= 0.5 + 1e-6, "{name}: {c} vs {p}");
        }
        let total: f64 = state.planned_nl().iter().sum();
        assert!(total > 0.0);
    }
}
