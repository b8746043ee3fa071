//! The lifecycle against a fake store, planner and machine: whole jobs, every odd turn
//! (a cancel during a port loss, a reset during a pause, an e-stop during a resume, a
//! store that cannot write, a planner that fails, a resume after a reset), and every
//! phase under every event.

use std::collections::{BTreeMap, VecDeque};

use super::*;
use crate::machine::{MoveKind, PositionUm, FACTOR_NOMINAL_PPT};

const MS: u64 = 1000;

/// Job `job`'s planned moves `from..to`: a layer mark every 5 moves, extrusions between.
fn job_moves(job: u32, from: u32, to: u32) -> Vec<Move> {
    (from..to)
        .map(|index| Move {
            job_id: job,
            index,
            kind: if index % 5 == 0 {
                MoveKind::LayerMark {
                    layer: index / 5,
                    z_um: 200,
                }
            } else {
                MoveKind::Extrude {
                    to: PositionUm {
                        x_um: index as i32,
                        y_um: 0,
                        z_um: 200,
                    },
                    feed_um_s: 10_000,
                    volumes_nl: vec![10, 30],
                    width_factor_ppt: FACTOR_NOMINAL_PPT,
                }
            },
        })
        .collect()
}

/// Where job moves `0..from` leave the nozzle, as the planner reports it.
fn resume_point(job: u32, from: u32) -> ResumePoint {
    let mut r = ResumePoint::default();
    for m in job_moves(job, 0, from) {
        match m.kind {
            MoveKind::LayerMark { layer, z_um } => r.layer_mark = Some((layer, z_um)),
            MoveKind::Extrude { to, volumes_nl, .. } => {
                r.position = Some(to);
                r.volumes_nl = Some(volumes_nl);
            }
            _ => {}
        }
    }
    r
}

fn queued(id: u32) -> JobInfo {
    JobInfo {
        id,
        state: JobState::Queued,
        checkpoint: Checkpoint::default(),
        total_moves: None,
        submitted_ms: 0,
    }
}

/// A machine as the lifecycle sees it through a link.
#[derive(Debug, Default)]
struct Machine {
    state: MachineState,
    queue: VecDeque<Move>,
    executed: Vec<Move>,
    faults: u32,
    /// Answers commands (acknowledgements, the status after an e-stop's query).
    answers: bool,
}

impl Machine {
    fn report(&self) -> MachineReport {
        let last = self.executed.last();
        MachineReport {
            state: self.state,
            last_executed: last.map(|m| MoveRef {
                job_id: m.job_id,
                index: m.index,
            }),
            executed_total: self.executed.len() as u64,
            queued: self.queue.len() as u32,
            faults: self.faults,
            position: PositionUm::default(),
            remaining_nl: vec![1_000_000, 1_000_000],
        }
    }
}

/// The lifecycle with everything around it faked.
struct Rig {
    lc: Lifecycle,
    now: u64,
    store: BTreeMap<u32, JobInfo>,
    /// Records are written as soon as they come.
    auto_store: bool,
    unstored: Vec<(u64, Record)>,
    /// Reads are answered as soon as they are asked.
    auto_read: bool,
    reads: Vec<Action>,
    next_request: u64,
    replies: BTreeMap<u64, Vec<Result<Answer, Refusal>>>,
    notes: Vec<StateNote>,
    commands: Vec<MachineCommand>,
    planner: Option<(u32, u32, u64)>,
    planner_stops: usize,
    machine: Machine,
    progress: Vec<Option<Progress>>,
    underruns: Vec<Underrun>,
    logs: Vec<String>,
    /// Moves the link takes per settle.
    room: usize,
    events: VecDeque<Event>,
}

impl Rig {
    fn new() -> Rig {
        let mut rig = Rig {
            lc: Lifecycle::new(Options::default(), 10, 1034),
            now: 1_000_000,
            store: BTreeMap::new(),
            auto_store: true,
            unstored: Vec::new(),
            auto_read: true,
            reads: Vec::new(),
            next_request: 1,
            replies: BTreeMap::new(),
            notes: Vec::new(),
            commands: Vec::new(),
            planner: None,
            planner_stops: 0,
            machine: Machine {
                answers: true,
                ..Machine::default()
            },
            progress: Vec::new(),
            underruns: Vec::new(),
            logs: Vec::new(),
            room: 1000,
            events: VecDeque::new(),
        };
        rig.settle();
        rig
    }

    /// A rig with the machine connected and idle and job 1 (queued) planning.
    fn printing() -> Rig {
        let mut rig = Rig::new();
        rig.submit(1);
        rig.connect();
        assert_eq!(rig.lc.phase(), Some(Phase::Streaming));
        rig
    }

    fn submit(&mut self, id: u32) {
        self.store.insert(id, queued(id));
        self.feed(Event::Submitted);
    }

    fn connect(&mut self) {
        let r = self.machine.report();
        self.feed(Event::MachineConnected(r));
    }

    fn feed(&mut self, e: Event) {
        self.events.push_back(e);
        self.settle();
    }

    fn at(&mut self, dt_us: u64) {
        self.now += dt_us;
        self.lc.handle_timeout(self.now);
        self.settle();
    }

    fn command(&mut self, command: Command) -> u64 {
        let request = self.next_request;
        self.next_request += 1;
        self.feed(Event::Command {
            request: RequestId(request),
            command,
        });
        request
    }

    fn reply(&self, request: u64) -> Option<Result<Answer, Refusal>> {
        let r = self.replies.get(&request)?;
        assert_eq!(r.len(), 1, "request {request} answered {} times", r.len());
        Some(r[0].clone())
    }

    fn applied(&self, request: u64) -> Applied {
        match self.reply(request) {
            Some(Ok(Answer::Applied(a))) => a,
            other => panic!("request {request}: {other:?}"),
        }
    }

    fn refused(&self, request: u64) -> RefusalKind {
        match self.reply(request) {
            Some(Err(r)) => r.kind,
            other => panic!("request {request}: {other:?}"),
        }
    }

    /// Carry out every action, answer writes and reads if automatic, deliver moves, until
    /// nothing more happens.
    fn settle(&mut self) {
        loop {
            if let Some(e) = self.events.pop_front() {
                self.lc.handle(e, self.now);
                continue;
            }
            let mut any = false;
            while let Some(a) = self.lc.poll_action() {
                any = true;
                self.carry_out(a);
            }
            if self.auto_store {
                self.write_all();
            }
            for _ in 0..self.room {
                let Some(mv) = self.lc.poll_move() else {
                    break;
                };
                assert!(self.lc.is_connected(), "a move while not connected");
                assert!(
                    mv.job_id == SERVICE_JOB_ID || Some(mv.job_id) == self.lc.active_job(),
                    "a move of job {} while job {:?} is active",
                    mv.job_id,
                    self.lc.active_job()
                );
                any = true;
                if self.machine.state != MachineState::EStopped {
                    self.machine.queue.push_back(mv);
                }
            }
            if !any && self.events.is_empty() {
                return;
            }
        }
    }

