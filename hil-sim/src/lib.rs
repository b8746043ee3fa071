//! hil-sim: the simulated multi-syringe slurry extrusion machine.
//!
//! It speaks the edo link protocol (`docs/protocol.md`) on a pseudo-terminal, with the
//! machine end of [`edo::link`] so the two ends share one codec.
//!
//! - [`model`]: axes, syringes, mixing chamber (V_dead, plug flow), move durations.
//! - [`faults`]: the fault list of `--faults` and the run-time commands.
//! - [`sim`]: the pty runtime (baud throttle, fault injector, recorder) and [`sim::spawn`]
//!   to run it in a thread of a test.
//! - [`gcode_sim`], [`gcode_machine`]: `--gcode rrf|marlin|klipper`, the firmware models
//!   of [`edo::gcode_link`] on the pty and the G-code interpreter feeding the same model.
//! - [`record`]: the JSON-lines recorder format and `hil-sim render` (SVG per layer).

/// The fault configuration (shared with `edod --check-config`).
pub use edo::link::sim_faults as faults;
pub mod gcode_machine;
pub mod gcode_sim;
pub mod model;
pub mod record;
pub mod sim;

pub use faults::{Faults, FAULTS_HELP};
pub use gcode_sim::GcodeOptions;
pub use sim::{run, spawn, Command, SimConfig, SimHandle, Summary};
