//! G-code export of a move stream, so labs with a Duet (RepRapFirmware) or Marlin mixing
//! syringe printer can build edo's plans without edod. Contract: `docs/gcode.md`.
//!
//! Extrusion is relative (`M83`) and in millimetres of plunger travel: a syringe's volume
//! V (nl) becomes E = V / 1000 / A mm for a barrel cross-section A (mm²). Printed E values
//! are rounded cumulatively per drive (to 10⁻⁵ mm), so the sum of each drive's E over the
//! file equals that drive's commanded volume / A within 10⁻⁵ mm.

use super::{Move, MoveKind, PositionUm};
use serde::{Deserialize, Serialize};
use std::fmt::Write;

/// Which firmware reads the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "daemon", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Flavor {
    /// RepRapFirmware 3: a tool over all drives (`M563 P0 D0:1:..`), per-move `E a:b:c`.
    Rrf,
    /// Marlin with `MIXING_EXTRUDER`: mix set per move with `M163`/`M164` (or `A B C ..`
    /// weights in `G1` with `DIRECT_MIXING_IN_G1`), total E per move.
    Marlin,
}

/// Export settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GcodeSettings {
    pub flavor: Flavor,
    /// Barrel cross-section of every syringe, mm². Default 165 (a 10 mL syringe, 14.5 mm
    /// bore).
    pub barrel_area_mm2: f64,
    /// Marlin only: put the mix into `G1` as `A B C ..` weights (`DIRECT_MIXING_IN_G1`)
    /// instead of `M163`/`M164` lines. Default false.
    pub marlin_direct_mixing: bool,
}

impl Default for GcodeSettings {
    fn default() -> Self {
        GcodeSettings {
            flavor: Flavor::Rrf,
            barrel_area_mm2: 165.0,
            marlin_direct_mixing: false,
        }
    }
}

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

fn e(units: i64) -> String {
    let sign = if units < 0 { "-" } else { "" };
    let u = units.unsigned_abs();
    format!("{sign}{}.{:06}", u / 1_000_000, u % 1_000_000)
}

fn mm(um: i32) -> String {
    let sign = if um < 0 { "-" } else { "" };
    let u = um.unsigned_abs();
    format!("{sign}{}.{:03}", u / 1000, u % 1000)
}

fn f_mm_min(um_s: u32) -> String {
    format!("{:.1}", f64::from(um_s) * 60.0 / 1000.0)
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
    let mut w = GcodeLines::new(drives, settings)?;
    out.push_str(&w.preamble(header));
    for m in moves {
        out.push_str(&w.of_move(m));
    }
    Ok(w.stats())
}

/// The G-code of a move stream, one move at a time: the lines [`write_gcode`] writes,
/// for a file or for edod's G-code link (`daemon::gcode_link`), which streams exactly
/// these lines without their comments. Keeps the E rounding and the Marlin mix between
/// moves, so a stream must go through one `GcodeLines` from its first move.
pub struct GcodeLines(GcodeWriter);

impl GcodeLines {
    /// Lines for a job over `drives` syringes written with `settings`.
    pub fn new(drives: usize, settings: &GcodeSettings) -> Result<Self, GcodeError> {
        let a = settings.barrel_area_mm2;
        if !(a.is_finite() && a > 0.0) {
            return Err(GcodeError::BarrelArea(a));
        }
        if settings.flavor == Flavor::Marlin && drives > MARLIN_MIX_AXES.len() {
            return Err(GcodeError::TooManyDrives(drives));
        }
        let drives = drives.max(1);
        Ok(Self(GcodeWriter {
            out: String::new(),
            lines: 0,
            settings: settings.clone(),
            drives,
            ext: vec![Drive::default(); drives],
            aux: vec![Drive::default(); drives],
            mix: MarlinMix::new(drives),
        }))
    }

    /// The file's start: `header` as comments, the flavour's tool set-up, units and
    /// modes; each line ends in `\n`.
    pub fn preamble(&mut self, header: &[String]) -> String {
        self.0.preamble(header);
        std::mem::take(&mut self.0.out)
    }

    /// The lines of move `m` (a Marlin mix it needs first); each ends in `\n`.
    pub fn of_move(&mut self, m: &Move) -> String {
        let mut s = String::new();
        self.0.command(m, &mut s);
        self.0.line(&s);
        std::mem::take(&mut self.0.out)
    }

    /// What was written so far.
    pub fn stats(&self) -> GcodeStats {
        GcodeStats {
            extrude_e_mm: self
                .0
                .ext
                .iter()
                .map(|d| d.printed_units as f64 / 1e6)
                .collect(),
            lines: self.0.lines,
        }
    }
}

/// The text being written and the E rounding state of every drive.
struct GcodeWriter {
    out: String,
    /// Lines written.
    lines: usize,
    settings: GcodeSettings,
    drives: usize,
    /// Extrusion E per drive.
    ext: Vec<Drive>,
    /// Retract/prime E, rounded on its own so it never disturbs the extrusion sums.
    aux: Vec<Drive>,
    mix: MarlinMix,
}

impl GcodeWriter {
    fn line(&mut self, s: &str) {
        self.out.push_str(s);
        self.out.push('\n');
        self.lines += 1;
    }