    fn carry_out(&mut self, a: Action) {
        match a {
            Action::Machine(c) => {
                self.commands.push(c);
                self.machine_does(c);
            }
            Action::StartPlanner {
                job_id,
                from_index,
                run,
            } => self.planner = Some((job_id, from_index, run)),
            Action::StopPlanner => {
                self.planner = None;
                self.planner_stops += 1;
            }
            Action::Persist { seq, record } => self.unstored.push((seq, record)),
            Action::LookUpJob(_) | Action::ListQueued if !self.auto_read => self.reads.push(a),
            Action::LookUpJob(id) => self.events.push_back(Event::JobLookedUp {
                id,
                job: Ok(self.store.get(&id).cloned()),
            }),
            Action::ListQueued => {
                let list = self
                    .store
                    .values()
                    .filter(|j| matches!(j.state, JobState::Queued | JobState::Interrupted))
                    .cloned()
                    .collect();
                self.events.push_back(Event::QueuedJobs(Ok(list)));
            }
            Action::Reply { request, result } => {
                self.replies.entry(request.0).or_default().push(result)
            }
            Action::JobState(n) => self.notes.push(n),
            Action::Progress(p) => self.progress.push(p),
            Action::Underrun(u) => self.underruns.push(u),
            Action::Log { message, .. } => self.logs.push(message),
        }
    }

    fn machine_does(&mut self, c: MachineCommand) {
        let m = &mut self.machine;
        match c {
            MachineCommand::EmergencyStop | MachineCommand::Flush => {
                m.state = MachineState::EStopped;
                m.queue.clear();
            }
            MachineCommand::FeedHold if m.state != MachineState::EStopped => {
                m.state = MachineState::Held
            }
            MachineCommand::Resume => m.state = MachineState::Idle,
            MachineCommand::ClearFaults => m.faults = 0,
            _ => {}
        }
        if !m.answers || !self.lc.is_connected() {
            return;
        }
        match c {
            MachineCommand::QueryStatus => {
                let r = self.machine.report();
                self.events.push_back(Event::MachineStatus(r));
            }
            MachineCommand::ClearFaults => {}
            c => self.events.push_back(Event::CommandAcked(c)),
        }
    }

    /// Write every record handed over, as the store would, and say so.
    fn write_all(&mut self) {
        let Some(upto) = self.unstored.last().map(|(s, _)| *s) else {
            return;
        };
        for (_, r) in std::mem::take(&mut self.unstored) {
            if let Record::Job(u) = r {
                let j = self
                    .store
                    .entry(u.job_id)
                    .or_insert_with(|| queued(u.job_id));
                if let Some(c) = u.checkpoint {
                    j.checkpoint = c;
                }
                if let Some(t) = u.total_moves {
                    j.total_moves = Some(t);
                }
                if let Some((s, _)) = u.state {
                    j.state = s;
                }
            }
        }
        self.events.push_back(Event::Stored { upto });
        self.settle();
    }

    /// The planner plans job moves up to `total` for its run.
    fn plan(&mut self, total: u32) {
        let Some((job, from, run)) = self.planner else {
            panic!("no planner running");
        };
        let mut out = vec![PlannerOutput::Layers(total.div_ceil(5))];
        if from > 0 {
            out.push(PlannerOutput::ResumeAt(resume_point(job, from)));
        }
        out.push(PlannerOutput::Moves(job_moves(job, from, total)));
        out.push(PlannerOutput::Done { total });
        out.push(PlannerOutput::Ended);
        for output in out {
            self.feed(Event::Planner { run, output });
        }
        self.planner = None;
    }

    /// The machine executes up to `n` moves, then reports.
    fn run(&mut self, n: usize) {
        let m = &mut self.machine;
        if matches!(m.state, MachineState::Idle | MachineState::Running) {
            for _ in 0..n {
                let Some(mv) = m.queue.pop_front() else {
                    break;
                };
                m.executed.push(mv);
            }
            m.state = if m.queue.is_empty() {
                MachineState::Idle
            } else {
                MachineState::Running
            };
        }
        self.now += 10 * MS;
        let r = self.machine.report();
        self.feed(Event::MachineStatus(r));
    }

    /// Job `job`'s move indices the machine executed, in order.
    fn executed(&self, job: u32) -> Vec<u32> {
        self.machine
            .executed
            .iter()
            .filter(|m| m.job_id == job)
            .map(|m| m.index)
            .collect()
    }

    fn service_kinds(&self) -> Vec<&'static str> {
        self.machine
            .executed
            .iter()
            .filter(|m| m.job_id == SERVICE_JOB_ID)
            .map(|m| match m.kind {
                MoveKind::Home => "home",
                MoveKind::Prime { .. } => "prime",
                MoveKind::Travel { .. } => "travel",
                MoveKind::LayerMark { .. } => "layer",
                MoveKind::Retract { .. } => "retract",
                _ => "other",
            })
            .collect()
    }

    fn states(&self, job: u32) -> Vec<JobState> {
        self.notes
            .iter()
            .filter(|n| n.job_id == job)
            .map(|n| n.state)
            .collect()
    }

    fn stored_state(&self, job: u32) -> Option<JobState> {
        self.store.get(&job).map(|j| j.state)
    }

    /// The machine connects again after a reset or a lost port, its queue as it is.
    fn reconnect(&mut self) {
        self.connect();
    }
}

fn assert_once_in_order(indices: &[u32], total: u32) {
    assert_eq!(indices, (0..total).collect::<Vec<_>>());
}

#[test]
fn a_job_runs_from_queued_to_done_and_every_move_executes_once() {
    let mut rig = Rig::printing();
    assert_eq!(rig.planner, Some((1, 0, 1)));
    rig.plan(23);
    rig.run(10);
    rig.run(100);
    assert_eq!(rig.lc.active_job(), None);
    assert_once_in_order(&rig.executed(1), 23);
    assert_eq!(
        rig.states(1),
        [JobState::Planning, JobState::Printing, JobState::Done]
    );
    let j = &rig.store[&1];
    assert_eq!(
        (j.state, j.checkpoint.next_index, j.total_moves),
        (JobState::Done, 23, Some(23))
    );
    assert_eq!(j.checkpoint.layer, Some(4));
    assert_eq!(j.checkpoint.composition, Some(vec![0.25, 0.75]));
    // The last progress is the job's end, then none.
    let n = rig.progress.len();
    assert_eq!(rig.progress[n - 1], None);
    let last = rig.progress[n - 2].clone().unwrap();
    assert_eq!(
        (last.executed, last.total, last.layers),
        (23, Some(23), Some(5))
    );
    assert!(rig.underruns.is_empty());
}

#[test]
fn jobs_wait_for_the_machine_and_run_in_order() {
    let mut rig = Rig::new();
    rig.submit(2);
    rig.submit(3);
    assert_eq!(rig.lc.active_job(), None, "not connected");
    rig.connect();
    assert_eq!(rig.lc.active_job(), Some(2));
    rig.plan(5);
    rig.run(10);
    assert_eq!(rig.lc.active_job(), Some(3));
    rig.plan(7);
    rig.run(10);
    assert_eq!(rig.lc.active_job(), None);
    assert_once_in_order(&rig.executed(2), 5);
    assert_once_in_order(&rig.executed(3), 7);
}

