//! The methods of `docs/api.md`: each one's name, params and result as a [`Method`], the
//! [`Call`] a daemon dispatches on, the [`MethodResult`] it answers with, and the
//! [`Event`]s it notifies subscribers of.
//!
//! Params are objects (named params) and every method refuses unknown keys; a wrong
//! shape is -32602 naming the problem. Results are read leniently by clients (a key a
//! newer daemon adds is ignored).

use serde::de::{DeserializeOwned, Error as _};
use serde::{Deserialize, Deserializer, Serialize};
use serde_json::Value;

use super::envelope::ApiError;
use super::job::{Job, JobState, JobStateChanged, Progress};
use super::machine::{EStopTiming, MachineSnapshot, MachineStatus};

/// A method: its name on the wire, its params and its result.
pub trait Method {
    /// The `method` of its requests.
    const NAME: &'static str;
    /// Its params (an object).
    type Params: Serialize + DeserializeOwned;
    /// Its result.
    type Result: Serialize + DeserializeOwned;
}

/// The params of a method that takes none: absent, null or `{}`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoParams {}

/// `{id}`: the job a method acts on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobIdParams {
    /// Job id.
    #[serde(deserialize_with = "named_id")]
    pub id: u32,
}

/// `job.start_next`'s params: `{id?}`, the queued job to start (the oldest when absent).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartNextParams {
    /// Job id; the oldest queued job when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u32>,
}

/// `log.recent`'s params: `{after?}`, the lines after sequence number `after` (all kept
/// when absent).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogParams {
    /// The last sequence number the caller has.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub after: Option<u64>,
}

/// A line of edod's log (`log.recent`): what edod logged at `info` or above.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LogLine {
    /// Sequence number, from 1 at edod's start, without gaps.
    pub seq: u64,
    /// When (ms since the Unix epoch).
    pub at_ms: i64,
    /// `"info"`, `"warn"` or `"error"`.
    pub level: String,
    /// The job it is about, if any.
    pub job_id: Option<u32>,
    /// The message, then its fields as `name=value`.
    pub message: String,
}

/// `job.submit`'s params: `{job, mesh_base64?, name?}` or `{dry_run_moves, name?}`
/// (checked by [`SubmitParams::submission`]).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmitParams {
    /// Job file text (TOML, `docs/job-format.md`).
    #[serde(
        default,
        deserialize_with = "named_job",
        skip_serializing_if = "Option::is_none"
    )]
    pub job: Option<String>,
    /// The mesh file's bytes, standard base64 (a mesh job only).
    #[serde(
        default,
        deserialize_with = "named_mesh_base64",
        skip_serializing_if = "Option::is_none"
    )]
    pub mesh_base64: Option<String>,
    /// Instead of a job file: a dry run of this many moves that extrude nothing.
    #[serde(
        default,
        deserialize_with = "named_dry_run_moves",
        skip_serializing_if = "Option::is_none"
    )]
    pub dry_run_moves: Option<u32>,
    /// Name shown in listings (default: the job file's, or "dry run of N moves").
    #[serde(
        default,
        deserialize_with = "named_name",
        skip_serializing_if = "Option::is_none"
    )]
    pub name: Option<String>,
}

/// Deserializers that put the field's name before serde's message ("id: invalid type:
/// string \"seven\", expected u32"): serde_json's own does not say which field it was.
macro_rules! named_field {
    ($($f:ident: $t:ty = $name:literal;)*) => {$(
        fn $f<'de, D: Deserializer<'de>>(d: D) -> Result<$t, D::Error> {
            <$t>::deserialize(d).map_err(|e| D::Error::custom(format_args!("{}: {e}", $name)))
        }
    )*};
}

named_field! {
    named_id: u32 = "id";
    named_job: Option<String> = "job";
    named_mesh_base64: Option<String> = "mesh_base64";
    named_dry_run_moves: Option<u32> = "dry_run_moves";
    named_name: Option<String> = "name";
}

