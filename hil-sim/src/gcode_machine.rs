//! The G-code interpreter of `hil-sim --gcode`: turns the commands the firmware model
//! ran into the machine model's moves, so the same syringes, mixing chamber and recorder
//! serve both protocols. Pure: text in, [`Move`]s out.
//!
//! It reads what `edoctl plan --gcode` writes (`docs/gcode.md`) and the mix writings of
//! `docs/firmware.md`: `G0`/`G1` with X Y Z in mm (absolute after `G90`, relative after
//! `G91`), plunger travel in mm as relative E (`M83`; `M82` absolute) split per drive by
//! RRF's `E a:b:c`, Marlin's `M163`/`M164` mix or `DIRECT_MIXING_IN_G1` weights
//! (`A B C D H I`), or one axis letter per syringe (absolute positions like X); F in
//! mm/min; `G4 P<ms>`/`S<s>`; `G28`. Volume = travel × barrel area, rounded cumulatively
//! per syringe so nothing drifts. Everything else runs as a no-op.

use edo::gcode_link::MixWriting;
use edo::machine::{Move, MoveKind, PositionUm};

/// Marlin's direct-mixing letters, drive by drive.
const DIRECT_MIX_LETTERS: [char; 6] = ['A', 'B', 'C', 'D', 'H', 'I'];

/// The interpreter's state.
#[derive(Debug, Clone)]
pub struct GcodeMachine {
    mix_writing: MixWriting,
    drives: usize,
    area_mm2: f64,
    absolute_xyz: bool,
    absolute_e: bool,
    position_mm: [f64; 3],
    feed_mm_min: f64,
    /// Committed mix weights (Marlin `M164`), and those being set (`M163`).
    mix: Vec<f64>,
    pending_mix: Vec<f64>,
    /// Plunger position per drive, mm (absolute E or axes).
    plunger_mm: Vec<f64>,
    /// Exact and dispensed volume per drive for cumulative rounding, nl.
    exact_nl: Vec<f64>,
    issued_nl: Vec<i64>,
    layer: u32,
    next_index: u32,
}

/// One G-code word: its letter and its text after the letter.
fn words(text: &str) -> impl Iterator<Item = (char, &str)> {
    text.split_ascii_whitespace().filter_map(|w| {
        let mut c = w.chars();
        let letter = c.next()?.to_ascii_uppercase();
        Some((letter, c.as_str()))
    })
}

fn number(s: &str) -> Option<f64> {
    s.parse::<f64>().ok().filter(|v| v.is_finite())
}

impl GcodeMachine {
    /// A machine of `drives` syringes of `area_mm2` barrel area, mix written as
    /// `mix_writing`, at the origin.
    pub fn new(mix_writing: MixWriting, drives: usize, area_mm2: f64) -> Self {
        let drives = drives.max(1);
        Self {
            mix_writing,
            drives,
            area_mm2,
            absolute_xyz: true,
            absolute_e: false,
            position_mm: [0.0; 3],
            feed_mm_min: 1200.0,
            mix: vec![1.0 / drives as f64; drives],
            pending_mix: vec![0.0; drives],
            plunger_mm: vec![0.0; drives],
            exact_nl: vec![0.0; drives],
            issued_nl: vec![0; drives],
            layer: 0,
            next_index: 0,
        }
    }

    /// The move a command makes, if any (job 0, indices counted from 0).
    pub fn command(&mut self, text: &str) -> Option<Move> {
        let word = edo::gcode_link::command_word(text)?;
        let kind = match word.as_str() {
            "G0" | "G1" => self.linear(text),
            "G4" => Some(self.dwell(text)),
            "G28" => {
                self.position_mm = [0.0; 3];
                Some(MoveKind::Home)
            }
            _ => {
                self.setting(&word, text);
                None
            }
        }?;
        let index = self.next_index;
        self.next_index += 1;
        Some(Move {
            job_id: 0,
            index,
            kind,
        })
    }

