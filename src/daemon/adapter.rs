//! What the streamer needs of a machine link, whatever its wire protocol: the adapter
//! interface between the protocol-neutral job lifecycle and a sans-IO link core. Two
//! adapters implement it: [`super::edo_link::EdoLink`] (edo's framed link, hil-sim and
//! edo machines) and [`super::gcode_link::GcodeLink`] (G-code lines to RepRapFirmware,
//! Marlin and Klipper, `docs/firmware.md`). The streamer owns the port and the clock and
//! pumps one of them; the lifecycle sees only [`Event`]s and [`MachineCommand`]s.

use crate::lifecycle::{Event, MachineCommand};
use crate::link::{LinkStats, Micros, Status};
use crate::machine::Move;

use super::store::GcodeMarkWrite;

/// A machine link under the lifecycle. Driven like the sans-IO cores it wraps: bytes in,
/// bytes out, events out, the caller's clock.
pub trait LinkAdapter: Send {
    /// The port was (re)opened: start a new session (handshake).
    fn reconnect(&mut self, now: Micros);
    /// The port closed or vanished (the streamer reports [`Event::PortLost`] itself).
    fn port_lost(&mut self);
    /// Feed bytes read from the port.
    fn handle_bytes(&mut self, bytes: &[u8], now: Micros);
    /// Run the link's timers.
    fn handle_timeout(&mut self, now: Micros);
    /// When the link's timers are next due.
    fn next_timeout(&self) -> Option<Micros>;
    /// Bytes to write to the port.
    fn poll_transmit(&mut self, now: Micros) -> Option<Vec<u8>>;
    /// The next lifecycle event from the link, if any.
    fn poll_event(&mut self, now: Micros) -> Option<Event>;
    /// Carry out a machine command. `flushing`: the lifecycle stops the machine to make
    /// the active job's checkpoint final before it restarts or parks (its phase is
    /// `Flushing`), not for an operator's e-stop or a fault; a link whose e-stop cannot
    /// be undone from the host (G-code's `M112`) flushes without it.
    fn command(&mut self, c: MachineCommand, flushing: bool, now: Micros);
    /// Whether the link takes another move now (`ahead`: moves it may hold unsent).
    fn has_room(&self, ahead: usize) -> bool;
    /// A job ended (done, cancelled or failed): a link may end the firmware's job state
    /// once the moves still in it ran (Klipper's syringe axes released).
    fn job_ended(&mut self, _job_id: u32) {}
    /// Queue a move; why not, if it cannot go.
    fn send_move(&mut self, mv: Move) -> Result<(), String>;
    /// Moves waiting in the link and moves sent and not acknowledged.
    fn in_link(&self) -> (usize, u64);
    /// The machine's identity, once it answered.
    fn identity(&self) -> Option<&str>;
    /// Its last status (for the machine snapshot; the lifecycle has its own copy).
    fn status(&self) -> &Status;
    /// The link's counters.
    fn stats(&self) -> LinkStats;
    /// A change to the store's G-code marks, to hand to the store's writer before the
    /// next bytes go out (`docs/firmware.md`; only the G-code link has any).
    fn poll_store_mark(&mut self) -> Option<GcodeMarkWrite> {
        None
    }
    /// While connected, why the machine does not answer as it should (the G-code link:
    /// an `ok` overdue and the firmware being asked where it is), for the snapshot's
    /// `link_problem`; `None` while it answers.
    fn link_problem(&self) -> Option<String> {
        None
    }
}
