// edo dashboard: the JSON-RPC API of docs/api.md over /websocket (docs/http.md).
// Plain modern JavaScript, no build step; every control has an accessible name.
"use strict";

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";

const state = {
  ws: null, nextId: 1, pending: new Map(), jobs: new Map(), machine: null,
  progress: null, server: null, layer: null, preview: null, token: sessionStorage.getItem("edo-token"),
  logSeq: 0,
};

// ---- theme: light, dark, or the system's ------------------------------------------

const THEMES = ["auto", "light", "dark"];

function applyTheme(t) {
  if (!THEMES.includes(t)) t = "auto";
  document.documentElement.dataset.theme = t;
  const next = THEMES[(THEMES.indexOf(t) + 1) % THEMES.length];
  $("theme").textContent = "Theme: " + t;
  $("theme").setAttribute("aria-label", "Theme: " + (t === "auto" ? "follows the system" : t) + " (click for " + next + ")");
  state.theme = t;
}

$("theme").addEventListener("click", () => {
  const next = THEMES[(THEMES.indexOf(state.theme) + 1) % THEMES.length];
  try { localStorage.setItem("edo-theme", next); } catch { /* private mode: not kept */ }
  applyTheme(next);
});
applyTheme((() => { try { return localStorage.getItem("edo-theme"); } catch { return null; } })());

// ---- toasts: done, fault, e-stop -----------------------------------------------------

// A notice in the corner that goes by itself (errors stay longer), with a close button.
function toast(text, kind = "info") {
  const box = document.createElement("div");
  box.className = "toast " + kind;
  box.setAttribute("role", kind === "error" ? "alert" : "status");
  const p = document.createElement("p");
  p.textContent = text;
  const close = document.createElement("button");
  close.type = "button";
  close.textContent = "×";
  close.setAttribute("aria-label", "Dismiss: " + text);
  close.addEventListener("click", () => box.remove());
  box.append(p, close);
  $("toasts").append(box);
  while ($("toasts").children.length > 5) $("toasts").firstElementChild.remove();
  setTimeout(() => box.remove(), kind === "error" ? 30000 : 10000);
}

// ---- the connection ---------------------------------------------------------------

function call(method, params) {
  return new Promise((resolve, reject) => {
    if (!state.ws || state.ws.readyState !== WebSocket.OPEN) {
      reject(new Error("not connected to edod"));
      return;
    }
    const id = state.nextId++;
    state.pending.set(id, { resolve, reject });
    const req = { jsonrpc: "2.0", id, method };
    if (params !== undefined) req.params = params;
    state.ws.send(JSON.stringify(req));
  });
}

function onMessage(ev) {
  let m;
  try { m = JSON.parse(ev.data); } catch { return; }
  if (m.id !== undefined && m.id !== null && state.pending.has(m.id)) {
    const p = state.pending.get(m.id);
    state.pending.delete(m.id);
    if (m.error) p.reject(Object.assign(new Error(m.error.message), { code: m.error.code }));
    else p.resolve(m.result);
    return;
  }
  if (m.method === "notify_job_progress") onProgress(m.params);
  else if (m.method === "notify_job_state") onJobState(m.params);
  else if (m.method === "notify_machine_state") onMachine(m.params);
  else if (m.error) setLink("edod: " + m.error.message);
}

// One call by POST /api/rpc: the way when the WebSocket is not open (edod serving its
// most clients keeps a place for e-stop and status, not for a WebSocket).
async function post(method, params) {
  const req = { jsonrpc: "2.0", id: 1, method };
  if (params !== undefined) req.params = params;
  const r = await api("/api/rpc", {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(req),
  });
  let m;
  try { m = await r.json(); } catch { throw new Error("edod answered " + r.status); }
  if (m.error) throw Object.assign(new Error(m.error.message), { code: m.error.code });
  return m.result;
}

function setLink(text) { $("link").textContent = text; }

// edod is not answering: say so over every panel, greyed and inert, with the time the
// page last knew its state; cleared only once the state has been read again.
function goOffline(why) {
  if (!document.body.classList.contains("offline")) state.lostAt = new Date();
  document.body.classList.add("offline");
  $("main").inert = true;
  const o = $("offline");
  o.textContent = "edod is not answering (" + why + "): what is shown is as it was at " +
    state.lostAt.toLocaleTimeString() + ". Reconnecting…";
  o.hidden = false;
}

function goOnline() {
  document.body.classList.remove("offline");
  $("main").inert = false;
  $("offline").hidden = true;
}

// A GET or POST of the API, with the token when there is one (beyond loopback every
// call of the API needs it, reads too).
function api(path, init = {}) {
  const headers = Object.assign({}, init.headers);
  if (state.token) headers.Authorization = "Bearer " + state.token;
  return fetch(path, Object.assign({}, init, { headers }));
}

function askToken(why) {
  state.token = null;
  sessionStorage.removeItem("edo-token");
  $("token-form").hidden = false;
  setLink(why);
  $("token").focus();
}

