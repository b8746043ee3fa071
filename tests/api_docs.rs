//! Every JSON example in `docs/api.md` against the types of `edo::proto`: each request
//! reads as its method's call, each result as that method's result type, each
//! notification and error as theirs, and each writes back as the same JSON (so an example
//! with a missing, misspelt or extra key fails). The tables of methods, notifications and
//! error codes list exactly what the types define.
//!
//! Examples are fenced blocks. A transcript block has one JSON-RPC line after each `→`
//! (client to edod) or `←` (edod to client); a response is checked against the request
//! with its id in the same block. A `json` block is checked as the type its section
//! (`### Job`, ...) names.

use std::collections::{BTreeSet, HashMap};

use edo::proto::{
    method, ApiError, Call, Event, Job, Method, Notification, Outcome, Request, Response, METHODS,
};
use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;

fn api_md() -> String {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/api.md");
    std::fs::read_to_string(path).expect("docs/api.md")
}

/// A fenced block: the heading it is under, its language, its lines, where it starts.
struct Block {
    heading: String,
    lang: String,
    lines: Vec<String>,
    line_no: usize,
}

fn blocks(md: &str) -> Vec<Block> {
    let mut out = Vec::new();
    let mut heading = String::new();
    let mut open: Option<Block> = None;
    for (i, line) in md.lines().enumerate() {
        if let Some(b) = open.as_mut() {
            if line.trim_start().starts_with("```") {
                out.extend(open.take());
            } else {
                b.lines.push(line.to_string());
            }
        } else if let Some(lang) = line.trim_start().strip_prefix("```") {
            open = Some(Block {
                heading: heading.clone(),
                lang: lang.trim().to_string(),
                lines: Vec::new(),
                line_no: i + 1,
            });
        } else if line.starts_with('#') {
            heading = line.trim_start_matches('#').trim().to_string();
        }
    }
    assert!(open.is_none(), "docs/api.md: a code block is not closed");
    out
}

/// `v` read as `T` writes back as `v`.
fn round_trip<T: Serialize + DeserializeOwned>(v: &Value) -> Result<(), String> {
    let t: T = serde_json::from_value(v.clone())
        .map_err(|e| format!("does not read as {}: {e}", std::any::type_name::<T>()))?;
    let back = serde_json::to_value(&t).map_err(|e| e.to_string())?;
    if &back != v {
        return Err(format!(
            "reads as {} but writes back as {back}",
            std::any::type_name::<T>()
        ));
    }
    Ok(())
}

/// `v` is the result of `method`.
fn check_result(method: &str, v: &Value) -> Result<(), String> {
    macro_rules! by_method {
        ($($m:ident),*) => {
            match method {
                $(method::$m::NAME => round_trip::<<method::$m as Method>::Result>(v),)*
                other => Err(format!("no result type for {other:?}")),
            }
        };
    }
    by_method!(
        ServerInfo,
        JobSubmit,
        JobList,
        JobGet,
        JobPause,
        JobResume,
        JobCancel,
        JobStartNext,
        JobDelete,
        JobReprint,
        MachineStatus,
        MachineEstop,
        MachineRefill,
        Subscribe,
        LogRecent
    )
}

/// What the examples showed.
#[derive(Default)]
struct Seen {
    results: BTreeSet<String>,
    events: BTreeSet<String>,
    codes: BTreeSet<i64>,
}

/// What a request line in a transcript read as.
enum Sent {
    /// A request: its method and the call its params read as.
    Request(String, Result<Call, ApiError>),
    /// Not a request: the error edod answers.
    Refused(ApiError),
}

