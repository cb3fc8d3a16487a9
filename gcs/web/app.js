// fleetgcs dashboard: plain JS, no build step, no network beyond the daemon (and optional tiles).
// State comes from the WebSocket stream (/api/v1/stream) plus a few REST reads; the map is a
// local equirectangular projection drawn on a canvas, so it works offline.
"use strict";

const R = 6371008.8;
const COLORS = ["#1f6feb", "#d9480f", "#2b8a3e", "#ae3ec9", "#e8590c", "#0b7285", "#c2255c", "#5c940d"];
const MAX_TRACK = 4000;

const S = {
  agents: new Map(),      // identity -> {view, status, received, track: [[lat, lon]], color}
  rows: new Map(),        // identity -> <tr> of the fleet table
  origin: null,           // [lat0, lon0] of the local projection
  view: { cx: 0, cy: 0, scale: 2 },  // map centre (m east/north) and pixels per metre
  mission: null,          // {id, name, progress, geometry, coverage}
  preview: null,          // PlanPreview of the last preview
  drawing: null,          // [[lat, lon], ...] while drawing, else null
  area: null,             // the chosen search area [[lat, lon], ...]
  geofence: null,
  events: [],
  clockOffset: 0,         // server_time - Date.now()/1000
  tileUrl: null,
  tiles: new Map(),
  ws: null,
  connected: false,
  dirty: true,
  userMoved: false,
  tracksSince: 0,         // server time of the last "clear tracks": older history is not redrawn
  cluster: null,          // GET /api/v1/cluster when the daemon is one of a cluster (docs/cluster.md)
};
window.fleetgcs = S;      // for tests and the curious

const $ = (id) => document.getElementById(id);
const canvas = $("map");
const ctx = canvas.getContext("2d");

// --- token & HTTP ---------------------------------------------------------------------------------
(function initToken() {
  const m = location.hash.match(/token=([^&]+)/);
  if (m) {
    localStorage.setItem("fleetgcs.token", decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname + location.search);
  }
  $("token").value = localStorage.getItem("fleetgcs.token") || "";
  $("token").addEventListener("change", () => localStorage.setItem("fleetgcs.token", $("token").value.trim()));
})();

async function api(method, path, body) {
  const headers = { "Content-Type": "application/json" };
  const token = $("token").value.trim();
  if (token) headers.Authorization = "Bearer " + token;
  const res = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  const text = await res.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (e) { data = text; }
  if (!res.ok) {
    const msg = data && data.detail ? `${data.title}: ${data.detail}` : `HTTP ${res.status}`;
    const err = new Error(msg);
    err.problem = data; // the problem document: extension members such as a bad area's outline
    throw err;
  }
  return data;
}

function toast(text, error) {
  const t = $("toast");
  t.textContent = text;
  t.className = "show" + (error ? " error" : "");
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => { t.className = ""; }, error ? 6000 : 2500);
}

async function act(label, fn) {
  try {
    const r = await fn();
    toast(label + ": done");
    return r;
  } catch (e) {
    toast(label + ": " + e.message, true);
    return null;
  }
}

// --- projection -------------------------------------------------------------------------------------
function toLocal(lat, lon) {
  const [lat0, lon0] = S.origin;
  return [((lon - lon0) * Math.PI / 180) * R * Math.cos(lat0 * Math.PI / 180), ((lat - lat0) * Math.PI / 180) * R];
}
function fromLocal(x, y) {
  const [lat0, lon0] = S.origin;
  return [lat0 + (y / R) * 180 / Math.PI, lon0 + (x / (R * Math.cos(lat0 * Math.PI / 180))) * 180 / Math.PI];
}
function toScreen(lat, lon) {
  const [x, y] = toLocal(lat, lon);
  return [canvas.width / 2 + (x - S.view.cx) * S.view.scale, canvas.height / 2 - (y - S.view.cy) * S.view.scale];
}
function screenToLatLon(px, py) {
  return fromLocal(S.view.cx + (px - canvas.width / 2) / S.view.scale, S.view.cy - (py - canvas.height / 2) / S.view.scale);
}
S.toScreen = (lat, lon) => {  // CSS pixels relative to the canvas, for tests
  const [x, y] = toScreen(lat, lon);
  const k = canvas.clientWidth / canvas.width;
  return [x * k, y * k];
};
function ensureOrigin(lat, lon) { if (!S.origin) { S.origin = [lat, lon]; S.dirty = true; } }

// --- agents -----------------------------------------------------------------------------------------
// A drone keeps its colour across reloads and daemon restarts: from its name, not its arrival order
// (drone-3 is the third colour; other names hash).
function colorOf(identity) {
  const m = /(\d+)$/.exec(identity);
  let n = m ? Number(m[1]) - 1 : 0;
  if (!m) for (const ch of identity) n = (n * 31 + ch.charCodeAt(0)) >>> 0;
  return COLORS[n % COLORS.length];
}

function agentEntry(identity) {
  let a = S.agents.get(identity);
  if (!a) {
    a = { identity, view: null, status: null, received: 0, track: [], color: colorOf(identity) };
    S.agents.set(identity, a);
    renderDronePicks();
  }
  return a;
}

// Why a drone is held: its holds by owner (operator, collision...) from the daemon's authority.
async function refreshHeld(a) {
  try {
    const c = await api("GET", `/api/v1/agents/${encodeURIComponent(a.identity)}/authority`);
    const holds = Object.entries(c.holds || {}).map(([owner, why]) => `${owner}: ${why}`);
    a.held = holds.join("; ") || (c.order ? `${c.order} (${c.order_source})` : "paused");
  } catch (e) { a.held = "paused"; }
  S.tableDirty = true; S.dirty = true;
}

// "-0" (a drone on the ground a few cm below home) reads as 0.
function fmtNum(v, digits) { const s = v.toFixed(digits); return /^-0(\.0*)?$/.test(s) ? s.slice(1) : s; }

function excludedWhy(identity) {
  const p = S.mission && S.mission.progress;
  const ag = p && p.state === "running" && p.agents.find((x) => x.agent === identity && x.excluded);
  return ag ? ag.why || "excluded" : null;
}

function onStatus(msg) {
  const a = agentEntry(msg.agent);
  const st = msg.status;
  if (Boolean(st.paused) !== Boolean(a.status && a.status.paused) || (st.paused && a.held === undefined)) {
    a.held = st.paused ? "" : undefined;
    if (st.paused) refreshHeld(a);
  }
  a.status = st;
  a.received = msg.received;
  const pos = st.position;  // absent until the vehicle has a GPS fix
  if (pos) {
    ensureOrigin(pos.lat, pos.lon);
    const last = a.track[a.track.length - 1];
    if (!last || last[0] !== pos.lat || last[1] !== pos.lon) {
      a.track.push([pos.lat, pos.lon, st.mission_id || null]);
      if (a.track.length > MAX_TRACK) a.track.splice(0, a.track.length - MAX_TRACK);
    }
  }
  S.dirty = true;
  S.tableDirty = true;
}