#[test]
fn a_job_on_a_machine_not_idle_starts_with_a_flush() {
    let mut rig = Rig::new();
    rig.machine.faults = 4;
    rig.submit(1);
    rig.connect();
    // Flush, ack, query, EStopped status, clear + resume, ack: prelude then the job.
    assert_eq!(rig.lc.phase(), Some(Phase::Streaming));
    assert_eq!(
        rig.commands,
        [
            MachineCommand::Flush,
            MachineCommand::QueryStatus,
            MachineCommand::ClearFaults,
            MachineCommand::Resume
        ]
    );
    rig.plan(12);
    rig.run(100);
    assert_eq!(rig.service_kinds(), ["home", "prime"]);
    assert_once_in_order(&rig.executed(1), 12);
}

#[test]
fn pause_holds_and_answers_once_stored_then_resume_continues() {
    let mut rig = Rig::printing();
    rig.plan(40);
    rig.run(10);
    let p = rig.command(Command::Pause(1));
    assert_eq!(rig.lc.phase(), Some(Phase::Holding));
    assert_eq!(rig.commands.last(), Some(&MachineCommand::FeedHold));
    assert_eq!(
        rig.applied(p),
        Applied {
            state: JobState::Paused,
            stored: true
        }
    );
    assert_eq!(
        rig.store[&1].checkpoint.next_index, 10,
        "stored with its checkpoint"
    );
    rig.run(10);
    assert_eq!(rig.executed(1).len(), 10, "held");
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.applied(r).state, JobState::Printing);
    rig.run(100);
    assert_once_in_order(&rig.executed(1), 40);
    assert_eq!(
        rig.states(1),
        [
            JobState::Planning,
            JobState::Printing,
            JobState::Paused,
            JobState::Printing,
            JobState::Done
        ]
    );
}

#[test]
fn a_store_that_cannot_write_delays_replies_and_notifications_not_the_machine() {
    let mut rig = Rig::printing();
    rig.plan(40);
    rig.run(10);
    rig.auto_store = false;
    let p = rig.command(Command::Pause(1));
    // The machine holds at once; the reply waits for the store.
    assert_eq!(rig.commands.last(), Some(&MachineCommand::FeedHold));
    assert_eq!(rig.reply(p), None);
    assert!(!rig.states(1).contains(&JobState::Paused));
    rig.at(74 * MS);
    assert_eq!(rig.reply(p), None);
    rig.at(2 * MS);
    assert_eq!(
        rig.applied(p),
        Applied {
            state: JobState::Paused,
            stored: false
        }
    );
    // A resume answered at once when the store reports its failure.
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.reply(r), None);
    rig.feed(Event::StoreFailed {
        error: "database is locked".into(),
        busy: true,
    });
    assert_eq!(
        rig.applied(r),
        Applied {
            state: JobState::Printing,
            stored: false
        }
    );
    rig.run(100);
    assert_eq!(rig.lc.active_job(), None, "done meanwhile");
    assert_eq!(
        rig.stored_state(1),
        Some(JobState::Printing),
        "nothing written yet"
    );
    // Written at last: the notifications come, in order.
    rig.write_all();
    assert_eq!(rig.stored_state(1), Some(JobState::Done));
    assert_eq!(
        rig.states(1),
        [
            JobState::Planning,
            JobState::Printing,
            JobState::Paused,
            JobState::Printing,
            JobState::Done
        ]
    );
    assert_eq!(rig.store[&1].checkpoint.next_index, 40);
    assert_once_in_order(&rig.executed(1), 40);
}

#[test]
fn a_reset_during_a_pause_interrupts_and_the_resume_continues_where_it_stopped() {
    let mut rig = Rig::printing();
    rig.plan(60);
    rig.run(17);
    rig.command(Command::Pause(1));
    // The machine resets: its queue is gone.
    rig.machine.queue.clear();
    rig.machine.state = MachineState::Idle;
    rig.feed(Event::MachineReset {
        last_executed: Some(MoveRef {
            job_id: 1,
            index: 16,
        }),
    });
    assert_eq!(rig.lc.phase(), Some(Phase::Interrupted));
    assert_eq!(rig.lc.job_state(1), Some(JobState::Interrupted));
    assert_eq!(rig.lc.poll_move(), None);
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.refused(r), RefusalKind::NotConnected);
    rig.reconnect();
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.applied(r).state, JobState::Printing);
    // Flushed and released: the planner starts from the first move not executed.
    assert_eq!(rig.planner, Some((1, 17, 2)));
    rig.plan(60);
    rig.run(100);
    assert_once_in_order(&rig.executed(1), 60);
    assert_eq!(
        rig.service_kinds(),
        ["home", "prime", "travel", "travel", "layer"]
    );
    let reasons: Vec<_> = rig.notes.iter().filter_map(|n| n.reason.clone()).collect();
    assert_eq!(reasons, ["paused by an operator", "machine reset"]);
}

#[test]
fn an_estop_during_a_resume_stops_it_there() {
    // E-stopped while the flush waits for its acknowledgement, and while the release
    // does: both leave the job interrupted and the machine stopped, no prelude sent.
    for release_first in [false, true] {
        let mut rig = Rig::printing();
        rig.plan(60);
        rig.run(20);
        rig.command(Command::EStop);
        assert_eq!(rig.lc.phase(), Some(Phase::Interrupted));
        rig.machine.answers = false;
        let r = rig.command(Command::Resume(1));
        assert_eq!(rig.applied(r).state, JobState::Printing);
        if release_first {
            rig.feed(Event::CommandAcked(MachineCommand::Flush));
            let report = rig.machine.report();
            rig.feed(Event::MachineStatus(report));
            assert_eq!(
                rig.lc.phase(),
                Some(Phase::Releasing {
                    then: AfterFlush::Continue
                })
            );
        }
        let e = rig.command(Command::EStop);
        assert_eq!(rig.reply(e), Some(Ok(Answer::Done)));
        assert_eq!(rig.lc.phase(), Some(Phase::Interrupted));
        // The acknowledgements that come late change nothing.
        rig.feed(Event::CommandAcked(MachineCommand::Flush));
        rig.feed(Event::CommandAcked(MachineCommand::EmergencyStop));
        rig.feed(Event::CommandAcked(MachineCommand::Resume));
        assert_eq!(rig.lc.phase(), Some(Phase::Interrupted));
        assert_eq!(rig.lc.poll_move(), None);
        assert_eq!(rig.planner, None);
        assert_eq!(rig.commands.last(), Some(&MachineCommand::EmergencyStop));
        let reason = rig.notes.last().and_then(|n| n.reason.clone());
        assert_eq!(reason.as_deref(), Some("emergency stop by an operator"));
        // And a resume then works.
        rig.machine.answers = true;
        rig.command(Command::Resume(1));
        rig.plan(60);
        rig.run(100);
        assert_once_in_order(&rig.executed(1), 60);
    }
}

