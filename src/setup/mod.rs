//! The machine a job is built on, as `[machine]` of edod.toml describes it
//! (`docs/firmware.md`, `config/edod.toml`), and the process settings a job plans with
//! on it. Pure: the daemon reads the file; edod, `edoctl plan --machine` and
//! `edoctl demo` all plan with [`process_settings`].

mod gcode;
mod machine;
mod process;

pub use gcode::{GcodeConfig, GcodeLink, MixName, Protocol, WindowSetting};
pub use machine::{MachineConfig, MixerConfig, SyringeConfig, SyringeRole};
pub use process::{process_settings, syringe_of_material};

/// A wrong value: the dotted key (`machine.syringes[1].name`) and what is wrong.
pub type KeyError = (String, String);