function onEvent(ev) {
  S.events.unshift(ev);
  if (S.events.length > 300) S.events.length = 300;
  renderEvents();
  if (ev.kind.startsWith("mission_") || ev.kind === "sync_released" || ev.kind.startsWith("fleet_")) {
    if (ev.mission_id && (!S.mission || S.mission.id !== ev.mission_id) && ev.kind === "mission_started") {
      loadMission(ev.mission_id);
    } else {
      refreshMission();
    }
  }
  if (ev.kind === "geofence_sent") loadGeofence();
  if (ev.kind.startsWith("retask_") && ev.data && ev.data.id && S.mission && ev.mission_id === S.mission.id) {
    S.mission.retask.set(ev.data.id, ev.data);
    renderRetask();
  }
  if (ev.kind === "agent_retired" && ev.agent) {
    S.agents.delete(ev.agent);
    renderDronePicks();
    S.dirty = S.tableDirty = true;
  }
}

// --- stream -----------------------------------------------------------------------------------------
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  // A browser cannot set headers on a WebSocket: the token (needed when the daemon listens beyond
  // loopback) travels as the subprotocol "bearer.<token>" beside "fleetgcs" (gcs/http/guard.py).
  const token = $("token").value.trim();
  const ws = new WebSocket(`${proto}//${location.host}/api/v1/stream?max_rate_hz=10`,
    token ? ["fleetgcs", "bearer." + token] : undefined);
  S.ws = ws;
  ws.onopen = () => { S.connected = true; setLinkState(); };
  ws.onclose = () => { S.connected = false; setLinkState(); setTimeout(connect, 1000); };
  ws.onerror = () => ws.close();
  ws.onmessage = (e) => {
    let batch;
    try { batch = JSON.parse(e.data); } catch (err) { return; }
    for (const msg of batch) {
      if (msg.type === "status") onStatus(msg);
      else if (msg.type === "event") onEvent(msg.event);
      else if (msg.type === "hello") onHello(msg);
      else if (msg.type === "coverage") onCoverage(msg);
    }
  };
}

function onHello(msg) {
  S.clockOffset = msg.server_time - Date.now() / 1000;
  for (const v of msg.agents) {
    const a = agentEntry(v.identity);
    a.view = v;
    if (v.status) {
      a.status = v.status;
      a.received = msg.server_time - (v.link_age_s || 0);
    }
    if (v.status && v.status.position) {
      ensureOrigin(v.status.position.lat, v.status.position.lon);
    } else if (v.home) {
      ensureOrigin(v.home.lat, v.home.lon);
    }
  }
  loadTracks();
  S.dirty = S.tableDirty = true;
}

function setLinkState() {
  const el = $("link-state");
  el.textContent = S.connected ? "live" : "offline";
  el.className = "badge " + (S.connected ? "ok" : "bad");
}

async function loadTracks() {
  for (const a of S.agents.values()) {
    try {
      const since = S.tracksSince ? `&since=${S.tracksSince}` : "";
      const samples = await api("GET", `/api/v1/agents/${encodeURIComponent(a.identity)}/history?limit=1500${since}`);
      const pts = samples.filter((s) => s.status.position)
        .map((s) => [s.status.position.lat, s.status.position.lon, s.status.mission_id || null]);
      a.track = pts.concat(a.track).slice(-MAX_TRACK);
    } catch (e) { /* agent gone: keep what we have */ }
  }
  S.dirty = true;
}

// --- missions ---------------------------------------------------------------------------------------
async function loadMission(id) {
  S.mission = { id, name: id, progress: null, geometry: null, coverage: null, live: null, retask: new Map() };
  renderRetask();
  try { S.mission.geometry = await api("GET", `/api/v1/missions/${id}/plan`); } catch (e) { /* none */ }
  await refreshMission();
  refreshCoverage();
  try {
    for (const d of await api("GET", `/api/v1/missions/${id}/retask`)) S.mission.retask.set(d.id, d);
    renderRetask();
  } catch (e) { /* no survey */ }
}

// The stream's coverage message (docs/api.md): seen %, distance, ETA and the raster as bit masks.
function unpackMask(b64, n) {
  const bytes = atob(b64);
  const out = new Uint8Array(n);
  for (let i = 0; i < n; i++) out[i] = (bytes.charCodeAt(i >> 3) >> (7 - (i & 7))) & 1;
  return out;
}

function onCoverage(msg) {
  if (!S.mission || S.mission.id !== msg.mission_id) {
    if (!S.mission || !S.mission.progress || S.mission.progress.state !== "running") loadMission(msg.mission_id);
    return;
  }
  const g = msg.grid;
  const n = g.rows * g.cols;
  const inside = unpackMask(g.inside, n), seen = unpackMask(g.seen, n);
  S.mission.live = { msg, inside, seen, ...coverageShapes(g, inside, seen) };
  S.mission.coverage = msg.covered_pct;
  S.mission.unseen = null;  // the raster replaces the polled GeoJSON
  S.dirty = true;
  renderCoverageText();
}

function renderCoverageText() {
  const live = S.mission && S.mission.live;
  if (!live) return;
  const m = live.msg;
  let text = `covered ${m.covered_pct.toFixed(1)} % · flown ${Math.round(m.flown_m)}/${Math.round(m.planned_m)} m`;
  const p = S.mission.progress;
  if (m.eta_s != null && (!p || p.state === "running")) text += ` · ETA ${fmtTime(m.eta_s)}`;
  $("coverage").textContent = text;
}

function renderRetask() {
  const box = $("retask");
  box.innerHTML = "";
  if (!S.mission) return;
  for (const d of S.mission.retask.values()) {
    const div = document.createElement("div");
    div.className = "retask" + (d.state === "pending" ? "" : " answered");
    div.dataset.id = d.id;
    div.dataset.state = d.state;
    const legs = (d.legs || []).map((l) => `<div>${esc(l.ident)}: +${Math.round(l.survey_m)} m, ${fmtTime(l.time_s)}, ${l.energy_wh.toFixed(1)} Wh</div>`).join("");
    const head = `<b>re-task ${esc(d.id)}</b> ${esc(d.dropped)} left (${esc(d.why)}): ${esc(d.reason)}`;
    const tail = d.state === "pending"
      ? `<button class="accept">Accept</button> <button class="reject danger">Reject</button>`
      : `<span class="muted">${esc(d.state)}${d.by ? " by the " + esc(d.by) : ""}</span>`;
    div.innerHTML = `<div>${head}</div><div class="legs">${legs}</div><div>${tail}</div>`;
    if (d.state === "pending") {
      div.querySelector(".accept").onclick = () => answerRetask(d.id, "accept");
      div.querySelector(".reject").onclick = () => answerRetask(d.id, "reject");
    }
    box.appendChild(div);
  }
}

