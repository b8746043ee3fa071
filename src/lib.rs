//! # edo — equal distance offset planning and printer host for graded-material extrusion
//!
//! edo turns a part and a material-gradient design into equal distance offset (EDO)
//! toolpaths (Xu & Shaw, "SFF-oriented modeling and process planning of functionally
//! graded materials using a novel equal distance offset approach") and drives a
//! multi-syringe slurry extruder over a serial link to build it.
//!
//! The crate is a pure synchronous core, one module per stage, data flowing one way
//! (see `docs/architecture.md`):
//!
//! - [`geom`]: loops and regions (outer boundary Ce, holes Ci), their validation.
//! - [`mesh`]: load a part (STL, 3MF) from bytes within size limits, validate and repair it.
//! - [`slice`]: layer heights (uniform, or adaptive from slope and a Z limit) and the
//!   sections of each layer as islands.
//! - [`material`]: compositions, gradient functions f(d), equations (1)–(7).
//! - [`plan`]: the EDO method on a layer: pre-subdivision into contours C1..Cm+1 and the
//!   equal distance offset fill of every sub-region, as a compact [`plan::LayerPlan`].
//! - [`job`]: the job file (`docs/job-format.md`).
//! - [`report`], [`svg`]: the plan report (`docs/plan-report.md`) and layer previews.
//! - [`toolpath`]: process planning (§4, Fig. 4(a)): filling order, seams, flow raise in
//!   narrow sub-areas, coverage measure.
//! - [`pipeline`]: planned layers to machine moves (the stable API the daemon streams).
//! - [`machine`]: the move stream in fixed point (µm, nl, ratios of 65535), the one move
//!   type host, link and simulator share.
//! - [`link`]: sans-IO host/machine protocol over a serial line (`docs/protocol.md`).
//! - [`lifecycle`]: the job lifecycle as a sans-IO state machine (queued → planning →
//!   printing ⇄ paused, interrupted, done, failed, cancelled; resume, refill, e-stop,
//!   reset and port-loss recovery, checkpoints): machine, operator, planner and store
//!   events and the caller's clock in, machine commands, moves, records to persist,
//!   replies and notifications out, of no wire protocol.
//! - [`proto`]: the typed JSON-RPC API (`docs/api.md`) edod, edoctl and clients share.
//!
//! Around the core, behind the cargo feature `daemon` (on by default): `cli` does
//! the command-line tools' I/O, and `daemon` is edod's tokio shell (socket
//! API, the job store on threads of its own, planner workers, the streamer that pumps
//! the lifecycle and the link, supervision); only they and the binaries touch files,
//! sockets and clocks. `cargo build --no-default-features` builds the core
//! alone, so the compiler holds the layering: no core module can reach into the shell,
//! and none of the shell's crates (tokio, SQLite, serial ports, clap) is linked into it.

pub mod adapter;
#[cfg(feature = "daemon")]
pub mod cli;
#[cfg(feature = "daemon")]
pub mod daemon;
pub mod gcode_link;
pub mod geom;
pub mod job;
pub mod lifecycle;
pub mod link;
pub mod machine;
pub mod material;
pub mod mesh;
pub mod mixer;
pub mod pipeline;
pub mod plan;
pub mod proto;
pub mod report;
pub mod setup;
pub mod slice;
pub mod svg;
pub mod toolpath;
