//! The lifecycle's settings: cadences, waits and the machine geometry its service
//! moves need, all in the units their names say.

/// Where the service moves go and how fast.
#[derive(Debug, Clone, PartialEq)]
pub struct ServiceMoves {
    /// Volume pushed when priming after a restart, split by the resumed composition (nl).
    pub prime_nl: u32,
    /// How far the nozzle is lifted on the way back to where a resumed job stopped (µm).
    pub resume_lift_um: i32,
    /// Feed of service travels (µm/s).
    pub feed_um_s: u32,
    /// Top of the build volume (µm): a lift never goes above it.
    pub build_top_um: i32,
    /// Where a cancelled job's nozzle parks (µm).
    pub park_um: [i32; 3],
    /// Names of the syringes, for messages ("syringe 1 (B)").
    pub syringe_names: Vec<String>,
}

impl Default for ServiceMoves {
    fn default() -> Self {
        Self {
            prime_nl: 2_000,
            resume_lift_um: 2_000,
            feed_um_s: 50_000,
            build_top_um: 150_000,
            park_um: [0, 0, 50_000],
            syringe_names: vec!["A".into(), "B".into()],
        }
    }
}

/// Cadences and waits (µs) and limits of the lifecycle.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// Most moves waiting here for the link: planner output is taken only below it, so
    /// the planner's bounded channel holds the job's future.
    pub moves_waiting_max: usize,
    /// Checkpoints are written at most this often while printing (and at every state
    /// change).
    pub checkpoint_every_us: u64,
    /// Progress at most this often.
    pub progress_every_us: u64,
    /// How long a pause, resume or cancel waits for its state to be stored before it is
    /// answered with `stored: false`.
    pub reply_wait_us: u64,
    /// How long a shutdown waits for the machine to hold.
    pub shutdown_hold_us: u64,
    /// How long a shutdown then waits for the job's state to be stored.
    pub shutdown_store_wait_us: u64,
    /// Service move indices reserved in the store at a time.
    pub service_index_block: u32,
    /// Wall clock (ms since the Unix epoch) at time 0 of the clock the lifecycle is
    /// given, for the time from submission to the first move.
    pub wall_ms_at_zero: i64,
    /// Service moves.
    pub service: ServiceMoves,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            moves_waiting_max: 512,
            checkpoint_every_us: 100_000,
            progress_every_us: 100_000,
            reply_wait_us: 75_000,
            shutdown_hold_us: 2_000_000,
            shutdown_store_wait_us: 2_500_000,
            service_index_block: 1024,
            wall_ms_at_zero: 0,
            service: ServiceMoves::default(),
        }
    }
}
