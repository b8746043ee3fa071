//! G-code export of a move stream, so labs with a Duet (RepRapFirmware), Marlin mixing or
//! Klipper syringe printer can build edo's plans without edod, and the lines edod streams
//! over the G-code link ([`MoveWriter`], one move at a time). Contract: `docs/gcode.md`.
//!
//! Extrusion is relative (`M83`) and in millimetres of plunger travel: a syringe's volume
//! V (nl) becomes E = V / 1000 / A mm for a barrel cross-section A (mm²). Printed E values
//! are rounded cumulatively per drive (to 10⁻⁵ mm), so the sum of each drive's E over the
//! file equals that drive's commanded volume / A within 10⁻⁵ mm.

use crate::machine::{Move, MoveKind, PositionUm};
use serde::{Deserialize, Serialize};
use std::fmt::Write;

/// Which firmware reads the file: the G-code link's [`Dialect`] (RepRapFirmware 3: a
/// tool over all drives (`M563 P0 D0:1:..`), per-move `E a:b:c`; Marlin with
/// `MIXING_EXTRUDER`: mix set per move with `M163`/`M164`, or `A B C ..` weights in `G1`
/// with `DIRECT_MIXING_IN_G1`, total E per move; Klipper: each syringe a manual stepper
/// moved as a `G1` axis of its own (`MANUAL_STEPPER STEPPER=syringe_a GCODE_AXIS=A`),
/// absolute plunger positions in mm, also what a Marlin multi-axis build reads).
pub use super::Dialect;

/// The G-code lines of `text` as streamed: comments and empty lines dropped.
pub fn streamed_lines(text: &str) -> impl Iterator<Item = &str> {
    text.lines().filter_map(streamed)
}

/// A writer's line as streamed: without its comment; `None` if nothing is left.
pub fn streamed(line: &str) -> Option<&str> {
    Some(line.split(';').next().unwrap_or("").trim()).filter(|l| !l.is_empty())
}

/// Export settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GcodeSettings {
    pub flavor: Dialect,
    /// Barrel cross-section of every syringe, mm². Default 165 (a 10 mL syringe, 14.5 mm
    /// bore).
    pub barrel_area_mm2: f64,
    /// Marlin only: put the mix into `G1` as `A B C ..` weights (`DIRECT_MIXING_IN_G1`)
    /// instead of `M163`/`M164` lines. Default false.
    pub marlin_direct_mixing: bool,
    /// Klipper only: one axis letter per drive, in drive order; empty: [`DEFAULT_AXES`]
    /// from the first.
    pub axes: Vec<char>,
    /// Klipper only: each drive's plunger limits, written as the axis' `LIMIT_VELOCITY`
    /// and `LIMIT_ACCEL` (Klipper leaves a `GCODE_AXIS` unlimited without them); a drive
    /// past the end takes [`PlungerLimits::default`].
    pub plunger_limits: Vec<PlungerLimits>,
}

/// How fast a syringe's plunger may move (`[[machine.syringes]] max_plunger_mm_s`,
/// `max_plunger_accel_mm_s2`): a syringe pump's lead screw and the slurry's back-pressure
/// bound it, whatever the toolhead does.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlungerLimits {
    /// Highest plunger speed, mm/s of plunger travel. Default 2: about 100 times the
    /// plunger speed of a 0.4 × 0.2 mm road at 40 mm/s through a 14.5 mm bore, and slow
    /// enough that a wrong position cannot empty a syringe in a flash.
    pub max_mm_s: f64,
    /// Highest plunger acceleration, mm/s². Default 20.
    pub max_accel_mm_s2: f64,
}

impl Default for PlungerLimits {
    fn default() -> Self {
        PlungerLimits {
            max_mm_s: 2.0,
            max_accel_mm_s2: 20.0,
        }
    }
}

impl PlungerLimits {
    /// Why these limits cannot be written, if they cannot: the setting's name and why.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        for (name, v) in [
            ("max_plunger_mm_s", self.max_mm_s),
            ("max_plunger_accel_mm_s2", self.max_accel_mm_s2),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 1000.0) {
                return Err((name, format!("{v}: must be above 0 and at most 1000")));
            }
        }
        Ok(())
    }
}

impl Default for GcodeSettings {
    fn default() -> Self {
        GcodeSettings {
            flavor: Dialect::Rrf,
            barrel_area_mm2: 165.0,
            marlin_direct_mixing: false,
            axes: Vec::new(),
            plunger_limits: Vec::new(),
        }
    }
}

impl GcodeSettings {
    /// The settings that write a G-code link's mix (`[machine.gcode] mix`,
    /// `docs/firmware.md`): per-drive E → RRF, `M163` or direct mixing → Marlin, axes →
    /// Klipper with those letters.
    pub fn for_mix(mix: &super::MixWriting, barrel_area_mm2: f64) -> Self {
        use super::MixWriting;
        let (flavor, marlin_direct_mixing, axes) = match mix {
            MixWriting::PerDriveE => (Dialect::Rrf, false, Vec::new()),
            MixWriting::MarlinM163 => (Dialect::Marlin, false, Vec::new()),
            MixWriting::MarlinDirect => (Dialect::Marlin, true, Vec::new()),
            MixWriting::Axes(letters) => (Dialect::Klipper, false, letters.clone()),
        };
        GcodeSettings {
            flavor,
            barrel_area_mm2,
            marlin_direct_mixing,
            axes,
            plunger_limits: Vec::new(),
        }
    }