    /// Layer number: counts rises of Z.
    pub fn layer(&self) -> u32 {
        self.layer
    }

    fn setting(&mut self, word: &str, text: &str) {
        match word {
            "G90" => {
                self.absolute_xyz = true;
                self.absolute_e = true;
            }
            "G91" => {
                self.absolute_xyz = false;
                self.absolute_e = false;
            }
            "M82" => self.absolute_e = true,
            "M83" => self.absolute_e = false,
            "G92" => {
                for (letter, value) in words(text).skip(1) {
                    if let (Some(i), Some(v)) = (self.drive_of_axis(letter), number(value)) {
                        self.plunger_mm[i] = v;
                    }
                }
            }
            "M163" => {
                let mut drive = None;
                let mut weight = None;
                for (letter, value) in words(text).skip(1) {
                    match letter {
                        'S' => drive = number(value).map(|v| v as usize),
                        'P' => weight = number(value),
                        _ => {}
                    }
                }
                if let (Some(d), Some(w)) = (drive, weight) {
                    if let Some(slot) = self.pending_mix.get_mut(d) {
                        *slot = w.max(0.0);
                    }
                }
            }
            "MANUAL_STEPPER" => self.manual_stepper(text),
            "M164" => {
                let total: f64 = self.pending_mix.iter().sum();
                if total > 0.0 {
                    self.mix = self.pending_mix.iter().map(|w| w / total).collect();
                }
            }
            _ => {}
        }
    }

    /// Klipper's `MANUAL_STEPPER STEPPER=syringe_a SET_POSITION=v`: the plunger of the
    /// syringe whose axis letter ends the stepper's name now stands at `v` (the firmware
    /// model refuses it while the axis is registered; a refused line never gets here).
    fn manual_stepper(&mut self, text: &str) {
        let param = |key: &str| edo::gcode_link::klipper_param(text, key);
        let drive = param("STEPPER")
            .and_then(|s| s.strip_prefix("syringe_"))
            .and_then(|s| s.chars().next())
            .and_then(|c| self.drive_of_axis(c.to_ascii_uppercase()));
        if let (Some(i), Some(v)) = (drive, param("SET_POSITION").and_then(number)) {
            self.plunger_mm[i] = v;
        }
    }

    fn drive_of_axis(&self, letter: char) -> Option<usize> {
        match &self.mix_writing {
            MixWriting::Axes(letters) => letters.iter().position(|&c| c == letter),
            _ => None,
        }
    }

    /// Plunger travel per drive (mm) of a `G1`'s E / axis words.
    fn plunger_travel(&mut self, text: &str) -> Vec<f64> {
        let mut travel = vec![0.0; self.drives];
        let mut direct = vec![0.0; self.drives];
        let mut has_direct = false;
        for (letter, value) in words(text).skip(1) {
            if let Some(i) = self.drive_of_axis(letter) {
                if let Some(v) = number(value) {
                    let to = if self.absolute_xyz {
                        v
                    } else {
                        self.plunger_mm[i] + v
                    };
                    travel[i] = to - self.plunger_mm[i];
                    self.plunger_mm[i] = to;
                }
                continue;
            }
            if self.mix_writing == MixWriting::MarlinDirect {
                if let Some(i) = DIRECT_MIX_LETTERS.iter().position(|&c| c == letter) {
                    if let (Some(slot), Some(v)) = (direct.get_mut(i), number(value)) {
                        *slot = v.max(0.0);
                        has_direct = true;
                    }
                    continue;
                }
            }
            if letter == 'E' {
                let parts: Vec<f64> = value.split(':').filter_map(number).collect();
                travel = self.split_e(&parts, has_direct.then_some(&direct));
            }
        }
        if has_direct && self.mix_writing == MixWriting::MarlinDirect {
            let total: f64 = direct.iter().sum();
            if total > 0.0 {
                self.mix = direct.iter().map(|w| w / total).collect();
            }
        }
        travel
    }