fn check_transcript(b: &Block, seen: &mut Seen) -> Vec<String> {
    let mut problems = Vec::new();
    let mut pending: HashMap<String, Sent> = HashMap::new();
    for (k, line) in b.lines.iter().enumerate() {
        let at = format!("docs/api.md:{}", b.line_no + k + 1);
        let r = if let Some(json) = line.strip_prefix("→ ") {
            check_sent(json, &mut pending)
        } else if let Some(json) = line.strip_prefix("← ") {
            check_received(json, &mut pending, seen)
        } else if line.trim().is_empty() {
            Ok(())
        } else {
            Err("a transcript line starts with → or ←".to_string())
        };
        if let Err(e) = r {
            problems.push(format!("{at}: {e}\n    {line}"));
        }
    }
    for id in pending.keys() {
        problems.push(format!(
            "docs/api.md:{}: request {id} is not answered in its block",
            b.line_no
        ));
    }
    problems
}

fn check_sent(json: &str, pending: &mut HashMap<String, Sent>) -> Result<(), String> {
    let request = match Request::from_line(json.as_bytes()) {
        Ok(r) => r,
        Err(refusal) => {
            pending.insert(id_key(&refusal.id), Sent::Refused(refusal.error));
            return Ok(());
        }
    };
    let call = Call::new(&request.method, request.params.clone());
    if let Ok(c) = &call {
        let again = Request::new(request.id.clone(), c.method(), c.params());
        let original: Value = serde_json::from_str(json).map_err(|e| e.to_string())?;
        if serde_json::to_value(&again).map_err(|e| e.to_string())? != original {
            return Err(format!(
                "the request reads as {c:?}, which is sent as {}",
                serde_json::to_string(&again).unwrap_or_default()
            ));
        }
    }
    match request.id {
        Some(id) => {
            pending.insert(id_key(&id), Sent::Request(request.method, call));
            Ok(())
        }
        None => call.map(|_| ()).map_err(|e| e.to_string()),
    }
}

fn check_received(
    json: &str,
    pending: &mut HashMap<String, Sent>,
    seen: &mut Seen,
) -> Result<(), String> {
    let v: Value = serde_json::from_str(json).map_err(|e| format!("not JSON: {e}"))?;
    let Some(id) = v.get("id") else {
        round_trip::<Notification>(&v)?;
        let n: Notification = serde_json::from_value(v).map_err(|e| e.to_string())?;
        seen.events.insert(n.event.method().to_string());
        return Ok(());
    };
    let sent = pending
        .remove(&id.to_string())
        .ok_or_else(|| format!("no request with id {id} before it"))?;
    round_trip::<Response<Value>>(&v)?;
    let response: Response<Value> = serde_json::from_value(v).map_err(|e| e.to_string())?;
    match (response.outcome, sent) {
        (Outcome::Error(e), sent) => {
            seen.codes.insert(e.code);
            if !ApiError::CODES.contains(&e.code) {
                return Err(format!("code {} is not in the table of errors", e.code));
            }
            match sent {
                Sent::Refused(expected) | Sent::Request(_, Err(expected)) if expected != e => {
                    Err(format!("edod answers that request with {expected:?}"))
                }
                _ => Ok(()),
            }
        }
        (Outcome::Result(r), Sent::Request(m, Ok(_))) => {
            check_result(&m, &r)?;
            seen.results.insert(m);
            Ok(())
        }
        (Outcome::Result(_), Sent::Request(_, Err(e))) => {
            Err(format!("a result to a request edod refuses: {e:?}"))
        }
        (Outcome::Result(_), Sent::Refused(e)) => {
            Err(format!("a result to a line that is not a request: {e:?}"))
        }
    }
}

fn id_key(id: &edo::proto::Id) -> String {
    serde_json::to_string(id).unwrap_or_default()
}

/// A `json` block, read as the type its section names.
fn check_json_block(b: &Block) -> Result<(), String> {
    let v: Value =
        serde_json::from_str(&b.lines.join("\n")).map_err(|e| format!("not JSON: {e}"))?;
    match b.heading.as_str() {
        "Job" => round_trip::<Job>(&v),
        #[cfg(feature = "daemon")]
        "The machine table" => round_trip::<edo::setup::MachineConfig>(&v),
        other => Err(format!(
            "a json example under {other:?}: name its type in tests/api_docs.rs"
        )),
    }
}

