//! JSON-RPC 2.0 framing as edod speaks it (`docs/api.md`): one object a line, a request
//! with an `id` is answered by a [`Response`] with the same `id`, one without is a
//! notification; the daemon's own notifications are [`Notification`]s. Errors are
//! [`ApiError`] objects with the codes listed there.

use serde::de::Error as _;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::Value;

use super::methods::Event;

/// The `"jsonrpc": "2.0"` member every line carries; anything else does not deserialize.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct JsonRpcVersion;

impl JsonRpcVersion {
    /// The only version spoken.
    pub const TEXT: &'static str = "2.0";
}

impl Serialize for JsonRpcVersion {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(Self::TEXT)
    }
}

impl<'de> Deserialize<'de> for JsonRpcVersion {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let v = String::deserialize(d)?;
        if v == Self::TEXT {
            Ok(JsonRpcVersion)
        } else {
            Err(D::Error::custom(NOT_VERSION_2))
        }
    }
}

const NOT_VERSION_2: &str = "\"jsonrpc\" must be \"2.0\"";

/// A request id: a number, a string or null, echoed in the response.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Id {
    /// A number, echoed exactly as sent ([`Request::from_line`]: `18446744073709551616`,
    /// `-0` and `1e5` stay what they were, not a float).
    Number(NumberText),
    /// A string.
    String(String),
    /// `null`: also the id of an error about a request whose id could not be read.
    Null,
}

impl From<u64> for Id {
    fn from(n: u64) -> Id {
        Id::Number(NumberText(n.to_string()))
    }
}

/// A JSON number as its text, written back unchanged.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NumberText(String);

impl NumberText {
    /// `text` if it is one JSON number.
    pub fn parse(text: &str) -> Option<NumberText> {
        let text = text.trim();
        matches!(serde_json::from_str(text), Ok(Value::Number(_))).then(|| NumberText(text.into()))
    }

    /// The number as sent.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl Serialize for NumberText {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let raw = serde_json::value::RawValue::from_string(self.0.clone())
            .map_err(serde::ser::Error::custom)?;
        raw.serialize(s)
    }
}

impl<'de> Deserialize<'de> for NumberText {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        serde_json::Number::deserialize(d).map(|n| NumberText(n.to_string()))
    }
}

/// The raw `id` of a request line, for [`Request::from_line`].
#[derive(Deserialize)]
struct RawId<'a> {
    #[serde(borrow, default)]
    id: Option<&'a serde_json::value::RawValue>,
}

/// An error object: its code (the table in `docs/api.md`) and a message for a person
/// that names the job, its state and what to do.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ApiError {
    /// JSON-RPC error code.
    pub code: i64,
    /// What went wrong, for a person.
    pub message: String,
}

impl ApiError {
    /// Not JSON.
    pub const PARSE: i64 = -32700;
    /// Not a JSON-RPC 2.0 request object (or over the size limit).
    pub const INVALID_REQUEST: i64 = -32600;
    /// No such method.
    pub const METHOD_NOT_FOUND: i64 = -32601;
    /// Params missing, unknown or of the wrong type.
    pub const INVALID_PARAMS: i64 = -32602;
    /// The daemon failed (store error, streamer stopped).
    pub const INTERNAL: i64 = -32603;
    /// No such job.
    pub const NO_SUCH_JOB: i64 = -32001;
    /// The job is not in a state that allows this.
    pub const BAD_STATE: i64 = -32002;
    /// The job file does not validate.
    pub const INVALID_JOB: i64 = -32003;
    /// The machine is not connected.
    pub const NOT_CONNECTED: i64 = -32004;
    /// The job store is busy (another process holds its write lock): nothing was done,
    /// retry.
    pub const STORE_BUSY: i64 = -32005;

    /// A limit of edod's was reached (too many clients, the request memory budget, the
    /// idle timeout): the message names the `[api]` setting; try again later.
    pub const LIMIT: i64 = -32006;

    /// The job store cannot write (a full disk, an I/O error): the change is not on disk
    /// (the message says what took effect on the machine), or nothing was done.
    pub const STORE_CANNOT_WRITE: i64 = -32007;

    /// Every code `docs/api.md` lists.
    pub const CODES: [i64; 12] = [
        Self::PARSE,
        Self::INVALID_REQUEST,
        Self::METHOD_NOT_FOUND,
        Self::INVALID_PARAMS,
        Self::INTERNAL,
        Self::NO_SUCH_JOB,
        Self::BAD_STATE,
        Self::INVALID_JOB,
        Self::NOT_CONNECTED,
        Self::STORE_BUSY,
        Self::LIMIT,
        Self::STORE_CANNOT_WRITE,
    ];

    /// An error with a code and message.
    pub fn new(code: i64, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} (code {})", self.message, self.code)
    }
}

impl std::error::Error for ApiError {}

