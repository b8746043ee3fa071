//! A job's planned machine time: how long the machine takes for its moves at their feed
//! rates ([`MoveKind::run_time_us`], acceleration left out, as hil-sim runs them), kept
//! as marks along the move indices so the time planned before any move is known without
//! keeping the moves. What progress and ETA are measured by (`docs/api.md`, Job).

use super::{Move, MoveKind, PositionUm};

/// Moves between two marks at most (a layer mark also makes one).
pub const MARK_EVERY_MOVES: u32 = 256;

/// The planned machine time of a job: marks `(move index, µs planned before it)` in
/// increasing order, the last one `(total moves, total µs)`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlannedTime {
    marks: Vec<(u32, u64)>,
}

impl PlannedTime {
    /// The whole job's planned time, µs.
    pub fn total_us(&self) -> u64 {
        self.marks.last().map_or(0, |m| m.1)
    }

    /// The job's moves.
    pub fn moves(&self) -> u32 {
        self.marks.last().map_or(0, |m| m.0)
    }

    /// Planned time before move `index` (of the moves before it), µs: exact at a mark,
    /// linear in the move index between two (at most [`MARK_EVERY_MOVES`] apart).
    pub fn before_us(&self, index: u32) -> u64 {
        let i = self.marks.partition_point(|m| m.0 <= index);
        let Some(&(i0, t0)) = i.checked_sub(1).and_then(|k| self.marks.get(k)) else {
            return 0;
        };
        let Some(&(i1, t1)) = self.marks.get(i) else {
            return t0;
        };
        let f = f64::from(index - i0) / f64::from((i1 - i0).max(1));
        t0 + (f * (t1 - t0) as f64).round() as u64
    }
}

/// Builds a [`PlannedTime`] from a job's moves, in order.
#[derive(Debug, Default)]
pub struct PlannedTimeBuilder {
    time: PlannedTime,
    at: Option<PositionUm>,
    t_us: u64,
    next_index: u32,
    since_mark: u32,
}

impl PlannedTimeBuilder {
    /// Start at the job's first move.
    pub fn new() -> Self {
        let mut b = Self::default();
        b.time.marks.push((0, 0));
        b
    }

    /// The next move of the job.
    pub fn push(&mut self, mv: &Move) {
        if matches!(mv.kind, MoveKind::LayerMark { .. }) || self.since_mark >= MARK_EVERY_MOVES {
            self.mark();
        }
        self.t_us += mv.kind.run_time_us(self.at).unwrap_or(0);
        match &mv.kind {
            MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => self.at = Some(*to),
            MoveKind::Home => self.at = None,
            _ => {}
        }
        self.next_index = mv.index.saturating_add(1);
        self.since_mark += 1;
    }

    fn mark(&mut self) {
        if self.time.marks.last().map(|m| m.0) != Some(self.next_index) {
            self.time.marks.push((self.next_index, self.t_us));
        }
        self.since_mark = 0;
    }

    /// Planned time so far, µs.
    pub fn so_far_us(&self) -> u64 {
        self.t_us
    }

    /// The job's planned time, its moves all pushed.
    pub fn finish(mut self) -> PlannedTime {
        self.mark();
        self.time
    }
}

/// Add what `kind` takes from each syringe to `used` (nl; a retract gives back, never
/// below nothing).
pub fn add_used_nl(used: &mut Vec<u64>, kind: &MoveKind) {
    let pull_back = match kind {
        MoveKind::Extrude { .. } | MoveKind::Prime { .. } => false,
        MoveKind::Retract { .. } => true,
        _ => return,
    };
    let volumes = kind.volumes_nl();
    if used.len() < volumes.len() {
        used.resize(volumes.len(), 0);
    }
    for (u, &v) in used.iter_mut().zip(volumes) {
        *u = if pull_back {
            u.saturating_sub(u64::from(v))
        } else {
            u.saturating_add(u64::from(v))
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mv(index: u32, kind: MoveKind) -> Move {
        Move {
            job_id: 1,
            index,
            kind,
        }
    }

    fn travel(index: u32, x_mm: i32) -> Move {
        mv(
            index,
            MoveKind::Travel {
                to: PositionUm {
                    x_um: x_mm * 1000,
                    y_um: 0,
                    z_um: 0,
                },
                feed_um_s: 10_000,
            },
        )
    }

    #[test]
    fn planned_time_is_the_moves_at_their_feed() {
        let mut b = PlannedTimeBuilder::new();
        b.push(&travel(0, 0)); // from nowhere: not known, 0
        b.push(&mv(
            1,
            MoveKind::LayerMark {
                layer: 0,
                z_um: 200,
            },
        ));
        for i in 2..1002 {
            b.push(&travel(i, ((i + 1) % 2) as i32)); // 1 mm at 10 mm/s: 0.1 s each
        }
        b.push(&mv(1002, MoveKind::Dwell { duration_ms: 500 }));
        let t = b.finish();
        assert_eq!(t.moves(), 1003);
        // Moves 2..1002 each travel 1 mm from where the last ended: 1000 of 0.1 s.
        assert_eq!(t.total_us(), 100_000_000 + 500_000);
        // Exact at the marks (the layer mark, then every 256 moves), within the
        // longest move's time between them (there the dwell's 0.5 s).
        assert_eq!(t.before_us(0), 0);
        assert_eq!(t.before_us(1), 0);
        assert_eq!(t.before_us(257), 25_500_000);
        let near = |index: u32, us: u64| t.before_us(index).abs_diff(us) <= 100_000;
        assert!(near(2, 0), "{}", t.before_us(2));
        assert!(near(502, 50_000_000), "{}", t.before_us(502));
        assert!(
            t.before_us(1002).abs_diff(100_000_000) <= 500_000,
            "{}",
            t.before_us(1002)
        );
        assert_eq!(t.before_us(1003), t.total_us());
        assert_eq!(t.before_us(5000), t.total_us());
        // Monotone everywhere.
        let mut last = 0;
        for i in 0..1010 {
            assert!(t.before_us(i) >= last);
            last = t.before_us(i);
        }
    }

    #[test]
    fn material_used_is_pushed_less_pulled_back() {
        let ex = |index, v: Vec<u32>| {
            mv(
                index,
                MoveKind::Extrude {
                    to: PositionUm {
                        x_um: 0,
                        y_um: 0,
                        z_um: 0,
                    },
                    feed_um_s: 1,
                    volumes_nl: v,
                    width_factor_ppt: 1000,
                },
            )
        };
        let moves = vec![
            ex(0, vec![100, 50]),
            mv(
                1,
                MoveKind::Retract {
                    volumes_nl: vec![10, 10],
                    duration_ms: 1,
                },
            ),
            mv(
                2,
                MoveKind::Prime {
                    volumes_nl: vec![10, 10],
                    duration_ms: 1,
                },
            ),
            ex(3, vec![0, 25]),
        ];
        let used_nl = |syringes: usize| {
            let mut used = vec![0; syringes];
            for mv in &moves {
                add_used_nl(&mut used, &mv.kind);
            }
            used
        };
        assert_eq!(used_nl(2), vec![100, 75]);
        assert_eq!(used_nl(3), vec![100, 75, 0]);
        // A record of fewer syringes than the move grows to the move's.
        assert_eq!(used_nl(0), vec![100, 75]);
    }
}
