//! `edod.toml`: the daemon's configuration (serial port, simulated machine, machine
//! description, API socket, state directory, planner and streaming bounds).
//!
//! Unknown keys are refused and every error names the file, line and column, so a typo
//! never silently falls back to a default. Every field has a documented default;
//! `config/edod.toml` is the annotated reference.

use std::path::{Path, PathBuf};

use serde::Deserialize;

#[cfg(test)]
mod gcode_tests;
mod http;

pub use crate::setup::{
    GcodeConfig, GcodeLink, MachineConfig, MixName, MixerConfig, Protocol, SyringeConfig,
    SyringeRole, WindowSetting,
};
pub use http::{read_token, HttpConfig, MIN_TOKEN_BYTES};

/// The literal `port` value that starts the built-in simulated machine.
pub const SIM_PORT: &str = "sim";

/// The whole configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Serial line to the machine.
    #[serde(default)]
    pub serial: SerialConfig,
    /// Options of the simulated machine (`serial.port = "sim"` only).
    #[serde(default)]
    pub sim: SimOptions,
    /// What the machine is.
    #[serde(default)]
    pub machine: MachineConfig,
    /// The Unix-socket API.
    #[serde(default)]
    pub api: ApiConfig,
    /// Where the job database lives.
    #[serde(default)]
    pub state: StateConfig,
    /// Planner and streaming bounds.
    #[serde(default)]
    pub planner: PlannerConfig,
    /// The web dashboard.
    #[serde(default)]
    pub http: HttpConfig,
}

/// `[serial]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SerialConfig {
    /// Device path (`/dev/ttyACM0`, a hil-sim link) or `"sim"` (default).
    #[serde(default = "default_port")]
    pub port: String,
    /// Line speed (default 250 000).
    #[serde(default = "default_baud")]
    pub baud: u32,
}

fn default_port() -> String {
    SIM_PORT.to_string()
}
fn default_baud() -> u32 {
    250_000
}

impl Default for SerialConfig {
    fn default() -> Self {
        Self {
            port: default_port(),
            baud: default_baud(),
        }
    }
}

/// `[sim]`: passed to the `hil-sim` binary that edod starts on a pty.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimOptions {
    /// Machine time runs this many times faster than wall time (default 20).
    #[serde(default = "default_speed")]
    pub speed: f64,
    /// `--faults` list, e.g. `"drop=0.01"` (default none).
    #[serde(default)]
    pub faults: String,
    /// Seed of the simulator (default 1).
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Record executed moves (JSON lines) to this file.
    #[serde(default)]
    pub record: Option<PathBuf>,
    /// The `hil-sim` executable (default: next to `edod`, then `PATH`).
    #[serde(default)]
    pub binary: Option<PathBuf>,
}

fn default_speed() -> f64 {
    20.0
}
fn default_seed() -> u64 {
    1
}

impl Default for SimOptions {
    fn default() -> Self {
        Self {
            speed: default_speed(),
            faults: String::new(),
            seed: default_seed(),
            record: None,
            binary: None,
        }
    }
}

/// `[api]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApiConfig {
    /// Socket path (default `/run/edo/edod.sock`).
    #[serde(default = "default_socket")]
    pub socket: PathBuf,
    /// Socket permission bits as an octal string (default `"0660"`).
    #[serde(default = "default_mode")]
    pub mode: String,
    /// Group owning the socket (default: edod's own group).
    #[serde(default)]
    pub group: Option<String>,
    /// Largest request line in bytes, mesh included (default 64 MiB).
    #[serde(default = "default_max_request")]
    pub max_request_bytes: usize,
    /// Most clients connected at once (default 256).
    #[serde(default = "default_max_clients")]
    pub max_clients: usize,
    /// Replies and notifications queued per client before it is cut off as too slow
    /// (default 1024).
    #[serde(default = "default_client_queue")]
    pub client_queue: usize,
    /// A connection must send a complete request within this many seconds of opening
    /// or of its previous request, or it is closed; a subscriber is idle only while a
    /// request is half sent (default 10).
    #[serde(default = "default_idle_timeout")]
    pub idle_timeout_s: f64,
    /// Connections beyond `max_clients` kept for `machine.estop` and `machine.status`
    /// only; a new one takes the place of the oldest that has sent nothing (default 4).
    #[serde(default = "default_control_clients")]
    pub control_clients: usize,
    /// Memory for requests in flight (lines being read, requests being decoded, mesh
    /// checks) across all clients, in bytes (default 256 MiB, or 4 × max_request_bytes
    /// if that is more; at least 4 × max_request_bytes).
    #[serde(default)]
    pub memory_budget_bytes: Option<usize>,
}