async function connect() {
  let r;
  try {
    r = await api("/api/server");
  } catch {
    setLink("edod does not answer; retrying…");
    goOffline("no answer");
    setTimeout(connect, 1000);
    return;
  }
  if (r.status === 401) {
    askToken(state.token ? "edod refused this token: enter the token of http.token_file" : "this printer needs its token (http.token_file)");
    return;
  }
  if (!r.ok) {
    setLink("edod answers " + r.status + "; retrying…");
    goOffline("HTTP " + r.status);
    setTimeout(connect, 1000);
    return;
  }
  state.server = await r.json();
  const url = new URL("/websocket", location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  if (state.token) url.searchParams.set("token", state.token);
  const ws = new WebSocket(url);
  state.ws = ws;
  ws.onmessage = onMessage;
  ws.onopen = async () => {
    setLink("connected to " + state.server.name + " " + state.server.version + " (" + state.server.port + ")");
    try {
      // Everything read again before it is shown: what changed while the page was
      // away (a restart interrupts the job; jobs deleted) replaces what it knew.
      await call("subscribe");
      const st = await call("machine.status");
      const jobs = await call("job.list");
      state.jobs = new Map(jobs.map((j) => [j.id, j]));
      state.progress = null;
      onMachine(st);
      if (st.progress) onProgress(st.progress);
      renderJobs();
      renderActive();
      goOnline();
      // The log of the edod connected to (it may have restarted): read whole again.
      state.logSeq = 0;
      $("console").replaceChildren();
      pollLog();
    } catch (e) { setLink("edod: " + e.message); }
  };
  ws.onclose = () => {
    for (const p of state.pending.values()) p.reject(new Error("connection lost"));
    state.pending.clear();
    // Reconnecting asks /api/server first: a token edod no longer takes is asked for.
    setLink("disconnected; reconnecting…");
    goOffline("connection lost");
    setTimeout(connect, 1000);
  };
}

$("token-form").addEventListener("submit", (e) => {
  e.preventDefault();
  state.token = $("token").value.trim();
  sessionStorage.setItem("edo-token", state.token);
  $("token-form").hidden = true;
  connect();
});

// ---- the queue ------------------------------------------------------------------

// What the API allows in each state (docs/api.md, Methods).
const ACTIONS = {
  queued: ["cancel"], planning: ["cancel"], printing: ["pause", "cancel"],
  paused: ["resume", "cancel"], interrupted: ["resume", "cancel"],
  done: ["reprint", "delete"], failed: ["reprint", "delete"], cancelled: ["reprint", "delete"],
};
const FINISHED = ["done", "failed", "cancelled"];

function fmtEta(s) {
  if (s === null || s === undefined) return "—";
  s = Math.round(s);
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), r = s % 60;
  return (h ? h + " h " : "") + (h || m ? m + " min " : "") + r + " s";
}

function fmtTime(ms) {
  if (ms === null || ms === undefined) return "—";
  const d = new Date(ms);
  const today = new Date().toDateString() === d.toDateString();
  return today ? d.toLocaleTimeString() : d.toLocaleString();
}

// Material per syringe, by the machine's syringe names, ml.
function materialText(nl) {
  if (!nl || !nl.length) return "—";
  const names = (state.server?.machine?.syringes || []).map((s) => s.name);
  return nl.map((v, i) => (names[i] || "syringe " + (i + 1)) + " " + (v / 1e6).toFixed(2) + " ml").join(", ");
}

// A job's state, and why where edod gives a reason (an interruption, a failure), or
// what a queued job waits for.
function stateText(j) {
  const held = state.machine?.queue_held_by;
  if (j.state === "queued" && held) return "queued: waits, job " + held + " holds the queue";
  return j.reason && j.state !== "done" ? j.state + ": " + j.reason : j.state;
}

function progressText(j) {
  const p = j.progress;
  if (!p) {
    if (j.state === "done") return "done";
    return j.total_moves ? j.total_moves + " moves" : "—";
  }
  const pct = p.percent !== null && p.percent !== undefined ? p.percent.toFixed(0) + " %, " : "";
  const layer = p.layers ? "layer " + ((p.layer ?? 0) + 1) + " of " + p.layers : "planning layers";
  const moves = p.executed + (p.total ? " of " + p.total : "") + " moves";
  return pct + layer + ", " + moves;
}

// Each table's cells of a job: [label, text, class].
function queueCells(j) {
  return [["#", String(j.id)], ["Job", j.name], ["State", stateText(j), "state"],
    ["Progress", progressText(j)], ["ETA", fmtEta(j.progress?.eta_s)]];
}

function historyCells(j) {
  const ended = j.ended_ms ?? null;
  const took = j.started_ms && ended ? fmtEta((ended - j.started_ms) / 1000) : "—";
  const moves = j.checkpoint.next_index + (j.total_moves ? " of " + j.total_moves : "");
  return [["#", String(j.id)], ["Job", j.name], ["Result", stateText(j), "state"],
    ["Started", fmtTime(j.started_ms)], ["Ended", fmtTime(ended)], ["Duration", took],
    ["Moves", moves], ["Material", materialText(j.checkpoint.used_nl)]];
}

