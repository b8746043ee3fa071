//! The edod API as types: every JSON-RPC 2.0 request (method and params), result,
//! notification and error of `docs/api.md`, and the envelopes that carry them.
//!
//! One definition for both ends: edod (`daemon::api`) reads a [`Call`] and answers with a
//! [`MethodResult`]; edoctl (`cli::client`) sends a [`Method`]'s params and reads its
//! typed result; a web page can share the same types. It depends on serde and serde_json
//! only (and the machine link's state names and the lifecycle's job state, checkpoint
//! and progress), so it stays in the pure core.
//!
//! - [`envelope`]: the JSON-RPC 2.0 framing: [`Request`], [`Response`], [`Notification`],
//!   [`Id`], [`ApiError`] and its codes.
//! - [`methods`]: each method's name, params and result ([`Method`]), and [`Call`], the
//!   request a daemon dispatches.
//! - [`job`], [`machine`]: what the results and notifications talk about (a job, its
//!   progress, the machine snapshot).

pub mod envelope;
pub mod job;
pub mod machine;
pub mod mesh_bytes;
pub mod methods;

pub use envelope::{
    ApiError, Id, JsonRpcVersion, Notification, Outcome, Refusal, Request, Response,
};
pub use job::{Checkpoint, Job, JobState, JobStateChanged, Progress};
pub use machine::{EStopTiming, MachineSnapshot, MachineStatus};
pub use methods::{
    method, Call, Deleted, Event, JobIdParams, JobSource, LogLine, LogParams, Method, MethodResult,
    NoParams, Refilled, ServerInfo, StartNextParams, StateChange, Submission, SubmitParams,
    Submitted, Subscribed, API_VERSION, CONTROL_METHODS, METHODS,
};
