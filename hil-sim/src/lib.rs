//! hil-sim: the simulated multi-syringe slurry extrusion machine.
//!
//! It speaks the edo link protocol (`docs/protocol.md`) on a pseudo-terminal, with the
//! machine end of [`edo::link`] so the two ends share one codec, or (`--gcode`) G-code
//! as Marlin, RepRapFirmware or Klipper, with the firmware models of [`edo::gcode_link`].
//!
//! - [`model`]: axes, syringes, mixing chamber (V_dead, plug flow), move durations.
//! - [`faults`]: the fault list of `--faults` and the run-time commands.
//! - [`sim`]: the one runtime of both protocols (the port, the clocks, the run-time
//!   commands, a fault injector each way, the recorder, the machine model) with the
//!   protocol end plugged in, and [`sim::spawn`] to run it in a thread of a test.
//! - `port`: the pty, throttled to the baud rate, that can be unplugged.
//! - `inject`: the fault injector, per unit: edo frames (0x00) or G-code lines (`\n`).
//! - `link_end`: the edo protocol end, the machine end of [`edo::link`].
//! - [`gcode_sim`], [`gcode_machine`]: `--gcode rrf|marlin|klipper`, the G-code protocol
//!   end (the firmware models of [`edo::gcode_link`]) and the G-code interpreter feeding
//!   the same model.
//! - [`record`]: the JSON-lines recorder format and `hil-sim render` (SVG per layer).

/// The fault configuration (shared with `edod --check-config`).
pub use edo::link::sim_faults as faults;
pub mod gcode_machine;
pub mod gcode_sim;
mod inject;
mod link_end;
pub mod model;
mod port;
pub mod record;
pub mod sim;

pub use faults::{Faults, FAULTS_HELP};
pub use gcode_sim::GcodeOptions;
pub use sim::{run, spawn, Command, SimConfig, SimHandle, StatusReply, Summary};