#[test]
fn a_cancel_during_a_port_loss_cancels_and_the_machine_is_stopped_when_back() {
    let mut rig = Rig::printing();
    rig.plan(300);
    rig.run(30);
    rig.feed(Event::PortLost {
        why: "end of file".into(),
    });
    assert_eq!(rig.lc.job_state(1), Some(JobState::Interrupted));
    let c = rig.command(Command::Cancel(1));
    assert_eq!(
        rig.applied(c),
        Applied {
            state: JobState::Cancelled,
            stored: true
        }
    );
    assert_eq!(rig.lc.active_job(), None);
    // The machine ran on meanwhile, and still has moves queued when it is back.
    rig.machine.executed.extend(rig.machine.queue.drain(..10));
    rig.machine.state = MachineState::Running;
    let n = rig.commands.len();
    rig.reconnect();
    assert_eq!(rig.commands[n..][0], MachineCommand::EmergencyStop);
    assert_eq!(rig.machine.queue.len(), 0);
    assert_eq!(rig.stored_state(1), Some(JobState::Cancelled));
    // The next job starts from the stopped machine with a flush.
    rig.submit(2);
    assert_eq!(rig.lc.active_job(), Some(2));
    rig.plan(5);
    rig.run(10);
    assert_once_in_order(&rig.executed(2), 5);
}

#[test]
fn cancel_stops_retracts_and_parks_and_a_lost_link_ends_it_unparked() {
    let mut rig = Rig::printing();
    rig.plan(100);
    rig.run(30);
    let c = rig.command(Command::Cancel(1));
    // The reply names the state the cancel leads to, not yet on disk.
    assert_eq!(
        rig.applied(c),
        Applied {
            state: JobState::Cancelled,
            stored: false
        }
    );
    assert_eq!(rig.lc.active_job(), None);
    assert_eq!(rig.stored_state(1), Some(JobState::Cancelled));
    rig.run(10);
    assert_eq!(rig.service_kinds(), ["retract", "travel", "travel"]);
    assert_eq!(rig.store[&1].checkpoint.next_index, 30);
    assert_once_in_order(&rig.executed(1), 30);

    let mut rig = Rig::printing();
    rig.plan(100);
    rig.run(30);
    rig.machine.answers = false;
    rig.command(Command::Cancel(1));
    assert!(rig.lc.phase().is_some_and(Phase::cancelling));
    rig.feed(Event::LinkSilent);
    assert_eq!(rig.lc.active_job(), None);
    let last = rig.notes.last().cloned().unwrap();
    assert_eq!(last.state, JobState::Cancelled);
    assert_eq!(
        last.reason.as_deref(),
        Some("cancelled by an operator; not parked: link to the machine lost")
    );
}

#[test]
fn a_planner_failure_fails_the_job_stops_its_moves_and_the_next_job_runs() {
    let mut rig = Rig::printing();
    rig.submit(2);
    let (_, _, run) = rig.planner.unwrap();
    rig.feed(Event::Planner {
        run,
        output: PlannerOutput::Moves(job_moves(1, 0, 8)),
    });
    rig.run(3);
    rig.feed(Event::Planner {
        run,
        output: PlannerOutput::Failed("layer 2: the mesh is open".into()),
    });
    assert_eq!(rig.stored_state(1), Some(JobState::Failed));
    assert_eq!(rig.store[&1].checkpoint.next_index, 3);
    assert!(rig.commands.contains(&MachineCommand::EmergencyStop));
    // Output of the failed run that arrives late is ignored.
    rig.feed(Event::Planner {
        run,
        output: PlannerOutput::Moves(job_moves(1, 8, 12)),
    });
    assert_eq!(rig.lc.active_job(), Some(2));
    rig.plan(6);
    rig.run(100);
    assert_eq!(rig.executed(1), [0, 1, 2]);
    assert_once_in_order(&rig.executed(2), 6);
}

#[test]
fn a_move_the_link_refuses_fails_its_job() {
    let mut rig = Rig::printing();
    rig.plan(10);
    let mv = job_moves(1, 3, 4).remove(0);
    rig.feed(Event::MoveRefused {
        mv,
        reason: "3 volumes for 2 syringes".into(),
    });
    let last = rig.notes.last().cloned().unwrap();
    assert_eq!(last.state, JobState::Failed);
    assert_eq!(
        last.reason.as_deref(),
        Some("move 3 refused by the link: 3 volumes for 2 syringes")
    );
}

#[test]
fn a_syringe_running_empty_pauses_until_a_refill() {
    let mut rig = Rig::printing();
    rig.plan(50);
    rig.run(12);
    rig.machine.queue.clear();
    rig.machine.state = MachineState::Faulted;
    rig.feed(Event::MachineFault(MachineFault::SyringeEmpty(1)));
    assert_eq!(rig.lc.phase(), Some(Phase::Empty));
    let last = rig.notes.last().cloned().unwrap();
    assert_eq!(last.state, JobState::Paused);
    assert_eq!(
        last.reason.as_deref(),
        Some("syringe 1 (B) is empty: swap it, then machine.refill")
    );
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.refused(r), RefusalKind::BadState);
    let f = rig.command(Command::Refill);
    assert_eq!(rig.reply(f), Some(Ok(Answer::Done)));
    rig.plan(50);
    rig.run(100);
    assert_once_in_order(&rig.executed(1), 50);
}

#[test]
fn after_an_edod_restart_the_machine_is_followed_and_the_resume_repeats_nothing() {
    // edod stopped at move 100 (stored checkpoint 90); the machine ran on to 140.
    let mut rig = Rig::new();
    let mut job = queued(7);
    job.state = JobState::Interrupted;
    job.checkpoint.next_index = 90;
    rig.store.insert(7, job);
    rig.machine.executed = job_moves(7, 0, 140);
    rig.machine.queue = job_moves(7, 140, 150).into();
    rig.machine.state = MachineState::Running;
    rig.connect();
    // The job is read, then followed.
    rig.run(5);
    rig.at(200 * MS);
    assert_eq!(rig.store[&7].checkpoint.next_index, 145);
    let r = rig.command(Command::Resume(7));
    assert_eq!(rig.applied(r).state, JobState::Printing);
    assert_eq!(rig.planner.map(|p| p.1), Some(145));
    rig.plan(200);
    rig.run(1000);
    assert_once_in_order(&rig.executed(7), 200);
}

#[test]
fn commands_about_jobs_not_known_wait_for_the_store_and_keep_their_order() {
    let mut rig = Rig::new();
    rig.auto_read = false;
    rig.reads.clear();
    let mut done = queued(4);
    done.state = JobState::Done;
    rig.store.insert(4, done);
    let a = rig.command(Command::Resume(4));
    let b = rig.command(Command::Cancel(4));
    let c = rig.command(Command::Pause(9));
    assert_eq!(rig.reads, [Action::LookUpJob(4), Action::LookUpJob(9)]);
    assert_eq!(rig.reply(a), None);
    rig.feed(Event::JobLookedUp {
        id: 9,
        job: Ok(None),
    });
    assert_eq!(rig.refused(c), RefusalKind::NoSuchJob);
    assert_eq!(rig.reply(a), None);
    let four = rig.store.get(&4).cloned();
    rig.feed(Event::JobLookedUp {
        id: 4,
        job: Ok(four),
    });
    assert_eq!(rig.refused(a), RefusalKind::BadState);
    assert_eq!(rig.refused(b), RefusalKind::BadState);
    // A read that fails answers with an error, nothing else.
    let d = rig.command(Command::Cancel(11));
    rig.feed(Event::JobLookedUp {
        id: 11,
        job: Err("disk I/O error".into()),
    });
    assert_eq!(rig.refused(d), RefusalKind::Internal);
}