function renderJobs() {
  const all = [...state.jobs.values()];
  const waiting = all.filter((j) => !FINISHED.includes(j.state)).sort((a, b) => a.id - b.id);
  const finished = all.filter((j) => FINISHED.includes(j.state)).sort((a, b) => b.id - a.id);
  renderRows($("jobs"), waiting, queueCells);
  renderRows($("history-jobs"), finished, historyCells);
  $("no-jobs").hidden = waiting.length > 0;
  $("no-history").hidden = finished.length > 0;
  renderHeld();
}

// A row is made anew only for a new job or a new state (its buttons change); else only
// its text cells that changed are written, so a button stays under the pointer and
// keeps the keyboard focus while progress streams in.
function renderRows(body, jobs, cellsOf) {
  const keep = new Set();
  jobs.forEach((j, i) => {
    const cells = cellsOf(j);
    let tr = $("job-" + j.id);
    let refocus = false;
    if (!tr || tr.dataset.state !== j.state || tr.parentNode !== body) {
      const row = jobRow(j, cells);
      // The keyboard focus was on the old row's control: it goes to the new row's
      // (pause becomes resume), not back to the page's body.
      // (A button disabled while its call is out may have lost the focus already.)
      refocus = !!tr && (tr.contains(document.activeElement) || state.focusJob === j.id);
      if (tr) tr.remove();
      tr = row;
    } else {
      cells.forEach(([, text], k) => {
        const td = tr.children[k];
        if (td && td.textContent !== text) td.textContent = text;
      });
    }
    if (body.children[i] !== tr) body.insertBefore(tr, body.children[i] || null);
    if (refocus) {
      tr.querySelector("button")?.focus();
      state.focusJob = null;
    }
    keep.add(tr);
  });
  for (const tr of [...body.children]) if (!keep.has(tr)) tr.remove();
}

function jobRow(j, cells) {
  const tr = document.createElement("tr");
  tr.id = "job-" + j.id;
  tr.dataset.state = j.state;
  for (const [label, text, cls] of cells) {
    const td = document.createElement("td");
    td.textContent = text;
    td.dataset.label = label;
    if (cls) td.className = cls;
    tr.append(td);
  }
  const td = document.createElement("td");
  td.dataset.label = "Actions";
  for (const action of ACTIONS[j.state] || []) {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = action;
    b.setAttribute("aria-label", action + " job " + j.id + " (" + j.name + ")");
    b.dataset.action = action;
    b.addEventListener("click", () => jobAction(action, j, b));
    td.append(b);
  }
  tr.append(td);
  return tr;
}

// What cannot be undone, and a resume after an interruption, are asked first, naming
// the job.
const CONFIRM = {
  cancel: (j) => "Cancel job " + j.id + " (" + j.name + ")? It stops for good: a cancelled job cannot be resumed.",
  delete: (j) => "Delete job " + j.id + " (" + j.name + ") and its record?",
  resume: (j) => j.state !== "interrupted" ? null : "Resume job " + j.id + " (" + j.name + ")?" +
    (j.reason ? " It was interrupted: " + j.reason + "." : "") +
    " Check the part is still on the bed and the nozzle is clear: the machine homes, primes and continues from move " +
    (j.checkpoint?.next_index ?? 0) + ".",
};

async function jobAction(action, j, button) {
  const id = j.id;
  const question = CONFIRM[action] && CONFIRM[action](state.jobs.get(id) || j);
  if (question && !window.confirm(question)) return;
  if (button.closest("tr")) state.focusJob = id;
  button.disabled = true;
  try {
    const r = await call("job." + action, { id });
    if (action === "delete") state.jobs.delete(id);
    else if (action === "reprint") {
      toast("Job " + id + " (" + j.name + ") queued again as job " + r.id + ".");
      await refreshJob(r.id, r.state);
      button.disabled = false;
    } else await refreshJob(id, r.state);
    renderJobs();
  } catch (e) {
    setLink("job " + id + ": " + e.message);
    toast("Job " + id + ": " + action + " refused: " + e.message, "error");
    button.disabled = false;
  }
}

// The queue held by a job edod found interrupted when it started: why, and the three
// ways on.
function renderHeld() {
  const id = state.machine?.queue_held_by;
  const j = id && state.jobs.get(id);
  $("held").hidden = !id;
  if (!id) return;
  const text = "The queue waits: job " + id + (j ? " (" + j.name + ")" : "") + " was interrupted" +
    (j && j.reason ? " (" + j.reason + ")" : "") + ". Resume it, cancel it, or, once its part is off the bed, start the next job.";
  if ($("held-text").textContent !== text) $("held-text").textContent = text;
  $("held-start-next").hidden = ![...state.jobs.values()].some((q) => q.state === "queued");
}

$("held-resume").addEventListener("click", () => {
  const j = state.jobs.get(state.machine?.queue_held_by);
  if (j) jobAction("resume", j, $("held-resume"));
});
$("held-cancel").addEventListener("click", () => {
  const j = state.jobs.get(state.machine?.queue_held_by);
  if (j) jobAction("cancel", j, $("held-cancel"));
});
$("held-start-next").addEventListener("click", async () => {
  const held = state.machine?.queue_held_by;
  if (!window.confirm("Start the next queued job now? Job " + held + " stays interrupted. Take its half-finished part off the bed first: the next job prints where it stands.")) return;
  const b = $("held-start-next");
  b.disabled = true;
  try {
    const r = await call("job.start_next");
    await refreshJob(r.id, r.state);
    renderJobs();
  } catch (e) {
    toast("Start next refused: " + e.message, "error");
  } finally {
    b.disabled = false;
  }
});

