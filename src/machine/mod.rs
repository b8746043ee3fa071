//! The move stream: the one definition of what the host sends the machine.
//!
//! Planning works in millimetres and `f64` compositions; the wire works in fixed point so
//! that host, machine and simulator agree to the last unit:
//!
//! - positions in micrometres (`_um`, `i32`), feed rates in micrometres per second (`_um_s`),
//! - volumes in nanolitres (`_nl`, `u32` per move and syringe),
//! - mixing ratios in parts of 65535 that sum to exactly 65535 ([`ratios_from_fractions`]),
//! - durations in milliseconds (`_ms`).
//!
//! Per-syringe volumes of one move are split from a total with [`split_volume_nl`] (largest
//! remainder), so the sum over syringes equals the planned total exactly, and cumulative
//! per-syringe volumes never drift from the plan by more than rounding of one move.
//!
//! Every [`Move`] carries its job id and its index within the job; the machine reports the
//! last one it executed, so a restarted host learns exactly where the machine is.
//! A move with [`MAX_SYRINGES`] syringes encodes (postcard) to at most [`MAX_MOVE_BYTES`]
//! bytes, well inside one link frame (see `docs/protocol.md`).

pub mod record;
mod report;
pub mod time;

pub use report::{MachineReport, MachineState, MoveRef};

use serde::{Deserialize, Serialize};

/// Most syringes (primary materials) a machine may have.
pub const MAX_SYRINGES: usize = 8;

/// Sum of a ratio vector: ratios are parts of 65535.
pub const RATIO_ONE: u16 = u16::MAX;

/// Upper bound of the postcard encoding of one [`Move`] with [`MAX_SYRINGES`] syringes
/// (every varint at its widest). Checked by a unit test.
pub const MAX_MOVE_BYTES: usize = 96;

/// Nominal width or flow factor (parts per thousand): 1000 = the planned nominal bead.
pub const FACTOR_NOMINAL_PPT: u16 = 1000;

/// A move of a job, addressed by job id and index within the job.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Move {
    /// Job the move belongs to (assigned by the host's job store).
    pub job_id: u32,
    /// Index of the move within its job, counting from 0 without gaps.
    pub index: u32,
    /// What to do.
    pub kind: MoveKind,
}

/// A machine position in micrometres (absolute, machine coordinates).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct PositionUm {
    /// X in µm.
    pub x_um: i32,
    /// Y in µm.
    pub y_um: i32,
    /// Z in µm.
    pub z_um: i32,
}

/// What a move does. Volumes are per syringe, index = syringe number.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum MoveKind {
    /// Move to `to` without extruding.
    Travel {
        /// Target position.
        to: PositionUm,
        /// Feed rate in µm/s.
        feed_um_s: u32,
    },
    /// Move to `to` while the syringes push `volumes_nl` into the mixing chamber.
    Extrude {
        /// Target position.
        to: PositionUm,
        /// Feed rate in µm/s.
        feed_um_s: u32,
        /// Volume each syringe dispenses during the move (nl).
        volumes_nl: Vec<u32>,
        /// Bead width relative to nominal, parts per thousand (1000 = nominal); the volumes
        /// already include it, the machine may use it for pressure advance or logging.
        width_factor_ppt: u16,
    },
    /// Pull the plungers back by `volumes_nl` (extrusion cessation), in place.
    Retract {
        /// Volume each syringe withdraws (nl).
        volumes_nl: Vec<u32>,
        /// Plunger rate as a duration for the whole retract (ms).
        duration_ms: u32,
    },
    /// Push the plungers forward by `volumes_nl` to re-pressurise after a retract, in place.
    Prime {
        /// Volume each syringe dispenses (nl).
        volumes_nl: Vec<u32>,
        /// Duration of the prime (ms).
        duration_ms: u32,
    },
    /// Wait in place.
    Dwell {
        /// Duration (ms).
        duration_ms: u32,
    },
    /// Start of a layer: no motion, marks the layer boundary in the machine's reports and
    /// the simulator's recorder.
    LayerMark {
        /// Layer number within the job.
        layer: u32,
        /// Layer height (top of the layer) in µm.
        z_um: i32,
    },
    /// Home all axes (position becomes the origin).
    Home,
}