/// What a submission builds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum JobSource {
    /// A job file, and the mesh it names (base64) for a mesh job.
    File {
        /// Job file text.
        job: String,
        /// Mesh bytes, base64.
        mesh_base64: Option<String>,
    },
    /// A dry run of this many moves (at least 1).
    DryRun {
        /// Moves.
        moves: u32,
    },
}

/// A submission whose params have one of the two shapes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Submission {
    /// What to build.
    pub source: JobSource,
    /// The name given, if any.
    pub name: Option<String>,
}

impl SubmitParams {
    /// A job file and its mesh (base64).
    pub fn file(job: String, mesh_base64: Option<String>) -> SubmitParams {
        SubmitParams {
            job: Some(job),
            mesh_base64,
            ..SubmitParams::default()
        }
    }

    /// A dry run of `moves` moves.
    pub fn dry_run(moves: u32) -> SubmitParams {
        SubmitParams {
            dry_run_moves: Some(moves),
            ..SubmitParams::default()
        }
    }

    /// The params as one of the two shapes `docs/api.md` gives, or -32602 naming what
    /// is wrong.
    pub fn submission(self) -> Result<Submission, ApiError> {
        let bad = |m: &str| ApiError::new(ApiError::INVALID_PARAMS, m);
        let source = match (self.job, self.dry_run_moves) {
            (Some(job), None) => JobSource::File {
                job,
                mesh_base64: self.mesh_base64,
            },
            (None, Some(_)) if self.mesh_base64.is_some() => {
                return Err(bad("mesh_base64: a dry run carries no mesh"))
            }
            (None, Some(0)) => return Err(bad("dry_run_moves must be at least 1")),
            (None, Some(moves)) => JobSource::DryRun { moves },
            _ => {
                return Err(bad(
                    "give either \"job\" (the job file text) or \"dry_run_moves\"",
                ))
            }
        };
        Ok(Submission {
            source,
            name: self.name,
        })
    }
}

/// `server.info`'s result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ServerInfo {
    /// `"edod"`.
    pub name: String,
    /// edod's version.
    pub version: String,
    /// This API's version (1).
    pub api_version: u32,
    /// The machine link's protocol version (`docs/protocol.md`).
    pub protocol_version: u16,
    /// The serial port.
    pub port: String,
    /// The `[machine]` table of edod's configuration.
    pub machine: serde_json::Map<String, Value>,
}

/// The version of the API these types describe.
pub const API_VERSION: u32 = 1;

/// `job.submit`'s result: the job is on disk.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Submitted {
    /// The new job's id.
    pub id: u32,
    /// `queued`.
    pub state: JobState,
    /// What the job will build that the operator should know first (layers with area
    /// resting on nothing beyond the allowed overhang); absent when none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// The result of `job.pause`, `job.resume` and `job.cancel`: the job's state after it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StateChange {
    /// Job id.
    pub id: u32,
    /// Its state now (`paused`, `printing`; `cancelled`, or `printing` while a printing
    /// job stops).
    pub state: JobState,
    /// Whether that state is on disk; `false` when the job store could not write it
    /// within 75 ms (another process holds its lock): the state is in effect and is
    /// written, and `notify_job_state` tells it, once the store takes it.
    pub stored: bool,
}

/// `job.delete`'s result.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Deleted {
    /// Job id.
    pub id: u32,
    /// `true`.
    pub deleted: bool,
}

/// `machine.refill`'s result.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Refilled {
    /// `true`.
    pub refilled: bool,
}

/// `subscribe`'s result: the notifications this connection will receive.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Subscribed {
    /// Notification methods.
    pub subscribed: Vec<String>,
}

impl Subscribed {
    /// Every notification.
    pub fn all() -> Subscribed {
        Subscribed {
            subscribed: Event::METHODS.iter().map(|m| m.to_string()).collect(),
        }
    }
}