async function refreshJob(id, fallbackState) {
  try {
    state.jobs.set(id, await call("job.get", { id }));
  } catch {
    const j = state.jobs.get(id);
    if (j && fallbackState) j.state = fallbackState;
  }
}

// What an operator should hear of at once, wherever the page is scrolled.
function announce(p, j) {
  const name = "Job " + p.job_id + (j ? " (" + j.name + ")" : "");
  if (p.state === "done") toast(name + " is done.", "success");
  else if (p.state === "failed") toast(name + " failed: " + (p.reason || "no reason given"), "error");
  else if (p.state === "interrupted") toast(name + " was interrupted: " + (p.reason || "no reason given") + ". Resume it from the queue.", "error");
  // A pause the operator asked for is no news; one the machine made (an empty syringe) is.
  else if (p.state === "paused" && p.reason && !p.reason.includes("by an operator")) toast(name + " is paused: " + p.reason, "error");
}

async function onJobState(p) {
  const j = state.jobs.get(p.job_id);
  if (j && j.state !== p.state) announce(p, j);
  if (j) { j.state = p.state; j.reason = p.reason; }
  await refreshJob(p.job_id, p.state);
  if (!["printing", "paused", "planning"].includes(p.state) && state.progress?.job_id === p.job_id) {
    // Ended or interrupted: no progress or ETA of it stays on the page.
    const jj = state.jobs.get(p.job_id);
    if (jj) delete jj.progress;
    state.progress = null;
  }
  // An e-stop's notice goes once a job prints again (its cause is over).
  if (p.state === "printing") $("estop-ack").hidden = true;
  renderJobs();
  renderActive();
}

// ---- the active job ---------------------------------------------------------------

function onProgress(p) {
  state.progress = p;
  const j = state.jobs.get(p.job_id);
  if (j) j.progress = p;
  renderJobs();
  renderActive();
  const layer = p.layer ?? 0;
  const want = p.job_id + "/" + layer;
  if (p.layers) loadStack(p.job_id, p.layers);
  if (!state.stack || state.stack.current !== layer) drawStack();
  if (p.layers && (!state.layer || state.layer.key !== want) && state.layerLoading !== want) {
    loadLayer(p.job_id, layer, want);
  } else {
    drawExecuted();
  }
}

async function loadLayer(job, layer, key) {
  state.layerLoading = key;
  try {
    const r = await api("/api/jobs/" + job + "/layers/" + layer);
    if (r.ok) {
      state.layer = Object.assign(await r.json(), { key, job });
      drawLayer($("layer-view"), state.layer);
      drawExecuted();
    }
  } finally {
    if (state.layerLoading === key) state.layerLoading = null;
  }
}

function renderActive() {
  const p = state.progress;
  const j = p && state.jobs.get(p.job_id);
  const bar = $("active-progress");
  if (!p || !j) {
    $("active").textContent = "No job is printing.";
    $("composition").textContent = "No job is printing.";
    bar.hidden = true;
    return;
  }
  bar.hidden = p.percent === null || p.percent === undefined;
  if (!bar.hidden) bar.value = p.percent;
  $("active").textContent = "Job " + j.id + " (" + j.name + "): " + j.state + ", " + progressText(j) + ", ETA " + fmtEta(p.eta_s);
  const road = roadAtNozzle();
  const pct = (c) => c.map((f) => (f * 100).toFixed(0) + " %").join(" / ");
  const designed = road && road[3] ? pct(road[3]) : "not known yet";
  const exit = road && road[5] ? pct(road[5]) : "not known yet";
  const pushed = p.composition ? pct(p.composition) : "not reported yet";
  $("composition").textContent = "Road at the nozzle: designed " + designed +
    "; predicted to leave the nozzle " + exit + " (the planner's model of the mixing chamber)" +
    "; syringes pushing " + pushed + " (they run the chamber's volume ahead).";
}

// The plan's entry for the extrusion the machine executed last.
function roadAtNozzle() {
  const l = state.layer, p = state.progress;
  if (!l || !p || l.job !== p.job_id || l.first_index === null) return null;
  for (let i = Math.min(p.executed - l.first_index - 1, l.moves.length - 1); i >= 0; i--) {
    const m = l.moves[i];
    if (m && m[2]) return m;
  }
  return null;
}

// The machine's faults (bits of the link's FaultKind) and what to do about each.
const FAULTS = [
  [1, "A syringe ran empty.", "Swap the syringe, then refill: the job continues.", "refill"],
  [2, "An axis hit its limit switch.", "Check the part and the axes, then refill to clear the fault and resume the job.", "refill"],
  [4, "The machine's emergency stop was pressed.", "Release it, then resume the job from the queue.", null],
  [8, "The machine's queue overflowed.", "Resume the job; report this if it repeats.", null],
  [16, "The machine could not read a message.", "Check edod and the firmware versions match.", null],
  [32, "The machine refused a move.", "Check the machine's configuration against edod.toml.", null],
];

