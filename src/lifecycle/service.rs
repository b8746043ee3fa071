//! Service moves (job id 0): the prelude of a restarted job (home, prime, travel back,
//! layer mark) and the park of a cancelled one (retract, lift, travel to the park
//! position), and their indices, which never repeat across edod runs (the machine's
//! order check of job 0): they come from blocks reserved in the store ahead of use.

use super::io::{Record, ResumePoint};
use super::job::{JobState, SERVICE_JOB_ID};
use super::Lifecycle;
use crate::machine::{
    composition_of, ratios_from_fractions, split_volume_nl, Move, MoveKind, PositionUm, RATIO_ONE,
};

/// Service move indices: the next one, the reserved end, and a reservation on its way
/// to the store.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Indices {
    next: u32,
    reserved_until: u32,
    block: u32,
    /// A reservation handed to the store: its sequence number and new end.
    reserving: Option<(u64, u32)>,
}

impl Indices {
    pub fn new(next: u32, reserved_until: u32, block: u32) -> Self {
        Self {
            next,
            reserved_until: reserved_until.max(next),
            block: block.max(2),
            reserving: None,
        }
    }
}

impl Lifecycle {
    /// The next service move index. Past half the reserved block the next block is
    /// reserved; an index past the reservation (only with the store unwritable for a
    /// whole block of service moves) could repeat after a crash, never within a run.
    fn service_index(&mut self) -> u32 {
        let s = &mut self.service;
        let index = s.next;
        s.next = s.next.wrapping_add(1);
        let left = s.reserved_until.saturating_sub(s.next);
        if left < s.block / 2 && s.reserving.is_none() {
            let until = s.reserved_until.max(s.next).saturating_add(s.block);
            let seq = self.persist(Record::ServiceIndices {
                reserved_until: until,
            });
            self.service.reserving = Some((seq, until));
        }
        index
    }

    /// Records up to `upto` are stored: a reservation among them is in effect.
    pub(super) fn service_stored(&mut self, upto: u64) {
        if let Some((seq, until)) = self.service.reserving {
            if seq <= upto {
                self.service.reserving = None;
                self.service.reserved_until = self.service.reserved_until.max(until);
            }
        }
    }

    fn service_move(&mut self, kind: MoveKind) {
        let index = self.service_index();
        self.outbox.push_back(Move {
            job_id: SERVICE_JOB_ID,
            index,
            kind,
        });
    }

    fn syringes(&self) -> usize {
        self.status.remaining_nl.len().max(1)
    }

    /// Home, prime with the resumed composition, travel (lifted) back to where the last
    /// executed move ended, layer mark; then the job streams.
    pub(super) fn send_prelude(&mut self) {
        let syringes = self.syringes();
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let ResumePoint {
            position,
            layer_mark,
            volumes_nl,
        } = a.resume_point.take().unwrap_or_default();
        a.phase = super::Phase::Streaming;
        let m = self.opts.service.clone();
        let ratios = volumes_nl
            .as_deref()
            .and_then(composition_of)
            .and_then(|c| ratios_from_fractions(&c).ok())
            .unwrap_or_else(|| {
                let mut r = vec![0u16; syringes];
                r[0] = RATIO_ONE;
                r
            });
        self.service_move(MoveKind::Home);
        self.service_move(MoveKind::Prime {
            volumes_nl: split_volume_nl(m.prime_nl, &ratios),
            duration_ms: 1000,
        });
        if let Some(p) = position {
            // Lifted, but not above the build volume's top.
            let lifted = p
                .z_um
                .saturating_add(m.resume_lift_um)
                .min(m.build_top_um.max(p.z_um));
            self.service_move(MoveKind::Travel {
                to: PositionUm { z_um: lifted, ..p },
                feed_um_s: m.feed_um_s,
            });
            self.service_move(MoveKind::Travel {
                to: p,
                feed_um_s: m.feed_um_s,
            });
        }
        if let Some((layer, z_um)) = layer_mark {
            self.service_move(MoveKind::LayerMark { layer, z_um });
        }
    }

    /// The cancel's flush is done (the checkpoint is final): the job is cancelled, the
    /// nozzle retracts, lifts and parks.
    pub(super) fn park(&mut self) {
        self.end_active(JobState::Cancelled, Some("cancelled by an operator".into()));
        let m = self.opts.service.clone();
        let n = self.syringes();
        let p = self.status.position;
        let z_um = p.z_um.max(m.park_um[2]);
        self.service_move(MoveKind::Retract {
            volumes_nl: vec![m.prime_nl / 4; n],
            duration_ms: 500,
        });
        self.service_move(MoveKind::Travel {
            to: PositionUm { z_um, ..p },
            feed_um_s: m.feed_um_s,
        });
        self.service_move(MoveKind::Travel {
            to: PositionUm {
                x_um: m.park_um[0],
                y_um: m.park_um[1],
                z_um,
            },
            feed_um_s: m.feed_um_s,
        });
    }
}