    /// E values to travel per drive: one per drive (RRF), or a total split by the mix.
    fn split_e(&mut self, parts: &[f64], direct: Option<&Vec<f64>>) -> Vec<f64> {
        let mut travel = vec![0.0; self.drives];
        if parts.len() > 1 || self.mix_writing == MixWriting::PerDriveE {
            for (i, v) in parts.iter().enumerate().take(self.drives) {
                travel[i] = self.e_to_travel(i, *v);
            }
            return travel;
        }
        let Some(&total) = parts.first() else {
            return travel;
        };
        let weights: Vec<f64> = match direct {
            Some(d) if d.iter().sum::<f64>() > 0.0 => {
                let s: f64 = d.iter().sum();
                d.iter().map(|w| w / s).collect()
            }
            _ => self.mix.clone(),
        };
        let total = self.e_to_travel(0, total);
        for (t, w) in travel.iter_mut().zip(weights) {
            *t = total * w;
        }
        travel
    }

    /// Relative E as is; absolute E (`M82`) against the plunger position.
    fn e_to_travel(&mut self, drive: usize, e: f64) -> f64 {
        if self.absolute_e {
            let d = e - self.plunger_mm[drive];
            self.plunger_mm[drive] = e;
            d
        } else {
            e
        }
    }

    /// Whole nanolitres for `travel` mm of each plunger, rounded cumulatively.
    fn volumes(&mut self, travel: &[f64]) -> Vec<i64> {
        let mut out = Vec::with_capacity(travel.len());
        for (i, t) in travel.iter().enumerate() {
            self.exact_nl[i] += t * self.area_mm2 * 1000.0;
            let target = self.exact_nl[i].round() as i64;
            out.push(target - self.issued_nl[i]);
            self.issued_nl[i] = target;
        }
        out
    }

    fn linear(&mut self, text: &str) -> Option<MoveKind> {
        let from = self.position_mm;
        for (letter, value) in words(text).skip(1) {
            let axis = match letter {
                'X' => 0,
                'Y' => 1,
                'Z' => 2,
                'F' => {
                    if let Some(f) = number(value).filter(|f| *f > 0.0) {
                        self.feed_mm_min = f;
                    }
                    continue;
                }
                _ => continue,
            };
            if let Some(v) = number(value) {
                self.position_mm[axis] = if self.absolute_xyz {
                    v
                } else {
                    self.position_mm[axis] + v
                };
            }
        }
        if self.position_mm[2] > from[2] + 1e-9 {
            self.layer += 1;
        }
        let travel = self.plunger_travel(text);
        let volumes = self.volumes(&travel);
        let moved = self.position_mm != from;
        let feed_um_s = (self.feed_mm_min * 1000.0 / 60.0).round().max(1.0) as u32;
        let nl = |v: &[i64], sign: i64| -> Vec<u32> {
            v.iter()
                .map(|x| u32::try_from((x * sign).max(0)).unwrap_or(u32::MAX))
                .collect()
        };
        let to = position_um(self.position_mm);
        let pushes = volumes.iter().any(|v| *v > 0);
        let pulls = volumes.iter().any(|v| *v < 0);
        Some(match (moved, pushes, pulls) {
            (true, true, _) => MoveKind::Extrude {
                to,
                feed_um_s,
                volumes_nl: nl(&volumes, 1),
                width_factor_ppt: 1000,
            },
            (true, false, _) => MoveKind::Travel { to, feed_um_s },
            (false, _, true) => MoveKind::Retract {
                volumes_nl: nl(&volumes, -1),
                duration_ms: plunger_ms(&travel, self.feed_mm_min),
            },
            (false, true, false) => MoveKind::Prime {
                volumes_nl: nl(&volumes, 1),
                duration_ms: plunger_ms(&travel, self.feed_mm_min),
            },
            (false, false, false) => MoveKind::Travel { to, feed_um_s },
        })
    }