// The machine panel, from machine.status and notify_machine_state (pushed as the
// machine moves, so the position follows the print).
function onMachine(m) {
  const before = state.machine;
  state.machine = m;
  // Written in place: each pushed status changes only the text that changed, so an
  // element read, selected or announced is not swapped under the reader.
  const rows = [
    ["connected", "Connected", m.connected ? "yes" : "no" + (m.disconnected_reason ? " (" + m.disconnected_reason + ")" : "")],
    ["state", "State", m.state || "not known"],
    ["position", "Position", ["x", "y", "z"].map((a, i) => a + " " + m.position_mm[i].toFixed(2)).join(", ") + " mm"],
    ["executed", "Executed", String(m.executed_total)],
    ["queued", "Queued", String(m.queued)],
    ["underruns", "Underruns", String(m.underruns)],
  ];
  const dl = $("machine");
  for (const [id, k, v] of rows) {
    let dd = $("machine-" + id);
    if (!dd) {
      const dt = document.createElement("dt");
      dt.textContent = k;
      dd = document.createElement("dd");
      dd.id = "machine-" + id;
      dl.append(dt, dd);
    }
    if (dd.textContent !== v) dd.textContent = v;
  }
  const caps = (state.server?.machine?.syringes) || [];
  const ul = $("syringes");
  if (ul.children.length !== m.remaining_nl.length) {
    ul.replaceChildren(...m.remaining_nl.map(() => {
      const li = document.createElement("li");
      li.append(document.createElement("span"), " ", document.createElement("meter"));
      return li;
    }));
  }
  m.remaining_nl.forEach((nl, i) => {
    const li = ul.children[i];
    const cap = caps[i] ? caps[i].capacity_ml * 1e6 : 0;
    const name = caps[i] ? caps[i].name : "syringe " + i;
    const label = name + ": " + (nl / 1e6).toFixed(2) + " ml";
    const span = li.querySelector("span"), meter = li.querySelector("meter");
    if (span.textContent !== label) span.textContent = label;
    meter.min = 0; meter.max = cap || nl || 1; meter.value = nl;
    meter.setAttribute("aria-label", name + " level");
  });
  // Alerts are announced when they appear: redrawn only when the faults change.
  const problems = (x) => [x.faults, x.connected, x.disconnected_reason, x.store_problem, x.link_problem].join("|");
  if (!before || problems(before) !== problems(m)) renderFaults(m);
  if (before && before.connected && !m.connected) {
    toast("The machine is not connected" + (m.disconnected_reason ? ": " + m.disconnected_reason : ""), "error");
  }
  if (before && !before.store_problem && m.store_problem) toast("The job store cannot write: " + m.store_problem, "error");
  if (before && (m.faults & ~before.faults)) {
    for (const [bit, what] of FAULTS) if (m.faults & ~before.faults & bit) toast(what, "error");
  }
  if (m.store_problem) setLink("job store: " + m.store_problem);
  if (!before || before.queue_held_by !== m.queue_held_by) renderJobs();
}

// Besides the machine's own faults, what keeps edod from printing: the machine not
// connected, a link not answering as it should, a job store that cannot write.
function hostProblems(m) {
  const found = [];
  if (!m.connected) {
    found.push([0, "The machine is not connected" + (m.disconnected_reason ? ": " + m.disconnected_reason : "") + ".",
      "Check its power and cable; edod connects again by itself, and an interrupted job resumes from the queue.", null]);
  }
  if (m.link_problem) found.push([0, m.link_problem + ".", "edod is asking the machine; if it stays silent the link is declared lost.", null]);
  if (m.store_problem) {
    found.push([0, "The job store cannot write: " + m.store_problem + ".",
      "Free space for edod's state directory: new jobs and state changes are refused until it can write again.", null]);
  }
  return found;
}

function renderFaults(m) {
  const box = $("faults");
  box.replaceChildren();
  const found = hostProblems(m).concat(FAULTS.filter(([bit]) => m.faults & bit));
  if (!found.length) { box.append(Object.assign(document.createElement("p"), { textContent: "None." })); return; }
  for (const [, what, todo, action] of found) {
    const div = document.createElement("div");
    div.className = "fault";
    div.setAttribute("role", "alert");
    div.append(Object.assign(document.createElement("p"), { textContent: what + " " + todo }));
    if (action === "refill") {
      const b = document.createElement("button");
      b.type = "button"; b.textContent = "Syringes refilled";
      b.addEventListener("click", () => call("machine.refill").catch((e) => setLink(e.message)));
      div.append(b);
    }
    box.append(div);
  }
}

// ---- drawing a layer ------------------------------------------------------------------