impl MoveKind {
    /// How long the move runs, µs: a motion from `from` at its feed (acceleration left
    /// out), a retract, prime or dwell its duration; `None` for a motion whose start is
    /// not known, a zero feed and a home (its length depends on where the axes stand).
    pub fn run_time_us(&self, from: Option<PositionUm>) -> Option<u64> {
        match self {
            MoveKind::Travel { to, feed_um_s } | MoveKind::Extrude { to, feed_um_s, .. } => {
                let from = from?;
                if *feed_um_s == 0 {
                    return None;
                }
                let d = |a: i32, b: i32| f64::from(b) - f64::from(a);
                let len_um = (d(from.x_um, to.x_um).powi(2)
                    + d(from.y_um, to.y_um).powi(2)
                    + d(from.z_um, to.z_um).powi(2))
                .sqrt();
                Some((len_um / f64::from(*feed_um_s) * 1e6).ceil() as u64)
            }
            MoveKind::Retract { duration_ms, .. }
            | MoveKind::Prime { duration_ms, .. }
            | MoveKind::Dwell { duration_ms } => Some(u64::from(*duration_ms) * 1000),
            MoveKind::LayerMark { .. } => Some(0),
            MoveKind::Home => None,
        }
    }

    /// Per-syringe volumes carried by the move (empty for moves without volumes).
    pub fn volumes_nl(&self) -> &[u32] {
        match self {
            MoveKind::Extrude { volumes_nl, .. }
            | MoveKind::Retract { volumes_nl, .. }
            | MoveKind::Prime { volumes_nl, .. } => volumes_nl,
            _ => &[],
        }
    }
}

/// A move the machine cannot take.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MoveError {
    /// More syringe volumes than the machine has syringes.
    #[error("move {job_id}/{index}: {given} syringe volumes but the machine has {syringes}")]
    TooManySyringes {
        /// Job id of the move.
        job_id: u32,
        /// Index of the move.
        index: u32,
        /// Volumes given.
        given: usize,
        /// Syringes present.
        syringes: usize,
    },
    /// A feed rate of zero on a move with motion.
    #[error("move {job_id}/{index}: feed rate is zero")]
    ZeroFeed {
        /// Job id of the move.
        job_id: u32,
        /// Index of the move.
        index: u32,
    },
}

impl Move {
    /// Check the move against a machine with `syringes` syringes.
    pub fn validate(&self, syringes: usize) -> Result<(), MoveError> {
        let given = self.kind.volumes_nl().len();
        if given > syringes.min(MAX_SYRINGES) {
            return Err(MoveError::TooManySyringes {
                job_id: self.job_id,
                index: self.index,
                given,
                syringes,
            });
        }
        if let MoveKind::Travel { feed_um_s: 0, .. } | MoveKind::Extrude { feed_um_s: 0, .. } =
            self.kind
        {
            return Err(MoveError::ZeroFeed {
                job_id: self.job_id,
                index: self.index,
            });
        }
        Ok(())
    }
}

/// Fractions that cannot be turned into ratios.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RatioError {
    /// No fractions.
    #[error("no fractions given")]
    Empty,
    /// More than [`MAX_SYRINGES`] fractions.
    #[error("{0} fractions given, at most {MAX_SYRINGES} syringes")]
    TooMany(usize),
    /// A fraction is negative, NaN or infinite.
    #[error("fraction {index} is {value}: must be finite and >= 0")]
    Invalid {
        /// Position of the bad fraction.
        index: usize,
        /// Its value.
        value: f64,
    },
    /// All fractions are zero.
    #[error("fractions sum to zero")]
    ZeroSum,
}

/// Largest-remainder apportionment of the integer `total` over non-negative `weights`
/// (which need not be normalised): results sum to exactly `total`; each differs from its
/// exact share by less than 1. Ties go to the lower index, so the result is deterministic.
fn apportion(total: u64, weights: &[f64]) -> Vec<u64> {
    let sum: f64 = weights.iter().sum();
    let mut out = Vec::with_capacity(weights.len());
    let mut rema = Vec::with_capacity(weights.len());
    let mut given: u64 = 0;
    for (i, w) in weights.iter().enumerate() {
        let exact = if sum > 0.0 {
            total as f64 * (w / sum)
        } else {
            0.0
        };
        let floor = exact.floor().max(0.0) as u64;
        let floor = floor.min(total - given);
        given += floor;
        out.push(floor);
        rema.push((exact - floor as f64, i));
    }
    // Hand out what is left, one unit each, biggest remainder first.
    rema.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut left = total - given;
    let mut k = 0;
    while left > 0 && !rema.is_empty() {
        out[rema[k % rema.len()].1] += 1;
        left -= 1;
        k += 1;
    }
    out
}

/// Composition fractions (one per syringe, any positive scale) to wire ratios in parts of
/// 65535 that sum to exactly 65535, by largest remainder.
pub fn ratios_from_fractions(fractions: &[f64]) -> Result<Vec<u16>, RatioError> {
    if fractions.is_empty() {
        return Err(RatioError::Empty);
    }
    if fractions.len() > MAX_SYRINGES {
        return Err(RatioError::TooMany(fractions.len()));
    }
    for (index, &value) in fractions.iter().enumerate() {
        if !value.is_finite() || value < 0.0 {
            return Err(RatioError::Invalid { index, value });
        }
    }
    if fractions.iter().sum::<f64>() <= 0.0 {
        return Err(RatioError::ZeroSum);
    }
    Ok(apportion(u64::from(RATIO_ONE), fractions)
        .into_iter()
        .map(|r| r as u16)
        .collect())
}