async function answerRetask(id, answer) {
  const mission = S.mission && S.mission.id;
  if (!mission) return;
  const r = await act(`re-task ${answer}`, () => api("POST", `/api/v1/missions/${mission}/retask/${id}/${answer}`));
  if (r && S.mission && S.mission.id === mission) { S.mission.retask.set(r.id, r); renderRetask(); }
}

async function refreshMission() {
  if (!S.mission) return;
  try {
    const p = await api("GET", `/api/v1/missions/${S.mission.id}`);
    S.mission.progress = p;
    S.mission.name = p.name;
  } catch (e) { return; }
  renderMission();
  S.dirty = true;
}

async function refreshCoverage() {
  if (!S.mission || !S.mission.geometry || !S.mission.geometry.area) return;
  try {
    // the daemon's seen/unseen raster (flown tracks, footprint by height): unseen cells drawn in red
    const c = await api("GET", `/api/v1/missions/${S.mission.id}/coverage?detail=geojson`);
    if (S.mission.live) return;  // the stream's message is newer and carries distance and ETA
    S.mission.coverage = c.covered_pct;
    S.mission.unseen = c.unseen || null;
    S.dirty = true;
    $("coverage").textContent = c.covered_pct == null ? "" : `covered ${c.covered_pct.toFixed(1)} %`;
  } catch (e) { /* ignore */ }
}

function renderMission() {
  const m = S.mission;
  const p = m && m.progress;
  $("mission-name").textContent = m ? m.name : "none";
  const state = p ? p.state : "idle";
  const paused = p && S.events.find((e) => e.mission_id === p.id && (e.kind === "mission_paused" || e.kind === "mission_resumed"));
  const shown = state === "running" && paused && paused.kind === "mission_paused" ? "paused" : state;
  const badge = $("mission-state");
  badge.textContent = shown;
  badge.className = "badge " + (shown === "running" ? "ok" : shown === "completed" ? "ok" : shown === "idle" ? "" : "warn");
  const running = state === "running";
  $("btn-pause").disabled = !running || shown === "paused";
  $("btn-resume").disabled = !running || shown !== "paused";
  $("btn-abort").disabled = !running;
  renderCoverageText();
  const box = $("progress");
  box.innerHTML = "";
  if (!p) return;
  for (const ag of p.agents) {
    const total = ag.last_step + 1;
    const done = ag.completed_step + 1;
    const pct = total > 0 ? Math.max(0, Math.min(100, (100 * done) / total)) : 0;
    const row = document.createElement("div");
    row.className = "progress" + (ag.done ? " done" : "");
    row.dataset.agent = ag.agent;
    row.dataset.pct = pct.toFixed(0);
    const what = ag.excluded ? `excluded: ${ag.why || "by the mission"}` : ag.done ? "done" : ag.waiting_sync != null ? `sync ${ag.waiting_sync}` : `step ${ag.step}`;
    row.innerHTML = `<span class="name"></span><span class="bar"><span class="fill" style="width:${pct}%"></span></span><span class="label">${done}/${total} ${what}</span>`;
    row.querySelector(".name").textContent = ag.agent;
    box.appendChild(row);
  }
}

async function missionCommand(kind, query) {
  if (!S.mission) return;
  const r = await act(kind, () => api("POST", `/api/v1/missions/${S.mission.id}/${kind}${query || ""}`));
  if (r) { S.mission.progress = r; renderMission(); }
}

// --- planner ----------------------------------------------------------------------------------------
function renderDronePicks() {
  const box = $("drone-picks");
  const checked = new Set([...box.querySelectorAll("input:checked")].map((i) => i.value));
  const fresh = box.children.length === 0;
  box.innerHTML = "";
  for (const a of [...S.agents.values()].sort((x, y) => x.identity.localeCompare(y.identity))) {
    const label = document.createElement("label");
    const input = document.createElement("input");
    input.type = "checkbox";
    input.value = a.identity;
    input.checked = fresh || checked.has(a.identity) || !box.dataset.touched;
    input.addEventListener("change", () => { box.dataset.touched = "1"; });
    label.appendChild(input);
    label.append(" " + a.identity);
    box.appendChild(label);
  }
}

function readArea() {
  if (S.area && S.area.length >= 3) return { area: S.area };
  const text = $("area-text").value.trim();
  if (!text) throw new Error("draw an area on the map, or paste/upload one");
  if (text.startsWith("<")) return { area_text: text }; // KML: the daemon parses it
  let doc;
  try { doc = JSON.parse(text); } catch (e) {
    throw new Error("the area is neither JSON (GeoJSON, QGC .plan, [[lat, lon], ...]) nor KML");
  }
  return Array.isArray(doc) ? { area: doc } : { area_document: doc };
}

function planRequest() {
  const req = {
    method: "search",
    name: "dashboard-search",
    pattern: $("pattern").value,
    division: $("division").value,
    swath_m: Number($("swath").value),
    altitude_m: Number($("altitude").value),
    speed_mps: Number($("speed").value),
    drones: [...$("drone-picks").querySelectorAll("input:checked")].map((i) => i.value),
  };
  return Object.assign(req, readArea());
}

async function preview() {
  let req;
  try { req = planRequest(); } catch (e) { toast(e.message, true); return; }
  S.crossings = null;
  const p = await act("preview", () => api("POST", "/api/v1/plan", req).catch((e) => { showBadArea(e.problem); throw e; }));
  S.preview = p;
  $("btn-start").disabled = !p;
  if (!p) { $("plan-result").textContent = ""; return; }
  if (p.area) { S.area = p.area; if (!S.origin) ensureOrigin(p.area[0][0], p.area[0][1]); }
  const rows = p.drones.map((d) => `${d.agent}: ${(d.length_m / 1000).toFixed(2)} km, ${fmtTime(d.time_s)}, ${d.energy_wh.toFixed(1)} Wh`);
  $("plan-result").innerHTML = `<div id="plan-summary">total ${(p.total_length_m / 1000).toFixed(2)} km, longest ${fmtTime(p.max_time_s)}, ${p.total_energy_wh.toFixed(1)} Wh` +
    (p.coverage_pct != null ? `, planned coverage ${p.coverage_pct.toFixed(1)} %` : "") + "</div>" + rows.map((r) => `<div>${r}</div>`).join("");
  S.dirty = true;
}