/// A request line: `method` and `params` as sent (the method's own types read them, see
/// [`super::Call::new`]); without `id` it is a notification and is not answered.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Request {
    /// `"2.0"`.
    pub jsonrpc: JsonRpcVersion,
    /// Absent for a notification; `Some(Id::Null)` for an explicit `null`.
    #[serde(
        default,
        deserialize_with = "present",
        skip_serializing_if = "Option::is_none"
    )]
    pub id: Option<Id>,
    /// Method name (`docs/api.md`, Methods).
    pub method: String,
    /// Params as sent; absent and `null` both mean none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub params: Option<Value>,
}

/// A field that is present, even as `null`, is `Some`.
fn present<'de, D: Deserializer<'de>, T: Deserialize<'de>>(d: D) -> Result<Option<T>, D::Error> {
    T::deserialize(d).map(Some)
}

/// A line that is not a JSON-RPC 2.0 request: the error to answer and the id to answer
/// it with (null when the id could not be read).
#[derive(Debug, Clone, PartialEq)]
pub struct Refusal {
    /// The request's id, or null.
    pub id: Id,
    /// -32700 or -32600.
    pub error: ApiError,
}

impl Request {
    /// A request for `method`; `params` that serialize to an empty object or null are
    /// left out (JSON-RPC lets a request without params omit them).
    pub fn new(id: Option<Id>, method: &str, params: Option<Value>) -> Request {
        let params =
            params.filter(|p| !(p.is_null() || p.as_object().is_some_and(|o| o.is_empty())));
        Request {
            jsonrpc: JsonRpcVersion,
            id,
            method: method.to_string(),
            params,
        }
    }

    /// Read one request line, with the errors `docs/api.md` promises: -32700 for a line
    /// that is not JSON, -32600 for JSON that is not a request object.
    pub fn from_line(line: &[u8]) -> Result<Request, Refusal> {
        let v: Value = serde_json::from_slice(line).map_err(|e| Refusal {
            id: Id::Null,
            error: ApiError::new(ApiError::PARSE, format!("not JSON: {e}")),
        })?;
        // A number id as sent: the parsed value holds one beyond 64-bit integers (and
        // `-0`, `1e5`) as an f64; only then is the line read again for its text (a job
        // line of 60 MiB is not scanned twice for an id of 7).
        let float_id = v
            .get("id")
            .and_then(Value::as_number)
            .is_some_and(serde_json::Number::is_f64);
        let raw_number = float_id
            .then(|| serde_json::from_slice::<RawId<'_>>(line).ok())
            .flatten()
            .and_then(|r| r.id)
            .and_then(|raw| NumberText::parse(raw.get()));
        let exact = |id: Id| match (id, &raw_number) {
            (Id::Number(_), Some(raw)) => Id::Number(raw.clone()),
            (id, _) => id,
        };
        match Request::from_value(v) {
            Ok(r) => Ok(Request {
                id: r.id.map(exact),
                ..r
            }),
            Err(refusal) => Err(Refusal {
                id: exact(refusal.id),
                ..refusal
            }),
        }
    }

    /// Check a JSON value is a request object (see [`Request::from_line`]).
    pub fn from_value(v: Value) -> Result<Request, Refusal> {
        let refuse = |id: Option<&Id>, m: &str| Refusal {
            id: id.cloned().unwrap_or(Id::Null),
            error: ApiError::new(ApiError::INVALID_REQUEST, m),
        };
        let Value::Object(mut obj) = v else {
            let m = if v.is_array() {
                "batches (JSON arrays) are not supported: send one request object a line"
            } else {
                "a request is a JSON object"
            };
            return Err(refuse(None, m));
        };
        // An id of another type is not echoed: the error goes out with id null.
        let id = obj.remove("id").map(|i| Id::deserialize(i).map_err(|_| ()));
        let readable_id = id.as_ref().and_then(|i| i.as_ref().ok());
        if obj.get("jsonrpc").and_then(Value::as_str) != Some(JsonRpcVersion::TEXT) {
            return Err(refuse(readable_id, NOT_VERSION_2));
        }
        let id = id
            .transpose()
            .map_err(|()| refuse(None, "\"id\" must be a string, a number or null"))?;
        let Some(Value::String(method)) = obj.remove("method") else {
            return Err(refuse(id.as_ref(), "\"method\" must be a string"));
        };
        let params = obj.remove("params").filter(|p| !p.is_null());
        Ok(Request {
            jsonrpc: JsonRpcVersion,
            id,
            method,
            params,
        })
    }
}

/// A response line: the request's id and its result (`R`, the method's result type) or
/// an error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Response<R = Value> {
    /// `"2.0"`.
    pub jsonrpc: JsonRpcVersion,
    /// The request's id (null if it could not be read).
    pub id: Id,
    /// `"result"` or `"error"`.
    #[serde(flatten)]
    pub outcome: Outcome<R>,
}

/// What a response carries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Outcome<R> {
    /// The method's result.
    Result(R),
    /// Why there is none.
    Error(ApiError),
}