#[test]
fn every_example_reads_as_its_type_and_writes_back_the_same() {
    let md = api_md();
    let mut seen = Seen::default();
    let mut problems = Vec::new();
    for b in blocks(&md) {
        let transcript = b
            .lines
            .iter()
            .any(|l| l.starts_with("→ ") || l.starts_with("← "));
        if transcript {
            problems.extend(check_transcript(&b, &mut seen));
        } else if b.lang == "json" {
            if let Err(e) = check_json_block(&b) {
                problems.push(format!("docs/api.md:{}: {e}", b.line_no));
            }
        } else if b.lang.is_empty() {
            problems.push(format!(
                "docs/api.md:{}: a block that is neither a transcript nor json",
                b.line_no
            ));
        }
    }
    let missing_results: Vec<_> = METHODS
        .iter()
        .filter(|m| !seen.results.contains(**m))
        .collect();
    let missing_events: Vec<_> = Event::METHODS
        .iter()
        .filter(|m| !seen.events.contains(**m))
        .collect();
    let missing_codes: Vec<_> = ApiError::CODES
        .iter()
        .filter(|c| !seen.codes.contains(c))
        .collect();
    assert!(
        problems.is_empty(),
        "examples in docs/api.md that do not match edo::proto:\n{}",
        problems.join("\n")
    );
    assert!(
        missing_results.is_empty() && missing_events.is_empty() && missing_codes.is_empty(),
        "docs/api.md has no example of: results {missing_results:?}, notifications \
         {missing_events:?}, errors {missing_codes:?}"
    );
}

/// The first cells of the table rows under `## {section}`.
fn table_keys(md: &str, section: &str) -> BTreeSet<String> {
    let mut keys = BTreeSet::new();
    let mut inside = false;
    for line in md.lines() {
        if let Some(heading) = line.strip_prefix("## ") {
            inside = heading.trim() == section;
        } else if let Some(row) = line.strip_prefix("| ").filter(|_| inside) {
            let cell = row.split('|').next().unwrap_or("").trim();
            keys.insert(cell.trim_matches('`').to_string());
        }
    }
    keys
}

#[test]
fn the_tables_list_what_the_types_define() {
    let md = api_md();
    let set = |items: &[&str]| items.iter().map(|s| s.to_string()).collect::<BTreeSet<_>>();
    let mut methods = set(METHODS);
    methods.insert("method".into());
    assert_eq!(table_keys(&md, "Methods"), methods);
    let mut events = set(&Event::METHODS);
    events.insert("method".into());
    assert_eq!(table_keys(&md, "Notifications (after `subscribe`)"), events);
    let mut codes: BTreeSet<String> = ApiError::CODES.iter().map(i64::to_string).collect();
    codes.insert("code".into());
    assert_eq!(table_keys(&md, "Errors"), codes);
}

/// The machine table lists every key `server.info`'s `machine` can hold: edod's
/// `[machine]` with every optional table set (`gcode`, `mixer`).
#[cfg(feature = "daemon")]
#[test]
fn the_machine_table_lists_every_key_of_the_machine_config() {
    use edo::setup::MachineConfig;
    let full: MachineConfig = serde_json::from_value(serde_json::json!({
        "protocol": "gcode",
        "gcode": {"firmware": "marlin"},
        "mixer": {"model": "dispersion", "volume_nl": 800.0, "peclet": 12.0},
    }))
    .expect("a machine table with gcode and mixer");
    let Value::Object(keys) = serde_json::to_value(&full).expect("serialises") else {
        panic!("the machine table is an object");
    };
    let mut expected: BTreeSet<String> = keys.keys().cloned().collect();
    assert!(
        expected.contains("mixer") && expected.contains("gcode"),
        "{expected:?}"
    );
    expected.insert("key".into());
    assert_eq!(table_keys(&api_md(), "The machine table"), expected);
}
