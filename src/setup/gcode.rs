//! `[machine] protocol` and the `[machine.gcode]` table (`docs/firmware.md`,
//! "Configuration"): which firmware is at the other end of a G-code line, how the mix is
//! written, the window and the timeouts, resolved into the host end's
//! [`LineLinkConfig`] and the mix writing. Every impossible combination is refused with
//! the dotted key that is wrong.

use serde::{Deserialize, Serialize};

use crate::gcode_link::{
    estop_bytes_for, Dialect, LineLinkConfig, MixWriting, Window as LinkWindow,
};

use super::{KeyError, SyringeConfig};

/// `machine.protocol`: what `serial.port` speaks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// edo's framed link (`docs/protocol.md`): hil-sim or an edo machine.
    #[default]
    Edo,
    /// G-code lines to RepRapFirmware, Marlin or Klipper (`docs/firmware.md`).
    Gcode,
}

/// `machine.gcode.mix`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum MixName {
    /// RRF `G1 ... E a:b:c`.
    PerDriveE,
    /// Marlin `M163`/`M164`.
    M163,
    /// Marlin `DIRECT_MIXING_IN_G1`.
    Direct,
    /// One axis per syringe (`axes`).
    Axes,
}

/// `machine.gcode.window`: `"auto"`, `"advanced-ok"` or a number of lines.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize)]
#[serde(untagged)]
pub enum WindowSetting {
    /// A number of lines.
    Lines(u64),
    /// `"auto"` or `"advanced-ok"`.
    Named(String),
}

impl Default for WindowSetting {
    fn default() -> Self {
        WindowSetting::Named("auto".into())
    }
}

/// `[machine.gcode]`.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct GcodeConfig {
    /// `"rrf"`, `"marlin"` or `"klipper"`.
    pub firmware: Dialect,
    /// How the mix is written (default per firmware).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mix: Option<MixName>,
    /// One axis letter per syringe, with `mix = "axes"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axes: Option<Vec<String>>,
    /// Barrel cross-section the firmware's steps/mm are set for, mm² (default: from the
    /// syringes' bore).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub barrel_area_mm2: Option<f64>,
    /// Lines in flight.
    #[serde(default)]
    pub window: WindowSetting,
    /// The firmware's receive buffer, bytes (default per firmware).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rx_buffer_bytes: Option<usize>,
    /// No `ok` for this long with lines in flight: the link timed out.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ok_timeout_ms: Option<u64>,
    /// The same once the firmware sends `busy:` keepalives.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub busy_timeout_ms: Option<u64>,
    /// The timeout while a slow command (homing, heating, `M400`) is in flight.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slow_command_timeout_s: Option<u64>,
    /// Each handshake attempt waits this long.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub handshake_timeout_ms: Option<u64>,
    /// RRF: the `inputs[]` channel edod is on (`"USB"`, `"Aux"`, `"Aux2"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rrf_input: Option<String>,
}

/// A `[machine.gcode]` resolved: the host end's settings and how moves are written.
#[derive(Debug, Clone, PartialEq)]
pub struct GcodeLink {
    /// The host end (`gcode_link::LineHost::new`).
    pub link: LineLinkConfig,
    /// How the mix is written.
    pub mix: MixWriting,
    /// Barrel cross-section, mm² (E = V / 1000 / A).
    pub barrel_area_mm2: f64,
    /// Each syringe's plunger limits (Klipper's `LIMIT_VELOCITY`, `LIMIT_ACCEL`).
    pub plunger_limits: Vec<crate::gcode_link::writer::PlungerLimits>,
}

impl GcodeLink {
    /// How edod writes this machine's moves: what `edoctl plan --machine` writes too.
    pub fn settings(&self) -> crate::gcode_link::writer::GcodeSettings {
        crate::gcode_link::writer::GcodeSettings {
            plunger_limits: self.plunger_limits.clone(),
            ..crate::gcode_link::writer::GcodeSettings::for_mix(&self.mix, self.barrel_area_mm2)
        }
    }
}

fn err<T>(key: &str, message: impl Into<String>) -> Result<T, KeyError> {
    Err((format!("machine.gcode.{key}"), message.into()))
}

/// Axis letters Klipper cannot take for a manual stepper (its own axes and words).
const KLIPPER_RESERVED: &str = "XYZEFGMNT";
/// Marlin's names for axes 4 and up (`AXIS4_NAME` ...).
const MARLIN_AXIS_NAMES: &str = "ABCUVW";
/// Marlin mixing letters A B C D H I: at most 6 drives.
const MARLIN_MIX_DRIVES: usize = 6;