/// Markers of the methods, one per method, each naming its params and result.
pub mod method {
    use super::{JobIdParams, LogParams, Method, NoParams, StartNextParams, SubmitParams};

    macro_rules! methods {
        ($($(#[$doc:meta])* $marker:ident = $name:literal, $params:ty => $result:ty;)*) => {
            $(
                $(#[$doc])*
                #[derive(Debug, Clone, Copy)]
                pub struct $marker;
                impl Method for $marker {
                    const NAME: &'static str = $name;
                    type Params = $params;
                    type Result = $result;
                }
            )*
            /// Every method's name, in the order of `docs/api.md`.
            pub const NAMES: &[&str] = &[$($name),*];
        };
    }

    methods! {
        /// Who answers: edod's version, the API's and the link's, the port and machine.
        ServerInfo = "server.info", NoParams => super::ServerInfo;
        /// Queue a job file (and its mesh) or a dry run.
        JobSubmit = "job.submit", SubmitParams => super::Submitted;
        /// Every job, oldest first.
        JobList = "job.list", NoParams => Vec<super::Job>;
        /// One job.
        JobGet = "job.get", JobIdParams => super::Job;
        /// Hold a printing job at the next move boundary.
        JobPause = "job.pause", JobIdParams => super::StateChange;
        /// Continue a paused or interrupted job.
        JobResume = "job.resume", JobIdParams => super::StateChange;
        /// Cancel a job (a printing one stops, retracts and parks).
        JobCancel = "job.cancel", JobIdParams => super::StateChange;
        /// Start a queued job although an interrupted one holds the queue.
        JobStartNext = "job.start_next", StartNextParams => super::StateChange;
        /// Delete a finished job and its mesh.
        JobDelete = "job.delete", JobIdParams => super::Deleted;
        /// Queue a finished job again from its stored file and mesh.
        JobReprint = "job.reprint", JobIdParams => super::Submitted;
        /// The machine snapshot and the active job's progress.
        MachineStatus = "machine.status", NoParams => super::MachineStatus;
        /// Emergency stop ahead of everything queued.
        MachineEstop = "machine.estop", NoParams => super::EStopTiming;
        /// The syringes were refilled: clear the fault and continue.
        MachineRefill = "machine.refill", NoParams => super::Refilled;
        /// Receive notifications from now on.
        Subscribe = "subscribe", NoParams => super::Subscribed;
        /// edod's log lines kept (the dashboard's console).
        LogRecent = "log.recent", LogParams => Vec<super::LogLine>;
    }
}

/// Every method's name, in the order of `docs/api.md`.
pub const METHODS: &[&str] = method::NAMES;

/// The methods a control connection may ask ([`Call::is_control`]).
pub const CONTROL_METHODS: &[&str] = &[method::MachineEstop::NAME, method::MachineStatus::NAME];

/// A request a daemon dispatches: the method and its params, read and checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Call {
    /// `server.info`.
    ServerInfo,
    /// `job.submit`.
    JobSubmit(SubmitParams),
    /// `job.list`.
    JobList,
    /// `job.get`.
    JobGet(JobIdParams),
    /// `job.pause`.
    JobPause(JobIdParams),
    /// `job.resume`.
    JobResume(JobIdParams),
    /// `job.cancel`.
    JobCancel(JobIdParams),
    /// `job.start_next`.
    JobStartNext(StartNextParams),
    /// `job.delete`.
    JobDelete(JobIdParams),
    /// `job.reprint`.
    JobReprint(JobIdParams),
    /// `machine.status`.
    MachineStatus,
    /// `machine.estop`.
    MachineEstop,
    /// `machine.refill`.
    MachineRefill,
    /// `subscribe`.
    Subscribe,
    /// `log.recent`.
    LogRecent(LogParams),
}

/// Read `M`'s params: absent and null are `{}`; anything but an object is refused.
fn params<M: Method>(p: Option<Value>) -> Result<M::Params, ApiError> {
    let bad = |m: String| ApiError::new(ApiError::INVALID_PARAMS, m);
    let p = match p {
        None | Some(Value::Null) => Value::Object(serde_json::Map::new()),
        Some(p @ Value::Object(_)) => p,
        Some(other) => {
            return Err(bad(format!(
                "params of {} must be an object (named params, docs/api.md), not {}",
                M::NAME,
                json_kind(&other)
            )))
        }
    };
    serde_json::from_value(p).map_err(|e| bad(e.to_string()))
}

/// What kind of JSON value `v` is, for messages.
fn json_kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

impl Call {
    /// Read a request's method and params: -32601 for an unknown method, -32602 for
    /// params of the wrong shape.
    pub fn new(name: &str, p: Option<Value>) -> Result<Call, ApiError> {
        use method as m;
        Ok(match name {
            m::ServerInfo::NAME => params::<m::ServerInfo>(p).map(|_| Call::ServerInfo)?,
            m::JobSubmit::NAME => Call::JobSubmit(params::<m::JobSubmit>(p)?),
            m::JobList::NAME => params::<m::JobList>(p).map(|_| Call::JobList)?,
            m::JobGet::NAME => Call::JobGet(params::<m::JobGet>(p)?),
            m::JobPause::NAME => Call::JobPause(params::<m::JobPause>(p)?),
            m::JobResume::NAME => Call::JobResume(params::<m::JobResume>(p)?),
            m::JobCancel::NAME => Call::JobCancel(params::<m::JobCancel>(p)?),
            m::JobStartNext::NAME => Call::JobStartNext(params::<m::JobStartNext>(p)?),
            m::JobDelete::NAME => Call::JobDelete(params::<m::JobDelete>(p)?),
            m::JobReprint::NAME => Call::JobReprint(params::<m::JobReprint>(p)?),
            m::MachineStatus::NAME => params::<m::MachineStatus>(p).map(|_| Call::MachineStatus)?,
            m::MachineEstop::NAME => params::<m::MachineEstop>(p).map(|_| Call::MachineEstop)?,
            m::MachineRefill::NAME => params::<m::MachineRefill>(p).map(|_| Call::MachineRefill)?,
            m::Subscribe::NAME => params::<m::Subscribe>(p).map(|_| Call::Subscribe)?,
            m::LogRecent::NAME => Call::LogRecent(params::<m::LogRecent>(p)?),
            other => {
                return Err(ApiError::new(
                    ApiError::METHOD_NOT_FOUND,
                    format!("no method {other:?}; see docs/api.md"),
                ))
            }
        })
    }

    /// Whether a control connection may ask it (the place kept for the e-stop when
    /// edod serves its most clients): [`CONTROL_METHODS`].
    pub fn is_control(&self) -> bool {
        matches!(self, Call::MachineEstop | Call::MachineStatus)
    }

    /// The method's name.
    pub fn method(&self) -> &'static str {
        use method as m;
        match self {
            Call::ServerInfo => m::ServerInfo::NAME,
            Call::JobSubmit(_) => m::JobSubmit::NAME,
            Call::JobList => m::JobList::NAME,
            Call::JobGet(_) => m::JobGet::NAME,
            Call::JobPause(_) => m::JobPause::NAME,
            Call::JobResume(_) => m::JobResume::NAME,
            Call::JobCancel(_) => m::JobCancel::NAME,
            Call::JobStartNext(_) => m::JobStartNext::NAME,
            Call::JobDelete(_) => m::JobDelete::NAME,
            Call::JobReprint(_) => m::JobReprint::NAME,
            Call::MachineStatus => m::MachineStatus::NAME,
            Call::MachineEstop => m::MachineEstop::NAME,
            Call::MachineRefill => m::MachineRefill::NAME,
            Call::Subscribe => m::Subscribe::NAME,
            Call::LogRecent(_) => m::LogRecent::NAME,
        }
    }

    /// The params a request for this call carries (none for a method without params).
    pub fn params(&self) -> Option<Value> {
        let job = |p: &JobIdParams| serde_json::to_value(p).ok();
        match self {
            Call::JobSubmit(p) => serde_json::to_value(p).ok(),
            Call::JobGet(p)
            | Call::JobPause(p)
            | Call::JobResume(p)
            | Call::JobCancel(p)
            | Call::JobDelete(p)
            | Call::JobReprint(p) => job(p),
            Call::JobStartNext(p) => serde_json::to_value(p).ok(),
            Call::LogRecent(p) => serde_json::to_value(p).ok(),
            Call::ServerInfo
            | Call::JobList
            | Call::MachineStatus
            | Call::MachineEstop
            | Call::MachineRefill
            | Call::Subscribe => None,
        }
    }
}

/// Any method's result, as a daemon answers (serialized as the result itself).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub enum MethodResult {
    /// `server.info`.
    ServerInfo(ServerInfo),
    /// `job.submit`.
    Submitted(Submitted),
    /// `job.list`.
    Jobs(Vec<Job>),
    /// `job.get`.
    Job(Job),
    /// `job.pause`, `job.resume`, `job.cancel`.
    StateChange(StateChange),
    /// `job.delete`.
    Deleted(Deleted),
    /// `machine.status`.
    MachineStatus(MachineStatus),
    /// `machine.estop`.
    EStop(EStopTiming),
    /// `machine.refill`.
    Refilled(Refilled),
    /// `subscribe`.
    Subscribed(Subscribed),
    /// `log.recent`.
    Log(Vec<LogLine>),
}

