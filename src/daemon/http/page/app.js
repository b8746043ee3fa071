// edo dashboard: the JSON-RPC API of docs/api.md over /websocket (docs/http.md).
// Plain modern JavaScript, no build step; every control has an accessible name.
"use strict";

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";

const state = {
  ws: null, nextId: 1, pending: new Map(), jobs: new Map(), machine: null,
  progress: null, server: null, layer: null, preview: null, token: sessionStorage.getItem("edo-token"),
};

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
  done: ["delete"], failed: ["delete"], cancelled: ["delete"],
};

function fmtEta(s) {
  if (s === null || s === undefined) return "—";
  s = Math.round(s);
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), r = s % 60;
  return (h ? h + " h " : "") + (h || m ? m + " min " : "") + r + " s";
}

// A job's state, and why where edod gives a reason (an interruption, a failure).
function stateText(j) {
  return j.reason && j.state !== "done" ? j.state + ": " + j.reason : j.state;
}

function progressText(j) {
  const p = j.progress;
  if (!p) {
    if (j.state === "done") return "done";
    return j.total_moves ? j.total_moves + " moves" : "—";
  }
  const layer = p.layers ? "layer " + ((p.layer ?? 0) + 1) + " of " + p.layers : "planning layers";
  const moves = p.executed + (p.total ? " of " + p.total : "") + " moves";
  return layer + ", " + moves;
}

// A row is made anew only for a new job or a new state (its buttons change); else only
// its text cells that changed are written, so a button stays under the pointer and
// keeps the keyboard focus while progress streams in.
function renderJobs() {
  const body = $("jobs");
  const jobs = [...state.jobs.values()].sort((a, b) => a.id - b.id);
  $("no-jobs").hidden = jobs.length > 0;
  const keep = new Set();
  for (const j of jobs) {
    const cells = [String(j.id), j.name, stateText(j), progressText(j), fmtEta(j.progress?.eta_s)];
    let tr = $("job-" + j.id);
    if (!tr || tr.dataset.state !== j.state) {
      const row = jobRow(j, cells);
      if (tr) tr.replaceWith(row); else body.append(row);
      tr = row;
    } else {
      cells.forEach((text, i) => {
        const td = tr.children[i];
        if (td && td.textContent !== text) td.textContent = text;
      });
    }
    keep.add(tr);
  }
  for (const tr of [...body.children]) if (!keep.has(tr)) tr.remove();
}

function jobRow(j, cells) {
  const tr = document.createElement("tr");
  tr.id = "job-" + j.id;
  tr.dataset.state = j.state;
  cells.forEach((text, i) => {
    const td = document.createElement("td");
    td.textContent = text;
    if (i === 2) td.className = "state";
    tr.append(td);
  });
  const td = document.createElement("td");
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

// What cannot be undone is asked first, naming the job.
const CONFIRM = {
  cancel: (j) => "Cancel job " + j.id + " (" + j.name + ")? It stops for good: a cancelled job cannot be resumed.",
  delete: (j) => "Delete job " + j.id + " (" + j.name + ") and its record?",
};

async function jobAction(action, j, button) {
  const id = j.id;
  if (CONFIRM[action] && !window.confirm(CONFIRM[action](j))) return;
  button.disabled = true;
  try {
    const r = await call("job." + action, { id });
    if (action === "delete") state.jobs.delete(id);
    else await refreshJob(id, r.state);
    renderJobs();
  } catch (e) {
    setLink("job " + id + ": " + e.message);
    button.disabled = false;
  }
}

async function refreshJob(id, fallbackState) {
  try {
    state.jobs.set(id, await call("job.get", { id }));
  } catch {
    const j = state.jobs.get(id);
    if (j && fallbackState) j.state = fallbackState;
  }
}

async function onJobState(p) {
  const j = state.jobs.get(p.job_id);
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
  if (!p || !j) {
    $("active").textContent = "No job is printing.";
    $("composition").textContent = "No job is printing.";
    return;
  }
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
  if (!before || before.faults !== m.faults) renderFaults(m);
  if (m.store_problem) setLink("job store: " + m.store_problem);
}

function renderFaults(m) {
  const box = $("faults");
  box.replaceChildren();
  const found = FAULTS.filter(([bit]) => m.faults & bit);
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

connect();