// Roads as planned: extrusions in their composition's colour, travels thin and grey.
function drawLayer(svg, l) {
  svg.replaceChildren();
  const pts = l.moves.filter(Boolean);
  if (!pts.length) return;
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (const [x, y] of pts) { x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y); }
  const pad = Math.max(x1 - x0, y1 - y0, 1) * 0.05;
  svg.setAttribute("viewBox", [x0 - pad, -(y1 + pad), x1 - x0 + 2 * pad, y1 - y0 + 2 * pad].join(" "));
  const width = Math.max(x1 - x0, y1 - y0, 1) / 250;
  const planned = document.createElementNS(SVG, "g");
  planned.setAttribute("opacity", "0.45");
  const done = document.createElementNS(SVG, "g");
  done.id = svg.id + "-done";
  let at = l.start || pts[0];
  svg.segments = [];
  l.moves.forEach((m, i) => {
    if (!m) { svg.segments.push(null); return; }
    const line = document.createElementNS(SVG, "line");
    line.setAttribute("x1", at[0]); line.setAttribute("y1", -at[1]);
    line.setAttribute("x2", m[0]); line.setAttribute("y2", -m[1]);
    line.setAttribute("stroke", m[2] || "#bbb");
    line.setAttribute("stroke-width", m[2] ? width * 3 : width);
    line.setAttribute("stroke-linecap", "round");
    planned.append(line);
    svg.segments.push(line);
    at = [m[0], m[1]];
  });
  svg.append(planned, done);
  svg.dataset.drawn = "0";
  $("layer-caption").textContent = "Layer " + (l.layer + 1) + (l.layers ? " of " + l.layers : "") + (l.z_mm != null ? ", z = " + l.z_mm.toFixed(2) + " mm" : "");
}

// The moves the machine has executed, over the plan: bold, in the composition predicted
// to leave the nozzle (the plan's design where there is no prediction).
function drawExecuted() {
  const svg = $("layer-view"), l = state.layer, p = state.progress;
  if (!l || !p || l.job !== p.job_id || !svg.segments || l.first_index === null) return;
  const upto = Math.max(0, Math.min(p.executed - l.first_index, l.moves.length));
  const done = $("layer-view-done");
  let drawn = Number(svg.dataset.drawn || 0);
  if (upto < drawn) { done.replaceChildren(); drawn = 0; }
  for (let i = drawn; i < upto; i++) {
    const seg = svg.segments[i];
    if (!seg) continue;
    const c = seg.cloneNode();
    c.setAttribute("stroke-width", Number(seg.getAttribute("stroke-width")) * 1.3);
    const m = l.moves[i];
    c.setAttribute("stroke", m[2] ? (m[4] || m[2]) : "#333");
    done.append(c);
  }
  svg.dataset.drawn = String(upto);
  svg.dataset.executed = String(p.executed);
  renderActive();
}

// ---- the whole part, stacked -------------------------------------------------------------

// Layers of a job drawn in the stacked view at most (spread evenly, the last always).
const STACK_LAYERS = 40;

// The job's layer views for the stacked view, fetched one after another (edod plans a
// stored job's layers as far as asked, once).
async function loadStack(job, layers) {
  const key = job + "/" + layers;
  if (state.stack && state.stack.key === key) return;
  const s = { key, job, layers, drawn: new Map(), current: null };
  state.stack = s;
  const step = Math.max(1, Math.ceil(layers / STACK_LAYERS));
  const wanted = [];
  for (let l = 0; l < layers; l += step) wanted.push(l);
  if (wanted[wanted.length - 1] !== layers - 1) wanted.push(layers - 1);
  for (const l of wanted) {
    if (state.stack !== s) return;
    let v;
    try {
      const r = await api("/api/jobs/" + job + "/layers/" + l);
      if (!r.ok) return;
      v = await r.json();
    } catch { return; }
    if (state.stack !== s) return;
    s.drawn.set(l, { z: v.z_mm ?? (l + 1) * 0.2, roads: roadsOf(v) });
    drawStack();
  }
}

// A layer view's extrusions as segments [x0, y0, x1, y1, colour].
function roadsOf(v) {
  const roads = [];
  let at = v.start;
  for (const m of v.moves) {
    if (!m) continue;
    if (m[2] && at) roads.push([at[0], at[1], m[0], m[1], m[2]]);
    at = [m[0], m[1]];
  }
  return roads;
}

