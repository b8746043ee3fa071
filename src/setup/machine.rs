//! `[machine]` of edod.toml: the syringes, sizes, speeds and build volume of the machine
//! a job is built on, each value checked and a wrong one named by its dotted key.

use serde::Deserialize;

use super::{GcodeConfig, KeyError, Protocol};

/// One syringe (primary material).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SyringeConfig {
    /// The syringe's name, unique on the machine: a job's material of this name is
    /// pushed from it (or a job maps its materials: `materials.syringes`).
    pub name: String,
    /// Barrel bore (mm).
    pub barrel_diameter_mm: f64,
    /// Capacity (ml).
    pub capacity_ml: f64,
    /// Highest plunger speed, mm/s (default 2). On Klipper it is the syringe axis'
    /// `LIMIT_VELOCITY` (`docs/gcode.md`).
    #[serde(default = "default_max_plunger")]
    pub max_plunger_mm_s: f64,
    /// Highest plunger acceleration, mm/s² (default 20); Klipper's `LIMIT_ACCEL`.
    #[serde(default = "default_max_plunger_accel")]
    pub max_plunger_accel_mm_s2: f64,
    /// What the syringe holds: a part material (`"part"`, default), or the support
    /// ink (`"support"`: a fugitive ink such as Pluronic or wax, pushed pure for a
    /// job's `[support] syringe` of its name; at most one per machine).
    #[serde(default, skip_serializing_if = "SyringeRole::is_part")]
    pub role: SyringeRole,
}

/// `[[machine.syringes]] role`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SyringeRole {
    #[default]
    Part,
    Support,
}

impl SyringeRole {
    fn is_part(&self) -> bool {
        *self == SyringeRole::Part
    }
}

impl SyringeConfig {
    /// The plunger's limits.
    pub fn plunger_limits(&self) -> crate::gcode_link::writer::PlungerLimits {
        crate::gcode_link::writer::PlungerLimits {
            max_mm_s: self.max_plunger_mm_s,
            max_accel_mm_s2: self.max_plunger_accel_mm_s2,
        }
    }
}

fn default_max_plunger() -> f64 {
    crate::gcode_link::writer::PlungerLimits::default().max_mm_s
}
fn default_max_plunger_accel() -> f64 {
    crate::gcode_link::writer::PlungerLimits::default().max_accel_mm_s2
}

/// `[machine]`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct MachineConfig {
    /// Syringes in order (default: two 10 ml syringes, 10 mm bore, "A" and "B").
    #[serde(default = "default_syringes")]
    pub syringes: Vec<SyringeConfig>,
    /// Nozzle diameter (mm, default 0.4).
    #[serde(default = "default_nozzle")]
    pub nozzle_mm: f64,
    /// Machine resolution R_mach (mm, default 0.2).
    #[serde(default = "default_r_mach")]
    pub r_mach_mm: f64,
    /// Build volume X, Y, Z (mm, default 200 × 200 × 150).
    #[serde(default = "default_build_volume")]
    pub build_volume_mm: [f64; 3],
    /// Highest feed rate (mm/s, default 50).
    #[serde(default = "default_max_feed")]
    pub max_feed_mm_s: f64,
    /// Highest flow/width factor in narrow areas (default 1.5).
    #[serde(default = "default_max_flow_factor")]
    pub max_flow_factor: f64,
    /// Mixing-chamber dead volume V_dead (nl, default 20 000).
    #[serde(default = "default_dead_volume")]
    pub dead_volume_nl: u64,
    /// Volume pushed through the nozzle when (re)priming (nl, default 2 000).
    #[serde(default = "default_prime")]
    pub prime_nl: u32,
    /// Where a cancelled job parks the nozzle (mm, default 0, 0, 50).
    #[serde(default = "default_park")]
    pub park_mm: [f64; 3],
    /// Lift above the resume point before travelling to it (mm, default 2).
    #[serde(default = "default_lift")]
    pub resume_lift_mm: f64,
    /// What `serial.port` speaks (default `"edo"`; `docs/firmware.md`).
    #[serde(default)]
    pub protocol: Protocol,
    /// `[machine.gcode]`: with `protocol = "gcode"` only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gcode: Option<GcodeConfig>,
    /// `[machine.mixer]`: the mixing chamber's residence-time distribution (default:
    /// plug flow through `dead_volume_nl`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mixer: Option<MixerConfig>,
}

/// `[machine.mixer]`: the mixing chamber (`edo::mixer`).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct MixerConfig {
    /// `"plug"` (default), `"mixed"` or `"dispersion"`.
    #[serde(default = "default_mixer_model")]
    pub model: String,
    /// The chamber's volume, nl (default `machine.dead_volume_nl`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume_nl: Option<f64>,
    /// Peclet number of the `dispersion` model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peclet: Option<f64>,
}

fn default_mixer_model() -> String {
    "plug".to_string()
}

