//! Where a line leaves the nozzle: the X, Y and Z a G-code line ends at, in µm, from where
//! the line before it ended. A firmware that cannot say whether a line ran (RRF's line
//! number is set before its checksum is checked) can say where its nozzle stands; when a
//! line and the one before it end at different places, that position says which ran
//! (`docs/firmware.md`, "Exactly once by position").

use super::command_word;

/// The nozzle's X, Y, Z in µm after a line, as edod's G-code writes them (three
/// decimals of a millimetre, so exact); `None` for an axis not known (after `G28`, before a
/// move names it; in relative mode).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct NozzleAt {
    /// X, Y, Z, µm.
    pub xyz_um: [Option<i64>; 3],
    /// `G91`: moves are relative, so their words say nothing of where they end.
    pub relative: bool,
}

impl NozzleAt {
    /// Nothing known.
    pub const UNKNOWN: Self = Self {
        xyz_um: [None; 3],
        relative: false,
    };

    /// Where `text` (a line without line number and checksum) leaves the nozzle when it
    /// starts here. Moves (`G0`–`G3`) set the axes they name; `G28` forgets the axes it
    /// homes (all when it names none); `G92` sets the axes it names; `G90`/`G91` switch
    /// absolute and relative. Anything else leaves it where it was.
    pub fn after(self, text: &str) -> Self {
        let code = text.split(';').next().unwrap_or_default();
        let Some(word) = command_word(code) else {
            return self;
        };
        let mut at = self;
        let named = axis_words(code);
        match word.as_str() {
            "G0" | "G1" | "G2" | "G3" => {
                for (k, value) in named.into_iter().enumerate() {
                    if let Some(v) = value {
                        at.xyz_um[k] = if at.relative { None } else { v };
                    }
                }
            }
            "G28" => {
                let all = named.iter().all(Option::is_none);
                for (k, value) in named.into_iter().enumerate() {
                    if all || value.is_some() {
                        at.xyz_um[k] = None;
                    }
                }
            }
            "G92" => {
                for (k, value) in named.into_iter().enumerate() {
                    if let Some(v) = value {
                        at.xyz_um[k] = v;
                    }
                }
            }
            "G90" => at.relative = false,
            "G91" => {
                at.relative = true;
            }
            _ => {}
        }
        at
    }

    /// Whether the firmware's reported position `xyz_um` is this one: every axis known
    /// here within `tolerance_um`, and at least one known.
    pub fn matches(&self, xyz_um: [i64; 3], tolerance_um: u32) -> bool {
        let tol = i64::from(tolerance_um);
        let mut any = false;
        for (known, at) in self.xyz_um.iter().zip(xyz_um) {
            if let Some(k) = known {
                any = true;
                if (k - at).abs() > tol {
                    return false;
                }
            }
        }
        any
    }

    /// Whether a position reading within `tolerance_um` can tell this from `other`: an
    /// axis both know differs by more than twice the tolerance.
    pub fn tells_apart(&self, other: &Self, tolerance_um: u32) -> bool {
        let tol = 2 * i64::from(tolerance_um);
        self.xyz_um
            .iter()
            .zip(other.xyz_um.iter())
            .any(|(a, b)| matches!((a, b), (Some(a), Some(b)) if (a - b).abs() > tol))
    }
}

/// The X, Y, Z words of a line, µm: `None` for an axis not named, `Some(None)` for one
/// named with a value that does not read as a number.
fn axis_words(code: &str) -> [Option<Option<i64>>; 3] {
    let mut named = [None; 3];
    for w in code.split_ascii_whitespace().skip(1) {
        let mut chars = w.chars();
        let k = match chars.next().map(|c| c.to_ascii_uppercase()) {
            Some('X') => 0,
            Some('Y') => 1,
            Some('Z') => 2,
            _ => continue,
        };
        named[k] = Some(mm_to_um(chars.as_str()));
    }
    named
}

/// A millimetre value as µm (rounded), if it reads as a finite number.
pub fn mm_to_um(text: &str) -> Option<i64> {
    um_of_mm(text.parse().ok()?)
}

/// `mm` in µm (rounded), if finite and within range.
fn um_of_mm(mm: f64) -> Option<i64> {
    let um = (mm * 1000.0).round();
    (um.is_finite() && um.abs() < 1e15).then_some(um as i64)
}