fn default_socket() -> PathBuf {
    PathBuf::from("/run/edo/edod.sock")
}
fn default_mode() -> String {
    "0660".to_string()
}
fn default_max_request() -> usize {
    64 << 20
}
fn default_max_clients() -> usize {
    256
}
fn default_client_queue() -> usize {
    1024
}
fn default_idle_timeout() -> f64 {
    10.0
}
fn default_control_clients() -> usize {
    4
}

/// The default of `api.memory_budget_bytes`: 256 MiB.
pub const DEFAULT_MEMORY_BUDGET: usize = 256 << 20;

impl ApiConfig {
    /// `memory_budget_bytes`, or its default: 256 MiB, or 4 × `max_request_bytes` if
    /// that is more.
    pub fn memory_budget(&self) -> usize {
        self.memory_budget_bytes
            .unwrap_or_else(|| DEFAULT_MEMORY_BUDGET.max(self.max_request_bytes.saturating_mul(4)))
    }

    /// `idle_timeout_s` as a duration.
    pub fn idle_timeout(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64(self.idle_timeout_s)
    }
}

impl Default for ApiConfig {
    fn default() -> Self {
        Self {
            socket: default_socket(),
            mode: default_mode(),
            group: None,
            max_request_bytes: default_max_request(),
            max_clients: default_max_clients(),
            client_queue: default_client_queue(),
            idle_timeout_s: default_idle_timeout(),
            control_clients: default_control_clients(),
            memory_budget_bytes: None,
        }
    }
}

/// `[state]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StateConfig {
    /// Directory of the job database (default `/var/lib/edo`).
    #[serde(default = "default_state_dir")]
    pub dir: PathBuf,
    /// Finished jobs (done, failed, cancelled) kept with their meshes; older ones are
    /// deleted as new jobs arrive, so the database does not grow without bound
    /// (default 1000, at least 1).
    #[serde(default = "default_keep_finished_jobs")]
    pub keep_finished_jobs: usize,
}

fn default_state_dir() -> PathBuf {
    PathBuf::from("/var/lib/edo")
}

fn default_keep_finished_jobs() -> usize {
    1000
}

impl Default for StateConfig {
    fn default() -> Self {
        Self {
            dir: default_state_dir(),
            keep_finished_jobs: default_keep_finished_jobs(),
        }
    }
}

/// `[planner]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlannerConfig {
    /// Layers planned ahead of the streamer (bounded channel; default 4).
    #[serde(default = "default_layers_ahead")]
    pub layers_ahead: usize,
    /// Moves handed to the link ahead of the machine's queue (default 256).
    #[serde(default = "default_moves_ahead")]
    pub moves_ahead: usize,
    /// Moves per layer of a dry-run job (default 200).
    #[serde(default = "default_dry_run_layer")]
    pub dry_run_moves_per_layer: u32,
}

fn default_layers_ahead() -> usize {
    4
}
fn default_moves_ahead() -> usize {
    256
}
fn default_dry_run_layer() -> u32 {
    200
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            layers_ahead: default_layers_ahead(),
            moves_ahead: default_moves_ahead(),
            dry_run_moves_per_layer: default_dry_run_layer(),
        }
    }
}

/// A configuration that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file cannot be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// File.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// TOML syntax, unknown key or wrong type.
    #[error("{path}:{line}:{column}: {message}")]
    Syntax {
        /// File.
        path: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What is wrong.
        message: String,
    },
    /// A value out of range.
    #[error("{path}: {key}: {message}")]
    Invalid {
        /// File.
        path: String,
        /// Dotted key.
        key: String,
        /// What is wrong.
        message: String,
    },
}

/// 1-based line and column of byte `offset` in `text`.
pub fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

impl Config {
    /// Parse and check a configuration; `path` names it in errors.
    pub fn from_toml(text: &str, path: &str) -> Result<Config, ConfigError> {
        let cfg: Config = toml::from_str(text).map_err(|e| {
            let (line, column) = e.span().map_or((0, 0), |s| line_col(text, s.start));
            ConfigError::Syntax {
                path: path.to_string(),
                line,
                column,
                message: e.message().trim_end().to_string(),
            }
        })?;
        cfg.check(path)?;
        Ok(cfg)
    }