#[test]
fn a_paused_job_cancelled_replies_cancelled_and_ends_so() {
    let mut rig = Rig::printing();
    rig.plan(100);
    rig.run(30);
    let p = rig.command(Command::Pause(1));
    assert_eq!(rig.applied(p).state, JobState::Paused);
    rig.run(100);
    let c = rig.command(Command::Cancel(1));
    assert_eq!(
        rig.applied(c),
        Applied {
            state: JobState::Cancelled,
            stored: false
        }
    );
    rig.run(10);
    assert_eq!(rig.stored_state(1), Some(JobState::Cancelled));
    assert_eq!(rig.notes.last().map(|n| n.state), Some(JobState::Cancelled));
}

/// A store as edod left it after a restart: job 3 interrupted at move 40, jobs 4 and 5
/// queued.
fn restarted_with_an_interrupted_job() -> Rig {
    let mut rig = Rig::new();
    let mut job = queued(3);
    job.state = JobState::Interrupted;
    job.checkpoint.next_index = 40;
    rig.store.insert(3, job);
    rig.store.insert(4, queued(4));
    rig.store.insert(5, queued(5));
    rig.feed(Event::Submitted);
    rig.connect();
    rig.at(500 * MS);
    rig
}

#[test]
fn an_interrupted_job_holds_the_queue_until_the_operator_decides() {
    // Resume: job 3 runs, then the queue.
    let mut rig = restarted_with_an_interrupted_job();
    assert_eq!(
        rig.lc.active_job(),
        None,
        "no job starts over an interrupted one"
    );
    assert_eq!(rig.lc.queue_held_by(), Some(3));
    assert_eq!(rig.planner, None);
    let r = rig.command(Command::Resume(3));
    assert_eq!(rig.applied(r).state, JobState::Printing);
    assert_eq!(rig.lc.queue_held_by(), None);
    rig.plan(60);
    rig.run(1000);
    assert_eq!(rig.stored_state(3), Some(JobState::Done));
    assert_eq!(rig.lc.active_job(), Some(4));

    // Cancel: the queue runs on.
    let mut rig = restarted_with_an_interrupted_job();
    let c = rig.command(Command::Cancel(3));
    assert_eq!(rig.applied(c).state, JobState::Cancelled);
    assert_eq!(rig.lc.active_job(), Some(4));

    // Start next: job 5 starts by name, job 3 stays interrupted, and holds the queue
    // again once job 5 is done.
    let mut rig = restarted_with_an_interrupted_job();
    let s = rig.command(Command::StartNext(5));
    assert_eq!(rig.applied(s).state, JobState::Planning);
    assert_eq!(rig.lc.active_job(), Some(5));
    assert!(rig
        .logs
        .iter()
        .any(|l| l.contains("while job 3 is interrupted")));
    let again = rig.command(Command::StartNext(4));
    assert_eq!(rig.refused(again), RefusalKind::BadState);
    rig.plan(20);
    rig.run(1000);
    assert_eq!(rig.stored_state(5), Some(JobState::Done));
    assert_eq!(rig.stored_state(3), Some(JobState::Interrupted));
    assert_eq!(rig.lc.active_job(), None);
    assert_eq!(rig.lc.queue_held_by(), Some(3));
    // Only a queued job can be started.
    let bad = rig.command(Command::StartNext(3));
    assert_eq!(rig.refused(bad), RefusalKind::BadState);
    let missing = rig.command(Command::StartNext(99));
    assert_eq!(rig.refused(missing), RefusalKind::NoSuchJob);
}

#[test]
fn a_job_cancelled_while_queued_never_starts() {
    let mut rig = Rig::new();
    rig.submit(1);
    rig.submit(2);
    let c = rig.command(Command::Cancel(1));
    assert_eq!(rig.applied(c).state, JobState::Cancelled);
    rig.connect();
    assert_eq!(rig.lc.active_job(), Some(2));
    let again = rig.command(Command::Cancel(1));
    assert_eq!(rig.refused(again), RefusalKind::BadState);
}

#[test]
fn shutdown_holds_interrupts_and_answers_once_stored_or_after_the_wait() {
    let mut rig = Rig::printing();
    rig.plan(100);
    rig.run(20);
    let s = rig.command(Command::Shutdown);
    assert_eq!(rig.commands.last(), Some(&MachineCommand::FeedHold));
    assert_eq!(rig.reply(s), None, "the machine has not said it holds");
    rig.run(0);
    assert_eq!(rig.reply(s), Some(Ok(Answer::Done)));
    assert!(rig.lc.is_stopped());
    let j = &rig.store[&1];
    assert_eq!(j.state, JobState::Interrupted);
    assert_eq!(j.checkpoint.next_index, 20);

    // The store locked: answered after the waits all the same.
    let mut rig = Rig::printing();
    rig.plan(100);
    rig.run(20);
    rig.auto_store = false;
    rig.machine.answers = false;
    let s = rig.command(Command::Shutdown);
    rig.at(1_999 * MS);
    assert_eq!(rig.reply(s), None);
    rig.at(2 * MS);
    assert_eq!(rig.reply(s), None, "waiting for the store");
    rig.at(2_500 * MS);
    assert_eq!(rig.reply(s), Some(Ok(Answer::Done)));
}

#[test]
fn service_move_indices_run_on_and_blocks_are_reserved_ahead() {
    let opts = Options {
        service_index_block: 8,
        ..Options::default()
    };
    let mut rig = Rig::new();
    rig.lc = Lifecycle::new(opts, 100, 108);
    rig.settle();
    rig.auto_store = false;
    // Jobs on a machine with a fault latched: each starts with a flush and a prelude.
    for k in 1..=5 {
        rig.machine.faults = 1;
        if k == 1 {
            rig.connect();
        } else {
            rig.run(0);
        }
        rig.submit(k);
        rig.plan(3);
        rig.run(10);
    }
    let indices: Vec<u32> = rig
        .machine
        .executed
        .iter()
        .filter(|m| m.job_id == SERVICE_JOB_ID)
        .map(|m| m.index)
        .collect();
    assert_eq!(indices, (100..110).collect::<Vec<_>>());
    // Past half the block the next is reserved, once while the store has not written it.
    let reservations: Vec<&Record> = rig
        .unstored
        .iter()
        .map(|(_, r)| r)
        .filter(|r| matches!(r, Record::ServiceIndices { .. }))
        .collect();
    assert_eq!(
        reservations,
        [&Record::ServiceIndices {
            reserved_until: 116
        }]
    );
    rig.write_all();
    for k in 6..=7 {
        rig.machine.faults = 1;
        rig.run(0);
        rig.submit(k);
        rig.plan(3);
        rig.run(10);
    }
    assert!(rig.unstored.iter().any(|(_, r)| *r
        == Record::ServiceIndices {
            reserved_until: 124
        }));
}