macro_rules! method_result_from {
    ($($t:ty => $v:ident),*) => {$(
        impl From<$t> for MethodResult {
            fn from(r: $t) -> MethodResult {
                MethodResult::$v(r)
            }
        }
    )*};
}

method_result_from!(
    ServerInfo => ServerInfo, Submitted => Submitted, Vec<Job> => Jobs, Job => Job,
    StateChange => StateChange, Deleted => Deleted, MachineStatus => MachineStatus,
    EStopTiming => EStop, Refilled => Refilled, Subscribed => Subscribed,
    Vec<LogLine> => Log
);

/// What a daemon notifies subscribers of: the `method` and `params` of a
/// [`super::Notification`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", content = "params")]
pub enum Event {
    /// A job changed state.
    #[serde(rename = "notify_job_state")]
    JobState(JobStateChanged),
    /// The active job's progress (at most 10 a second while it changes).
    #[serde(rename = "notify_job_progress")]
    JobProgress(Progress),
    /// The machine's connection, state, faults or active job changed.
    #[serde(rename = "notify_machine_state")]
    MachineState(MachineSnapshot),
}

impl Event {
    /// The notification methods, in the order `subscribe` lists them.
    pub const METHODS: [&'static str; 3] = [
        "notify_job_progress",
        "notify_job_state",
        "notify_machine_state",
    ];