    /// The axis letter of every drive (Klipper), checked.
    fn axis_letters(&self, drives: usize) -> Result<Vec<char>, GcodeError> {
        if self.axes.is_empty() {
            if drives > DEFAULT_AXES.len() {
                return Err(GcodeError::AxesCount {
                    letters: DEFAULT_AXES.len(),
                    drives,
                });
            }
            return Ok(DEFAULT_AXES[..drives].to_vec());
        }
        if self.axes.len() != drives {
            return Err(GcodeError::AxesCount {
                letters: self.axes.len(),
                drives,
            });
        }
        for (i, &c) in self.axes.iter().enumerate() {
            let upper = c.to_ascii_uppercase();
            if !upper.is_ascii_uppercase() || KLIPPER_RESERVED.contains(upper) {
                return Err(GcodeError::ReservedAxis(c));
            }
            if self.axes[..i]
                .iter()
                .any(|o| o.to_ascii_uppercase() == upper)
            {
                return Err(GcodeError::RepeatedAxis(c));
            }
        }
        Ok(self.axes.iter().map(|c| c.to_ascii_uppercase()).collect())
    }
}

/// Axis letters Klipper cannot give a manual stepper (its own axes and words).
const KLIPPER_RESERVED: &str = "XYZEFGMNT";

/// The Klipper flavor's axis letters when none are given, drive 0 first.
pub const DEFAULT_AXES: [char; 17] = [
    'A', 'B', 'C', 'D', 'H', 'I', 'J', 'K', 'L', 'O', 'P', 'Q', 'R', 'S', 'U', 'V', 'W',
];

/// What the file commands in total.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GcodeStats {
    /// Sum of each drive's printed E over Extrude moves, mm.
    pub extrude_e_mm: Vec<f64>,
    pub lines: usize,
}

/// Marlin's mixing letters for drives 0..5.
const MARLIN_MIX_AXES: [char; 6] = ['A', 'B', 'C', 'D', 'H', 'I'];

/// The file cannot represent the stream.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GcodeError {
    #[error("barrel_area_mm2 must be a positive number, got {0}")]
    BarrelArea(f64),
    #[error("Marlin mixing supports at most 6 drives (A B C D H I), the job has {0}")]
    TooManyDrives(usize),
    #[error("Klipper axes: {letters} letter(s) for {drives} drive(s); give one per syringe")]
    AxesCount { letters: usize, drives: usize },
    #[error("Klipper axis {0:?} is not a letter Klipper can give a manual stepper (not X Y Z E F G M N T)")]
    ReservedAxis(char),
    #[error("Klipper axis {0:?} is given twice")]
    RepeatedAxis(char),
}

/// Cumulative rounding of one drive's E to 10⁻⁶ mm (a syringe plunger moves a few
/// 10⁻⁴ mm per move, so E is printed with six decimals).
#[derive(Default, Clone)]
struct Drive {
    exact_mm: f64,
    printed_units: i64,
}

impl Drive {
    /// Add `mm` and return the increment to print, in 10⁻⁶ mm units.
    fn add(&mut self, mm: f64) -> i64 {
        self.exact_mm += mm;
        let target = (self.exact_mm * 1e6).round() as i64;
        let d = target - self.printed_units;
        self.printed_units = target;
        d
    }
}

/// `units` of `10^-digits`, written shortest: no trailing zeros, no point when whole
/// (`1200` at 3 digits is `1.2`, `0` is `0`).
fn fixed(units: i64, digits: u32) -> String {
    let sign = if units < 0 { "-" } else { "" };
    let u = units.unsigned_abs();
    let scale = 10u64.pow(digits);
    let (whole, mut frac) = (u / scale, u % scale);
    if frac == 0 {
        return format!("{sign}{whole}");
    }
    let mut width = digits as usize;
    while frac % 10 == 0 {
        frac /= 10;
        width -= 1;
    }
    format!("{sign}{whole}.{frac:0width$}")
}

/// Plunger travel in 10⁻⁶ mm units, as mm.
fn e(units: i64) -> String {
    fixed(units, 6)
}

fn mm(um: i32) -> String {
    fixed(i64::from(um), 3)
}

/// A feed in µm/s as mm/min to 0.1.
fn f_mm_min(um_s: u32) -> String {
    fixed((f64::from(um_s) * 0.6).round() as i64, 1)
}

/// A plunger feed in mm/min to four significant digits: a retract of 0.3 µm over
/// 150 ms is `F0.1212`. Marlin, RepRapFirmware and Klipper read F as a float, so the
/// retract lasts what was planned; `F1` when nothing moves (any feed does, and Klipper
/// refuses 0).
fn f_plunger(mm_min: f64) -> String {
    if !(mm_min.is_finite() && mm_min > 0.0) {
        return "1".into();
    }
    significant(mm_min)
}

/// `v` to four significant digits (at most nine decimals; at least one, so 1234.56 is
/// `1234.6`), written shortest (`2`, not `2.0`).
fn significant(v: f64) -> String {
    let digits = (3 - v.abs().log10().floor() as i32).clamp(1, 9);
    fixed((v * 10f64.powi(digits)).round() as i64, digits as u32)
}

/// The `[manual_stepper]` section name of axis `c`: `syringe_a` for `A`.
pub fn stepper_name(c: char) -> String {
    format!("syringe_{}", c.to_ascii_lowercase())
}