    fn dwell(&self, text: &str) -> MoveKind {
        let mut ms = 0.0;
        for (letter, value) in words(text).skip(1) {
            match (letter, number(value)) {
                ('P', Some(v)) => ms = v,
                ('S', Some(v)) => ms = v * 1000.0,
                _ => {}
            }
        }
        MoveKind::Dwell {
            duration_ms: ms.clamp(0.0, f64::from(u32::MAX)) as u32,
        }
    }
}

fn position_um(p: [f64; 3]) -> PositionUm {
    let um = |v: f64| {
        (v * 1000.0)
            .round()
            .clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
    };
    PositionUm {
        x_um: um(p[0]),
        y_um: um(p[1]),
        z_um: um(p[2]),
    }
}

/// How long the longest plunger travel takes at `feed_mm_min`, ms.
fn plunger_ms(travel: &[f64], feed_mm_min: f64) -> u32 {
    let longest = travel.iter().fold(0.0f64, |m, t| m.max(t.abs()));
    (longest / (feed_mm_min / 60_000.0)).clamp(0.0, f64::from(u32::MAX)) as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volumes(m: &Move) -> Vec<u32> {
        m.kind.volumes_nl().to_vec()
    }

    #[test]
    fn rrf_per_drive_e() {
        let mut g = GcodeMachine::new(MixWriting::PerDriveE, 2, 100.0);
        assert!(g.command("M83").is_none());
        let m = g.command("G1 X10 Y0 E0.001:0.003 F600").unwrap();
        assert_eq!(volumes(&m), vec![100, 300]);
        assert!(matches!(
            m.kind,
            MoveKind::Extrude {
                feed_um_s: 10_000,
                ..
            }
        ));
        let m = g.command("G1 E-0.001:-0.001 F60").unwrap();
        assert!(matches!(m.kind, MoveKind::Retract { duration_ms: 1, .. }));
        assert_eq!(volumes(&m), vec![100, 100]);
        assert_eq!(m.index, 1);
    }

    #[test]
    fn marlin_m163_and_direct_mixing_split_the_total() {
        let mut g = GcodeMachine::new(MixWriting::MarlinM163, 2, 100.0);
        g.command("M163 S0 P0.25");
        g.command("M163 S1 P0.75");
        g.command("M164 S0");
        let m = g.command("G1 X1 E0.004").unwrap();
        assert_eq!(volumes(&m), vec![100, 300]);
        let mut g = GcodeMachine::new(MixWriting::MarlinDirect, 2, 100.0);
        let m = g.command("G1 X1 E0.004 A0.5 B0.5").unwrap();
        assert_eq!(volumes(&m), vec![200, 200]);
    }

    #[test]
    fn axes_are_absolute_plunger_positions_and_rounding_does_not_drift() {
        let mut g = GcodeMachine::new(MixWriting::Axes(vec!['A', 'B']), 2, 1.0);
        let mut total = 0;
        for i in 1..=1000 {
            let m = g
                .command(&format!("G1 X{i} A{:.6} B0", f64::from(i) * 0.0004))
                .unwrap();
            total += volumes(&m).first().copied().unwrap_or(0);
        }
        assert_eq!(total, 400); // 0.4 mm x 1 mm² = 400 nl, exactly
    }

    #[test]
    fn travel_dwell_home_and_layers() {
        let mut g = GcodeMachine::new(MixWriting::PerDriveE, 2, 100.0);
        assert!(matches!(
            g.command("G0 X5 Z0.2").unwrap().kind,
            MoveKind::Travel { .. }
        ));
        assert_eq!(g.layer(), 1);
        assert!(matches!(
            g.command("G4 P100").unwrap().kind,
            MoveKind::Dwell { duration_ms: 100 }
        ));
        assert!(matches!(g.command("G28").unwrap().kind, MoveKind::Home));
        assert!(g.command("M115").is_none());
    }
}
