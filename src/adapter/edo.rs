//! The adapter between the job lifecycle and the edo link: the one place that knows both.
//! It holds the sans-IO [`Host`] and turns its events into the lifecycle's
//! protocol-neutral [`Event`]s, and the lifecycle's [`MachineCommand`]s and moves into
//! link calls. The lifecycle never sees a frame, a priority lane or a session id; the
//! G-code firmware link is the second adapter of the same shape
//! ([`super::GcodeLink`], both behind [`LinkAdapter`]).

use crate::lifecycle::{Event, MachineCommand, MachineFault};
use crate::link::{
    FaultKind, Host, HostEvent, HostState, LinkConfig, MachineInfo, Micros, PriorityCmd, Status,
};
use crate::machine::{MachineReport, Move};

use super::{LinkAdapter, LinkCounters, LogLine, LogQueue};

/// The edo link under the lifecycle.
pub struct EdoLink {
    host: Host,
    /// Session seed: a new one for every (re)connection.
    seed: u64,
    /// The machine, as its handshake said.
    info: Option<MachineInfo>,
    /// Its last report.
    report: MachineReport,
    /// Lines for the daemon's log.
    log: LogQueue,
    /// The stops sent and not acknowledged: a flush, e-stops. The link has one e-stop
    /// (a flush is one); its acknowledgement answers each of them.
    stops_unacked: StopsUnacked,
    /// Events to give before the link's next.
    events: std::collections::VecDeque<Event>,
}

/// Stops sent on the priority lane and not acknowledged yet.
#[derive(Debug, Default, Clone, Copy)]
struct StopsUnacked {
    flush: bool,
    estop: bool,
}

/// The edo link's status report as the machine's report.
fn report_of(s: &Status) -> MachineReport {
    MachineReport {
        state: s.state,
        last_executed: s.last_executed,
        executed_total: s.executed_total,
        queued: u32::from(s.queued),
        faults: s.faults,
        position: s.position,
        remaining_nl: s.remaining_nl.clone(),
    }
}

fn command_of(p: PriorityCmd) -> MachineCommand {
    match p {
        PriorityCmd::EmergencyStop => MachineCommand::EmergencyStop,
        PriorityCmd::FeedHold => MachineCommand::FeedHold,
        PriorityCmd::Resume => MachineCommand::Resume,
    }
}

impl EdoLink {
    /// A link configured by `cfg`, its first session seeded `seed`, at `now`.
    pub fn new(cfg: LinkConfig, seed: u64, now: Micros) -> Self {
        Self {
            host: Host::new(cfg, seed, now),
            seed,
            info: None,
            report: MachineReport::default(),
            log: LogQueue::default(),
            stops_unacked: StopsUnacked::default(),
            events: std::collections::VecDeque::new(),
        }
    }

    fn translate(&mut self, e: HostEvent, now: Micros) -> Option<Event> {
        Some(match e {
            HostEvent::Connected(i) => {
                self.log.info(format!(
                    "machine connected identity={} boot_id={} last={:?}",
                    i.machine.identity, i.machine.boot_id, i.status.last_executed
                ));
                self.report = report_of(&i.status);
                self.info = Some(i);
                Event::MachineConnected(self.report.clone())
            }
            HostEvent::Status(s) => {
                self.report = report_of(&s);
                Event::MachineStatus(self.report.clone())
            }
            HostEvent::Fault(f) => {
                self.log
                    .warn(format!("machine fault fault={:?} at={:?}", f.kind, f.at));
                Event::MachineFault(match f.kind {
                    FaultKind::SyringeEmpty(n) => MachineFault::SyringeEmpty(n),
                    FaultKind::EStopPressed => MachineFault::EStopPressed,
                    other => MachineFault::Other(format!("{other:?}")),
                })
            }
            HostEvent::MachineReset { last_executed, .. } => {
                // The link never resumes a session silently: a new one starts now.
                self.stops_unacked = StopsUnacked::default();
                self.seed = self.seed.wrapping_add(1);
                self.host.reconnect(self.seed, now);
                Event::MachineReset { last_executed }
            }
            HostEvent::LinkLost { silent_us } => {
                self.log
                    .warn(format!("link lost silent_ms={}", silent_us / 1000));
                Event::LinkSilent
            }
            HostEvent::LinkRestored => {
                self.log.info("link restored".into());
                Event::LinkRestored
            }
            HostEvent::PriorityAcked(PriorityCmd::EmergencyStop) => {
                return self.stop_acked();
            }
            HostEvent::PriorityAcked(cmd) => Event::CommandAcked(command_of(cmd)),
            HostEvent::Incompatible { machine_version } => {
                self.log.warn(format!(
                    "machine speaks another protocol version machine_version={machine_version}"
                ));
                Event::MachineIncompatible
            }
        })
    }
}