/// Write the G-code for `moves` (one job, in order) over `drives` syringes into `out`.
/// `header` lines are written as comments first.
pub fn write_gcode(
    moves: &[Move],
    drives: usize,
    settings: &GcodeSettings,
    header: &[String],
    out: &mut String,
) -> Result<GcodeStats, GcodeError> {
    let mut w = MoveWriter::new(drives, settings)?;
    let mut lines = Vec::new();
    w.preamble(header, &mut lines);
    for m in moves {
        w.move_lines(m, &mut lines);
        for l in lines.drain(..) {
            out.push_str(&l);
            out.push('\n');
        }
    }
    w.epilogue(&mut lines);
    for l in lines.drain(..) {
        out.push_str(&l);
        out.push('\n');
    }
    Ok(w.stats())
}

/// The lines of a job, one move at a time, with the E rounding state of every drive:
/// what [`write_gcode`] writes to a file and what edod streams over the G-code link, so
/// the two are the same lines.
#[derive(Clone)]
pub struct MoveWriter {
    /// Lines written.
    lines: usize,
    settings: GcodeSettings,
    drives: usize,
    /// Klipper: each drive's axis letter.
    axes: Vec<char>,
    /// Extrusion E per drive.
    ext: Vec<Drive>,
    /// Retract/prime E, rounded on its own so it never disturbs the extrusion sums.
    aux: Vec<Drive>,
    mix: MarlinMix,
    /// What the firmware holds from the lines written so far, so a line carries only
    /// the words that change it (modal G-code, as slicers write it).
    modal: Modal,
}

/// The modal state a line leaves in the firmware: the position, the feed and (Klipper)
/// each syringe axis' position, each `None` until a line sets it (and after `G28`).
#[derive(Clone, Default)]
struct Modal {
    xyz_um: [Option<i32>; 3],
    feed: Option<String>,
    axes_units: Vec<Option<i64>>,
}

impl Modal {
    /// The ` X.. Y.. Z..` words that move to `to`; all three when none changes (a line
    /// without them would read as a plunger-only move).
    fn xyz_words(&mut self, to: &PositionUm) -> String {
        let target = [to.x_um, to.y_um, to.z_um];
        let mut words = String::new();
        for (k, c) in ['X', 'Y', 'Z'].into_iter().enumerate() {
            if self.xyz_um[k] != Some(target[k]) {
                let _ = write!(words, " {c}{}", mm(target[k]));
            }
        }
        if words.is_empty() {
            for (k, c) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                let _ = write!(words, " {c}{}", mm(target[k]));
            }
        }
        self.xyz_um = target.map(Some);
        words
    }

    /// ` F..` when the feed changes, else nothing.
    fn feed_word(&mut self, feed: String) -> String {
        if self.feed.as_deref() == Some(feed.as_str()) {
            return String::new();
        }
        let word = format!(" F{feed}");
        self.feed = Some(feed);
        word
    }

    /// After `G28`: the position is the firmware's, and its homing may leave another
    /// feed.
    fn forget(&mut self) {
        self.xyz_um = [None; 3];
        self.feed = None;
    }
}

impl MoveWriter {
    /// A writer for `drives` syringes; refuses settings the file cannot carry.
    pub fn new(drives: usize, settings: &GcodeSettings) -> Result<Self, GcodeError> {
        let a = settings.barrel_area_mm2;
        if !(a.is_finite() && a > 0.0) {
            return Err(GcodeError::BarrelArea(a));
        }
        if settings.flavor == Dialect::Marlin && drives > MARLIN_MIX_AXES.len() {
            return Err(GcodeError::TooManyDrives(drives));
        }
        let drives = drives.max(1);
        let axes = match settings.flavor {
            Dialect::Klipper => settings.axis_letters(drives)?,
            _ => Vec::new(),
        };
        Ok(MoveWriter {
            lines: 0,
            settings: settings.clone(),
            drives,
            axes,
            ext: vec![Drive::default(); drives],
            aux: vec![Drive::default(); drives],
            mix: MarlinMix::new(drives),
            modal: Modal {
                axes_units: vec![None; drives],
                ..Modal::default()
            },
        })
    }

    /// What was written so far.
    pub fn stats(&self) -> GcodeStats {
        GcodeStats {
            extrude_e_mm: self
                .ext
                .iter()
                .map(|d| d.printed_units as f64 / 1e6)
                .collect(),
            lines: self.lines,
        }
    }

    fn line(&mut self, s: String, out: &mut Vec<String>) {
        out.push(s);
        self.lines += 1;
    }

    /// The header comments, the flavour's tool set-up and the units and modes, into `out`.
    /// Klipper: each syringe's axis is released, zeroed and registered again, which
    /// Klipper accepts whatever state the axis was in (a second job, a resume), so the
    /// writer's absolute plunger positions start at 0 where the plunger stands.
    pub fn preamble(&mut self, header: &[String], out: &mut Vec<String>) {
        for h in header {
            self.line(format!("; {h}"), out);
        }
        self.set_up(true, out);
    }

    /// What a G-code connection starts with (`docs/firmware.md`): the tool set-up, the
    /// units and modes and, on Klipper, each syringe's axis released (a no-op when it is
    /// not registered), so a macro can move the plungers between jobs; a job's preamble
    /// takes the axes again.
    pub fn connection_prologue(&mut self, out: &mut Vec<String>) {
        self.set_up(false, out);
        self.epilogue(out);
    }

