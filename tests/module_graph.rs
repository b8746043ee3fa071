//! The core's modules depend on each other one way (docs/architecture.md): no `crate::`
//! path in a top-level module of the core may close a cycle between them. Each edge is
//! a `crate::name` in a module's code (comments and its unit tests left out); a cycle is
//! reported with the file and line of every edge on it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Top-level modules of the I/O shell (feature `daemon`): they may use anything.
const SHELL: [&str; 2] = ["daemon", "cli"];

/// Where module `from` names module `to`: file and line.
type Edges = BTreeMap<String, BTreeMap<String, Vec<String>>>;

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// The core's top-level modules, from `src/lib.rs`.
fn core_modules() -> Vec<String> {
    let lib = std::fs::read_to_string(src().join("lib.rs")).unwrap();
    lib.lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod "))
        .map(|m| m.trim_end_matches(';').to_string())
        .filter(|m| !SHELL.contains(&m.as_str()))
        .collect()
}

/// Module `m`'s files: `src/m.rs` and everything under `src/m/`, unit-test files left out.
fn files_of(m: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let file = src().join(format!("{m}.rs"));
    if file.exists() {
        out.push(file);
    }
    let mut dirs = vec![src().join(m)];
    while let Some(d) = dirs.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "rs")
                && !p.to_string_lossy().ends_with("tests.rs")
            {
                out.push(p);
            }
        }
    }
    out
}

/// The `crate::name` paths of a line of code (none in a comment).
fn named_modules(line: &str) -> Vec<String> {
    let code = line.trim_start();
    if code.starts_with("//") {
        return Vec::new();
    }
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(at) = rest.find("crate::") {
        let after = &rest[at + "crate::".len()..];
        let name: String = after
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        out.push(name);
        rest = after;
    }
    out
}

fn edges(core: &[String]) -> Edges {
    let mut edges = Edges::new();
    for m in core {
        for f in files_of(m) {
            let text = std::fs::read_to_string(&f).unwrap();
            // A module's unit tests may reach anything.
            let code = text
                .split("#[cfg(test)]\nmod tests")
                .next()
                .unwrap_or_default();
            for (n, line) in code.lines().enumerate() {
                for to in named_modules(line) {
                    if &to != m && core.contains(&to) {
                        let at = format!(
                            "{}:{}",
                            f.strip_prefix(env!("CARGO_MANIFEST_DIR"))
                                .unwrap()
                                .display(),
                            n + 1
                        );
                        edges
                            .entry(m.clone())
                            .or_default()
                            .entry(to)
                            .or_default()
                            .push(at);
                    }
                }
            }
        }
    }
    edges
}

/// A cycle through `start`, if any: the modules in order, back to `start`.
fn cycle_through(start: &str, edges: &Edges) -> Option<Vec<String>> {
    // Depth first from `start`, remembering the path.
    fn walk(
        at: &str,
        start: &str,
        edges: &Edges,
        path: &mut Vec<String>,
        seen: &mut BTreeSet<String>,
    ) -> bool {
        for to in edges.get(at).map(|t| t.keys()).into_iter().flatten() {
            if to == start {
                path.push(to.clone());
                return true;
            }
            if seen.insert(to.clone()) {
                path.push(to.clone());
                if walk(to, start, edges, path, seen) {
                    return true;
                }
                path.pop();
            }
        }
        false
    }
    let mut path = vec![start.to_string()];
    let mut seen = BTreeSet::new();
    walk(start, start, edges, &mut path, &mut seen).then_some(path)
}

#[test]
fn the_core_s_modules_depend_one_way() {
    let core = core_modules();
    assert!(core.len() > 10, "{core:?}");
    assert!(core.contains(&"lifecycle".to_string()));
    let edges = edges(&core);
    let mut problems = Vec::new();
    for m in &core {
        if let Some(cycle) = cycle_through(m, &edges) {
            let steps: Vec<String> = cycle
                .windows(2)
                .map(|w| format!("  {} -> {} ({})", w[0], w[1], edges[&w[0]][&w[1]][0]))
                .collect();
            problems.push(format!("{}\n{}", cycle.join(" -> "), steps.join("\n")));
        }
    }
    assert!(
        problems.is_empty(),
        "the core's module graph has cycles:\n{}",
        problems.join("\n")
    );
}

#[test]
fn a_cycle_is_found_and_named() {
    let mut e = Edges::new();
    let at = |f: &str| vec![f.to_string()];
    e.entry("job".into())
        .or_default()
        .insert("machine".into(), at("src/job.rs:1"));
    e.entry("machine".into())
        .or_default()
        .insert("pipeline".into(), at("src/machine/a.rs:2"));
    e.entry("pipeline".into())
        .or_default()
        .insert("job".into(), at("src/pipeline.rs:3"));
    e.entry("geom".into())
        .or_default()
        .insert("material".into(), at("src/geom/x.rs:4"));
    assert_eq!(
        cycle_through("job", &e),
        Some(vec![
            "job".into(),
            "machine".into(),
            "pipeline".into(),
            "job".into()
        ])
    );
    assert_eq!(cycle_through("geom", &e), None);
    assert_eq!(
        named_modules("use crate::job::Job; let x = crate::machine::MAX;"),
        ["job", "machine"]
    );
    assert!(named_modules("/// see [`crate::job`]").is_empty());
}