// A self-intersecting area comes back with its outline and crossings (lat/lon): draw them, so the
// operator sees where the boundary crosses itself instead of reading metres in the planner's frame.
function showBadArea(problem) {
  if (!problem || !Array.isArray(problem.area) || problem.area.length < 3) return;
  S.area = problem.area;
  S.crossings = Array.isArray(problem.crossings) ? problem.crossings : [];
  if (!S.origin) ensureOrigin(problem.area[0][0], problem.area[0][1]);
  S.userMoved = false; fitView(); S.dirty = true;
}

async function startMission() {
  let req;
  try { req = planRequest(); } catch (e) { toast(e.message, true); return; }
  const r = await act("start", () => api("POST", "/api/v1/missions/plan", req));
  if (!r) return;
  S.preview = null;
  $("btn-start").disabled = true;
  await loadMission(r.mission_id);
}

function fmtTime(s) { return s >= 60 ? `${Math.floor(s / 60)} min ${Math.round(s % 60)} s` : `${Math.round(s)} s`; }

// --- fleet table & events ---------------------------------------------------------------------------
const CONTROLS = [
  ["rtl", "RTL", "return to launch (aborts this drone's mission)"],
  ["land", "Land", "land where it is (aborts this drone's mission)"],
  ["hold", "Hold", "stop where it is, queue kept"],
  ["resume", "Resume", "continue after a hold"],
];

function tableRow(a) {
  // one row per drone, built once and updated in place, so a click on its buttons is never lost
  let tr = S.rows.get(a.identity);
  if (tr) return tr;
  tr = document.createElement("tr");
  tr.dataset.agent = a.identity;
  const cells = ["name", "mode", "armed", "alt num", "gs num", "batt num", "volt num", "gps", "step num", "link", "exc", "ctl"];
  for (const c of cells) { const td = document.createElement("td"); td.className = c; tr.appendChild(td); }
  tr.querySelector(".name").innerHTML = `<span style="color:${a.color}">&#9650;</span> `;
  tr.querySelector(".name").append(a.identity);
  const ctl = tr.querySelector(".ctl");
  for (const [cmd, label, title] of CONTROLS) {
    const b = document.createElement("button");
    b.textContent = label;
    b.title = title;
    b.dataset.cmd = cmd;
    b.className = cmd === "rtl" || cmd === "land" ? "danger" : cmd === "hold" ? "warn" : "";
    b.onclick = () => droneCommand(a.identity, cmd, label);
    ctl.appendChild(b);
  }
  S.rows.set(a.identity, tr);
  return tr;
}

function renderTable() {
  const body = $("fleet-table").querySelector("tbody");
  const now = Date.now() / 1000 + S.clockOffset;
  const agents = [...S.agents.values()].sort((x, y) => x.identity.localeCompare(y.identity));
  for (const [identity, tr] of S.rows) if (!S.agents.has(identity)) { tr.remove(); S.rows.delete(identity); }
  agents.forEach((a, index) => {
    const tr = tableRow(a);
    if (body.children[index] !== tr) body.insertBefore(tr, body.children[index] || null);
    const st = a.status;
    const pos = st && st.position;
    const bat = st && st.battery;
    const age = a.received ? Math.max(0, now - a.received) : null;
    const speed = st && st.velocity ? Math.hypot(st.velocity.vn, st.velocity.ve) : null;
    const set = (cls, text) => { const td = tr.querySelector("td." + cls.split(" ")[0]); if (td.textContent !== text) td.textContent = text; };
    // A pilot (RC or another ground station) flies it: the daemon sends it nothing (docs/cooperation.md).
    set("mode", st ? (st.pilot ? `PILOT ${st.pilot}` : st.mode + (st.paused ? " (held)" : "")) : "-");
    tr.querySelector("td.mode").classList.toggle("pilot", !!(st && st.pilot));
    set("armed", st ? (st.armed ? "yes" : "no") : "-");
    set("alt", pos ? fmtNum(pos.alt_rel, 1) + " m" : "-");
    set("gs", speed != null ? speed.toFixed(1) + " m/s" : "-");
    set("batt", bat && bat.pct != null ? bat.pct.toFixed(0) + " %" : "-");
    set("volt", bat && bat.voltage_v != null ? bat.voltage_v.toFixed(1) + " V" : "-");
    set("gps", st ? `${st.gps ? st.gps.fix : 0}/${st.gps ? st.gps.satellites : 0}` : "-");
    set("step", st && st.step >= 0 ? String(st.step) : "-");  // -1: no mission step yet
    set("link", age == null ? "-" : age.toFixed(1) + " s");
    tr.querySelector("td.link").classList.toggle("stale", age != null && age > 3);
    const out = excludedWhy(a.identity);  // why it is held or out of the mission, then its exceptions
    const notes = [...(st && st.paused ? [`held: ${a.held || "..."}`] : []), ...(out ? [`excluded: ${out}`] : [])];
    set("exc", [...notes, ...(st && st.exceptions ? st.exceptions : [])].join("; "));
  });
  $("fleet-count").textContent = `${S.agents.size} drones`;
}

// In a cluster the table lists every daemon's drones: commands go through /api/v1/cluster/fleet/*,
// which applies each drone's command on the daemon holding its link (through its vehicle authority).
function fleetPath(cmd) { return S.cluster ? `/api/v1/cluster/fleet/${cmd}` : `/api/v1/fleet/${cmd}`; }

// Commands that take one drone off its mission ask first, as the fleet-wide ones do.
const DRONE_QUESTIONS = {
  rtl: "Return {agent} to launch? Its part of the running mission is aborted.",
  land: "Land {agent} where it is? Its part of the running mission is aborted.",
};

async function droneCommand(identity, cmd, label) {
  const question = DRONE_QUESTIONS[cmd];
  if (question && !(await confirmAction(question.replace("{agent}", identity)))) {
    toast(`${label} ${identity}: cancelled`);
    return;
  }
  await act(`${label} ${identity}`, () => api("POST", fleetPath(cmd), { agents: [identity], reason: "dashboard" }));
}

// A modal question; resolves true only on Confirm (Escape and Cancel say no).
function confirmAction(text) {
  const dialog = $("confirm");
  $("confirm-text").textContent = text;
  return new Promise((resolve) => {
    dialog.onclose = () => resolve(dialog.returnValue === "ok");
    dialog.returnValue = "";
    dialog.showModal();
  });
}