impl GcodeConfig {
    /// Check every key against the firmware and the syringes, and resolve the settings;
    /// `baud` caps the bytes in flight (the e-stop's bound).
    pub fn resolve(&self, syringes: &[SyringeConfig], baud: u32) -> Result<GcodeLink, KeyError> {
        let mix = self.mix_writing(syringes.len())?;
        let barrel_area_mm2 = self.barrel_area(syringes, &mix)?;
        let mut link = LineLinkConfig::for_dialect(self.firmware);
        link.window = self.window()?;
        if let Some(rx) = self.rx_buffer_bytes {
            let least = link.max_line_bytes + 1 + link.estop_reserve_bytes;
            if !(least..=65_536).contains(&rx) {
                return err(
                    "rx_buffer_bytes",
                    format!("{rx}: must hold the longest line and the e-stop ({least} to 65536)"),
                );
            }
            link.rx_buffer_bytes = rx;
        }
        link.max_bytes_in_flight = estop_bytes_for(baud, link.max_line_bytes);
        self.timeouts(&mut link)?;
        if let Some(input) = &self.rrf_input {
            if self.firmware != Dialect::Rrf {
                return err("rrf_input", "only with firmware = \"rrf\"");
            }
            if !["USB", "Aux", "Aux2"].contains(&input.as_str()) {
                return err(
                    "rrf_input",
                    format!("{input:?}: \"USB\", \"Aux\" or \"Aux2\""),
                );
            }
            link.rrf_input_name = input.clone();
        }
        Ok(GcodeLink {
            link,
            mix,
            barrel_area_mm2,
            plunger_limits: syringes.iter().map(SyringeConfig::plunger_limits).collect(),
        })
    }

    /// `mix` and `axes` against the firmware and the number of syringes.
    fn mix_writing(&self, syringes: usize) -> Result<MixWriting, KeyError> {
        let mix = self.mix.unwrap_or(match self.firmware {
            Dialect::Rrf => MixName::PerDriveE,
            Dialect::Marlin => MixName::M163,
            Dialect::Klipper => MixName::Axes,
        });
        let possible = match self.firmware {
            Dialect::Rrf => mix == MixName::PerDriveE,
            Dialect::Marlin => mix != MixName::PerDriveE,
            Dialect::Klipper => mix == MixName::Axes,
        };
        if !possible {
            return err(
                "mix",
                format!(
                    "{mix:?} is not a mix {:?} can write (rrf: \"per-drive-e\"; marlin: \"m163\", \
                     \"direct\" or \"axes\"; klipper: \"axes\")",
                    self.firmware
                ),
            );
        }
        if mix != MixName::Axes {
            if self.axes.is_some() {
                return err("axes", "only with mix = \"axes\"");
            }
            if self.firmware == Dialect::Marlin && syringes > MARLIN_MIX_DRIVES {
                return Err((
                    "machine.syringes".into(),
                    format!("{syringes} syringes: Marlin mixing drives at most 6"),
                ));
            }
        }
        Ok(match mix {
            MixName::PerDriveE => MixWriting::PerDriveE,
            MixName::M163 => MixWriting::MarlinM163,
            MixName::Direct => MixWriting::MarlinDirect,
            MixName::Axes => MixWriting::Axes(self.axis_letters(syringes)?),
        })
    }

    /// `axes`: one distinct letter per syringe, none the firmware reserves.
    fn axis_letters(&self, syringes: usize) -> Result<Vec<char>, KeyError> {
        let Some(axes) = &self.axes else {
            return err("axes", "mix = \"axes\" needs one axis letter per syringe");
        };
        if axes.len() != syringes {
            return err(
                "axes",
                format!("{} letters for {syringes} syringes", axes.len()),
            );
        }
        let mut letters = Vec::with_capacity(axes.len());
        for a in axes {
            let mut chars = a.chars();
            let (Some(c), None) = (chars.next(), chars.next()) else {
                return err("axes", format!("{a:?} is not one letter"));
            };
            let c = c.to_ascii_uppercase();
            let allowed = match self.firmware {
                Dialect::Marlin => MARLIN_AXIS_NAMES.contains(c),
                _ => c.is_ascii_alphabetic() && !KLIPPER_RESERVED.contains(c),
            };
            if !allowed {
                let which = match self.firmware {
                    Dialect::Marlin => "Marlin names extra axes A B C U V W",
                    _ => "Klipper takes any letter but X Y Z E F G M N T",
                };
                return err("axes", format!("{a:?}: {which}"));
            }
            if letters.contains(&c) {
                return err("axes", format!("{a:?} is given twice"));
            }
            letters.push(c);
        }
        Ok(letters)
    }