impl EdoLink {
    /// The e-stop's acknowledgement answers every stop sent (a flush and an e-stop sent
    /// together are one stop of the machine); one with none sent answers an e-stop.
    fn stop_acked(&mut self) -> Option<Event> {
        let sent = std::mem::take(&mut self.stops_unacked);
        if sent.flush {
            self.events
                .push_back(Event::CommandAcked(MachineCommand::Flush));
        }
        if sent.estop || !sent.flush {
            self.events
                .push_back(Event::CommandAcked(MachineCommand::EmergencyStop));
        }
        self.events.pop_front()
    }
}

impl LinkAdapter for EdoLink {
    /// The port was (re)opened: start a new session.
    fn reconnect(&mut self, now: Micros) {
        self.seed = self.seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
        // A new session: the stops of the old one are answered by nothing now.
        self.stops_unacked = StopsUnacked::default();
        self.host.reconnect(self.seed, now);
    }

    /// Feed bytes read from the port.
    fn handle_bytes(&mut self, bytes: &[u8], now: Micros) {
        self.host.handle_bytes(bytes, now);
    }

    /// Run the link's timers.
    fn handle_timeout(&mut self, now: Micros) {
        self.host.handle_timeout(now);
    }

    /// When the link's timers are next due.
    fn next_timeout(&self) -> Option<Micros> {
        self.host.next_timeout()
    }

    /// Bytes to write to the port.
    fn poll_transmit(&mut self, now: Micros) -> Option<Vec<u8>> {
        self.host.poll_transmit(now).map(|t| t.bytes)
    }

    /// The next lifecycle event from the link, if any.
    fn poll_event(&mut self, now: Micros) -> Option<Event> {
        if let Some(e) = self.events.pop_front() {
            return Some(e);
        }
        loop {
            let e = self.host.poll_event()?;
            if let Some(e) = self.translate(e, now) {
                return Some(e);
            }
        }
    }

    /// Carry out a machine command: the stops and the resume go ahead of every move
    /// queued (the priority lane); clearing faults and a status query are in order with
    /// the moves, and are dropped while the link is not connected (the lifecycle asks
    /// again after a reconnection).
    fn command(&mut self, c: MachineCommand, now: Micros) {
        match c {
            MachineCommand::EmergencyStop => {
                self.stops_unacked.estop = true;
                self.host.priority(PriorityCmd::EmergencyStop, now);
            }
            MachineCommand::Flush => {
                self.stops_unacked.flush = true;
                self.host.priority(PriorityCmd::EmergencyStop, now);
            }
            MachineCommand::FeedHold => {
                self.host.priority(PriorityCmd::FeedHold, now);
            }
            MachineCommand::Resume => {
                self.host.priority(PriorityCmd::Resume, now);
            }
            MachineCommand::ClearFaults => {
                let _ = self.host.clear_faults();
            }
            MachineCommand::QueryStatus => {
                let _ = self.host.query();
            }
        }
    }

    /// Whether the link takes another move now: connected, and fewer than `ahead`
    /// waiting in it.
    fn has_room(&self, ahead: usize) -> bool {
        self.host.state() == HostState::Connected && self.host.pending() < ahead
    }

    /// Queue a move; why not, if it cannot go.
    fn send_move(&mut self, mv: Move) -> Result<(), String> {
        self.host.send_move(mv).map_err(|e| e.to_string())
    }

    /// Moves waiting in the link and moves sent and not acknowledged.
    fn in_link(&self) -> (usize, u64) {
        (self.host.pending(), self.host.moves_in_flight())
    }

    /// The machine's identity, once it answered.
    fn identity(&self) -> Option<&str> {
        self.info.as_ref().map(|i| i.machine.identity.as_str())
    }

    /// Its last report.
    fn report(&self) -> &MachineReport {
        &self.report
    }

    /// The link's counters.
    fn counters(&self) -> LinkCounters {
        let s = self.host.stats();
        LinkCounters {
            bytes_sent: s.bytes_sent,
            bytes_received: s.bytes_received,
            resent: s.frames_retransmitted,
            srtt_us: Some(s.srtt_us),
        }
    }