    /// The end of a job: Klipper's syringe axes released (`GCODE_AXIS=`), so a refill or
    /// purge macro can move the plungers with `MANUAL_STEPPER ... MOVE=`; nothing on the
    /// other flavours.
    pub fn epilogue(&mut self, out: &mut Vec<String>) {
        if self.settings.flavor != Dialect::Klipper {
            return;
        }
        for (d, c) in self.axes.clone().into_iter().enumerate() {
            let name = stepper_name(c);
            self.line(format!("MANUAL_STEPPER STEPPER={name} GCODE_AXIS="), out);
            // A move to where the plunger stands: nothing moves, but Kalico steps the
            // end of the job it still holds for the axis (its SET_POSITION, unlike
            // Klipper's, does not), so the next job's SET_POSITION=0 is clean.
            let at = self.ext[d].printed_units + self.aux[d].printed_units;
            if at != 0 {
                self.line(format!("MANUAL_STEPPER STEPPER={name} MOVE={}", e(at)), out);
            }
        }
        self.modal.axes_units = vec![None; self.drives];
    }

    fn set_up(&mut self, take_axes: bool, out: &mut Vec<String>) {
        let all: Vec<String> = (0..self.drives).map(|d| d.to_string()).collect();
        match self.settings.flavor {
            Dialect::Rrf => {
                self.line(
                    "; RepRapFirmware 3: one mixing tool over all syringe drives".into(),
                    out,
                );
                self.line(format!("M563 P0 D{} H-1 S\"edo\"", all.join(":")), out);
                self.line("T0".into(), out);
            }
            Dialect::Marlin => {
                self.line(
                    "; Marlin MIXING_EXTRUDER: mix per move, E is the total plunger travel".into(),
                    out,
                );
                self.line("T0".into(), out);
            }
            Dialect::Klipper if take_axes => {
                self.line(
                    "; Klipper: each syringe a manual stepper on its own G1 axis, positions in mm"
                        .into(),
                    out,
                );
                self.take_axes(out);
            }
            Dialect::Klipper => {}
        }
        self.line("G21 ; millimetres".into(), out);
        self.line("G90 ; absolute positions".into(), out);
        self.line("M83 ; relative extrusion".into(), out);
    }

    /// Klipper: release, zero and register each syringe's axis with its limits.
    fn take_axes(&mut self, out: &mut Vec<String>) {
        for (d, c) in self.axes.clone().into_iter().enumerate() {
            let name = stepper_name(c);
            let limits = self
                .settings
                .plunger_limits
                .get(d)
                .copied()
                .unwrap_or_default();
            self.line(format!("MANUAL_STEPPER STEPPER={name} GCODE_AXIS="), out);
            self.line(format!("MANUAL_STEPPER STEPPER={name} SET_POSITION=0"), out);
            self.line(
                format!(
                    "MANUAL_STEPPER STEPPER={name} GCODE_AXIS={c} LIMIT_VELOCITY={} LIMIT_ACCEL={}",
                    significant(limits.max_mm_s),
                    significant(limits.max_accel_mm_s2)
                ),
                out,
            );
        }
        self.modal.axes_units = vec![None; self.drives];
    }

    /// A comment line `; text` into `out`.
    pub fn comment(&mut self, text: &str, out: &mut Vec<String>) {
        self.line(format!("; {text}"), out);
    }

    /// A feature line `;TYPE:name` into `out`, as PrusaSlicer marks what the next
    /// roads build (`Perimeter`, `Gap fill`, `Support material`, `Support material
    /// interface`), for G-code viewers and checks.
    pub fn feature(&mut self, name: &str, out: &mut Vec<String>) {
        self.line(format!(";TYPE:{name}"), out);
    }

    /// The lines of one move into `out`: a Marlin mix it needs first, then its command.
    pub fn move_lines(&mut self, m: &Move, out: &mut Vec<String>) {
        let mut s = String::new();
        self.command(m, &mut s, out);
        self.line(s, out);
    }

    /// The command of one move into `s` (a Marlin mix it needs goes to `out` first).
    fn command(&mut self, m: &Move, s: &mut String, out: &mut Vec<String>) {
        match &m.kind {
            MoveKind::Home => {
                self.modal.forget();
                s.push_str("G28");
            }
            MoveKind::LayerMark { layer, z_um } => {
                let _ = write!(s, ";LAYER:{layer} Z{}", mm(*z_um));
            }
            MoveKind::Dwell { duration_ms } => {
                let _ = write!(s, "G4 P{duration_ms}");
            }
            MoveKind::Travel { to, feed_um_s } => {
                s.push_str("G0");
                s.push_str(&self.modal.xyz_words(to));
                s.push_str(&self.modal.feed_word(f_mm_min(*feed_um_s)));
            }
            MoveKind::Retract {
                volumes_nl,
                duration_ms,
            } => self.plunger(-1.0, volumes_nl, *duration_ms, s),
            MoveKind::Prime {
                volumes_nl,
                duration_ms,
            } => self.plunger(1.0, volumes_nl, *duration_ms, s),
            MoveKind::Extrude {
                to,
                feed_um_s,
                volumes_nl,
                ..
            } => self.extrude(to, *feed_um_s, volumes_nl, s, out),
        }
    }

    /// Klipper: each drive's axis at its plunger position (extrusion and retract/prime
    /// rounded apart, so the extrusion moves' increments sum exactly), the axes that
    /// move; all of them when none does and `words_before` is false (a line needs one).
    fn axis_positions(&mut self, words_before: bool, s: &mut String) {
        let at: Vec<i64> = (0..self.axes.len())
            .map(|d| self.ext[d].printed_units + self.aux[d].printed_units)
            .collect();
        let moving = |d: usize| self.modal.axes_units.get(d).copied().flatten() != Some(at[d]);
        let any = (0..at.len()).any(moving);
        for (d, c) in self.axes.iter().enumerate() {
            if moving(d) || (!any && !words_before) {
                let _ = write!(s, " {c}{}", e(at[d]));
            }
        }
        self.modal.axes_units = at.into_iter().map(Some).collect();
    }