#[test]
fn an_underrun_is_counted_once_per_dry_spell() {
    let mut rig = Rig::printing();
    let (_, _, run) = rig.planner.unwrap();
    rig.feed(Event::Planner {
        run,
        output: PlannerOutput::Moves(job_moves(1, 0, 5)),
    });
    rig.run(100);
    rig.run(100);
    assert_eq!(rig.lc.underruns(), 1);
    rig.feed(Event::Planner {
        run,
        output: PlannerOutput::Moves(job_moves(1, 5, 10)),
    });
    rig.run(2);
    rig.run(100);
    assert_eq!(rig.lc.underruns(), 2);
    assert_eq!(rig.underruns.len(), 2);
}

// ---- every phase under every event ------------------------------------------------------

/// A rig streaming job 1 (30 moves planned, 5 executed).
fn streaming_rig() -> Rig {
    let mut r = Rig::printing();
    let (_, _, run) = r.planner.unwrap();
    r.feed(Event::Planner {
        run,
        output: PlannerOutput::Moves(job_moves(1, 0, 30)),
    });
    r.run(5);
    r
}

/// A streaming rig whose machine stops answering, then `then` (a resume after an
/// e-stop, or a cancel), then `acks` of the flush: 0 none, 1 the e-stop's, 2 the
/// e-stop's and the `EStopped` status.
fn restarting_rig(then: Command, acks: u8) -> Rig {
    let mut r = streaming_rig();
    if then == Command::Resume(1) {
        r.command(Command::EStop);
    }
    r.machine.answers = false;
    r.command(then);
    if acks >= 1 {
        r.feed(Event::CommandAcked(MachineCommand::Flush));
    }
    if acks >= 2 {
        let report = r.machine.report();
        r.feed(Event::MachineStatus(MachineReport {
            state: MachineState::EStopped,
            ..report
        }));
    }
    r
}

