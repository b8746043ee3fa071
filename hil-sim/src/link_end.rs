//! The edo link's protocol end: the machine end of the link ([`MachineLink`],
//! `docs/protocol.md`) plugged into the [`crate::sim`] runtime, with the frame faults of
//! [`Frames`].

use edo::link::testkit::SimRng;
use edo::link::{
    FaultKind, MachineDescription, MachineEvent, MachineLink, MachineLinkConfig, Micros,
    PriorityCmd,
};
use edo::machine::Move;

use crate::faults::Faults;
use crate::inject::{Frames, Injector};
use crate::sim::{Booted, Executing, FaultOutcome, ProtocolEnd, Rebooted, SimConfig, Summary};

/// Line credit the edo simulator banks while idle: its frames (up to 512 bytes) are read
/// at once after a pause.
const EDO_BANK_BYTES: f64 = 512.0;

/// The machine end of the edo link, and the seeds of its boot ids.
pub(crate) struct LinkEnd {
    link: MachineLink,
    /// The link's settings but the boot id.
    config: MachineLinkConfig,
    rng: SimRng,
}

impl LinkEnd {
    /// The link booted from `seeds` (the boot id, then the injectors' seeds).
    pub(crate) fn boot(cfg: &SimConfig, mut seeds: SimRng) -> Booted<Self> {
        let config = link_config(cfg);
        let mut boot = config.clone();
        boot.machine.boot_id = seeds.next_u64();
        let link = MachineLink::new(boot, Micros(0));
        let to_machine = Injector::new(seeds.next_u64(), Frames::new());
        let to_host = Injector::new(seeds.next_u64(), Frames::new());
        let end = LinkEnd {
            link,
            config,
            rng: seeds,
        };
        (end, to_machine, to_host)
    }
}

impl ProtocolEnd for LinkEnd {
    type Unit = Frames;
    type Tag = ();
    const BANK_BYTES: f64 = EDO_BANK_BYTES;
    const BATCHES_RESETS: bool = true;

    fn receive(&mut self, unit: &[u8], now_us: u64, _f: &Faults, _sum: &mut Summary) {
        self.link.handle_bytes(unit, Micros(now_us));
    }

    fn poll(&mut self, _now_us: u64) -> bool {
        let mut stop = false;
        while let Some(e) = self.link.poll_event() {
            // An emergency stop aborts the move being executed: it is not reported
            // executed, so a host resuming after the stop sends it again.
            if e == MachineEvent::Priority(PriorityCmd::EmergencyStop) {
                stop = true;
            }
        }
        stop
    }

    fn next_move(&mut self) -> Option<(Move, ())> {
        self.link.pop_move().map(|mv| (mv, ()))
    }

    fn move_failed(&mut self, fault: FaultKind, _tag: &(), _now_us: u64) {
        self.link.fault(fault);
    }

    fn move_done(
        &mut self,
        done: &Executing<()>,
        remaining: &[u32],
        _now_us: u64,
        _f: &Faults,
        _sum: &mut Summary,
    ) {
        self.link.move_done(&done.mv, done.ex.to, remaining);
    }

    fn record_fields(&self, done: &Executing<()>) -> (u32, Option<String>) {
        (done.ex.layer, None)
    }

    fn machine_fault(&mut self, fault: FaultKind, _now_us: u64) -> FaultOutcome {
        let stops = matches!(fault, FaultKind::EStopPressed);
        self.link.fault(fault);
        if stops {
            FaultOutcome::MotionStopped
        } else {
            FaultOutcome::Reported
        }
    }

    /// A new boot of the link, its boot banner on the line.
    fn reset(&mut self, now_us: u64) -> Rebooted {
        let mut boot = self.config.clone();
        boot.machine.boot_id = self.rng.next_u64();
        self.link = MachineLink::new(boot, Micros(now_us));
        Rebooted {
            banner: b"\r\nhil-sim boot\r\n\xff\xfe",
            unplugs: false,
        }
    }

    fn poll_transmit(&mut self, now_us: u64) -> Option<Vec<u8>> {
        self.link.poll_transmit(Micros(now_us)).map(|t| t.bytes)
    }

    fn holds_work(&self) -> bool {
        self.link.queue_len() > 0
    }

    fn status(&self) -> serde_json::Map<String, serde_json::Value> {
        let mut m = serde_json::Map::new();
        m.insert("status".into(), format!("{:?}", self.link.status()).into());
        m
    }
}

/// The link's settings for the simulated machine (boot id 0).
fn link_config(cfg: &SimConfig) -> MachineLinkConfig {
    MachineLinkConfig {
        machine: MachineDescription {
            identity: format!("hil-sim {}", env!("CARGO_PKG_VERSION")),
            boot_id: 0,
            barrel_area_um2: vec![cfg.barrel_area_um2; cfg.syringes],
            capacity_nl: vec![cfg.capacity_nl; cfg.syringes],
            queue_depth: cfg.queue.max(1),
            rx_buffer_bytes: cfg.rx_buffer_bytes,
        },
        ..MachineLinkConfig::default()
    }
}