// The stacked view: each layer drawn seen from the front left (x and y on a 30° axonometry,
// z up, exaggerated when the part is flat), bottom first; the layers still to print faint,
// the current one outlined.
function drawStack() {
  const s = state.stack, canvas = $("stack");
  if (!s || !canvas) return;
  const current = state.progress && state.progress.job_id === s.job ? (state.progress.layer ?? 0) : null;
  s.current = current;
  const ratio = window.devicePixelRatio || 1;
  const w = Math.max(200, Math.round(canvas.clientWidth * ratio)), h = Math.round(w * 0.6);
  if (canvas.width !== w) canvas.width = w;
  if (canvas.height !== h) canvas.height = h;
  const g = canvas.getContext("2d");
  g.clearRect(0, 0, w, h);
  const layers = [...s.drawn.entries()].sort((a, b) => a[0] - b[0]);
  if (!layers.length) return;
  let [x0, y0, z0, x1, y1, z1] = [Infinity, Infinity, Infinity, -Infinity, -Infinity, -Infinity];
  for (const [, l] of layers) {
    z0 = Math.min(z0, l.z); z1 = Math.max(z1, l.z);
    for (const r of l.roads) {
      x0 = Math.min(x0, r[0], r[2]); x1 = Math.max(x1, r[0], r[2]);
      y0 = Math.min(y0, r[1], r[3]); y1 = Math.max(y1, r[1], r[3]);
    }
  }
  if (!isFinite(x0)) return;
  const span = Math.max(x1 - x0, y1 - y0, 1e-3);
  const zs = Math.max(1, (0.5 * span) / Math.max(z1 - z0, 1e-3));
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  const u = (x, y) => (x - cx - (y - cy)) * 0.866;
  const v = (x, y, z) => (x - cx + (y - cy)) * 0.5 - (z - z0) * zs;
  const uSpan = (span * 2) * 0.866, vSpan = span + (z1 - z0) * zs;
  const k = Math.min(w / uSpan, h / vSpan) * 0.9;
  const ox = w / 2, oy = h / 2 + ((z1 - z0) * zs * k) / 2;
  const lw = Math.max(1, k * 0.3);
  for (const [index, l] of layers) {
    const ahead = current !== null && index > current;
    g.globalAlpha = ahead ? 0.12 : 0.9;
    g.lineWidth = lw;
    for (const r of l.roads) {
      g.strokeStyle = r[4];
      g.beginPath();
      g.moveTo(ox + u(r[0], r[1]) * k, oy + v(r[0], r[1], l.z) * k);
      g.lineTo(ox + u(r[2], r[3]) * k, oy + v(r[2], r[3], l.z) * k);
      g.stroke();
    }
  }
  // The current layer (or the nearest drawn below it), outlined over everything.
  const mark = current === null ? null : layers.filter(([i]) => i <= current).pop();
  if (mark) {
    const [, l] = mark;
    g.globalAlpha = 1;
    g.strokeStyle = getComputedStyle(document.documentElement).getPropertyValue("--fg") || "#000";
    g.lineWidth = lw * 2.5;
    g.beginPath();
    for (const r of l.roads) {
      g.moveTo(ox + u(r[0], r[1]) * k, oy + v(r[0], r[1], l.z) * k);
      g.lineTo(ox + u(r[2], r[3]) * k, oy + v(r[2], r[3], l.z) * k);
    }
    g.globalAlpha = 0.35;
    g.stroke();
    g.globalAlpha = 1;
  }
  canvas.dataset.layersDrawn = String(layers.length);
  canvas.dataset.current = current === null ? "" : String(current);
  $("stack-caption").textContent = "Job " + s.job + ": " + layers.length + " of " + s.layers + " layers drawn" +
    (current !== null ? ", layer " + (current + 1) + " printing" : "") +
    (zs > 1.01 ? "; height drawn " + zs.toFixed(0) + " times" : "") + ".";
}

// ---- e-stop -----------------------------------------------------------------------

$("estop").addEventListener("click", async () => {
  const ack = $("estop-ack");
  ack.hidden = false;
  ack.textContent = "E-stop sent… waiting for the machine's acknowledgement";
  try {
    // Over the WebSocket when it is open, else (or if it is lost meanwhile) by POST;
    // an error edod answers is shown, not sent again.
    const t = await call("machine.estop")
      .catch((e) => (e.code === undefined ? post("machine.estop") : Promise.reject(e)));
    ack.textContent = t.acked_after_us !== null
      ? "E-stop acknowledged by the machine after " + (t.acked_after_us / 1000).toFixed(1) + " ms"
      : "E-stop written after " + (t.written_after_us / 1000).toFixed(1) + " ms; the machine has NOT acknowledged it: cut its power";
    ack.dataset.acked = t.acked_after_us !== null ? "yes" : "no";
    toast(ack.textContent, "error");
  } catch (e) {
    ack.textContent = "E-stop failed: " + e.message + ": cut the machine's power";
    ack.dataset.acked = "no";
  }
});

// ---- submit -------------------------------------------------------------------------

function readFile(input, asBase64) {
  const f = input.files[0];
  if (!f) return Promise.resolve(null);
  return new Promise((resolve, reject) => {
    const r = new FileReader();
    r.onerror = () => reject(r.error);
    r.onload = () => resolve(asBase64 ? String(r.result).split(",", 2)[1] : r.result);
    if (asBase64) r.readAsDataURL(f); else r.readAsText(f);
  });
}

// The plan of the chosen files, kept by edod under its id; its layers' images are the
// SVG previews `edoctl plan --svg` draws.
async function preview() {
  const r = await api("/api/preview", {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(state.preview.ask),
  });
  const v = await r.json();
  if (!r.ok) throw new Error(v.error ? v.error.message : r.statusText);
  return v;
}

$("submit-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  $("submit-result").textContent = "planning the preview…";
  try {
    const job = await readFile($("job-file"), false);
    const mesh = await readFile($("mesh-file"), true);
    const ask = { job };
    if (mesh) ask.mesh_base64 = mesh;
    state.preview = { ask };
    showPreview(await preview());
    $("submit-result").textContent = "";
  } catch (err) {
    $("submit-result").textContent = "preview failed: " + err.message;
  }
});