/// The nozzle position in an RRF object-model answer to `M409 K"move.axes"` (or
/// `K"move"`): the `userPosition` of axes 0, 1 and 2 (X, Y, Z), µm. `Ok(None)` for an
/// answer to another key.
pub fn rrf_user_position(json: &str) -> Result<Option<[i64; 3]>, String> {
    let v: serde_json::Value = serde_json::from_str(json).map_err(|e| format!("not JSON: {e}"))?;
    let axes = match v.get("key").and_then(|k| k.as_str()) {
        Some("move.axes") => v.get("result"),
        Some("move") => v.get("result").and_then(|r| r.get("axes")),
        _ => return Ok(None),
    };
    let axes = axes
        .and_then(|a| a.as_array())
        .ok_or("no array of axes in the answer")?;
    let mut at = [0i64; 3];
    for (k, slot) in at.iter_mut().enumerate() {
        let mm = axes
            .get(k)
            .and_then(|a| a.get("userPosition"))
            .and_then(|p| p.as_f64())
            .ok_or_else(|| format!("axis {k} has no userPosition"))?;
        *slot = um_of_mm(mm).ok_or_else(|| format!("axis {k}: {mm} mm"))?;
    }
    Ok(Some(at))
}

/// The object-model answer RRF gives to `M409 K"move.axes" F"f"` for a nozzle at `at`
/// (axes not known read 0, where RRF's homing leaves them on edo's machines).
pub fn rrf_axes_json(at: &NozzleAt) -> String {
    let axes: Vec<serde_json::Value> = at
        .xyz_um
        .iter()
        .map(|um| {
            let mm = um.unwrap_or(0) as f64 / 1000.0;
            serde_json::json!({"machinePosition": mm, "userPosition": mm})
        })
        .collect();
    serde_json::json!({"key": "move.axes", "flags": "f", "result": axes}).to_string()
}

/// Klipper's `GET_POSITION` answer lines that say where the G-code position stands
/// (`gcode_move.py` `cmd_GET_POSITION`, each line of its `respond_info` behind `// `):
/// `// gcode: X:.. Y:.. Z:.. E:..` (the last move queued, which after `M400` is where the
/// nozzle stopped) and `// gcode base: X:.. Y:.. Z:.. E:..` (the `G92` offsets), µm.
/// `M114` would say the same, but Kalico 2026.10 formats its answer with every axis and
/// shuts down (`not all arguments converted`) once syringe axes are registered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KlipperPositionLine {
    /// `gcode:`.
    Gcode([i64; 3]),
    /// `gcode base:`.
    GcodeBase([i64; 3]),
}

/// Read one line of Klipper's `GET_POSITION` answer ([`KlipperPositionLine`]).
pub fn klipper_position_line(line: &str) -> Option<KlipperPositionLine> {
    let rest = line.trim().strip_prefix("//")?.trim_start();
    let (kind, rest): (fn([i64; 3]) -> KlipperPositionLine, &str) =
        if let Some(r) = rest.strip_prefix("gcode base:") {
            (KlipperPositionLine::GcodeBase, r)
        } else if let Some(r) = rest.strip_prefix("gcode:") {
            (KlipperPositionLine::Gcode, r)
        } else {
            return None;
        };
    let mut words = rest.split_ascii_whitespace();
    let mut at = [0i64; 3];
    for (slot, axis) in at.iter_mut().zip(["X:", "Y:", "Z:"]) {
        *slot = mm_to_um(words.next()?.strip_prefix(axis)?)?;
    }
    Some(kind(at))
}

/// Klipper's answer lines to `GET_POSITION` for a nozzle at `at` (axes not known read
/// 0), as its `respond_info` writes them.
pub fn klipper_get_position_lines(at: &NozzleAt) -> Vec<String> {
    let mm = |k: usize| at.xyz_um[k].unwrap_or(0) as f64 / 1000.0;
    let xyze = format!("X:{:.6} Y:{:.6} Z:{:.6} E:0.000000", mm(0), mm(1), mm(2));
    vec![
        "mcu: stepper_x:0 stepper_y:0 stepper_z:0".into(),
        format!(
            "stepper: stepper_x:{:.6} stepper_y:{:.6} stepper_z:{:.6}",
            mm(0),
            mm(1),
            mm(2)
        ),
        format!("kinematic: X:{:.6} Y:{:.6} Z:{:.6}", mm(0), mm(1), mm(2)),
        format!("toolhead: {xyze}"),
        format!("gcode: {xyze}"),
        "gcode base: X:0.000000 Y:0.000000 Z:0.000000 E:0.000000".into(),
        "gcode homing: X:0.000000 Y:0.000000 Z:0.000000".into(),
    ]
}