fn default_syringes() -> Vec<SyringeConfig> {
    ["A", "B"]
        .iter()
        .map(|n| SyringeConfig {
            role: SyringeRole::Part,
            name: (*n).to_string(),
            barrel_diameter_mm: 10.0,
            capacity_ml: 10.0,
            max_plunger_mm_s: default_max_plunger(),
            max_plunger_accel_mm_s2: default_max_plunger_accel(),
        })
        .collect()
}
fn default_nozzle() -> f64 {
    0.4
}
fn default_r_mach() -> f64 {
    0.2
}
fn default_build_volume() -> [f64; 3] {
    [200.0, 200.0, 150.0]
}
fn default_max_feed() -> f64 {
    50.0
}
fn default_max_flow_factor() -> f64 {
    1.5
}
fn default_dead_volume() -> u64 {
    20_000
}
fn default_prime() -> u32 {
    2_000
}
fn default_park() -> [f64; 3] {
    [0.0, 0.0, 50.0]
}
fn default_lift() -> f64 {
    2.0
}

impl MachineConfig {
    /// `[machine]`: syringes, sizes and speeds, the build volume and what must lie in it.
    pub fn check(&self) -> Result<(), KeyError> {
        let bad = |key: &str, message: String| (key.to_string(), message);
        self.mixer()
            .map_err(|e| bad(&format!("machine.mixer.{}", e.key), e.message))?;
        let n = self.syringes.len();
        if n == 0 || n > crate::machine::MAX_SYRINGES {
            return Err(bad(
                "machine.syringes",
                format!(
                    "{n} syringes; 1 to {} allowed",
                    crate::machine::MAX_SYRINGES
                ),
            ));
        }
        for (i, s) in self.syringes.iter().enumerate() {
            // Jobs name their syringes (`materials.names`, `materials.syringes`).
            crate::job::check_name(&s.name)
                .map_err(|why| bad(&format!("machine.syringes[{i}].name"), why))?;
            if self.syringes[..i].iter().any(|o| o.name == s.name) {
                return Err(bad(
                    &format!("machine.syringes[{i}].name"),
                    format!("\"{}\" names another syringe too", s.name),
                ));
            }
            if !(s.barrel_diameter_mm > 0.0 && s.barrel_diameter_mm.is_finite()) {
                return Err(bad(
                    &format!("machine.syringes[{i}].barrel_diameter_mm"),
                    "must be positive".into(),
                ));
            }
            if !(s.capacity_ml > 0.0 && s.capacity_ml.is_finite()) {
                return Err(bad(
                    &format!("machine.syringes[{i}].capacity_ml"),
                    "must be positive".into(),
                ));
            }
            if let Err((key, why)) = s.plunger_limits().check() {
                return Err(bad(&format!("machine.syringes[{i}].{key}"), why));
            }
            let supports_before = self.syringes[..i]
                .iter()
                .filter(|o| o.role == SyringeRole::Support)
                .count();
            if s.role == SyringeRole::Support && supports_before > 0 {
                return Err(bad(
                    &format!("machine.syringes[{i}].role"),
                    "a machine has at most one support syringe".into(),
                ));
            }
        }
        if self.syringes.iter().all(|s| s.role == SyringeRole::Support) {
            return Err(bad(
                "machine.syringes",
                "no syringe holds a part material (role = \"part\")".into(),
            ));
        }
        for (key, v) in [
            ("machine.nozzle_mm", self.nozzle_mm),
            ("machine.r_mach_mm", self.r_mach_mm),
            ("machine.max_feed_mm_s", self.max_feed_mm_s),
            ("machine.max_flow_factor", self.max_flow_factor),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(bad(key, format!("{v} must be positive")));
            }
        }
        let volume = self
            .build_volume()
            .map_err(|e| bad("machine.build_volume_mm", e))?;
        if !volume.contains_mm(self.park_mm) {
            let [x, y, z] = self.park_mm;
            let [sx, sy, sz] = volume.size_mm();
            return Err(bad(
                "machine.park_mm",
                format!("[{x}, {y}, {z}] is outside the build volume (0 to {sx}, 0 to {sy}, 0 to {sz} mm)"),
            ));
        }
        if !(self.resume_lift_mm.is_finite() && self.resume_lift_mm >= 0.0) {
            return Err(bad(
                "machine.resume_lift_mm",
                format!("{} must be a distance, 0 or more", self.resume_lift_mm),
            ));
        }
        Ok(())
    }

    /// The mixing chamber: `[machine.mixer]`, else plug flow through `dead_volume_nl`
    /// (an error names the key in the table).
    pub fn mixer(&self) -> Result<crate::mixer::MixerOptions, crate::mixer::MixerError> {
        let dead = self.dead_volume_nl as f64;
        match &self.mixer {
            None => Ok(crate::mixer::MixerOptions::plug(dead)),
            Some(m) => {
                crate::mixer::MixerOptions::new(&m.model, m.volume_nl.unwrap_or(dead), m.peclet)
            }
        }
    }

    /// `build_volume_mm` as a [`BuildVolume`] (an error names the bad side).
    pub fn build_volume(&self) -> Result<crate::job::placement::BuildVolume, String> {
        crate::job::placement::BuildVolume::new(self.build_volume_mm)
    }
}

impl Default for MachineConfig {
    fn default() -> Self {
        Self {
            syringes: default_syringes(),
            nozzle_mm: default_nozzle(),
            r_mach_mm: default_r_mach(),
            build_volume_mm: default_build_volume(),
            max_feed_mm_s: default_max_feed(),
            max_flow_factor: default_max_flow_factor(),
            dead_volume_nl: default_dead_volume(),
            prime_nl: default_prime(),
            park_mm: default_park(),
            resume_lift_mm: default_lift(),
            protocol: Protocol::default(),
            gcode: None,
            mixer: None,
        }
    }
}