    /// `barrel_area_mm2`, or the syringes' common bore.
    fn barrel_area(&self, syringes: &[SyringeConfig], mix: &MixWriting) -> Result<f64, KeyError> {
        let bores: Vec<f64> = syringes.iter().map(|s| s.barrel_diameter_mm).collect();
        let same_bore = bores.windows(2).all(|w| (w[0] - w[1]).abs() < 1e-9);
        let mixing = matches!(mix, MixWriting::MarlinM163 | MixWriting::MarlinDirect);
        if mixing && !same_bore {
            return Err((
                "machine.syringes".into(),
                format!(
                    "bores {bores:?} differ: Marlin mixing drives share one steps/mm, so every \
                     barrel must have the same bore"
                ),
            ));
        }
        match self.barrel_area_mm2 {
            Some(a) if a.is_finite() && a > 0.0 => Ok(a),
            Some(a) => err("barrel_area_mm2", format!("{a} must be positive")),
            None if same_bore => {
                let d = bores.first().copied().unwrap_or(0.0);
                Ok(std::f64::consts::PI / 4.0 * d * d)
            }
            None => err(
                "barrel_area_mm2",
                format!(
                    "the syringes' bores {bores:?} differ: give the area the firmware's steps/mm \
                     are set for"
                ),
            ),
        }
    }

    /// `window` against the firmware.
    fn window(&self) -> Result<LinkWindow, KeyError> {
        let w = match &self.window {
            WindowSetting::Named(n) if n == "auto" => LinkWindow::Auto,
            WindowSetting::Named(n) if n == "advanced-ok" => {
                if self.firmware != Dialect::Marlin {
                    return err("window", "\"advanced-ok\" is Marlin's (ADVANCED_OK)");
                }
                LinkWindow::AdvancedOk
            }
            WindowSetting::Named(n) => {
                return err(
                    "window",
                    format!("{n:?}: \"auto\", \"advanced-ok\" or a number of lines"),
                )
            }
            WindowSetting::Lines(n) => {
                let most = match self.firmware {
                    Dialect::Rrf => 1,
                    Dialect::Klipper => 19,
                    Dialect::Marlin => 64,
                };
                if *n == 0 || *n > most {
                    let why = match self.firmware {
                        Dialect::Rrf => {
                            "RRF drops a bad line silently and runs the next: edod keeps one \
                             line in flight (docs/firmware.md, \"Windows\")"
                        }
                        Dialect::Klipper => "Klipper sees M112 at once only below 20 lines pending",
                        Dialect::Marlin => "Marlin's command queue holds fewer",
                    };
                    return err("window", format!("{n}: 1 to {most} lines; {why}"));
                }
                LinkWindow::Lines(u16::try_from(*n).unwrap_or(1))
            }
        };
        Ok(w)
    }

    /// The timeout keys, each within bounds.
    fn timeouts(&self, link: &mut LineLinkConfig) -> Result<(), KeyError> {
        const MS: std::ops::RangeInclusive<u64> = 100..=600_000;
        for (key, value, target) in [
            ("ok_timeout_ms", self.ok_timeout_ms, &mut link.ok_timeout_us),
            (
                "busy_timeout_ms",
                self.busy_timeout_ms,
                &mut link.busy_timeout_us,
            ),
            (
                "handshake_timeout_ms",
                self.handshake_timeout_ms,
                &mut link.handshake_timeout_us,
            ),
        ] {
            if let Some(ms) = value {
                if !MS.contains(&ms) {
                    return err(key, format!("{ms} ms: 100 ms to 10 min"));
                }
                *target = ms * 1000;
            }
        }
        if let Some(s) = self.slow_command_timeout_s {
            if !(1..=86_400).contains(&s) {
                return err("slow_command_timeout_s", format!("{s} s: 1 s to 24 h"));
            }
            link.slow_command_timeout_us = s * 1_000_000;
        }
        Ok(())
    }
}
