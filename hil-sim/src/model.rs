//! The machine model: axes, syringes (capacity, barrel area, remaining volume) and the
//! mixing chamber of volume V_dead through which composition reaches the nozzle exit (plug
//! flow, first in first out, or another of [`edo::mixer`]'s models).

use edo::link::FaultKind;
use edo::machine::{Move, MoveKind, PositionUm};
use edo::mixer::{Mixer, MixerOptions};

/// One syringe.
#[derive(Debug, Clone, PartialEq)]
pub struct Syringe {
    /// Capacity (nl).
    pub capacity_nl: u32,
    /// Barrel cross-section (µm²).
    pub barrel_area_um2: u32,
    /// Volume left (nl).
    pub remaining_nl: u32,
}

/// The mixing chamber: [`edo::mixer::Mixer`] (plug flow through V_dead unless hil-sim
/// is started with another `--mixer`), pushed with every extrusion move's volumes.
#[derive(Debug, Clone, PartialEq)]
pub struct MixingChamber {
    mixer: Mixer,
}

impl MixingChamber {
    /// A chamber described by `options`, full of `initial` composition.
    pub fn new(options: &MixerOptions, initial: Vec<f64>) -> Self {
        Self {
            mixer: Mixer::new(options, &initial),
        }
    }

    /// The chamber's state (what it holds).
    pub fn mixer(&self) -> &Mixer {
        &self.mixer
    }

    /// Push per-syringe volumes in; returns the volume-weighted composition of what left
    /// the nozzle (`None` when nothing was pushed).
    pub fn push(&mut self, volumes_nl: &[u32]) -> Option<Vec<f64>> {
        let total: u64 = volumes_nl.iter().map(|&v| u64::from(v)).sum();
        if total == 0 {
            return None;
        }
        let inflow: Vec<f64> = volumes_nl
            .iter()
            .map(|&v| v as f64 / total as f64)
            .collect();
        self.mixer.push(total as f64, &inflow)
    }
}

/// What executing one move did.
#[derive(Debug, Clone, PartialEq)]
pub struct Executed {
    /// Position before.
    pub from: PositionUm,
    /// Position after.
    pub to: PositionUm,
    /// Machine time the move took (µs, before the speed-up).
    pub duration_us: u64,
    /// Composition at the nozzle exit during the move (extrusion only).
    pub exit_composition: Option<Vec<f64>>,
    /// Layer number of the last layer mark.
    pub layer: u32,
}

/// The machine model.
#[derive(Debug, Clone, PartialEq)]
pub struct MachineModel {
    /// Current position.
    pub position: PositionUm,
    /// Syringes.
    pub syringes: Vec<Syringe>,
    /// Mixing chamber.
    pub chamber: MixingChamber,
    /// Current layer (from the last layer mark).
    pub layer: u32,
}

impl MachineModel {
    /// `n` syringes of `capacity_nl` each with `barrel_area_um2`, a chamber described by
    /// `mixer` primed with syringe 0's material.
    pub fn new(n: usize, capacity_nl: u32, barrel_area_um2: u32, mixer: &MixerOptions) -> Self {
        let mut initial = vec![0.0; n];
        if let Some(first) = initial.first_mut() {
            *first = 1.0;
        }
        Self {
            position: PositionUm::default(),
            syringes: vec![
                Syringe {
                    capacity_nl,
                    barrel_area_um2,
                    remaining_nl: capacity_nl,
                };
                n
            ],
            chamber: MixingChamber::new(mixer, initial),
            layer: 0,
        }
    }

    /// Remaining volume per syringe.
    pub fn remaining_nl(&self) -> Vec<u32> {
        self.syringes.iter().map(|s| s.remaining_nl).collect()
    }