/// The query whose answer [`klipper_position_line`] reads.
pub const KLIPPER_POSITION_QUERY: &str = "GET_POSITION";

/// The query [`rrf_user_position`] reads.
pub const RRF_POSITION_QUERY: &str = "M409 K\"move.axes\" F\"f\"";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moves_set_what_they_name_and_homing_forgets() {
        let at = NozzleAt::UNKNOWN.after("G0 X102.639 Y102.468 Z0.15 F2400");
        assert_eq!(at.xyz_um, [Some(102_639), Some(102_468), Some(150)]);
        let at = at.after("G1 X100.589 E0.00003:0.000539 F600 ; road");
        assert_eq!(at.xyz_um, [Some(100_589), Some(102_468), Some(150)]);
        assert_eq!(at.after("G1 E-0.001211:0 F0.4844 ; retract"), at);
        assert_eq!(at.after("G4 P100"), at);
        assert_eq!(at.after("G28").xyz_um, [None; 3]);
        assert_eq!(
            at.after("G28 Z").xyz_um,
            [Some(100_589), Some(102_468), None]
        );
        assert_eq!(at.after("G92 X0").xyz_um[0], Some(0));
        let rel = at.after("G91").after("G1 X1");
        assert_eq!(rel.xyz_um[0], None);
        assert_eq!(rel.after("G90").after("G1 X1").xyz_um[0], Some(1000));
        assert_eq!(at.after("G1 X1e400").xyz_um[0], None);
    }

    #[test]
    fn a_reading_tells_two_ends_apart_only_where_they_differ() {
        let a = NozzleAt::UNKNOWN.after("G1 X1 Y2 Z3");
        let b = a.after("G1 X1.5");
        assert!(a.tells_apart(&b, 2));
        assert!(!a.tells_apart(&a.after("G1 E1"), 2));
        assert!(!a.tells_apart(&NozzleAt::UNKNOWN, 2));
        assert!(b.matches([1_501, 2_000, 3_000], 2));
        assert!(!b.matches([1_000, 2_000, 3_000], 2));
        assert!(!NozzleAt::UNKNOWN.matches([0, 0, 0], 2));
    }

    #[test]
    fn klipper_get_position_reads_back() {
        let at = NozzleAt::UNKNOWN.after("G1 X102.639 Y0.001 Z12.5");
        let lines = klipper_get_position_lines(&at);
        let read: Vec<_> = lines
            .iter()
            .filter_map(|l| klipper_position_line(&format!("// {l}")))
            .collect();
        assert_eq!(
            read,
            vec![
                KlipperPositionLine::Gcode([102_639, 1, 12_500]),
                KlipperPositionLine::GcodeBase([0, 0, 0])
            ]
        );
        // As Kalico prints it with the syringes registered (extra axes are not listed).
        assert_eq!(
            klipper_position_line("// gcode: X:10.000000 Y:20.500000 Z:0.200000 E:0.000000"),
            Some(KlipperPositionLine::Gcode([10_000, 20_500, 200]))
        );
        assert_eq!(klipper_position_line("// gcode homing: X:0 Y:0 Z:0"), None);
        assert_eq!(klipper_position_line("// toolhead: X:1 Y:2 Z:3 E:0"), None);
        assert_eq!(klipper_position_line("gcode: X:1 Y:2 Z:3"), None);
        assert_eq!(klipper_position_line("// gcode: X:1 Y:2"), None);
    }

    #[test]
    fn rrf_answers_read_back() {
        let at = NozzleAt::UNKNOWN.after("G1 X102.639 Y0.001 Z12.5");
        let json = rrf_axes_json(&at);
        assert_eq!(rrf_user_position(&json), Ok(Some([102_639, 1, 12_500])));
        let full = r#"{"key":"move","flags":"","result":{"axes":[{"userPosition":1.5},{"userPosition":2},{"userPosition":0.25}]}}"#;
        assert_eq!(rrf_user_position(full), Ok(Some([1_500, 2_000, 250])));
        assert_eq!(
            rrf_user_position(r#"{"key":"inputs","result":[]}"#),
            Ok(None)
        );
        assert!(rrf_user_position(r#"{"key":"move.axes","result":[{}]}"#).is_err());
        assert!(rrf_user_position("{").is_err());
    }
}