async function fleetCommand(cmd, label, question) {
  if (question) {
    const now = Date.now() / 1000 + S.clockOffset;
    const n = [...S.agents.values()].filter((a) => a.received && now - a.received < 5).length;
    if (!(await confirmAction(question.replace("{n}", String(n))))) { toast(`${label}: cancelled`); return; }
  }
  await act(label, () => api("POST", fleetPath(cmd), {}));
}

function clearTracks() {
  S.tracksSince = Date.now() / 1000 + S.clockOffset;
  for (const a of S.agents.values()) a.track = [];
  S.dirty = true;
}

function renderEvents() {
  const ol = $("events");
  ol.innerHTML = S.events.slice(0, 200).map((e) =>
    `<li class="${e.severity}" data-kind="${esc(e.kind)}"><span class="t">${new Date(e.time * 1000).toLocaleTimeString([], { hourCycle: "h23" })}</span>` +
    `<b>${esc(e.kind)}</b>${e.agent ? " [" + esc(e.agent) + "]" : ""} ${esc(e.message)}</li>`).join("");
}

function esc(s) { return String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]); }

async function loadGeofence() {
  try { S.geofence = (await api("GET", "/api/v1/geofence")).geofence; S.dirty = true; } catch (e) { /* ignore */ }
}

// --- drawing ----------------------------------------------------------------------------------------
function resize() {
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(canvas.clientWidth * dpr));
  const h = Math.max(1, Math.round(canvas.clientHeight * dpr));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; S.dirty = true; }
}