    /// The header comments, the flavour's tool set-up and the units and modes.
    fn preamble(&mut self, header: &[String]) {
        for h in header {
            self.line(&format!("; {h}"));
        }
        let all: Vec<String> = (0..self.drives).map(|d| d.to_string()).collect();
        match self.settings.flavor {
            Flavor::Rrf => {
                self.line("; RepRapFirmware 3: one mixing tool over all syringe drives");
                self.line(&format!("M563 P0 D{} H-1 S\"edo\"", all.join(":")));
                self.line("T0");
            }
            Flavor::Marlin => {
                self.line("; Marlin MIXING_EXTRUDER: mix per move, E is the total plunger travel");
                self.line("T0");
            }
        }
        self.line("G21 ; millimetres");
        self.line("G90 ; absolute positions");
        self.line("M83 ; relative extrusion");
    }

    /// The command of one move into `s` (a Marlin mix it needs is written first).
    fn command(&mut self, m: &Move, s: &mut String) {
        match &m.kind {
            MoveKind::Home => s.push_str("G28"),
            MoveKind::LayerMark { layer, z_um } => {
                let _ = write!(s, ";LAYER:{layer} Z{}", mm(*z_um));
            }
            MoveKind::Dwell { duration_ms } => {
                let _ = write!(s, "G4 P{duration_ms}");
            }
            MoveKind::Travel { to, feed_um_s } => {
                let _ = write!(
                    s,
                    "G0 X{} Y{} Z{} F{}",
                    mm(to.x_um),
                    mm(to.y_um),
                    mm(to.z_um),
                    f_mm_min(*feed_um_s)
                );
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
            } => self.extrude(to, *feed_um_s, volumes_nl, s),
        }
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
            Flavor::Rrf => {
                let es: Vec<String> = units.iter().map(|&u| e(u)).collect();
                let _ = write!(s, "G1 E{} F{:.1} ; {what}", es.join(":"), feed.max(1.0));
            }
            Flavor::Marlin => {
                let total: i64 = units.iter().sum();
                let _ = write!(s, "G1 E{} F{:.1} ; {what}", e(total), feed.max(1.0));
            }
        }
    }

    /// An extruding move: per-drive E (RRF), or total E with the mix as `G1` weights or
    /// `M163`/`M164` lines before it (Marlin).
    fn extrude(&mut self, to: &PositionUm, feed_um_s: u32, volumes_nl: &[u32], s: &mut String) {
        let area_mm2 = self.settings.barrel_area_mm2;
        let units: Vec<i64> = (0..self.drives)
            .map(|d| {
                let travel_mm = volumes_nl.get(d).map_or(0.0, |&v| nl_to_mm(v, area_mm2));
                self.ext[d].add(travel_mm)
            })
            .collect();
        let xyz = format!("G1 X{} Y{} Z{}", mm(to.x_um), mm(to.y_um), mm(to.z_um));
        match self.settings.flavor {
            Flavor::Rrf => {
                let es: Vec<String> = units.iter().map(|&u| e(u)).collect();
                let _ = write!(s, "{xyz} E{} F{}", es.join(":"), f_mm_min(feed_um_s));
            }
            Flavor::Marlin => {
                let total: i64 = units.iter().sum();
                if self.settings.marlin_direct_mixing {
                    let _ = write!(s, "{xyz} E{}", e(total));
                    if total > 0 {
                        for (d, u) in units.iter().enumerate() {
                            let _ = write!(s, " {}{}", MARLIN_MIX_AXES[d], e(*u));
                        }
                    }
                    let _ = write!(s, " F{}", f_mm_min(feed_um_s));
                } else {
                    if let Some(weights) = self.mix.next(&units) {
                        for (d, w) in weights.iter().enumerate() {
                            self.line(&format!("M163 S{d} P{w:.6}"));
                        }
                        self.line("M164 S0");
                    }
                    let _ = write!(s, "{xyz} E{} F{}", e(total), f_mm_min(feed_um_s));
                }
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
        let off_after = |w: &[f64]| {
            let wsum: f64 = w.iter().sum();
            self.split
                .iter()
                .zip(&self.planned)
                .zip(w)
                .map(|((s, p), wi)| (s + t * wi / wsum - p).abs())
                .fold(0.0, f64::max)
        };
        let new = match (&self.weights, self.paying) {
            (None, _) => Some(base.clone()),
            (Some(w), _) if off_after(w) > Self::DRIFT => {
                // Pay back what is owed before this move over the next WINDOW moves.
                self.paying = Some(Self::WINDOW);
                let k = Self::WINDOW as f64;
                Some(
                    base.iter()
                        .zip(&before)
                        .map(|(b, owed)| (b + owed / (k * t)).max(0.0))
                        .collect(),
                )
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
/// (or the `A B C` weights on the line).
pub fn summed_drive_e(gcode: &str, drives: usize, flavor: Flavor) -> Vec<f64> {
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
        if !code.starts_with("G1 X") {
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
            Flavor::Rrf => {
                for (s, v) in sums.iter_mut().zip(&es) {
                    *s += v;
                }
            }
            Flavor::Marlin => {
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