/// Split a move's total volume (nl) over syringes by wire ratios: the parts sum to exactly
/// `total_nl` (largest remainder). An all-zero ratio vector puts the whole total on
/// syringe 0 (the total must go somewhere); no ratios give no parts.
pub fn split_volume_nl(total_nl: u32, ratios: &[u16]) -> Vec<u32> {
    if ratios.is_empty() {
        return Vec::new();
    }
    let weights: Vec<f64> = ratios.iter().map(|&r| f64::from(r)).collect();
    if weights.iter().all(|&w| w == 0.0) {
        let mut out = vec![0; ratios.len()];
        out[0] = total_nl;
        return out;
    }
    apportion(u64::from(total_nl), &weights)
        .into_iter()
        .map(|v| v as u32)
        .collect()
}

/// Composition (fractions summing to 1) of a set of per-syringe volumes; `None` when the
/// volumes are all zero.
pub fn composition_of(volumes_nl: &[u32]) -> Option<Vec<f64>> {
    let total: u64 = volumes_nl.iter().map(|&v| u64::from(v)).sum();
    if total == 0 {
        return None;
    }
    Some(
        volumes_nl
            .iter()
            .map(|&v| v as f64 / total as f64)
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ratios_sum_exactly() {
        for f in [
            vec![1.0],
            vec![1.0, 1.0, 1.0],
            vec![0.1, 0.2, 0.7],
            vec![1e-9, 1.0 - 1e-9],
            vec![0.125; 8],
            vec![0.3, 0.0, 0.3, 0.4],
        ] {
            let r = ratios_from_fractions(&f).unwrap();
            assert_eq!(r.iter().map(|&x| u32::from(x)).sum::<u32>(), 65535, "{f:?}");
        }
        assert_eq!(ratios_from_fractions(&[1.0, 1.0, 1.0]).unwrap(), [21845; 3]);
        assert_eq!(ratios_from_fractions(&[]), Err(RatioError::Empty));
        assert!(ratios_from_fractions(&[f64::NAN]).is_err());
        assert!(ratios_from_fractions(&[0.0, 0.0]).is_err());
        assert!(ratios_from_fractions(&[0.1; 9]).is_err());
    }

    #[test]
    fn split_sums_exactly() {
        let r = ratios_from_fractions(&[0.2, 0.3, 0.5]).unwrap();
        for total in [0, 1, 2, 7, 1000, 123_457, u32::MAX] {
            let s = split_volume_nl(total, &r);
            assert_eq!(
                s.iter().map(|&v| u64::from(v)).sum::<u64>(),
                u64::from(total)
            );
        }
        assert_eq!(split_volume_nl(10, &[0, 0]), [10, 0]);
        assert_eq!(split_volume_nl(100, &r), [20, 30, 50]);
    }

    #[test]
    fn cumulative_split_tracks_plan() {
        // 10,000 moves of 333 nl at 1/3 each: rounding per move never exceeds 1 nl.
        let r = ratios_from_fractions(&[1.0, 1.0, 1.0]).unwrap();
        let mut sum = [0u64; 3];
        for _ in 0..10_000 {
            for (s, v) in sum.iter_mut().zip(split_volume_nl(333, &r)) {
                *s += u64::from(v);
            }
        }
        for s in sum {
            let planned = 333.0 * 10_000.0 / 3.0;
            assert!((s as f64 - planned).abs() / planned < 1e-3, "{s}");
        }
    }

    #[test]
    fn widest_move_fits() {
        let m = Move {
            job_id: u32::MAX,
            index: u32::MAX,
            kind: MoveKind::Extrude {
                to: PositionUm {
                    x_um: i32::MIN,
                    y_um: i32::MIN,
                    z_um: i32::MIN,
                },
                feed_um_s: u32::MAX,
                volumes_nl: vec![u32::MAX; MAX_SYRINGES],
                width_factor_ppt: u16::MAX,
            },
        };
        let bytes = postcard::to_allocvec(&m).unwrap();
        assert!(bytes.len() <= MAX_MOVE_BYTES, "{}", bytes.len());
        let back: Move = postcard::from_bytes(&bytes).unwrap();
        assert_eq!(back, m);
        assert!(m.validate(8).is_ok());
        assert!(m.validate(2).is_err());
    }
}