function polyline(points, close) {
  ctx.beginPath();
  points.forEach((p, i) => { const [x, y] = toScreen(p[0], p[1]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
  if (close) ctx.closePath();
}

function fitView() {
  const pts = [];
  for (const a of S.agents.values()) if (a.status && a.status.position) pts.push([a.status.position.lat, a.status.position.lon]);
  const g = S.mission && S.mission.geometry;
  if (g && g.area) pts.push(...g.area);
  if (g) for (const p of Object.values(g.paths)) pts.push(...p);
  if (S.area) pts.push(...S.area);
  if (!pts.length || !S.origin) return;
  const xy = pts.map((p) => toLocal(p[0], p[1]));
  const xs = xy.map((p) => p[0]), ys = xy.map((p) => p[1]);
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  S.view.cx = (x0 + x1) / 2;
  S.view.cy = (y0 + y1) / 2;
  const span = Math.max(x1 - x0, y1 - y0, 30);
  S.view.scale = Math.min(canvas.width, canvas.height) / (span * 1.3);
  S.dirty = true;
}

function drawTiles() {
  if (!S.tileUrl || !S.origin) return;
  const mpp = 1 / S.view.scale;  // metres per pixel
  const z = Math.max(0, Math.min(20, Math.round(Math.log2((156543.03 * Math.cos(S.origin[0] * Math.PI / 180)) / mpp))));
  const n = 2 ** z;
  const tileOf = (lat, lon) => [Math.floor(((lon + 180) / 360) * n),
    Math.floor(((1 - Math.log(Math.tan(lat * Math.PI / 180) + 1 / Math.cos(lat * Math.PI / 180)) / Math.PI) / 2) * n)];
  const [la0, lo0] = screenToLatLon(0, 0), [la1, lo1] = screenToLatLon(canvas.width, canvas.height);
  const [tx0, ty0] = tileOf(la0, lo0), [tx1, ty1] = tileOf(la1, lo1);
  if ((tx1 - tx0 + 1) * (ty1 - ty0 + 1) > 64) return;
  const lonOf = (x) => (x / n) * 360 - 180;
  const latOf = (y) => (Math.atan(Math.sinh(Math.PI * (1 - (2 * y) / n))) * 180) / Math.PI;
  for (let tx = tx0; tx <= tx1; tx++) {
    for (let ty = ty0; ty <= ty1; ty++) {
      const url = S.tileUrl.replace("{z}", z).replace("{x}", tx).replace("{y}", ty);
      let img = S.tiles.get(url);
      if (!img) {
        img = new Image();
        img.onload = () => { S.dirty = true; };
        img.src = url;
        S.tiles.set(url, img);
        if (S.tiles.size > 400) S.tiles.delete(S.tiles.keys().next().value);
      }
      if (!img.complete || !img.naturalWidth) continue;
      const [xa, ya] = toScreen(latOf(ty), lonOf(tx));
      const [xb, yb] = toScreen(latOf(ty + 1), lonOf(tx + 1));
      ctx.drawImage(img, xa, ya, xb - xa, yb - ya);
    }
  }
}

function drawGrid() {
  const step = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000].find((s) => s * S.view.scale > 60) || 10000;
  ctx.strokeStyle = "#d5dbe1";
  ctx.lineWidth = 1;
  const [w, h] = [canvas.width, canvas.height];
  const xmin = S.view.cx - w / 2 / S.view.scale, ymin = S.view.cy - h / 2 / S.view.scale;
  ctx.beginPath();
  for (let x = Math.floor(xmin / step) * step; x < xmin + w / S.view.scale; x += step) {
    const px = w / 2 + (x - S.view.cx) * S.view.scale; ctx.moveTo(px, 0); ctx.lineTo(px, h);
  }
  for (let y = Math.floor(ymin / step) * step; y < ymin + h / S.view.scale; y += step) {
    const py = h / 2 - (y - S.view.cy) * S.view.scale; ctx.moveTo(0, py); ctx.lineTo(w, py);
  }
  ctx.stroke();
  $("map-info").textContent = `grid ${step} m` + (S.origin ? ` · origin ${S.origin[0].toFixed(5)}, ${S.origin[1].toFixed(5)}` : "");
}

function drawGeofence() {
  const g = S.geofence;
  if (!g) return;
  ctx.strokeStyle = "#c92a2a";
  ctx.lineWidth = 2;
  ctx.setLineDash([8, 5]);
  if (g.polygon) { polyline(g.polygon.map((v) => [v.lat, v.lon]), true); ctx.stroke(); }
  if (g.circle) {
    const [x, y] = toScreen(g.circle.lat, g.circle.lon);
    ctx.beginPath(); ctx.arc(x, y, g.circle.radius_m * S.view.scale, 0, 2 * Math.PI); ctx.stroke();
  }
  ctx.setLineDash([]);
}

function drawDrone(a) {
  const st = a.status;
  if (!st || !st.position) return;
  const [x, y] = toScreen(st.position.lat, st.position.lon);
  const dpr = window.devicePixelRatio || 1;
  ctx.save();
  ctx.translate(x, y);
  ctx.rotate(((st.heading_deg || 0) * Math.PI) / 180);
  ctx.beginPath();
  const s = 9 * dpr;
  ctx.moveTo(0, -s); ctx.lineTo(s * 0.65, s * 0.75); ctx.lineTo(0, s * 0.35); ctx.lineTo(-s * 0.65, s * 0.75); ctx.closePath();
  ctx.fillStyle = st.pilot ? "#f08c00" : st.exceptions && st.exceptions.length ? "#c92a2a" : a.color;
  ctx.strokeStyle = st.pilot ? "#1d2329" : "#fff";
  ctx.lineWidth = st.pilot ? 2.5 : 1.5;
  ctx.fill(); ctx.stroke();
  ctx.restore();
  const out = excludedWhy(a.identity);
  const why = st.paused ? `held${a.held ? ": " + a.held : ""}` : out ? `excluded: ${out}` : "";
  if (why) {  // an operator order or an exclusion: a ring round the marker and the reason under it
    ctx.beginPath();
    ctx.arc(x, y, 14 * dpr, 0, 2 * Math.PI);
    ctx.strokeStyle = st.paused ? "#e8590c" : "#868e96";
    ctx.lineWidth = 2.5 * dpr;
    ctx.setLineDash(st.paused ? [] : [4 * dpr, 3 * dpr]);
    ctx.stroke();
    ctx.setLineDash([]);
  }
  a.markerNote = why;
  const who = st.pilot ? ` PILOT ${st.pilot}` : "";
  const lines = [{ text: `${a.identity} ${fmtNum(st.position.alt_rel, 0)} m${who}`, color: "#1d2329" }];
  if (why) lines.push({ text: why, color: "#e8590c" });
  return { identity: a.identity, x, y, lines };
}

// Labels of drones closer than a label's size would overlap (5 m apart at a survey's zoom): each
// label goes to the first free place next to its marker (right, then left, stepping up and down
// by a line), clear of the labels placed before it and of the other markers, with a leader line
// when it had to move (leaders that would cross another leader or label are avoided where a free place allows),
// as QGC and Mission Planner declutter theirs. Stable order (by name), so
// labels do not swap places between frames.
const LABEL_TRIES = 24;
function boxesOverlap(a, b) { return a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h; }
function leader(spec, box) {  // marker to the nearest point of its label box
  return [spec.x, spec.y, Math.min(Math.max(spec.x, box.x), box.x + box.w), Math.min(Math.max(spec.y, box.y), box.y + box.h)];
}
function segmentsCross([ax, ay, bx, by], [cx, cy, dx, dy]) {
  const side = (px, py, qx, qy, rx, ry) => Math.sign((qx - px) * (ry - py) - (qy - py) * (rx - px));
  return side(ax, ay, bx, by, cx, cy) * side(ax, ay, bx, by, dx, dy) < 0 && side(cx, cy, dx, dy, ax, ay) * side(cx, cy, dx, dy, bx, by) < 0;
}
function segmentHitsBox([x0, y0, x1, y1], box) {  // any inner point of the segment inside the box
  for (let i = 1; i < 12; i++) {
    const x = x0 + ((x1 - x0) * i) / 12, y = y0 + ((y1 - y0) * i) / 12;
    if (x > box.x && x < box.x + box.w && y > box.y && y < box.y + box.h) return true;
  }
  return false;
}
function labelCandidates(spec, w, h, gap, step) {
  const out = [];
  for (let k = 0; k < LABEL_TRIES; k++) {
    const dy = k === 0 ? 0 : (k % 2 ? 1 : -1) * Math.ceil(k / 2) * step;  // 0, +1, -1, +2, -2 ... lines
    out.push({ x: spec.x + gap, y: spec.y - h / 2 - gap / 2 + dy, w, h, moved: k > 0 });
    out.push({ x: spec.x - gap - w, y: spec.y - h / 2 - gap / 2 + dy, w, h, moved: true });
  }
  return out;
}
function placeLabels(specs) {
  const dpr = window.devicePixelRatio || 1;
  const lineH = 14 * dpr, pad = 3 * dpr, gap = 11 * dpr, mark = 10 * dpr;
  ctx.font = `${11 * dpr}px system-ui`;
  const markers = specs.map((s) => ({ x: s.x - mark, y: s.y - mark, w: 2 * mark, h: 2 * mark, identity: s.identity }));
  const placed = [];
  for (const spec of [...specs].sort((p, q) => (p.identity < q.identity ? -1 : p.identity > q.identity ? 1 : 0))) {
    const w = Math.max(...spec.lines.map((l) => ctx.measureText(l.text).width)) + 2 * pad;
    const h = spec.lines.length * lineH + pad;
    const tries = labelCandidates(spec, w, h, gap, lineH + 2 * dpr);
    // only what is within reach of this label's candidates can collide (a large fleet stays cheap)
    const reach = w + gap + LABEL_TRIES * lineH;
    const near = (o) => Math.abs(o.x - spec.x) < 2 * reach && Math.abs(o.y - spec.y) < 2 * reach;
    const others = placed.filter((o) => near(o.spec)), marks = markers.filter((m) => m.identity !== spec.identity && near(m));
    const free = (b) => !others.some((o) => boxesOverlap(b, o.box)) && !marks.some((m) => boxesOverlap(b, m));
    const uncrossed = (b) => !b.moved || !others.some((o) => o.box.moved && segmentsCross(leader(spec, b), leader(o.spec, o.box)));
    const clear = (b) => !others.some((o) => (b.moved && segmentHitsBox(leader(spec, b), o.box)) || (o.box.moved && segmentHitsBox(leader(o.spec, o.box), b)));
    const box = tries.find((b) => free(b) && uncrossed(b) && clear(b)) || tries.find((b) => free(b) && uncrossed(b)) || tries.find(free) || tries[0];
    placed.push({ spec, box });
  }
  for (const { spec, box } of placed) {
    if (box.moved) {  // a leader line from the marker to the nearest point of its label
      const [x0, y0, x1, y1] = leader(spec, box);
      ctx.strokeStyle = "#495057"; ctx.lineWidth = 1 * dpr;
      ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
    }
    ctx.fillStyle = "rgba(255,255,255,0.82)";
    ctx.fillRect(box.x, box.y, box.w, box.h);
    spec.lines.forEach((l, i) => { ctx.fillStyle = l.color; ctx.fillText(l.text, box.x + pad, box.y + pad + (i + 0.8) * lineH); });
  }
  const k = canvas.clientWidth / canvas.width;  // CSS pixels, for tests (like S.toScreen)
  S.labelBoxes = placed.map(({ spec, box }) => ({ identity: spec.identity, x: box.x * k, y: box.y * k, w: box.w * k, h: box.h * k }));
}

function draw() {
  resize();
  if (S.tableDirty) { renderTable(); S.tableDirty = false; }
  if (!S.dirty) return;
  S.dirty = false;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  $("map-empty").classList.toggle("hidden", !!S.origin);
  if (!S.origin) return;
  if ($("follow").checked && !S.userMoved) fitView();
  drawTiles();
  drawGrid();
  const g = S.mission && S.mission.geometry;
  const area = (g && g.area) || S.area;
  if (area) {
    ctx.fillStyle = "rgba(31,111,235,0.07)"; ctx.strokeStyle = "#1f6feb"; ctx.lineWidth = 2;
    polyline(area, true); ctx.fill(); ctx.stroke();
  }
  if (S.crossings && !g) {
    ctx.strokeStyle = "#c92a2a"; ctx.lineWidth = 2;
    for (const c of S.crossings) {
      const [x, y] = toScreen(c[0], c[1]);
      ctx.beginPath(); ctx.arc(x, y, 7, 0, 2 * Math.PI); ctx.stroke();
      ctx.beginPath(); ctx.moveTo(x - 5, y - 5); ctx.lineTo(x + 5, y + 5); ctx.moveTo(x + 5, y - 5); ctx.lineTo(x - 5, y + 5); ctx.stroke();
    }
  }
  if (S.mission && S.mission.live) drawCoverage(S.mission.live);
  if (S.mission && S.mission.unseen && S.mission.unseen.coordinates) {
    ctx.fillStyle = "rgba(201,42,42,0.16)";
    for (const cell of S.mission.unseen.coordinates) { polyline(cell[0].map((q) => [q[1], q[0]]), true); ctx.fill(); }
  }
  if (S.drawing && S.drawing.length) {
    ctx.strokeStyle = "#e8590c"; ctx.lineWidth = 2; polyline(S.drawing, false); ctx.stroke();
    for (const p of S.drawing) { const [x, y] = toScreen(p[0], p[1]); ctx.fillStyle = "#e8590c"; ctx.fillRect(x - 3, y - 3, 6, 6); }
  }
  // coverage so far: the flown track of the mission, as wide as the swath
  if (g && g.swath_m && S.mission && !S.mission.live) {
    ctx.strokeStyle = "rgba(46,125,50,0.22)"; ctx.lineWidth = Math.max(1, g.swath_m * S.view.scale); ctx.lineCap = "round"; ctx.lineJoin = "round";
    for (const a of S.agents.values()) {
      const pts = a.track.filter((p) => p[2] === S.mission.id);
      if (pts.length > 1) { polyline(pts, false); ctx.stroke(); }
    }
    ctx.lineCap = "butt";
  }
  const planned = g ? g.paths : S.preview ? Object.fromEntries(S.preview.drones.map((d) => [d.agent, d.points])) : null;
  if (planned) {
    ctx.setLineDash([6, 4]); ctx.lineWidth = 1.5;
    for (const [name, pts] of Object.entries(planned)) {
      const a = S.agents.get(name);
      ctx.strokeStyle = a ? a.color : "#555";
      if (pts.length > 1) { polyline(pts, false); ctx.stroke(); }
    }
    ctx.setLineDash([]);
  }
  if (g && g.targets) {
    ctx.fillStyle = "#c92a2a";
    for (const t of g.targets) { const [x, y] = toScreen(t[0], t[1]); ctx.fillRect(x - 2, y - 2, 4, 4); }
  }
  ctx.lineWidth = 2;
  for (const a of S.agents.values()) {
    if (a.track.length > 1) { ctx.strokeStyle = a.color; polyline(a.track.slice(-1500), false); ctx.stroke(); }
  }
  drawGeofence();
  placeLabels([...S.agents.values()].map(drawDrone).filter(Boolean));
}

// The coverage layer: seen cells shaded green (a row's run of cells is one quad), the unseen part
// of the area outlined in red (the cell edges between unseen and anything else). Runs and edges are
// found once per message (up to 160k cells); a frame only projects and draws them.
function coverageShapes(g, inside, seen) {
  const runs = [], edges = [];
  for (let r = 0; r < g.rows; r++) {
    let c = 0;
    while (c < g.cols) {
      if (!seen[r * g.cols + c]) { c++; continue; }
      const c0 = c;
      while (c < g.cols && seen[r * g.cols + c]) c++;
      runs.push([r, c0, c]);
    }
  }
  const unseen = (r, c) => r >= 0 && c >= 0 && r < g.rows && c < g.cols && inside[r * g.cols + c] && !seen[r * g.cols + c];
  for (let r = 0; r < g.rows; r++) {
    for (let c = 0; c < g.cols; c++) {
      if (!unseen(r, c)) continue;
      if (!unseen(r - 1, c)) edges.push([r, c, r, c + 1]);
      if (!unseen(r + 1, c)) edges.push([r + 1, c, r + 1, c + 1]);
      if (!unseen(r, c - 1)) edges.push([r, c, r + 1, c]);
      if (!unseen(r, c + 1)) edges.push([r, c + 1, r + 1, c + 1]);
    }
  }
  return { runs, edges };
}

function drawCoverage(live) {
  const g = live.msg.grid;
  const dLat = (g.ne[0] - g.sw[0]) / g.rows, dLon = (g.ne[1] - g.sw[1]) / g.cols;
  const at = (r, c) => toScreen(g.sw[0] + r * dLat, g.sw[1] + c * dLon);
  ctx.fillStyle = "rgba(46,125,50,0.35)";
  ctx.beginPath();
  for (const [r, c0, c1] of live.runs) {
    const p = [at(r, c0), at(r, c1), at(r + 1, c1), at(r + 1, c0)];
    ctx.moveTo(p[0][0], p[0][1]);
    for (let i = 1; i < 4; i++) ctx.lineTo(p[i][0], p[i][1]);
    ctx.closePath();
  }
  ctx.fill();
  ctx.strokeStyle = "#c92a2a"; ctx.lineWidth = 1.5;
  ctx.beginPath();
  for (const [r0, c0, r1, c1] of live.edges) {
    const p = at(r0, c0), q = at(r1, c1);
    ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]);
  }
  ctx.stroke();
}