type Setup = (&'static str, Box<dyn Fn() -> Rig>);

/// Ways to bring the rig into each phase (and the states around a job), by events only.
fn setups() -> Vec<Setup> {
    let mut out: Vec<Setup> = vec![
        (
            "idle",
            Box::new(|| {
                let mut r = Rig::new();
                r.connect();
                r
            }),
        ),
        (
            "queued, not connected",
            Box::new(|| {
                let mut r = Rig::new();
                r.submit(1);
                r
            }),
        ),
        ("planning", Box::new(Rig::printing)),
        ("streaming", Box::new(streaming_rig)),
        (
            "holding",
            Box::new(|| {
                let mut r = streaming_rig();
                r.command(Command::Pause(1));
                r
            }),
        ),
        (
            "empty",
            Box::new(|| {
                let mut r = streaming_rig();
                r.feed(Event::MachineFault(MachineFault::SyringeEmpty(0)));
                r
            }),
        ),
        (
            "interrupted, offline",
            Box::new(|| {
                let mut r = streaming_rig();
                r.feed(Event::LinkSilent);
                r
            }),
        ),
        (
            "interrupted",
            Box::new(|| {
                let mut r = streaming_rig();
                r.command(Command::EStop);
                r
            }),
        ),
        (
            "prelude",
            Box::new(|| {
                let mut r = streaming_rig();
                r.command(Command::EStop);
                r.command(Command::Resume(1));
                r
            }),
        ),
        (
            "tracking after a restart",
            Box::new(|| {
                let mut r = Rig::new();
                let mut job = queued(7);
                job.state = JobState::Interrupted;
                r.store.insert(7, job);
                r.machine.executed = job_moves(7, 0, 4);
                r.machine.queue = job_moves(7, 4, 9).into();
                r.machine.state = MachineState::Running;
                r.connect();
                r
            }),
        ),
        (
            "done",
            Box::new(|| {
                let mut r = Rig::printing();
                r.plan(12);
                r.run(100);
                r
            }),
        ),
        (
            "failed",
            Box::new(|| {
                let mut r = streaming_rig();
                let (_, _, run) = r.planner.unwrap();
                r.feed(Event::Planner {
                    run,
                    output: PlannerOutput::Failed("the mesh is open".into()),
                });
                r
            }),
        ),
        (
            "cancelled while queued",
            Box::new(|| {
                let mut r = Rig::new();
                r.submit(1);
                r.command(Command::Cancel(1));
                r.connect();
                r
            }),
        ),
        (
            "streaming, the store locked, a pause waiting for it",
            Box::new(|| {
                let mut r = streaming_rig();
                r.auto_store = false;
                r.command(Command::Pause(1));
                r
            }),
        ),
        (
            "interrupted, the store locked, a resume waiting for it",
            Box::new(|| {
                let mut r = streaming_rig();
                r.command(Command::EStop);
                r.auto_store = false;
                r.command(Command::Resume(1));
                r
            }),
        ),
        (
            "stopping",
            Box::new(|| {
                let mut r = streaming_rig();
                r.machine.answers = false;
                r.command(Command::Shutdown);
                r
            }),
        ),
        (
            "stopped",
            Box::new(|| {
                let mut r = streaming_rig();
                r.command(Command::Shutdown);
                r.run(0);
                r
            }),
        ),
    ];
    for (name, then) in [
        ("resume", Command::Resume(1)),
        ("cancel", Command::Cancel(1)),
    ] {
        for (stage, acks) in [("flushing", 0), ("flush acked", 1), ("releasing", 2)] {
            out.push((
                Box::leak(format!("{stage} for a {name}").into_boxed_str()),
                Box::new(move || restarting_rig(then, acks)),
            ));
        }
    }
    out
}

/// One of every event, about job 1 (the one the setups run) and job 2.
fn every_event(run: u64) -> Vec<Event> {
    let report = |state| MachineReport {
        state,
        last_executed: Some(MoveRef {
            job_id: 1,
            index: 3,
        }),
        executed_total: 4,
        queued: 2,
        faults: 0,
        position: PositionUm::default(),
        remaining_nl: vec![5, 5],
    };
    let mut v = vec![
        Event::MachineConnected(report(MachineState::Idle)),
        Event::MachineConnected(report(MachineState::Running)),
        Event::MachineStatus(report(MachineState::Idle)),
        Event::MachineStatus(report(MachineState::Running)),
        Event::MachineStatus(report(MachineState::Held)),
        Event::MachineStatus(report(MachineState::EStopped)),
        Event::MachineStatus(report(MachineState::Faulted)),
        Event::MachineFault(MachineFault::SyringeEmpty(1)),
        Event::MachineFault(MachineFault::EStopPressed),
        Event::MachineFault(MachineFault::Other("LimitHit(0)".into())),
        Event::MachineReset {
            last_executed: Some(MoveRef {
                job_id: 1,
                index: 4,
            }),
        },
        Event::MachineReset {
            last_executed: None,
        },
        Event::LinkSilent,
        Event::LinkRestored,
        Event::PortLost { why: "EOF".into() },
        Event::MachineIncompatible,
        Event::MoveRefused {
            mv: job_moves(1, 6, 7).remove(0),
            reason: "bad".into(),
        },
        Event::MoveRefused {
            mv: job_moves(SERVICE_JOB_ID, 6, 7).remove(0),
            reason: "bad".into(),
        },
        Event::Submitted,
        Event::QueuedJobs(Ok(vec![queued(2)])),
        Event::QueuedJobs(Err("locked".into())),
        Event::JobLookedUp {
            id: 2,
            job: Ok(Some(queued(2))),
        },
        Event::JobLookedUp {
            id: 3,
            job: Ok(None),
        },
        // Stale: every setup has written more since (its own writes are stored as made).
        Event::Stored { upto: 1 },
        Event::StoreFailed {
            error: "locked".into(),
            busy: true,
        },
        Event::StoreFailed {
            error: "disk full".into(),
            busy: false,
        },
    ];
    for c in [
        MachineCommand::EmergencyStop,
        MachineCommand::Flush,
        MachineCommand::FeedHold,
        MachineCommand::Resume,
        MachineCommand::ClearFaults,
        MachineCommand::QueryStatus,
    ] {
        v.push(Event::CommandAcked(c));
    }
    for job in [1, 2, 3] {
        for c in [
            Command::Pause(job),
            Command::Resume(job),
            Command::Cancel(job),
        ] {
            v.push(Event::Command {
                request: RequestId(0),
                command: c,
            });
        }
    }
    for c in [Command::EStop, Command::Refill, Command::Shutdown] {
        v.push(Event::Command {
            request: RequestId(0),
            command: c,
        });
    }
    for r in [run, run + 1] {
        for output in [
            PlannerOutput::ResumeAt(resume_point(1, 3)),
            PlannerOutput::Layers(6),
            PlannerOutput::Moves(job_moves(1, 30, 33)),
            PlannerOutput::Done { total: 33 },
            PlannerOutput::Failed("boom".into()),
            PlannerOutput::Ended,
        ] {
            v.push(Event::Planner { run: r, output });
        }
    }
    v
}

/// What must hold whatever happened (besides what [`Rig::settle`] checks of every move:
/// none while not connected, only service moves and the active job's): the active job
/// is in a state a job moving can be in; every request is answered at most once, and
/// once the store and the clock caught up, exactly once, and the store holds the
/// states the lifecycle does, the last of which the clients were told.
fn check_invariants(name: &str, event: &str, rig: &mut Rig) {
    let ctx = format!("{name} / {event}");
    if let Some(id) = rig.lc.active_job() {
        let s = rig.lc.job_state(id);
        assert!(
            matches!(
                s,
                Some(
                    JobState::Planning
                        | JobState::Printing
                        | JobState::Paused
                        | JobState::Interrupted
                )
            ),
            "{ctx}: active job {id} is {s:?}"
        );
    }
    for (req, answers) in &rig.replies {
        assert!(answers.len() <= 1, "{ctx}: request {req} answered twice");
    }
    // Catch up: writes, reads, the clock.
    rig.auto_store = true;
    rig.auto_read = true;
    for a in std::mem::take(&mut rig.reads) {
        rig.carry_out(a);
    }
    rig.settle();
    rig.at(5_000 * MS);
    let asked: Vec<u64> = (1..rig.next_request).collect();
    for req in asked {
        let n = rig.replies.get(&req).map_or(0, Vec::len);
        assert_eq!(n, 1, "{ctx}: request {req} answered {n} times");
    }
    if !rig.lc.is_connected() {
        assert_eq!(rig.lc.poll_move(), None, "{ctx}: a move while offline");
    }
    // What is stored is what the lifecycle holds, and the clients were told it.
    for (id, j) in &rig.store {
        if let Some(s) = rig.lc.job_state(*id) {
            assert_eq!(s, j.state, "{ctx}: job {id} stored as {:?}", j.state);
            if let Some(told) = rig.states(*id).last() {
                assert_eq!(*told, s, "{ctx}: job {id} told as {told:?}");
            }
        }
    }
}

#[test]
fn every_phase_under_every_event() {
    let mut cases = 0;
    let mut phases = std::collections::BTreeSet::new();
    let mut states = std::collections::BTreeSet::new();
    for (name, setup) in setups() {
        let count = every_event(1).len();
        for k in 0..count {
            let mut rig = setup();
            if let Some(p) = rig.lc.phase() {
                phases.insert(format!("{p:?}"));
            }
            if let Some(s) = rig.lc.job_state(1) {
                states.insert(s.as_str());
            }
            let run = rig.planner.map_or(1, |p| p.2);
            let mut event = every_event(run).remove(k);
            if let Event::Command { request, .. } = &mut event {
                *request = RequestId(rig.next_request);
                rig.next_request += 1;
            }
            let label = format!("{event:?}");
            rig.store.insert(2, queued(2));
            rig.feed(event);
            check_invariants(name, &label, &mut rig);
            cases += 1;
        }
    }
    // Every phase, and every state of job 1, was a starting point.
    assert_eq!(phases.len(), Phase::ALL.len(), "{phases:?}");
    assert_eq!(states.len(), JobState::ALL.len(), "{states:?}");
    assert!(cases > 1000, "{cases} cases");
}

#[test]
fn time_left_from_moves_once_known_else_from_layers() {
    // 1,000 of 4,000 moves in 10 s since a fresh start: 30 s left.
    assert_eq!(
        time_left_s(Some((4000, 1000, 1000)), Some((8, 2)), 0, 10.0),
        Some(30.0)
    );
    // Resumed at move 600: the rate counts only moves since the restart.
    assert_eq!(
        time_left_s(Some((4000, 1000, 400)), None, 0, 10.0),
        Some(75.0)
    );
    // Total not planned yet: layer 3 of 10 (0-based 2) after 20 s: 2 layers a 10 s,
    // 8 layers (the current one whole) left.
    assert_eq!(time_left_s(None, Some((10, 2)), 0, 20.0), Some(80.0));
    // Resumed at layer 5: only layers finished since then count.
    assert_eq!(time_left_s(None, Some((10, 7)), 5, 20.0), Some(30.0));
    // No rate yet: still in the first layer, nothing executed, or nothing known.
    assert_eq!(time_left_s(None, Some((10, 0)), 0, 20.0), None);
    assert_eq!(time_left_s(Some((4000, 0, 0)), None, 0, 5.0), None);
    assert_eq!(time_left_s(None, None, 0, 5.0), None);
    // Past the last layer (a count from an older plan): nothing left, not negative.
    assert_eq!(time_left_s(None, Some((10, 12)), 0, 20.0), Some(0.0));
}

#[test]
fn time_left_is_the_planned_time_left_at_the_measured_pace() {
    // Nothing printed yet: the plan's own pace (100 s planned left: 100 s).
    assert_eq!(time_left_planned_s(100_000_000, 0, 0), 100.0);
    // 60 s planned done in 120 s of printing (a machine at half the planned speed),
    // 30 s of the plan's pace blended in: pace (120 + 30) / (60 + 30) = 5/3.
    let eta = time_left_planned_s(60_000_000, 60_000_000, 120_000_000);
    assert!((eta - 100.0).abs() < 1e-9, "{eta}");
    // Long into the job the measured pace is nearly all of it.
    let eta = time_left_planned_s(10_000_000, 3_600_000_000, 7_200_000_000);
    assert!((eta - 20.0).abs() < 0.2, "{eta}");
    // A clock that ran while nothing moved (it does not, but bounded if it did).
    assert_eq!(time_left_planned_s(1_000_000, 0, u64::MAX / 2), 100.0);
}

/// The lifecycle knows no wire protocol: no code of it names the link (a G-code link
/// plugs in below it the way the edo link does, through an adapter in the daemon).
#[test]
fn the_lifecycle_names_no_link() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/lifecycle");
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        if path.ends_with("tests.rs") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        for (n, line) in text.lines().enumerate() {
            let code = line.trim_start();
            if code.starts_with("//") {
                continue;
            }
            assert!(
                !code.contains("link::") && !code.contains("gcode_link"),
                "{}:{}: {line}",
                path.display(),
                n + 1
            );
        }
    }
}