    /// Read, parse and check a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: name.clone(),
            source,
        })?;
        Config::from_toml(&text, &name)
    }

    /// Every value in range; the first that is not is named by its dotted key.
    fn check(&self, path: &str) -> Result<(), ConfigError> {
        let bad = |key: &str, message: String| ConfigError::Invalid {
            path: path.to_string(),
            key: key.to_string(),
            message,
        };
        self.check_serial(&bad)?;
        self.check_machine(&bad)?;
        self.gcode_link()
            .map_err(|(key, message)| bad(&key, message))?;
        self.check_api(&bad)?;
        self.http.check().map_err(|(key, m)| bad(key, m))?;
        self.check_bounds(&bad)
    }

    /// `[serial]` and `[sim]`.
    fn check_serial(&self, bad: &impl Fn(&str, String) -> ConfigError) -> Result<(), ConfigError> {
        if self.serial.port.is_empty() {
            return Err(bad("serial.port", "empty; use \"sim\" or a device".into()));
        }
        if self.serial.baud == 0 {
            return Err(bad("serial.baud", "must be positive".into()));
        }
        if !(self.sim.speed.is_finite() && self.sim.speed > 0.0 && self.sim.speed <= 10_000.0) {
            return Err(bad(
                "sim.speed",
                format!("{} is not in (0, 10000]", self.sim.speed),
            ));
        }
        Ok(())
    }

    /// `[machine]` (`setup::MachineConfig::check`).
    fn check_machine(&self, bad: &impl Fn(&str, String) -> ConfigError) -> Result<(), ConfigError> {
        self.machine
            .check()
            .map_err(|(key, message)| bad(&key, message))
    }

    /// `[api]`.
    fn check_api(&self, bad: &impl Fn(&str, String) -> ConfigError) -> Result<(), ConfigError> {
        if u32::from_str_radix(self.api.mode.trim_start_matches("0o"), 8)
            .ok()
            .filter(|m| *m <= 0o777)
            .is_none()
        {
            return Err(bad(
                "api.mode",
                format!("{:?} is not an octal mode like \"0660\"", self.api.mode),
            ));
        }
        if self.socket_mode() & 0o002 != 0 {
            return Err(bad(
                "api.mode",
                format!(
                    "{:?} lets every user on the host write to the socket (submit, cancel, \
                     e-stop); give access through the group, like \"0660\"",
                    self.api.mode
                ),
            ));
        }
        if self.api.max_request_bytes < 1024 {
            return Err(bad("api.max_request_bytes", "at least 1024".into()));
        }
        if self.api.max_clients == 0 || self.api.client_queue == 0 {
            return Err(bad(
                "api",
                "max_clients and client_queue must be positive".into(),
            ));
        }
        self.check_api_limits(bad)
    }

    /// `[api]`'s limits on idle clients and memory.
    fn check_api_limits(
        &self,
        bad: &impl Fn(&str, String) -> ConfigError,
    ) -> Result<(), ConfigError> {
        let idle = self.api.idle_timeout_s;
        if !(idle.is_finite() && (0.01..=86_400.0).contains(&idle)) {
            return Err(bad(
                "api.idle_timeout_s",
                format!("{idle} is not in [0.01, 86400] seconds"),
            ));
        }
        if self.api.control_clients == 0 {
            return Err(bad(
                "api.control_clients",
                "at least 1 (kept for machine.estop)".into(),
            ));
        }
        let need = self.api.max_request_bytes.saturating_mul(4);
        if self.api.memory_budget() < need {
            return Err(bad(
                "api.memory_budget_bytes",
                format!(
                    "{} is less than 4 × api.max_request_bytes ({need}): a largest request \
                     could never be read and checked",
                    self.api.memory_budget()
                ),
            ));
        }
        Ok(())
    }

    /// `[state]` and `[planner]`: the bounds on what is kept and planned ahead.
    fn check_bounds(&self, bad: &impl Fn(&str, String) -> ConfigError) -> Result<(), ConfigError> {
        if self.state.keep_finished_jobs == 0 {
            return Err(bad(
                "state.keep_finished_jobs",
                "at least 1 (delete single jobs with job.delete)".into(),
            ));
        }
        if self.planner.layers_ahead == 0
            || self.planner.moves_ahead == 0
            || self.planner.dry_run_moves_per_layer == 0
        {
            return Err(bad("planner", "bounds must be positive".into()));
        }
        Ok(())
    }

    /// The G-code link's settings with `machine.protocol = "gcode"` (`None` for the edo
    /// protocol); an impossible `[machine.gcode]` names its dotted key.
    pub fn gcode_link(&self) -> Result<Option<GcodeLink>, (String, String)> {
        match (self.machine.protocol, &self.machine.gcode) {
            (Protocol::Edo, None) => Ok(None),
            (Protocol::Edo, Some(_)) => Err((
                "machine.gcode".into(),
                "only with machine.protocol = \"gcode\"".into(),
            )),
            (Protocol::Gcode, None) => Err((
                "machine.gcode".into(),
                "machine.protocol = \"gcode\" needs a [machine.gcode] table with its firmware"
                    .into(),
            )),
            (Protocol::Gcode, Some(g)) => g
                .resolve(&self.machine.syringes, self.serial.baud)
                .map(Some),
        }
    }

    /// Socket permission bits.
    pub fn socket_mode(&self) -> u32 {
        u32::from_str_radix(self.api.mode.trim_start_matches("0o"), 8).unwrap_or(0o660)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn at_most_one_support_syringe_and_one_part_syringe_at_least() {
        let syringe = |name: &str, role: &str| {
            format!(
                "[[machine.syringes]]\nname = \"{name}\"\nbarrel_diameter_mm = 10.0\n\
                 capacity_ml = 10.0\nrole = \"{role}\"\n"
            )
        };
        let ok = syringe("A", "part") + &syringe("S", "support");
        let c = Config::from_toml(&ok, "s.toml").unwrap();
        assert_eq!(c.machine.syringes[1].role, SyringeRole::Support);
        for (text, key) in [
            (
                ok.clone() + &syringe("W", "support"),
                "machine.syringes[2].role",
            ),
            (syringe("S", "support"), "machine.syringes"),
        ] {
            match Config::from_toml(&text, "s.toml").unwrap_err() {
                ConfigError::Invalid { key: k, .. } => assert_eq!(k, key, "{text}"),
                e => panic!("{text}: {e}"),
            }
        }
        let e = Config::from_toml(&syringe("A", "ink"), "s.toml").unwrap_err();
        assert!(
            e.to_string().contains("expected `part` or `support`"),
            "{e}"
        );
    }

    #[test]
    fn empty_config_is_all_defaults() {
        let c = Config::from_toml("", "x.toml").unwrap();
        assert_eq!(c.serial.port, "sim");
        assert_eq!(c.machine.syringes.len(), 2);
        assert_eq!(c.socket_mode(), 0o660);
    }

    #[test]
    fn unknown_key_is_refused_with_line_and_column() {
        let e = Config::from_toml("[serial]\nport = \"sim\"\n  bauds = 3\n", "e.toml").unwrap_err();
        let msg = e.to_string();
        assert!(msg.starts_with("e.toml:3:3: "), "{msg}");
        assert!(msg.contains("bauds"), "{msg}");
    }

    #[test]
    fn bad_values_name_their_key() {
        let e = Config::from_toml("[api]\nmode = \"rw\"\n", "m.toml").unwrap_err();
        assert!(e.to_string().contains("api.mode"), "{e}");
        // A socket every user may write: refused (issue 41: "0777" passed --check-config).
        for mode in ["0777", "0662", "0o666"] {
            let e =
                Config::from_toml(&format!("[api]\nmode = \"{mode}\"\n"), "m.toml").unwrap_err();
            assert!(
                e.to_string().contains("every user on the host"),
                "{mode}: {e}"
            );
        }
        assert!(Config::from_toml("[api]\nmode = \"0660\"\n", "m.toml").is_ok());
        for (key, value) in [
            ("max_plunger_mm_s", "0.0"),
            ("max_plunger_mm_s", "nan"),
            ("max_plunger_accel_mm_s2", "-1.0"),
            ("max_plunger_accel_mm_s2", "1e9"),
        ] {
            let toml = format!(
                "[[machine.syringes]]\nname = \"A\"\nbarrel_diameter_mm = 10.0\n\
                 capacity_ml = 10.0\n{key} = {value}\n"
            );
            let e = Config::from_toml(&toml, "m.toml").unwrap_err().to_string();
            assert!(e.contains(&format!("machine.syringes[0].{key}")), "{e}");
        }
        let e = Config::from_toml("[machine]\nsyringes = []\n", "m.toml").unwrap_err();
        assert!(e.to_string().contains("machine.syringes"), "{e}");
        let twice = "[machine]\nsyringes = [{ name = \"A\", barrel_diameter_mm = 10.0, capacity_ml = 10.0 }, \
                     { name = \"A\", barrel_diameter_mm = 10.0, capacity_ml = 10.0 }]\n";
        let e = Config::from_toml(twice, "m.toml").unwrap_err().to_string();
        assert!(
            e.contains("machine.syringes[1].name") && e.contains("another syringe"),
            "{e}"
        );
        let e = Config::from_toml("[state]\nkeep_finished_jobs = 0\n", "m.toml").unwrap_err();
        assert!(e.to_string().contains("state.keep_finished_jobs"), "{e}");
        for (text, key) in [
            (
                "build_volume_mm = [200.0, 0.0, 150.0]",
                "machine.build_volume_mm",
            ),
            (
                "build_volume_mm = [200.0, 200.0, nan]",
                "machine.build_volume_mm",
            ),
            (
                "build_volume_mm = [5000.0, 200.0, 150.0]",
                "machine.build_volume_mm",
            ),
            ("park_mm = [0.0, 250.0, 50.0]", "machine.park_mm"),
            ("park_mm = [-1.0, 0.0, 50.0]", "machine.park_mm"),
            ("resume_lift_mm = -2.0", "machine.resume_lift_mm"),
            ("resume_lift_mm = nan", "machine.resume_lift_mm"),
        ] {
            let e = Config::from_toml(&format!("[machine]\n{text}\n"), "m.toml").unwrap_err();
            assert!(e.to_string().contains(key), "{text}: {e}");
        }
    }

    #[test]
    fn the_mixer_table_is_checked_naming_its_key() {
        for (text, key) in [
            ("model = \"turbulent\"", "machine.mixer.model"),
            ("volume_nl = -5.0", "machine.mixer.volume_nl"),
            ("volume_nl = nan", "machine.mixer.volume_nl"),
            (
                "model = \"dispersion\"\npeclet = 0.0",
                "machine.mixer.peclet",
            ),
            ("model = \"dispersion\"", "machine.mixer.peclet"),
            ("model = \"mixed\"\npeclet = 3.0", "machine.mixer.peclet"),
        ] {
            let e = Config::from_toml(&format!("[machine.mixer]\n{text}\n"), "m.toml").unwrap_err();
            assert!(e.to_string().contains(key), "{text}: {e}");
        }
        let c = Config::from_toml(
            "[machine]\ndead_volume_nl = 700\n[machine.mixer]\nmodel = \"dispersion\"\npeclet = 12.5\n",
            "m.toml",
        )
        .unwrap();
        let m = c.machine.mixer().unwrap();
        assert_eq!(
            (m.model, m.volume_nl, m.peclet),
            (crate::mixer::MixerModel::Dispersion, 700.0, Some(12.5))
        );
        let plain = Config::from_toml("", "m.toml")
            .unwrap()
            .machine
            .mixer()
            .unwrap();
        assert_eq!(plain, crate::mixer::MixerOptions::plug(20_000.0));
    }

    #[test]
    fn shipped_configs_parse() {
        for f in [
            "config/edod.toml",
            "config/edod-hardware.toml",
            "systemd/edod.toml",
        ] {
            let p = Path::new(env!("CARGO_MANIFEST_DIR")).join(f);
            Config::load(&p).unwrap_or_else(|e| panic!("{e}"));
        }
    }

    /// The Debian package's /etc/edo/edod.toml uses the paths the unit gives edod
    /// (systemd/edod.service: RuntimeDirectory=edo, StateDirectory=edo, Group=edo).
    #[test]
    fn installed_config_matches_the_unit() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd/edod.toml");
        let c = Config::load(&p).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(c.api.socket, Path::new("/run/edo/edod.sock"));
        assert_eq!(c.api.group.as_deref(), Some("edo"));
        assert_eq!(c.state.dir, Path::new("/var/lib/edo"));
        let unit = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd/edod.service"),
        )
        .unwrap();
        for line in [
            "RuntimeDirectory=edo",
            "StateDirectory=edo",
            "Group=edo",
            "ExecStart=/usr/bin/edod --config /etc/edo/edod.toml",
        ] {
            assert!(unit.lines().any(|l| l == line), "{line}");
        }
    }
}