    /// A plunger-only move (retract: `sign` −1, prime: +1): E over the duration, as a
    /// feed in mm/min of the largest drive's travel.
    fn plunger(&mut self, sign: f64, volumes_nl: &[u32], duration_ms: u32, s: &mut String) {
        let area_mm2 = self.settings.barrel_area_mm2;
        let units: Vec<i64> = (0..self.drives)
            .map(|d| {
                let travel_mm = volumes_nl.get(d).map_or(0.0, |&v| nl_to_mm(v, area_mm2));
                self.aux[d].add(sign * travel_mm)
            })
            .collect();
        let most = units.iter().map(|u| u.abs()).max().unwrap_or(0) as f64 / 1e6;
        let feed = most * 60_000.0 / f64::from(duration_ms.max(1));
        let what = if sign < 0.0 { "retract" } else { "prime" };
        match self.settings.flavor {
            Dialect::Rrf => {
                let es: Vec<String> = units.iter().map(|&u| e(u)).collect();
                let f = self.modal.feed_word(f_plunger(feed));
                let _ = write!(s, "G1 E{}{f} ; {what}", es.join(":"));
            }
            Dialect::Marlin => {
                let total: i64 = units.iter().sum();
                let f = self.modal.feed_word(f_plunger(feed));
                let _ = write!(s, "G1 E{}{f} ; {what}", e(total));
            }
            Dialect::Klipper => {
                s.push_str("G1");
                self.axis_positions(false, s);
                let f = self.modal.feed_word(f_plunger(feed));
                let _ = write!(s, "{f} ; {what}");
            }
        }
    }

    /// An extruding move: per-drive E (RRF), total E with the mix as `G1` weights or
    /// `M163`/`M164` lines before it (Marlin), or each drive's axis position (Klipper).
    fn extrude(
        &mut self,
        to: &PositionUm,
        feed_um_s: u32,
        volumes_nl: &[u32],
        s: &mut String,
        out: &mut Vec<String>,
    ) {
        let area_mm2 = self.settings.barrel_area_mm2;
        let units: Vec<i64> = (0..self.drives)
            .map(|d| {
                let travel_mm = volumes_nl.get(d).map_or(0.0, |&v| nl_to_mm(v, area_mm2));
                self.ext[d].add(travel_mm)
            })
            .collect();
        let xyz = format!("G1{}", self.modal.xyz_words(to));
        let f = self.modal.feed_word(f_mm_min(feed_um_s));
        let total: i64 = units.iter().sum();
        match self.settings.flavor {
            Dialect::Rrf => {
                let es: Vec<String> = units.iter().map(|&u| e(u)).collect();
                let _ = write!(s, "{xyz} E{}{f}", es.join(":"));
            }
            Dialect::Marlin if self.settings.marlin_direct_mixing => {
                let _ = write!(s, "{xyz} E{}", e(total));
                if total > 0 {
                    for (d, u) in units.iter().enumerate() {
                        let _ = write!(s, " {}{}", MARLIN_MIX_AXES[d], e(*u));
                    }
                }
                s.push_str(&f);
            }
            Dialect::Marlin => {
                if let Some(weights) = self.mix.next(&units) {
                    for (d, w) in weights.iter().enumerate() {
                        self.line(format!("M163 S{d} P{w:.6}"), out);
                    }
                    self.line("M164 S0".into(), out);
                }
                let _ = write!(s, "{xyz} E{}{f}", e(total));
            }
            Dialect::Klipper => {
                s.push_str(&xyz);
                self.axis_positions(true, s);
                s.push_str(&f);
            }
        }
    }
}

/// Plunger travel for `v` nl through a barrel of `area_mm2`, mm.
fn nl_to_mm(v: u32, area_mm2: f64) -> f64 {
    f64::from(v) / 1000.0 / area_mm2
}

/// Marlin `M163`/`M164` mixes, sent only when needed. The mix is the composition of the
/// last [`MarlinMix::WINDOW`] moves' E (cumulatively rounded per drive, so exact to a
/// unit over the window, unlike one small move's). A new mix goes out when splitting the
/// moves' total E by the current one would leave any drive more than
/// [`MarlinMix::DRIFT`] units (1e-6 mm each) off its planned E — a composition change
/// does that within a few moves, rounding only after hundreds: that mix pays the drift
/// back over `WINDOW` moves, after which the plain composition is sent again. So every
/// drive's E summed over the file stays within `DRIFT` units of the plan, with a few
/// mixes per path instead of one per move.
#[derive(Clone)]
struct MarlinMix {
    /// Current weights (fractions summing to 1), none before the first mix.
    weights: Option<Vec<f64>>,
    /// Per drive: planned E so far and E the firmware has split to it so far (units).
    planned: Vec<f64>,
    split: Vec<f64>,
    /// The last moves' per-drive E.
    recent: std::collections::VecDeque<Vec<i64>>,
    /// Moves left before a pay-back mix is replaced by the plain composition.
    paying: Option<usize>,
}

impl MarlinMix {
    /// Largest drift of a drive's split E from its planned E, units (5e-5 mm, 8 nl in a
    /// 165 mm² barrel).
    const DRIFT: f64 = 50.0;
    /// Moves the composition is taken over, and a drift is paid back over.
    const WINDOW: usize = 8;

