//! The machine model: axes, syringes (capacity, barrel area, remaining volume) and the
//! mixing chamber of dead volume V_dead through which composition reaches the nozzle exit
//! by plug flow (first in, first out).

use std::collections::VecDeque;

use edo::link::FaultKind;
use edo::machine::{Move, MoveKind, PositionUm};

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

/// The mixing chamber: a plug-flow column of `dead_volume_nl`. Every nanolitre pushed in
/// pushes the oldest nanolitre out at the nozzle.
#[derive(Debug, Clone, PartialEq)]
pub struct MixingChamber {
    dead_volume_nl: u64,
    /// Slices from nozzle (front) to inlet (back): (volume nl, composition).
    slices: VecDeque<(u64, Vec<f64>)>,
}

impl MixingChamber {
    /// A chamber full of `initial` composition.
    pub fn new(dead_volume_nl: u64, initial: Vec<f64>) -> Self {
        let mut slices = VecDeque::new();
        if dead_volume_nl > 0 {
            slices.push_back((dead_volume_nl, initial));
        }
        Self {
            dead_volume_nl,
            slices,
        }
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
        if self.dead_volume_nl == 0 {
            return Some(inflow);
        }
        self.slices.push_back((total, inflow));
        // Take `total` nl from the front.
        let mut need = total;
        let mut out = vec![0.0; volumes_nl.len()];
        while need > 0 {
            let Some(front) = self.slices.front_mut() else {
                break;
            };
            let take = front.0.min(need);
            for (o, c) in out.iter_mut().zip(&front.1) {
                *o += c * take as f64;
            }
            front.0 -= take;
            need -= take;
            if front.0 == 0 {
                self.slices.pop_front();
            }
        }
        for o in &mut out {
            *o /= total as f64;
        }
        Some(out)
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
    /// `n` syringes of `capacity_nl` each with `barrel_area_um2`, chamber of `dead_nl`
    /// primed with syringe 0's material.
    pub fn new(n: usize, capacity_nl: u32, barrel_area_um2: u32, dead_nl: u64) -> Self {
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
            chamber: MixingChamber::new(dead_nl, initial),
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
            MoveKind::Travel { to, feed_um_s } => {
                self.position = *to;
                motion_us(from, *to, *feed_um_s)
            }
            MoveKind::Extrude {
                to,
                feed_um_s,
                volumes_nl,
                ..
            } => {
                self.dispense(volumes_nl)?;
                let mut padded = volumes_nl.clone();
                padded.resize(self.syringes.len(), 0);
                exit_composition = self.chamber.push(&padded);
                self.position = *to;
                motion_us(from, *to, *feed_um_s)
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
                motion_us(from, PositionUm::default(), 50_000)
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

fn motion_us(from: PositionUm, to: PositionUm, feed_um_s: u32) -> u64 {
    let d = |a: i32, b: i32| (f64::from(a) - f64::from(b)).powi(2);
    let len_um = (d(from.x_um, to.x_um) + d(from.y_um, to.y_um) + d(from.z_um, to.z_um)).sqrt();
    if feed_um_s == 0 {
        return 0;
    }
    (len_um / f64::from(feed_um_s) * 1e6) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plug_flow_delays_composition_by_dead_volume() {
        let mut c = MixingChamber::new(1000, vec![1.0, 0.0]);
        // First 1000 nl of pure B push out the initial A.
        for _ in 0..10 {
            assert_eq!(c.push(&[0, 100]), Some(vec![1.0, 0.0]));
        }
        assert_eq!(c.push(&[0, 100]), Some(vec![0.0, 1.0]));
        // Half-and-half straddling.
        let mut c = MixingChamber::new(100, vec![1.0, 0.0]);
        assert_eq!(c.push(&[0, 200]), Some(vec![0.5, 0.5]));
        assert_eq!(c.push(&[0, 0]), None);
    }

    #[test]
    fn moves_take_length_over_feed_and_empty_syringes_fault() {
        let mut m = MachineModel::new(2, 1000, 1, 0);
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