function loop() { draw(); requestAnimationFrame(loop); }

// --- map interaction --------------------------------------------------------------------------------
(function mapInput() {
  let drag = null;
  const dpr = () => window.devicePixelRatio || 1;
  canvas.addEventListener("mousedown", (e) => { drag = { x: e.offsetX, y: e.offsetY, moved: false }; });
  canvas.addEventListener("mousemove", (e) => {
    if (!drag) return;
    const dx = (e.offsetX - drag.x) * dpr(), dy = (e.offsetY - drag.y) * dpr();
    if (Math.abs(dx) + Math.abs(dy) > 3) drag.moved = true;
    if (!drag.moved) return;
    S.view.cx -= dx / S.view.scale; S.view.cy += dy / S.view.scale;
    drag.x = e.offsetX; drag.y = e.offsetY;
    S.userMoved = true; S.dirty = true;
  });
  window.addEventListener("mouseup", (e) => {
    if (drag && !drag.moved && S.drawing && e.target === canvas && S.origin) {
      S.drawing.push(screenToLatLon(e.offsetX * dpr(), e.offsetY * dpr()));
      S.dirty = true;
    }
    drag = null;
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const k = e.deltaY < 0 ? 1.2 : 1 / 1.2;
    const [lat, lon] = S.origin ? screenToLatLon(e.offsetX * dpr(), e.offsetY * dpr()) : [0, 0];
    S.view.scale = Math.max(0.005, Math.min(200, S.view.scale * k));
    if (S.origin) {  // keep the point under the cursor fixed
      const [x, y] = toLocal(lat, lon);
      S.view.cx = x - (e.offsetX * dpr() - canvas.width / 2) / S.view.scale;
      S.view.cy = y + (e.offsetY * dpr() - canvas.height / 2) / S.view.scale;
    }
    S.userMoved = true; S.dirty = true;
  }, { passive: false });
})();