    fn port_lost(&mut self) {}

    fn poll_log(&mut self) -> Option<LogLine> {
        self.log.pop()
    }
}

/// The link's settings for a line of `baud`.
pub fn link_config(baud: u32) -> LinkConfig {
    LinkConfig::default().with_priority_latency(baud, crate::link::PRIORITY_LATENCY_US)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::{MachineLink, MachineLinkConfig};

    /// Bytes both ways between the adapter and a machine end over an instant wire,
    /// until both are quiet; the adapter's events.
    fn pump(link: &mut EdoLink, machine: &mut MachineLink, now: Micros) -> Vec<Event> {
        let mut events = Vec::new();
        for _ in 0..50 {
            let mut quiet = true;
            link.handle_timeout(now);
            while let Some(b) = link.poll_transmit(now) {
                machine.handle_bytes(&b, now);
                quiet = false;
            }
            machine.handle_timeout(now);
            while machine.poll_event().is_some() {}
            while let Some(t) = machine.poll_transmit(now) {
                link.handle_bytes(&t.bytes, now);
                quiet = false;
            }
            events.extend(std::iter::from_fn(|| link.poll_event(now)));
            if quiet {
                break;
            }
        }
        events
    }

    fn connected() -> (EdoLink, MachineLink) {
        let mut link = EdoLink::new(LinkConfig::default(), 7, Micros(0));
        let mut machine = MachineLink::new(MachineLinkConfig::default(), Micros(0));
        link.reconnect(Micros(0));
        let events = pump(&mut link, &mut machine, Micros(1_000));
        assert!(
            matches!(events.first(), Some(Event::MachineConnected(_))),
            "{events:?}"
        );
        let line = link.poll_log().map(|l| l.text).unwrap_or_default();
        assert!(
            line.starts_with("machine connected identity=edo machine"),
            "{line}"
        );
        (link, machine)
    }

    fn acks(events: &[Event]) -> Vec<MachineCommand> {
        events
            .iter()
            .filter_map(|e| match e {
                Event::CommandAcked(c) => Some(*c),
                _ => None,
            })
            .collect()
    }

    /// The lifecycle's flush and an operator's e-stop are both the link's e-stop, and
    /// each is acknowledged as itself: a flush never answers an e-stop.
    #[test]
    fn a_flush_and_an_estop_are_each_acknowledged_as_themselves() {
        let (mut link, mut machine) = connected();
        link.command(MachineCommand::Flush, Micros(2_000));
        let events = pump(&mut link, &mut machine, Micros(2_000));
        assert_eq!(acks(&events), [MachineCommand::Flush]);
        link.command(MachineCommand::Resume, Micros(3_000));
        let events = pump(&mut link, &mut machine, Micros(3_000));
        assert_eq!(acks(&events), [MachineCommand::Resume]);
        link.command(MachineCommand::EmergencyStop, Micros(4_000));
        let events = pump(&mut link, &mut machine, Micros(4_000));
        assert_eq!(acks(&events), [MachineCommand::EmergencyStop]);
        // Both before the machine answers: its one stop answers both.
        link.command(MachineCommand::Resume, Micros(5_000));
        pump(&mut link, &mut machine, Micros(5_000));
        link.command(MachineCommand::Flush, Micros(6_000));
        link.command(MachineCommand::EmergencyStop, Micros(6_000));
        let events = pump(&mut link, &mut machine, Micros(6_000));
        let got = acks(&events);
        assert!(got.contains(&MachineCommand::Flush), "{got:?}");
        assert!(got.contains(&MachineCommand::EmergencyStop), "{got:?}");
        // A stop of a session that ended is not answered by the next session's.
        link.command(MachineCommand::Resume, Micros(7_000));
        pump(&mut link, &mut machine, Micros(7_000));
        link.command(MachineCommand::EmergencyStop, Micros(8_000));
        link.reconnect(Micros(8_000));
        let mut machine = MachineLink::new(MachineLinkConfig::default(), Micros(8_000));
        pump(&mut link, &mut machine, Micros(9_000));
        link.command(MachineCommand::Flush, Micros(10_000));
        let events = pump(&mut link, &mut machine, Micros(10_000));
        assert_eq!(acks(&events), [MachineCommand::Flush]);
    }
}