    /// The notification's method.
    pub fn method(&self) -> &'static str {
        match self {
            Event::JobProgress(_) => Event::METHODS[0],
            Event::JobState(_) => Event::METHODS[1],
            Event::MachineState(_) => Event::METHODS[2],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn refused(method: &str, p: Value) -> ApiError {
        match Call::new(method, Some(p)) {
            Ok(c) => panic!("{method} read as {c:?}"),
            Err(e) => e,
        }
    }

    #[test]
    fn params_of_the_wrong_shape_are_refused_naming_the_problem() {
        let e = refused("job.get", json!([5]));
        assert_eq!(e.code, ApiError::INVALID_PARAMS);
        assert_eq!(
            e.message,
            "params of job.get must be an object (named params, docs/api.md), not an array"
        );
        let e = refused("server.info", json!([]));
        assert_eq!(e.code, ApiError::INVALID_PARAMS);
        assert_eq!(
            refused("job.get", json!({"id": "seven"})).message,
            "id: invalid type: string \"seven\", expected u32"
        );
        assert_eq!(
            refused("job.delete", json!({"id": 1, "extra": 2})).message,
            "unknown field `extra`, expected `id`"
        );
        assert_eq!(
            refused("job.pause", json!({})).message,
            "missing field `id`"
        );
        assert_eq!(
            refused("job.submit", json!({"dry_run_moves": -1})).message,
            "dry_run_moves: invalid value: integer `-1`, expected u32"
        );
        assert_eq!(
            refused("machine.refill", json!({"now": true})).code,
            ApiError::INVALID_PARAMS
        );
        assert_eq!(
            refused("job.frobnicate", json!({})).code,
            ApiError::METHOD_NOT_FOUND
        );
    }

    #[test]
    fn every_call_reads_back_from_its_request() {
        for p in [None, Some(Value::Null), Some(json!({}))] {
            assert_eq!(Call::new("machine.status", p), Ok(Call::MachineStatus));
        }
        let job = JobIdParams { id: 7 };
        let calls = [
            Call::ServerInfo,
            Call::JobSubmit(SubmitParams::dry_run(3)),
            Call::JobList,
            Call::JobGet(job),
            Call::JobPause(job),
            Call::JobResume(job),
            Call::JobCancel(job),
            Call::JobStartNext(StartNextParams { id: Some(7) }),
            Call::JobDelete(job),
            Call::JobReprint(job),
            Call::MachineStatus,
            Call::MachineEstop,
            Call::MachineRefill,
            Call::Subscribe,
            Call::LogRecent(LogParams { after: Some(3) }),
        ];
        assert_eq!(calls.clone().map(|c| c.method()), METHODS);
        // The control lane is a property of the call, and CONTROL_METHODS names it.
        let control: Vec<&str> = calls
            .iter()
            .filter(|c| c.is_control())
            .map(|c| c.method())
            .collect();
        assert_eq!(control, ["machine.status", "machine.estop"]);
        assert!(CONTROL_METHODS.iter().all(|m| control.contains(m)));
        assert_eq!(CONTROL_METHODS.len(), control.len());
        for c in calls {
            assert_eq!(Call::new(c.method(), c.params()), Ok(c));
        }
    }

    #[test]
    fn a_submission_is_a_job_file_or_a_dry_run() {
        let file = SubmitParams::file("name = \"x\"".into(), Some("AQI=".into()));
        assert!(matches!(
            file.submission().unwrap().source,
            JobSource::File { .. }
        ));
        let dry = SubmitParams {
            name: Some("qualify".into()),
            ..SubmitParams::dry_run(5)
        };
        assert_eq!(
            dry.submission().unwrap(),
            Submission {
                source: JobSource::DryRun { moves: 5 },
                name: Some("qualify".into())
            }
        );
        let refusal = |p: SubmitParams| p.submission().unwrap_err().message;
        assert_eq!(
            refusal(SubmitParams::dry_run(0)),
            "dry_run_moves must be at least 1"
        );
        assert!(refusal(SubmitParams::default()).starts_with("give either"));
        assert!(refusal(SubmitParams {
            job: Some(String::new()),
            ..SubmitParams::dry_run(3)
        })
        .starts_with("give either"));
        assert!(refusal(SubmitParams {
            mesh_base64: Some("AQI=".into()),
            ..SubmitParams::dry_run(3)
        })
        .starts_with("mesh_base64"));
    }

    #[test]
    fn events_name_their_methods() {
        let e = Event::JobState(JobStateChanged {
            job_id: 7,
            state: JobState::Planning,
            reason: None,
        });
        assert_eq!(
            serde_json::to_value(super::super::Notification::new(e.clone())).unwrap(),
            json!({"jsonrpc": "2.0", "method": "notify_job_state",
                   "params": {"job_id": 7, "state": "planning", "reason": null}})
        );
        assert_eq!(e.method(), "notify_job_state");
        assert_eq!(Subscribed::all().subscribed, Event::METHODS);
    }
}