function zoom(k) { S.view.scale = Math.max(0.005, Math.min(200, S.view.scale * k)); S.userMoved = true; S.dirty = true; }

// --- wiring -----------------------------------------------------------------------------------------
$("btn-zoom-in").onclick = () => zoom(1.5);
$("btn-zoom-out").onclick = () => zoom(1 / 1.5);
$("btn-fit").onclick = () => { S.userMoved = false; fitView(); };
$("follow").onchange = () => { S.userMoved = false; S.dirty = true; };
$("btn-draw").onclick = () => {
  S.drawing = []; S.area = null; S.crossings = null; S.preview = null; $("btn-start").disabled = true;
  $("btn-draw").classList.add("active"); $("btn-finish-draw").disabled = false; canvas.classList.add("drawing");
  $("follow").checked = false; S.dirty = true;
};
$("btn-finish-draw").onclick = () => {
  if (S.drawing && S.drawing.length >= 3) { S.area = S.drawing; $("area-text").value = JSON.stringify(S.area.map((p) => [+p[0].toFixed(7), +p[1].toFixed(7)])); }
  else toast("an area needs at least 3 corners", true);
  S.drawing = null; $("btn-draw").classList.remove("active"); $("btn-finish-draw").disabled = true; canvas.classList.remove("drawing"); S.dirty = true;
};
$("btn-clear-area").onclick = () => { S.area = null; S.crossings = null; S.drawing = null; S.preview = null; $("area-text").value = ""; $("btn-start").disabled = true; S.dirty = true; };
$("area-text").addEventListener("input", () => { S.area = null; S.crossings = null; S.preview = null; $("btn-start").disabled = true; });
$("area-file").addEventListener("change", async (e) => {
  const f = e.target.files[0];
  if (!f) return;
  const text = await f.text();
  if (!text.trim()) { toast(`${f.name} is empty: no area in it`, true); e.target.value = ""; return; }
  $("area-text").value = text;
  S.area = null; S.crossings = null;
  toast(`loaded ${f.name}; press Preview`);
});
// QGC .plan / Mission Planner .waypoints files, one per drone (the file name names it): fly them.
$("mission-files").addEventListener("change", async (e) => {
  const input = e.target;
  const files = {};
  for (const f of input.files) files[f.name] = await f.text();
  input.value = "";
  const names = Object.keys(files);
  if (!names.length) return;
  const drones = names.map((n) => n.replace(/\.[^.]*$/, "")).join(", ");
  if (!(await confirmAction(`Fly ${names.join(", ")} on ${drones}? The drones take off.`))) { toast("mission files: cancelled"); return; }
  const r = await act("fly mission files", () => api("POST", "/api/v1/missions/import", { name: names.length === 1 ? drones : "imported-mission", files }));
  if (r) await loadMission(r.mission_id);
});
$("btn-preview").onclick = preview;
$("btn-start").onclick = startMission;
$("btn-pause").onclick = () => missionCommand("pause");
$("btn-resume").onclick = () => missionCommand("resume");
$("btn-abort").onclick = () => missionCommand("abort", "?then=hold");
$("btn-hold-all").onclick = () => fleetCommand("hold", "hold all");
$("btn-resume-all").onclick = () => fleetCommand("resume", "resume all");
$("btn-rtl-all").onclick = () => fleetCommand("rtl", "RTL all", "Return all {n} drones to launch? Running missions are aborted.");
$("btn-land-all").onclick = () => fleetCommand("land", "land all", "Land all {n} drones where they are? Running missions are aborted.");
$("btn-clear-tracks").onclick = clearTracks;
window.addEventListener("resize", () => { S.dirty = true; });

async function init() {
  let ui = {};
  try { ui = await api("GET", "/api/v1/ui-config"); S.tileUrl = ui.tile_url; } catch (e) { /* ignore */ }
  // only a cluster daemon has /api/v1/cluster: asking a single daemon logged a 404 on every load
  if (ui.cluster) { try { S.cluster = await api("GET", "/api/v1/cluster"); } catch (e) { S.cluster = null; } }
  try {
    const evs = await api("GET", "/api/v1/events?last=100");
    S.events = evs.reverse();
    renderEvents();
  } catch (e) { /* ignore */ }
  try {
    const running = await api("GET", "/api/v1/missions?state=running&limit=1");
    // a reload shows the running mission, else the last one (a completed mission stays in view)
    const last = running.length ? running : await api("GET", "/api/v1/missions?limit=1");
    if (last.length) await loadMission(last[0].id);
  } catch (e) { /* ignore */ }
  loadGeofence();
  connect();
  setInterval(() => { S.tableDirty = true; }, 1000);
  setInterval(() => { if (S.mission && S.mission.progress && S.mission.progress.state === "running") { refreshMission(); refreshCoverage(); } }, 1500);
  requestAnimationFrame(loop);
}
init();