    /// Execute a move, or refuse it with the fault that stops the machine.
    pub fn execute(&mut self, mv: &Move) -> Result<Executed, FaultKind> {
        let from = self.position;
        let mut exit_composition = None;
        let duration_us = match &mv.kind {
            MoveKind::Travel { to, .. } => {
                self.position = *to;
                mv.kind.run_time_us(Some(from)).unwrap_or(0)
            }
            MoveKind::Extrude { to, volumes_nl, .. } => {
                self.dispense(volumes_nl)?;
                let mut padded = volumes_nl.clone();
                padded.resize(self.syringes.len(), 0);
                exit_composition = self.chamber.push(&padded);
                self.position = *to;
                mv.kind.run_time_us(Some(from)).unwrap_or(0)
            }
            MoveKind::Prime {
                volumes_nl,
                duration_ms,
            } => {
                self.dispense(volumes_nl)?;
                u64::from(*duration_ms) * 1000
            }
            MoveKind::Retract {
                volumes_nl,
                duration_ms,
            } => {
                for (s, &v) in self.syringes.iter_mut().zip(volumes_nl) {
                    s.remaining_nl = s.remaining_nl.saturating_add(v).min(s.capacity_nl);
                }
                u64::from(*duration_ms) * 1000
            }
            MoveKind::Dwell { duration_ms } => u64::from(*duration_ms) * 1000,
            MoveKind::LayerMark { layer, .. } => {
                self.layer = *layer;
                0
            }
            MoveKind::Home => {
                self.position = PositionUm::default();
                // Homing as a travel to the origin at 50 mm/s.
                let to_origin = MoveKind::Travel {
                    to: PositionUm::default(),
                    feed_um_s: 50_000,
                };
                to_origin.run_time_us(Some(from)).unwrap_or(0)
            }
        };
        Ok(Executed {
            from,
            to: self.position,
            duration_us,
            exit_composition,
            layer: self.layer,
        })
    }

    fn dispense(&mut self, volumes_nl: &[u32]) -> Result<(), FaultKind> {
        for (i, (s, &v)) in self.syringes.iter().zip(volumes_nl).enumerate() {
            if s.remaining_nl < v {
                return Err(FaultKind::SyringeEmpty(i as u8));
            }
        }
        for (s, &v) in self.syringes.iter_mut().zip(volumes_nl) {
            s.remaining_nl -= v;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plug_flow_delays_composition_by_dead_volume() {
        let mut c = MixingChamber::new(&MixerOptions::plug(1000.0), vec![1.0, 0.0]);
        // First 1000 nl of pure B push out the initial A.
        for _ in 0..10 {
            assert_eq!(c.push(&[0, 100]), Some(vec![1.0, 0.0]));
        }
        assert_eq!(c.push(&[0, 100]), Some(vec![0.0, 1.0]));
        // Half-and-half straddling.
        let mut c = MixingChamber::new(&MixerOptions::plug(100.0), vec![1.0, 0.0]);
        assert_eq!(c.push(&[0, 200]), Some(vec![0.5, 0.5]));
        assert_eq!(c.push(&[0, 0]), None);
    }

    #[test]
    fn a_well_mixed_chamber_records_an_exponential_washout() {
        let mixed = MixerOptions::new("mixed", 1000.0, None).unwrap();
        let mut m = MachineModel::new(2, 1_000_000, 1, &mixed);
        for k in 0..20u32 {
            let mv = Move {
                job_id: 1,
                index: k,
                kind: MoveKind::Extrude {
                    to: PositionUm::default(),
                    feed_um_s: 10_000,
                    volumes_nl: vec![0, 100],
                    width_factor_ppt: 1000,
                },
            };
            let exit = m.execute(&mv).unwrap().exit_composition.unwrap();
            let v0 = f64::from(k) * 100.0;
            let a = 1000.0 / 100.0 * ((-v0 / 1000.0).exp() - (-(v0 + 100.0) / 1000.0).exp());
            assert!((exit[0] - a).abs() < 1e-12, "{k}: {exit:?}");
        }
    }

    #[test]
    fn moves_take_length_over_feed_and_empty_syringes_fault() {
        let mut m = MachineModel::new(2, 1000, 1, &MixerOptions::plug(0.0));
        let mv = Move {
            job_id: 1,
            index: 0,
            kind: MoveKind::Extrude {
                to: PositionUm {
                    x_um: 30_000,
                    y_um: 40_000,
                    z_um: 0,
                },
                feed_um_s: 10_000,
                volumes_nl: vec![600, 0],
                width_factor_ppt: 1000,
            },
        };
        let e = m.execute(&mv).unwrap();
        assert_eq!(e.duration_us, 5_000_000);
        assert_eq!(e.exit_composition, Some(vec![1.0, 0.0]));
        assert_eq!(m.execute(&mv), Err(FaultKind::SyringeEmpty(0)));
    }
}