/// The writer's report of a write that failed on a full disk.
fn disk_full() -> Event {
    Event::StoreFailed {
        error: "disk full".into(),
        busy: false,
    }
}

#[test]
fn a_full_disk_lets_planned_moves_go_on_but_starts_nothing_until_it_catches_up() {
    let mut rig = Rig::printing();
    rig.submit(2);
    rig.plan(40);
    rig.run(10);
    rig.auto_store = false;
    rig.logs.clear();
    rig.feed(disk_full());
    // The job's moves go on to its end; its end is not on disk, and job 2 waits.
    rig.run(100);
    assert_once_in_order(&rig.executed(1), 40);
    assert_eq!(rig.lc.active_job(), None);
    assert_eq!(rig.lc.job_state(1), Some(JobState::Done));
    assert_eq!(rig.stored_state(1), Some(JobState::Printing));
    assert_eq!(rig.planner, None, "job 2 does not start");
    assert_eq!(rig.lc.job_state(2), Some(JobState::Queued));
    // A failure every 150 ms for 15 s: a warning at once and one after 10 s.
    for _ in 0..100 {
        rig.now += 150 * MS;
        rig.feed(disk_full());
    }
    let warnings: Vec<&String> = rig
        .logs
        .iter()
        .filter(|l| l.starts_with("job store cannot write: disk full"))
        .collect();
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[1].contains("(66 failed tries since the last warning)"),
        "{warnings:?}"
    );
    // Room again: the states go to disk and out in order, and job 2 starts.
    rig.write_all();
    assert!(rig
        .logs
        .iter()
        .any(|l| l.contains("written again, after 101 failed tries")));
    assert_eq!(rig.stored_state(1), Some(JobState::Done));
    assert_eq!(
        rig.states(1),
        [JobState::Planning, JobState::Printing, JobState::Done]
    );
    assert_eq!(rig.planner.map(|p| p.0), Some(2), "job 2 starts");
}

#[test]
fn on_a_full_disk_operators_are_told_what_is_not_on_disk_and_nothing_is_reversed() {
    let mut rig = Rig::printing();
    rig.submit(2);
    rig.plan(40);
    rig.run(10);
    rig.auto_store = false;
    rig.feed(disk_full());
    // The pause holds the machine at once; it is not on disk, and the reply says so.
    let p = rig.command(Command::Pause(1));
    assert_eq!(rig.commands.last(), Some(&MachineCommand::FeedHold));
    rig.at(76 * MS);
    assert_eq!(rig.refused(p), RefusalKind::StoreCannotWrite);
    let Some(Err(refusal)) = rig.reply(p) else {
        unreachable!()
    };
    assert!(
        refusal.message.starts_with(
            "job store cannot write: disk full; job 1 is paused here but that is not on disk"
        ),
        "{}",
        refusal.message
    );
    // A resume would start it moving: refused, nothing done.
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.refused(r), RefusalKind::StoreCannotWrite);
    assert_eq!(rig.machine.state, MachineState::Held);
    assert_eq!(rig.lc.job_state(1), Some(JobState::Paused));
    // A cancel takes effect here, and is told as not on disk.
    let c = rig.command(Command::Cancel(2));
    rig.at(76 * MS);
    assert_eq!(rig.refused(c), RefusalKind::StoreCannotWrite);
    assert!(rig.notes.iter().all(|n| n.state != JobState::Paused));
    // Room again: the operator's decisions are on disk, then told.
    rig.write_all();
    assert_eq!(rig.stored_state(1), Some(JobState::Paused));
    assert_eq!(rig.stored_state(2), Some(JobState::Cancelled));
    assert_eq!(rig.states(2), [JobState::Cancelled]);
    rig.auto_store = true;
    let r = rig.command(Command::Resume(1));
    assert_eq!(
        rig.applied(r),
        Applied {
            state: JobState::Printing,
            stored: true
        }
    );
    rig.run(100);
    assert_once_in_order(&rig.executed(1), 40);
    assert_eq!(rig.stored_state(1), Some(JobState::Done));
    assert!(rig.executed(2).is_empty(), "the cancelled job never runs");
}

#[test]
fn a_job_whose_start_cannot_be_stored_is_paused_before_its_first_move() {
    let mut rig = Rig::new();
    rig.submit(1);
    rig.auto_store = false;
    rig.connect();
    assert_eq!(rig.lc.job_state(1), Some(JobState::Planning));
    rig.feed(disk_full());
    assert_eq!(rig.lc.job_state(1), Some(JobState::Paused));
    assert_eq!(rig.commands.last(), Some(&MachineCommand::FeedHold));
    rig.plan(40);
    rig.run(100);
    assert!(
        rig.executed(1).is_empty(),
        "no move while its start is not on disk"
    );
    rig.write_all();
    let last = rig.notes.last().unwrap();
    assert_eq!(
        (last.state, last.reason.as_deref()),
        (JobState::Paused, Some("job store cannot write: disk full"))
    );
    assert_eq!(rig.stored_state(1), Some(JobState::Paused));
    rig.auto_store = true;
    let r = rig.command(Command::Resume(1));
    assert_eq!(rig.applied(r).state, JobState::Printing);
    rig.run(100);
    assert_once_in_order(&rig.executed(1), 40);
    assert_eq!(rig.stored_state(1), Some(JobState::Done));
}

#[test]
fn on_a_full_disk_a_cancel_of_the_active_job_stops_it_and_says_it_is_not_on_disk() {
    let mut rig = Rig::printing();
    rig.plan(40);
    rig.run(10);
    rig.auto_store = false;
    rig.feed(disk_full());
    let c = rig.command(Command::Cancel(1));
    assert_eq!(rig.refused(c), RefusalKind::StoreCannotWrite);
    let Some(Err(refusal)) = rig.reply(c) else {
        unreachable!()
    };
    assert!(
        refusal
            .message
            .contains("job 1 is being cancelled on the machine but that is not on disk"),
        "{}",
        refusal.message
    );
    assert!(rig.commands.contains(&MachineCommand::Flush));
    rig.run(10);
    rig.write_all();
    rig.auto_store = true;
    rig.run(10);
    assert_eq!(rig.stored_state(1), Some(JobState::Cancelled));
}