    fn new(drives: usize) -> Self {
        MarlinMix {
            weights: None,
            planned: vec![0.0; drives],
            split: vec![0.0; drives],
            recent: Default::default(),
            paying: None,
        }
    }

    /// How far the worst drive's split would end from its plan after a move of `t`
    /// units at weights `w` (the move already added to `planned`).
    fn off_after(&self, w: &[f64], t: f64) -> f64 {
        let wsum: f64 = w.iter().sum();
        self.split
            .iter()
            .zip(&self.planned)
            .zip(w)
            .map(|((s, p), wi)| (s + t * wi / wsum - p).abs())
            .fold(0.0, f64::max)
    }

    /// Weights that pay back what is `owed` before this move: spread over the next
    /// WINDOW moves on top of the window's `base` composition, or, when that still ends
    /// over DRIFT (a long move), this move's own split and all that is owed at once.
    fn repay(&self, base: &[f64], owed: &[f64], units: &[i64]) -> Vec<f64> {
        let t: f64 = units.iter().sum::<i64>() as f64;
        let k = Self::WINDOW as f64;
        let spread: Vec<f64> = base
            .iter()
            .zip(owed)
            .map(|(b, o)| (b + o / (k * t)).max(0.0))
            .collect();
        if self.off_after(&spread, t) <= Self::DRIFT {
            return spread;
        }
        units
            .iter()
            .zip(owed)
            .map(|(&u, o)| ((u as f64 + o) / t).max(0.0))
            .collect()
    }

    /// Account for a move of per-drive `units`; the weights to send first, if any.
    fn next(&mut self, units: &[i64]) -> Option<Vec<f64>> {
        let total: i64 = units.iter().sum();
        if total <= 0 {
            return None;
        }
        let t = total as f64;
        if self.recent.len() == Self::WINDOW {
            self.recent.pop_front();
        }
        self.recent.push_back(units.to_vec());
        let mut sums = vec![0.0; units.len()];
        for r in &self.recent {
            for (s, &u) in sums.iter_mut().zip(r) {
                *s += u as f64;
            }
        }
        let window_total: f64 = sums.iter().sum();
        let base: Vec<f64> = sums.iter().map(|x| x / window_total).collect();
        let before: Vec<f64> = self
            .split
            .iter()
            .zip(&self.planned)
            .map(|(s, p)| p - s)
            .collect();
        for (p, &u) in self.planned.iter_mut().zip(units) {
            *p += u as f64;
        }
        let new = match (&self.weights, self.paying) {
            (None, _) => Some(base.clone()),
            (Some(w), _) if self.off_after(w, t) > Self::DRIFT => {
                self.paying = Some(Self::WINDOW);
                Some(self.repay(&base, &before, units))
            }
            (Some(_), Some(0)) => {
                self.paying = None;
                Some(base.clone())
            }
            (Some(_), Some(n)) => {
                self.paying = Some(n - 1);
                None
            }
            (Some(_), None) => None,
        };
        let sent = new.map(|w| {
            let sum: f64 = w.iter().sum();
            let w: Vec<f64> = w.iter().map(|x| (x / sum * 1e6).round() / 1e6).collect();
            self.weights = Some(w.clone());
            w
        });
        let w = self.weights.as_deref().unwrap_or_default();
        let wsum: f64 = w.iter().sum();
        if wsum > 0.0 {
            for (s, wi) in self.split.iter_mut().zip(w) {
                *s += t * wi / wsum;
            }
        }
        sent
    }
}

/// Sum each drive's E over the Extrude lines of a file this module wrote (for checks).
/// RRF: the `E a:b:c` values; Marlin: the total E split by the preceding `M163` weights
/// (or the `A B C` weights on the line); Klipper: each axis' travel on those lines.
pub fn summed_drive_e(gcode: &str, drives: usize, flavor: Dialect) -> Vec<f64> {
    if flavor == Dialect::Klipper {
        return summed_axis_travel(gcode, drives);
    }
    let mut sums = vec![0.0; drives];
    let mut weights = vec![0.0; drives];
    for l in gcode.lines() {
        let code = l.split(';').next().unwrap_or("").trim();
        if let Some(rest) = code.strip_prefix("M163 ") {
            let mut s = None;
            let mut p = None;
            for w in rest.split_whitespace() {
                if let Some(v) = w.strip_prefix('S') {
                    s = v.parse::<usize>().ok();
                } else if let Some(v) = w.strip_prefix('P') {
                    p = v.parse::<f64>().ok();
                }
            }
            if let (Some(s), Some(p)) = (s, p) {
                if s < drives {
                    weights[s] = p;
                }
            }
            continue;
        }
        if !extruding_line(code) {
            continue;
        }
        let mut es: Vec<f64> = Vec::new();
        let mut line_weights = vec![0.0; drives];
        let mut direct = false;
        for w in code.split_whitespace() {
            if let Some(v) = w.strip_prefix('E') {
                es = v.split(':').filter_map(|x| x.parse().ok()).collect();
            }
            for (d, c) in MARLIN_MIX_AXES.iter().enumerate().take(drives) {
                if let Some(v) = w.strip_prefix(*c) {
                    line_weights[d] = v.parse().unwrap_or(0.0);
                    direct = true;
                }
            }
        }
        match flavor {
            Dialect::Rrf => {
                for (s, v) in sums.iter_mut().zip(&es) {
                    *s += v;
                }
            }
            Dialect::Marlin | Dialect::Klipper => {
                let total = es.first().copied().unwrap_or(0.0);
                let w = if direct { &line_weights } else { &weights };
                let wsum: f64 = w.iter().sum();
                if wsum > 0.0 {
                    for (s, wi) in sums.iter_mut().zip(w) {
                        *s += total * wi / wsum;
                    }
                }
            }
        }
    }
    sums
}