function showPreview(v) {
  state.preview.id = v.id;
  state.preview.layers = v.layers.length;
  $("preview").hidden = false;
  const n = v.layers.length;
  $("preview-summary").textContent = (v.name ? v.name + ": " : "") + n + " layers, " + (v.total_moves ?? 0) + " moves" + (v.ok ? "" : ": cannot be printed as it is");
  showTakes(v);
  const ul = $("preview-problems");
  ul.replaceChildren();
  for (const p of v.problems) {
    ul.append(Object.assign(document.createElement("li"), { textContent: p, className: "problem" }));
  }
  // What may be submitted but should be known first (layers resting on nothing).
  const warnings = v.warnings || [];
  for (const w of warnings) {
    ul.append(Object.assign(document.createElement("li"), { textContent: w, className: "warning" }));
  }
  $("preview-warnings").hidden = v.problems.length === 0 && warnings.length === 0;
  const slider = $("preview-layer");
  slider.max = String(Math.max(0, n - 1));
  slider.value = "0";
  slider.disabled = n === 0;
  $("confirm").disabled = !v.ok;
  showPreviewLayer(0);
}

// What the plan takes: machine time, material per syringe, and where the part stands
// on the bed.
function showTakes(v) {
  const rows = [["Machine time", v.time_s != null ? fmtEta(v.time_s) + " planned (at the planned feeds)" : "—"],
    ["Material", materialText(v.used_nl)]];
  const e = v.extent_mm, bed = state.server?.machine?.build_volume_mm;
  if (e) {
    const r = (k) => e.min[k].toFixed(1) + "–" + e.max[k].toFixed(1);
    rows.push(["Placement", "x " + r(0) + ", y " + r(1) + " mm, " + e.max[2].toFixed(1) + " mm high" +
      (bed ? ", on the " + bed[0] + " × " + bed[1] + " mm bed" : "")]);
  }
  const dl = $("preview-takes");
  dl.replaceChildren(...rows.flatMap(([k, val]) => [
    Object.assign(document.createElement("dt"), { textContent: k }),
    Object.assign(document.createElement("dd"), { textContent: val }),
  ]));
}

// Layer `layer`'s image, fetched with the token and shown from a blob: URL. A preview
// edod no longer keeps is made again once.
async function showPreviewLayer(layer, again = true) {
  const img = $("preview-image"), p = state.preview;
  if (!p || p.layers === 0) {
    img.hidden = true;
    $("preview-layer-out").textContent = "no layers";
    return;
  }
  $("preview-layer-out").textContent = (layer + 1) + " of " + p.layers;
  const r = await api("/api/previews/" + p.id + "/layers/" + layer);
  if (state.preview !== p || Number($("preview-layer").value) !== layer) return;
  if (r.status === 404 && again) {
    showPreview(await preview());
    $("preview-layer").value = String(layer);
    return showPreviewLayer(layer, false);
  }
  if (!r.ok) {
    const v = await r.json().catch(() => null);
    img.hidden = true;
    $("preview-layer-out").textContent += ": " + (v && v.error ? v.error.message : r.statusText);
    return;
  }
  const url = URL.createObjectURL(await r.blob());
  if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
  img.src = url;
  img.alt = "Layer " + (layer + 1) + " of " + p.layers + " as planned: contours and offsets coloured by composition";
  img.dataset.layer = String(layer);
  img.hidden = false;
}

$("preview-layer").addEventListener("input", (e) => {
  showPreviewLayer(Number(e.target.value)).catch((err) => { $("submit-result").textContent = err.message; });
});

$("confirm").addEventListener("click", async () => {
  try {
    const r = await call("job.submit", state.preview.ask);
    $("submit-result").textContent = "job " + r.id + " submitted: " + r.state;
    await refreshJob(r.id, r.state);
    renderJobs();
    $("preview").hidden = true;
    $("submit-form").reset();
    location.hash = "#queue";
  } catch (err) {
    $("submit-result").textContent = "refused: " + err.message;
  }
});

$("discard").addEventListener("click", () => {
  $("preview").hidden = true;
  state.preview = null;
  $("job-file").focus();
});

// ---- console --------------------------------------------------------------------------

// edod's log lines (log.recent), read every second while connected; newest last.
async function pollLog() {
  if (state.logTimer) clearTimeout(state.logTimer);
  try {
    if (state.ws && state.ws.readyState === WebSocket.OPEN) {
      const lines = await call("log.recent", state.logSeq ? { after: state.logSeq } : {});
      for (const l of lines) addLogLine(l);
      if (lines.length) state.logSeq = lines[lines.length - 1].seq;
    }
  } catch { /* offline: the notice says so */ }
  state.logTimer = setTimeout(pollLog, 1000);
}

function addLogLine(l) {
  const ol = $("console");
  const atEnd = ol.scrollTop + ol.clientHeight >= ol.scrollHeight - 4;
  const li = document.createElement("li");
  li.className = "log-" + l.level;
  li.textContent = new Date(l.at_ms).toLocaleTimeString() + " " + l.level.toUpperCase() +
    (l.job_id ? " job " + l.job_id : "") + ": " + l.message;
  ol.append(li);
  while (ol.children.length > 500) ol.firstElementChild.remove();
  if (atEnd) ol.scrollTop = ol.scrollHeight;
}

connect();