impl<R> Response<R> {
    /// A response to `id`.
    pub fn new(id: Id, outcome: Result<R, ApiError>) -> Response<R> {
        Response {
            jsonrpc: JsonRpcVersion,
            id,
            outcome: match outcome {
                Ok(r) => Outcome::Result(r),
                Err(e) => Outcome::Error(e),
            },
        }
    }

    /// The result, or the error.
    pub fn into_result(self) -> Result<R, ApiError> {
        match self.outcome {
            Outcome::Result(r) => Ok(r),
            Outcome::Error(e) => Err(e),
        }
    }
}

/// A notification line from the daemon (after `subscribe`): an [`Event`] and no id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Notification {
    /// `"2.0"`.
    pub jsonrpc: JsonRpcVersion,
    /// `method` and `params`.
    #[serde(flatten)]
    pub event: Event,
}

impl Notification {
    /// A notification of `event`.
    pub fn new(event: Event) -> Notification {
        Notification {
            jsonrpc: JsonRpcVersion,
            event,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn refused(line: &str) -> Refusal {
        match Request::from_line(line.as_bytes()) {
            Ok(r) => panic!("{line} read as {r:?}"),
            Err(r) => r,
        }
    }

    #[test]
    fn request_lines_are_read_or_refused_with_the_documented_codes() {
        let r = Request::from_line(
            br#"{"jsonrpc":"2.0","id":"a","method":"job.get","params":{"id":1}}"#,
        )
        .unwrap();
        assert_eq!(r.id, Some(Id::String("a".into())));
        assert_eq!(r.params, Some(json!({"id": 1})));
        let n =
            Request::from_line(br#"{"jsonrpc":"2.0","method":"subscribe","params":null}"#).unwrap();
        assert_eq!((n.id, n.params), (None, None));
        let null_id = Request::from_line(br#"{"jsonrpc":"2.0","id":null,"method":"x"}"#).unwrap();
        assert_eq!(null_id.id, Some(Id::Null));

        assert_eq!(refused("{not json").error.code, ApiError::PARSE);
        assert!(refused("[]").error.message.starts_with("batches"));
        let e = refused(r#"{"jsonrpc":"1.0","id":4,"method":"server.info"}"#);
        assert_eq!(e.id, Id::from(4));
        assert_eq!(
            e.error,
            ApiError::new(ApiError::INVALID_REQUEST, NOT_VERSION_2)
        );
        let e = refused(r#"{"jsonrpc":"2.0","id":[4],"method":"server.info"}"#);
        assert_eq!((e.id, e.error.code), (Id::Null, ApiError::INVALID_REQUEST));
        let e = refused(r#"{"jsonrpc":"2.0","id":5,"method":7}"#);
        assert_eq!(
            (e.id, e.error.code),
            (Id::from(5), ApiError::INVALID_REQUEST)
        );
    }

    #[test]
    fn responses_and_notifications_keep_their_wire_shape() {
        let ok: Response<Value> = Response::new(Id::from(1), Ok(json!({"refilled": true})));
        assert_eq!(
            serde_json::to_value(&ok).unwrap(),
            json!({"jsonrpc": "2.0", "id": 1, "result": {"refilled": true}})
        );
        let err: Response<Value> =
            Response::new(Id::Null, Err(ApiError::new(ApiError::PARSE, "not JSON")));
        let line = serde_json::to_string(&err).unwrap();
        assert_eq!(
            line,
            r#"{"jsonrpc":"2.0","id":null,"error":{"code":-32700,"message":"not JSON"}}"#
        );
        let back: Response<Value> = serde_json::from_str(&line).unwrap();
        assert_eq!(back, err);
        let wrong: Result<Response<Value>, _> =
            serde_json::from_str(r#"{"jsonrpc":"1.0","id":1,"result":1}"#);
        assert!(wrong.is_err());
    }

    #[test]
    fn number_ids_are_echoed_exactly_as_sent() {
        for id in [
            "18446744073709551616",
            "-0",
            "1e5",
            "-170141183460469231731687303715884105728",
            "7",
            "1.50",
        ] {
            let line = format!(r#"{{"jsonrpc":"2.0","id":{id},"method":"server.info"}}"#);
            let r = Request::from_line(line.as_bytes()).unwrap();
            let answer =
                serde_json::to_string(&Response::<Value>::new(r.id.unwrap(), Ok(json!(true))))
                    .unwrap();
            assert_eq!(
                answer,
                format!(r#"{{"jsonrpc":"2.0","id":{id},"result":true}}"#)
            );
            // Refused requests too.
            let line = format!(r#"{{"jsonrpc":"1.0","id":{id},"method":"server.info"}}"#);
            let e = Request::from_line(line.as_bytes()).unwrap_err();
            assert_eq!(e.id, Id::Number(NumberText::parse(id).unwrap()));
        }
        assert_eq!(NumberText::parse("\"1\""), None);
        assert_eq!(NumberText::parse("1 2"), None);
    }
}