/// A `G1` that moves the toolhead (an X, Y or Z word): an extrusion in a file this
/// module wrote, where plunger-only `G1` lines are retracts and primes.
fn extruding_line(code: &str) -> bool {
    code.starts_with("G1 ")
        && code
            .split_whitespace()
            .skip(1)
            .any(|w| w.starts_with(['X', 'Y', 'Z']))
}

/// Klipper: the axis letters from the `GCODE_AXIS=` lines, then each axis' travel summed
/// over the extruding `G1 X` lines (positions are absolute; retract/prime lines move the
/// position without counting).
fn summed_axis_travel(gcode: &str, drives: usize) -> Vec<f64> {
    let mut letters: Vec<char> = Vec::new();
    let mut position = vec![0.0; drives];
    let mut sums = vec![0.0; drives];
    for l in gcode.lines() {
        let code = l.split(';').next().unwrap_or("").trim();
        if let Some((_, axis)) = code.split_once("GCODE_AXIS=") {
            letters.extend(axis.chars().next().filter(|c| !letters.contains(c)));
            continue;
        }
        if let Some((_, at)) = code.split_once(" SET_POSITION=") {
            let axis = code
                .split_once("STEPPER=syringe_")
                .and_then(|(_, rest)| rest.chars().next())
                .map(|c| c.to_ascii_uppercase());
            let d = letters.iter().position(|&l| Some(l) == axis);
            if let (Some(d), Ok(to)) = (d.filter(|&d| d < drives), at.trim().parse::<f64>()) {
                position[d] = to;
            }
            continue;
        }
        if !code.starts_with("G1 ") {
            continue;
        }
        let extruding = extruding_line(code);
        for w in code.split_whitespace().skip(1) {
            let mut chars = w.chars();
            let Some(c) = chars.next() else { continue };
            let Some(d) = letters.iter().position(|&l| l == c).filter(|&d| d < drives) else {
                continue;
            };
            let Ok(to) = chars.as_str().parse::<f64>() else {
                continue;
            };
            if extruding {
                sums[d] += to - position[d];
            }
            position[d] = to;
        }
    }
    sums
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mv(index: u32, kind: MoveKind) -> Move {
        Move {
            job_id: 0,
            index,
            kind,
        }
    }

    fn extrude(x_um: i32, volumes_nl: Vec<u32>) -> MoveKind {
        MoveKind::Extrude {
            to: PositionUm {
                x_um,
                y_um: 0,
                z_um: 200,
            },
            feed_um_s: 10_000,
            volumes_nl,
            width_factor_ppt: 1000,
        }
    }

    fn klipper(axes: Vec<char>) -> GcodeSettings {
        GcodeSettings {
            flavor: Dialect::Klipper,
            barrel_area_mm2: 100.0,
            axes,
            ..GcodeSettings::default()
        }
    }

    #[test]
    fn numbers_are_written_shortest() {
        assert_eq!(e(0), "0");
        assert_eq!(e(12), "0.000012");
        assert_eq!(e(-120), "-0.00012");
        assert_eq!(e(2_500_000), "2.5");
        assert_eq!(mm(200), "0.2");
        assert_eq!(mm(-10_250), "-10.25");
        assert_eq!(mm(-5), "-0.005");
        assert_eq!(f_mm_min(10_000), "600");
        assert_eq!(f_mm_min(403), "24.2");
        assert_eq!(f_plunger(0.96), "0.96");
        assert_eq!(f_plunger(0.121_249), "0.1212");
        assert_eq!(f_plunger(1234.56), "1234.6");
        assert_eq!(f_plunger(0.0), "1");
        assert_eq!(significant(2.0), "2");
    }

    /// A line carries the words that change the firmware's state; after `G28`, a
    /// retract's feed, or a move that goes nowhere, the words come back.
    #[test]
    fn lines_leave_out_what_the_firmware_already_holds() {
        let travel = |x_um, z_um| MoveKind::Travel {
            to: PositionUm {
                x_um,
                y_um: 0,
                z_um,
            },
            feed_um_s: 40_000,
        };
        let moves = vec![
            mv(0, MoveKind::Home),
            mv(1, travel(1000, 200)),
            mv(2, extrude(2000, vec![1000, 0])),
            mv(3, extrude(3000, vec![1000, 0])),
            mv(
                4,
                MoveKind::Retract {
                    volumes_nl: vec![50, 50],
                    duration_ms: 100,
                },
            ),
            mv(5, extrude(4000, vec![0, 1000])),
            mv(6, extrude(4000, vec![0, 1000])),
            mv(7, MoveKind::Home),
            mv(8, travel(1000, 400)),
        ];
        let mut text = String::new();
        write_gcode(&moves, 2, &GcodeSettings::default(), &[], &mut text).unwrap();
        let lines: Vec<&str> = text.lines().skip_while(|l| *l != "G28").collect();
        assert_eq!(
            lines,
            vec![
                "G28",
                "G0 X1 Y0 Z0.2 F2400",
                "G1 X2 E0.006061:0 F600",
                "G1 X3 E0.00606:0",
                "G1 E-0.000303:-0.000303 F0.1818 ; retract",
                "G1 X4 E0:0.006061 F600",
                "G1 X4 Y0 Z0.2 E0:0.00606",
                "G28",
                "G0 X1 Y0 Z0.4 F2400",
            ]
        );
    }

    #[test]
    fn klipper_writes_absolute_axis_positions_per_syringe() {
        let moves = vec![
            mv(0, MoveKind::Home),
            mv(1, extrude(1000, vec![300, 100])),
            mv(
                2,
                MoveKind::Retract {
                    volumes_nl: vec![50, 50],
                    duration_ms: 100,
                },
            ),
            mv(
                3,
                MoveKind::Prime {
                    volumes_nl: vec![50, 50],
                    duration_ms: 100,
                },
            ),
            mv(4, extrude(2000, vec![300, 0])),
        ];
        let mut text = String::new();
        let stats = write_gcode(&moves, 2, &klipper(vec!['u', 'V']), &[], &mut text).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        // Released, zeroed and taken again, whatever state the axis was in; released
        // at the end so a macro can move the plunger.
        let u = lines
            .iter()
            .position(|l| l.starts_with("MANUAL_STEPPER STEPPER=syringe_u"))
            .unwrap();
        assert_eq!(
            lines[u..u + 3],
            [
                "MANUAL_STEPPER STEPPER=syringe_u GCODE_AXIS=",
                "MANUAL_STEPPER STEPPER=syringe_u SET_POSITION=0",
                "MANUAL_STEPPER STEPPER=syringe_u GCODE_AXIS=U LIMIT_VELOCITY=2 LIMIT_ACCEL=20",
            ]
        );
        assert!(lines.contains(
            &"MANUAL_STEPPER STEPPER=syringe_v GCODE_AXIS=V LIMIT_VELOCITY=2 LIMIT_ACCEL=20"
        ));
        assert_eq!(
            lines[lines.len() - 4..],
            [
                "MANUAL_STEPPER STEPPER=syringe_u GCODE_AXIS=",
                "MANUAL_STEPPER STEPPER=syringe_u MOVE=0.006",
                "MANUAL_STEPPER STEPPER=syringe_v GCODE_AXIS=",
                "MANUAL_STEPPER STEPPER=syringe_v MOVE=0.001",
            ]
        );
        // 300 nl in a 100 mm² barrel: 0.003 mm; the retract pulls 0.0005 back and the
        // prime pushes it again; the second move adds 0.003 to U only. Words that do
        // not change what the firmware holds are left out (modal).
        assert!(
            lines.contains(&"G1 X1 Y0 Z0.2 U0.003 V0.001 F600"),
            "{lines:?}"
        );
        // 0.0005 mm in 100 ms: 0.3 mm/min, so the retract lasts what was planned.
        assert!(lines.contains(&"G1 U0.0025 V0.0005 F0.3 ; retract"));
        assert!(lines.contains(&"G1 U0.003 V0.001 ; prime"));
        assert!(lines.contains(&"G1 X2 U0.006 F600"));
        assert_eq!(stats.extrude_e_mm, vec![0.006, 0.001]);
        assert_eq!(
            summed_drive_e(&text, 2, Dialect::Klipper),
            vec![0.006, 0.001]
        );
        assert_eq!(stats.lines, lines.len());
    }

    #[test]
    fn klipper_axes_default_and_refusals() {
        let mut out = Vec::new();
        let mut w = MoveWriter::new(3, &klipper(Vec::new())).unwrap();
        w.preamble(&[], &mut out);
        assert!(out.iter().any(|l| l.contains("GCODE_AXIS=C ")));
        let refuse = |axes: Vec<char>, drives| MoveWriter::new(drives, &klipper(axes)).err();
        assert_eq!(
            refuse(vec!['A'], 2),
            Some(GcodeError::AxesCount {
                letters: 1,
                drives: 2
            })
        );
        assert_eq!(
            refuse(vec!['A', 'E'], 2),
            Some(GcodeError::ReservedAxis('E'))
        );
        assert_eq!(
            refuse(vec!['A', 'a'], 2),
            Some(GcodeError::RepeatedAxis('a'))
        );
        assert_eq!(
            refuse(vec!['A', '1'], 2),
            Some(GcodeError::ReservedAxis('1'))
        );
        assert!(refuse(Vec::new(), 18).is_some());
    }

    #[test]
    fn move_writer_lines_are_the_file_lines() {
        use crate::gcode_link::MixWriting;
        for mix in [
            MixWriting::PerDriveE,
            MixWriting::MarlinM163,
            MixWriting::MarlinDirect,
            MixWriting::Axes(vec!['A', 'B']),
        ] {
            let settings = GcodeSettings::for_mix(&mix, 165.0);
            let moves: Vec<Move> = (0..50)
                .map(|i| mv(i, extrude(i as i32 * 100, vec![100 + i * 7, 400 - i * 3])))
                .collect();
            let mut file = String::new();
            write_gcode(&moves, 2, &settings, &["h".into()], &mut file).unwrap();
            let mut w = MoveWriter::new(2, &settings).unwrap();
            let mut lines = Vec::new();
            w.preamble(&["h".into()], &mut lines);
            for m in &moves {
                w.move_lines(m, &mut lines);
            }
            w.epilogue(&mut lines);
            let streamed: Vec<&str> = lines.iter().map(String::as_str).collect();
            assert_eq!(file.lines().collect::<Vec<_>>(), streamed, "{mix:?}");
        }
    }
}
