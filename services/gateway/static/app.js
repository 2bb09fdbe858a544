// The operator's page: talks to the gateway's /v1 API only (no library, nothing fetched from
// elsewhere). Task progress comes from the task's event stream (read with fetch, so the
// bearer token can be sent: EventSource cannot send headers), the map and the driver state
// are polled a few times a second. Every request goes through api(): a 401 asks for the token.
"use strict";

const API = "/v1";
const TOKEN_KEY = "ovamos.gateway.token";
const MAX_TARGETS = 16;
const PERIOD_MS = { robot: 500, map: 400, tasks: 1500, health: 2000 };
const STALE_DRIVER_S = 2.0;
const MAPPING = "mapping";  // the map is asked for only while this service is alive (no 503 spam)
const MAX_EVENTS = 300;
// the planner's routine lock-step waits, several per step: not worth a line in the log
const ROUTINE_WAIT = /^waiting for (odometry after command|the map to fuse a frame taken after command) \d+$/;
const COLOURS = {
  frontier: "rgb(200,0,200)", candidate: "#facc15", path: "rgb(20,60,200)", goal: "#dc2626",
  robot: "rgb(20,60,200)", confirmed: "rgb(40,170,40)", unconfirmed: "rgb(255,140,0)", found: "#16a34a",
  other: "rgb(160,160,160)",  // an object of a label the map's task does not search (an earlier task's)
};

const $ = (id) => document.getElementById(id);
const state = {
  robot: null, robots: [], taskId: null, stream: null, streamTask: null, views: new Map(),
  chips: [], needToken: false, mapBusy: false, lastMap: null, image: null, lastWait: new Map(),
  services: new Map(),  // robot -> names of its live services
  lastActive: null,  // the robot's running task when the list was last read
  tasks: new Map(),  // task id -> its view in the latest list (the map's task's targets)
};

// -- the API ---------------------------------------------------------------------------------------
class ApiError extends Error {
  constructor(status, body) {
    super(body && body.detail ? body.detail : `HTTP ${status}`);
    this.status = status;
    this.errors = (body && body.errors) || [];
  }
}

function authHeaders() {
  const token = sessionStorage.getItem(TOKEN_KEY);
  return token ? { Authorization: `Bearer ${token}` } : {};
}

async function api(method, path, body) {
  const headers = authHeaders();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let response;
  try {
    response = await fetch(API + path, {
      method, headers, cache: "no-store", body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (err) {
    throw new ApiError(0, { detail: `cannot reach the gateway (${err.message})` });
  }
  const data = await response.json().catch(() => ({ detail: response.statusText }));
  if (response.status === 401) askForToken(data.detail);
  if (!response.ok) throw new ApiError(response.status, data);
  return data;
}

function askForToken(detail) {
  const had = sessionStorage.getItem(TOKEN_KEY) !== null;
  sessionStorage.removeItem(TOKEN_KEY);
  if (state.needToken) return;
  state.needToken = true;
  $("token-message").textContent = had
    ? `The gateway refused the token (401: ${detail}). Enter the right one.`
    : `This gateway needs a token (401: ${detail}). Enter it to continue.`;
  $("token-form").hidden = false;
  $("token").focus();
}

$("token-form").addEventListener("submit", (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("token").value.trim());
  $("token").value = "";
  $("token-form").hidden = true;
  state.needToken = false;
  refreshAll();
});

function banner(message) {
  $("banner").textContent = message || "";
  $("banner").hidden = !message;
}

// -- pollers ---------------------------------------------------------------------------------------
function every(ms, fn) {
  const run = async () => {
    if (!state.needToken) {
      try { await fn(); } catch (err) { if (err.status !== 401) banner(err.message); }
    }
    setTimeout(run, ms);
  };
  run();
}

function refreshAll() {
  for (const fn of [loadHealth, loadRobot, loadTasks]) fn().catch((err) => banner(err.message));
}

// -- the log of events -----------------------------------------------------------------------------
// `at`: when it happened (a task's updated_at, as the gateway stamped it), so a task that ended
// before the page was opened is listed at its own time and in its place; default: now.
function logEvent(text, kind = "", at = new Date()) {
  const li = document.createElement("li");
  const time = document.createElement("time");
  time.dateTime = at.toISOString();
  time.textContent = at.toLocaleTimeString([], { hour12: false });
  li.dataset.t = String(at.getTime());
  li.append(time, text);
  if (kind) li.className = kind;
  const list = $("events");
  const later = [...list.children].find((other) => Number(other.dataset.t) <= at.getTime());
  list.insertBefore(li, later || null);  // newest first
  while (list.children.length > MAX_EVENTS) list.lastChild.remove();
}

// -- robots and health -----------------------------------------------------------------------------
function setRobots(robots) {
  if (robots.join() === state.robots.join()) return;
  state.robots = robots;
  for (const select of [$("robot"), $("submit-robot")]) {
    const keep = select.value;
    select.replaceChildren(...robots.map((r) => new Option(r, r)));
    if (robots.includes(keep)) select.value = keep;
  }
  if (!robots.includes(state.robot)) selectRobot(robots[0]);
}

function selectRobot(robot) {
  state.robot = robot;
  $("robot").value = robot;
  $("submit-robot").value = robot;
  state.taskId = null;
  state.lastActive = null;
  state.lastMap = null;
  loadRobot().catch((err) => banner(err.message));
  loadTasks().catch((err) => banner(err.message));
}

$("robot").addEventListener("change", () => selectRobot($("robot").value));

async function loadHealth() {
  const health = await api("GET", "/health");
  setRobots(Object.keys(health.robots));
  state.services = new Map(Object.entries(health.robots).map(([r, info]) => [r, new Set(info.services.map((s) => s.service))]));
  const blocks = Object.entries(health.robots).map(([robot, info]) => {
    const div = document.createElement("div");
    div.className = "robot-health";
    div.dataset.robot = robot;
    const title = document.createElement("strong");
    title.textContent = `${robot}: ${info.active_task ? "searching" : "idle"}, ${info.queued} queued`;
    const list = document.createElement("ul");
    const services = [...info.services].sort((a, b) => a.service.localeCompare(b.service));
    for (const s of services) {
      const li = document.createElement("li");
      li.textContent = `${s.service} (${s.instance}${s.pid ? `, pid ${s.pid}` : ""})`;
      li.dataset.service = s.service;
      list.append(li);
    }
    if (!services.length) {
      const li = document.createElement("li");
      li.className = "none";
      li.textContent = "no service alive";
      list.append(li);
    }
    div.append(title, list);
    return div;
  });
  $("health").replaceChildren(...blocks);
  banner("");
}

// -- the driver and the e-stop ---------------------------------------------------------------------
function showDriver(robot) {
  const box = $("driver-state");
  const d = robot.driver;
  let text, kind;
  if (!d) {
    text = "driver: no state received";
    kind = "unknown";
  } else if (robot.driver_age_s > STALE_DRIVER_S) {
    text = `driver: silent for ${robot.driver_age_s.toFixed(1)} s (last: ${d.mode})`;
    kind = "stale";
  } else {
    text = `driver: ${d.mode}${d.estop_latched ? " (e-stop latched)" : ""}`;
    if (d.faults.length) text += ` – ${d.faults.join("; ")}`;
    kind = d.mode;
  }
  box.textContent = text;
  box.className = `driver mode-${kind}`;
  box.dataset.mode = d ? d.mode : "";
  box.dataset.latched = d && d.estop_latched ? "true" : "false";
  $("clear-estop").hidden = !(d && d.estop_latched);
}

async function loadRobot() {
  if (!state.robot) return;
  showDriver(await api("GET", `/robots/${encodeURIComponent(state.robot)}`));
}

$("estop").addEventListener("click", async () => {
  const robot = state.robot;
  if (!robot) { banner("no robot known yet: the gateway has not answered"); return; }
  logEvent(`E-STOP pressed for ${robot}`, "bad");
  try {
    showDriver(await api("POST", `/robots/${encodeURIComponent(robot)}/estop`, { reason: "operator's E-STOP" }));
    logEvent(`e-stop latched on ${robot} (the driver confirms)`, "bad");
    banner("");
  } catch (err) {
    banner(`E-STOP: ${err.message}`);
    logEvent(`E-STOP not confirmed: ${err.message}`, "bad");
  }
});

$("clear-estop").addEventListener("click", () => {
  $("clear-text").textContent = `Robot ${state.robot} may move again, and a running search resumes.`;
  $("clear-dialog").showModal();
});

$("clear-dialog").addEventListener("close", async () => {
  if ($("clear-dialog").returnValue !== "confirm") return;
  const robot = state.robot;
  try {
    showDriver(await api("POST", `/robots/${encodeURIComponent(robot)}/estop/clear`, { confirm: true }));
    logEvent(`e-stop cleared on ${robot} (the driver confirms)`, "good");
    banner("");
  } catch (err) {
    banner(`clearing the e-stop: ${err.message}`);
  }
});

// -- submitting a search ---------------------------------------------------------------------------
function renderChips() {
  const box = $("chips");
  for (const chip of box.querySelectorAll(".chip")) chip.remove();
  state.chips.forEach((name, i) => {
    const chip = document.createElement("span");
    const blank = name.trim() === "";
    chip.className = blank ? "chip blank" : "chip";
    chip.textContent = blank ? "(blank)" : name;
    const remove = document.createElement("button");
    remove.type = "button";
    remove.textContent = "×";
    remove.setAttribute("aria-label", `remove ${blank ? "blank name" : name}`);
    remove.addEventListener("click", () => { state.chips.splice(i, 1); renderChips(); $("target-input").focus(); });
    chip.append(remove);
    box.insertBefore(chip, $("target-input"));
  });
  $("target-count").textContent = `${state.chips.length} / ${MAX_TARGETS}`;
}

function addChips(text) {
  // the gateway validates the names (one set of rules): the page sends what was typed
  state.chips.push(...text.split(","));
  renderChips();
}

$("target-input").addEventListener("keydown", (event) => {
  const input = event.target;
  if ((event.key === "Enter" || event.key === ",") && input.value !== "") {
    event.preventDefault();
    addChips(input.value);
    input.value = "";
  } else if (event.key === "Backspace" && input.value === "" && state.chips.length) {
    state.chips.pop();
    renderChips();
  }
});

function clearErrors() {
  for (const p of document.querySelectorAll("#submit-form .error")) p.textContent = "";
  for (const el of document.querySelectorAll("#submit-form [aria-invalid]")) el.removeAttribute("aria-invalid");
}

const FIELD_INPUT = { targets: "target-input", robot_id: "submit-robot", max_steps: "max-steps" };

function showErrors(err) {
  const problems = err.errors.length ? err.errors : [{ field: "body", message: err.message }];
  for (const { field, message } of problems) {
    const name = field.split(/[.[]/)[0];
    const target = $(`error-${name}`) || $("error-body");
    target.textContent = target.textContent ? `${target.textContent} ${message}` : message;
    if (FIELD_INPUT[name]) $(FIELD_INPUT[name]).setAttribute("aria-invalid", "true");
  }
}

$("submit-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  clearErrors();
  const pending = $("target-input").value;
  if (pending !== "") { addChips(pending); $("target-input").value = ""; }
  const body = { targets: state.chips, robot_id: $("submit-robot").value };
  const steps = $("max-steps").value.trim();
  if (steps !== "") body.max_steps = /^\d+$/.test(steps) ? Number(steps) : steps;
  try {
    const accepted = await api("POST", "/tasks", body);
    const where = accepted.queue_position ? `queued at position ${accepted.queue_position}` : accepted.status;
    logEvent(`submitted ${state.chips.join(", ")} to ${accepted.robot_id}: ${where}`);
    state.chips = [];
    renderChips();
    if (accepted.robot_id !== state.robot) selectRobot(accepted.robot_id);
    selectTask(accepted.id);
    await loadTasks();
  } catch (err) {
    showErrors(err);
  }
});

// -- tasks -----------------------------------------------------------------------------------------
function cell(tr, name) {
  return tr.querySelector(`td.${name}`);
}

function taskRow(view) {
  const tr = document.createElement("tr");
  tr.dataset.task = view.id;
  for (const name of ["status", "found", "steps", "distance", "actions"]) {
    const td = document.createElement("td");
    td.className = name;
    tr.append(td);
  }
  const watch = document.createElement("button");
  watch.type = "button";
  watch.className = "watch";
  watch.textContent = "Watch";
  watch.addEventListener("click", () => selectTask(view.id));
  const cancel = document.createElement("button");
  cancel.type = "button";
  cancel.className = "cancel";
  cancel.textContent = "Cancel";
  cancel.addEventListener("click", () => cancelTask(view.id));
  const buttons = document.createElement("div");
  buttons.className = "buttons";
  buttons.append(watch, cancel);
  cell(tr, "actions").append(buttons);
  return tr;
}

function updateRow(tr, v) {
  const status = cell(tr, "status");
  const note = v.queue_position ? ` #${v.queue_position}` : v.message && !ROUTINE_WAIT.test(v.message) ? ` – ${v.message}` : "";
  status.textContent = v.status + note;
  status.className = `status ${v.status}`;
  tr.dataset.status = v.status;
  const found = v.found.map((f) => f.label);
  const f = cell(tr, "found");
  f.replaceChildren();
  if (found.length) {
    const ok = document.createElement("span");
    ok.className = "found-ok";
    ok.textContent = `✓ ${found.join(", ")}`;
    f.append(ok, v.remaining.length ? " / " : "");
  }
  f.append(v.remaining.join(", "));
  cell(tr, "steps").textContent = `${v.steps}/${v.max_steps}`;
  tr.dataset.steps = v.steps;
  cell(tr, "distance").textContent = `${v.distance_m.toFixed(1)} m`;
  tr.querySelector("button.cancel").hidden = isFinal(v);
  tr.classList.toggle("selected", v.id === state.taskId);
  tr.setAttribute("aria-selected", v.id === state.taskId ? "true" : "false");
}

function isFinal(view) {
  return ["done", "failed", "cancelled"].includes(view.status);
}

async function loadTasks() {
  if (!state.robot) return;
  const { tasks } = await api("GET", `/tasks?robot_id=${encodeURIComponent(state.robot)}&limit=25`);
  state.tasks = new Map(tasks.map((t) => [t.id, t]));
  const body = $("tasks").tBodies[0];
  const rows = new Map([...body.rows].map((tr) => [tr.dataset.task, tr]));
  tasks.forEach((listed, i) => {
    // the stream's view of the watched task is newer than a poll's
    const v = listed.id === state.streamTask && state.views.has(listed.id) ? state.views.get(listed.id) : listed;
    const tr = rows.get(v.id) || taskRow(v);
    // newest first; a row already in place is not moved (a focused button keeps its focus)
    if (body.rows[i] !== tr) body.insertBefore(tr, body.rows[i] || null);
    updateRow(tr, v);
    rows.delete(v.id);
  });
  for (const tr of rows.values()) tr.remove();
  $("tasks-empty").hidden = tasks.length > 0;
  // watch the robot's running task: at first, and whenever another one starts (from this page
  // or anywhere else); a task picked with Watch stays watched until then
  const active = tasks.find((t) => t.status === "searching");
  if (active && active.id !== state.lastActive) {
    state.lastActive = active.id;
    selectTask(active.id);
  } else if (state.taskId === null && tasks.length) {
    selectTask(tasks[0].id);
  }
}

function selectTask(taskId) {
  state.taskId = taskId;
  for (const tr of $("tasks").tBodies[0].rows) {
    tr.classList.toggle("selected", tr.dataset.task === taskId);
    tr.setAttribute("aria-selected", tr.dataset.task === taskId ? "true" : "false");
  }
  if (state.streamTask !== taskId) follow(taskId);
}

async function cancelTask(taskId) {
  try {
    const view = await api("DELETE", `/tasks/${taskId}`);
    logEvent(`cancel requested: task ${taskId.slice(0, 8)} is ${view.status}`);
    onTaskView(view);
  } catch (err) {
    banner(`cancel: ${err.message}`);
  }
}

// The task's event stream, parsed by hand (text/event-stream: blocks separated by a blank line).
async function follow(taskId) {
  if (state.stream) state.stream.abort();
  const controller = new AbortController();
  state.stream = controller;
  state.streamTask = taskId;
  let final = false;
  try {
    const response = await fetch(`${API}/tasks/${taskId}/events`, { headers: authHeaders(), signal: controller.signal });
    if (!response.ok) {
      const data = await response.json().catch(() => ({}));
      if (response.status === 401) askForToken(data.detail);
      throw new ApiError(response.status, data);
    }
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buffer += value;
      let end;
      while ((end = buffer.indexOf("\n\n")) >= 0) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end + 2);
        const fields = Object.fromEntries(block.split("\n").filter((l) => !l.startsWith(":"))
          .map((l) => [l.slice(0, l.indexOf(":")), l.slice(l.indexOf(":") + 1).trimStart()]));
        if (fields.event === "task" && fields.data) {
          const view = JSON.parse(fields.data);
          final = isFinal(view);
          onTaskView(view);
        }
      }
    }
  } catch (err) {
    if (err.name === "AbortError") return;
    if (err.status !== 401) banner(`event stream of task ${taskId.slice(0, 8)}: ${err.message}`);
  }
  if (state.stream === controller && !final && !state.needToken) {
    setTimeout(() => { if (state.stream === controller) follow(taskId); }, 1000);  // reconnect
  }
}

function onTaskView(view) {
  const before = state.views.get(view.id);
  state.views.set(view.id, view);
  describeChange(before, view);
  const tr = $("tasks").tBodies[0].querySelector(`tr[data-task="${view.id}"]`);
  if (tr) updateRow(tr, view);
}

function describeChange(before, v) {
  const id = v.id.slice(0, 8);
  const at = new Date(v.updated_at);
  if (!before || before.status !== v.status) {
    const kind = v.status === "done" ? "good" : ["failed", "cancelled"].includes(v.status) ? "bad" : "";
    logEvent(`task ${id} ${v.status}${isFinal(v) && v.message ? `: ${v.message}` : ""}`, kind, at);
  }
  const known = new Set((before ? before.found : []).map((f) => f.label));
  for (const f of v.found) {
    if (!known.has(f.label)) logEvent(`found ${f.label} at step ${f.step} (${f.x.toFixed(1)}, ${f.y.toFixed(1)})`, "good", at);
  }
  if (v.status !== "searching") return;
  const wait = ROUTINE_WAIT.test(v.message) ? "" : v.message;
  const last = state.lastWait.get(v.id) || "";
  if (wait !== last) {
    state.lastWait.set(v.id, wait);
    logEvent(wait ? `task ${id} waiting: ${wait}` : `task ${id} resumed`, wait ? "bad" : "good", at);
  }
}

// -- the map ---------------------------------------------------------------------------------------
$("layer").addEventListener("change", () => { state.lastMap = null; loadMap().catch((err) => banner(err.message)); });

async function loadMap() {
  if (!state.robot || state.mapBusy) return;
  if (!(state.services.get(state.robot) || new Set()).has(MAPPING)) {
    $("map-status").textContent = `no ${MAPPING} service alive for ${state.robot}: no map`;
    return;
  }
  state.mapBusy = true;
  try {
    const layer = $("layer").value;
    const query = layer ? `?layer=${encodeURIComponent(layer)}` : "";
    let view;
    try {
      view = await api("GET", `/robots/${encodeURIComponent(state.robot)}/map${query}`);
    } catch (err) {
      if (err.status === 422 && layer) { $("layer").value = ""; return; }  // the layer went away
      if (err.status === 503 || err.status === 0) { $("map-status").textContent = err.message; return; }
      throw err;
    }
    setLayers(view.layers);
    const image = new Image();
    image.src = view.image;
    await image.decode();
    state.image = image;
    state.lastMap = view;
    drawMap();
    const steps = state.views.get(view.task_id);
    $("map-status").textContent = `map of frame ${view.seq}` + (steps ? `, step ${steps.steps}` : "") +
      (view.odom_session ? `, odometry session ${view.odom_session}` : "") + localized(view.map_T_odom);
  } finally {
    state.mapBusy = false;
  }
}

// localization's correction of odometry's drift: where the odometry frame lies in the map
function localized(t) {
  if (!t || (t.x === 0 && t.y === 0 && t.yaw === 0)) return "";
  const deg = (t.yaw * 180) / Math.PI;
  return `, odometry corrected by ${Math.hypot(t.x, t.y).toFixed(2)} m, ${deg.toFixed(1)}\u00b0`;
}

function setLayers(layers) {
  const select = $("layer");
  const have = [...select.options].slice(1).map((o) => o.value);
  if (have.join() === layers.join()) return;
  const keep = select.value;
  select.replaceChildren(new Option("all targets", ""), ...layers.map((l) => new Option(l, l)));
  select.value = layers.includes(keep) ? keep : "";
}

function drawMap() {
  const view = state.lastMap;
  const canvas = $("map");
  const box = canvas.parentElement.getBoundingClientRect();
  const dpr = window.devicePixelRatio || 1;
  canvas.width = Math.max(1, Math.round(box.width * dpr));
  canvas.height = Math.max(1, Math.round(box.height * dpr));
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#464646";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (!view) return;
  const scale = Math.min(canvas.width / view.width, canvas.height / view.height);  // pixels per cell
  const ox = (canvas.width - view.width * scale) / 2;
  const oy = (canvas.height - view.height * scale) / 2;
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(state.image, ox, oy, view.width * scale, view.height * scale);
  const perMetre = scale / view.resolution;
  const px = (x, y) => [ox + (x - view.x0) * perMetre, oy + (view.height * scale - (y - view.y0) * perMetre)];
  const unit = Math.max(4 * dpr, 0.1 * perMetre);
  ctx.lineWidth = Math.max(1.5, dpr * 1.5);

  ctx.strokeStyle = COLOURS.frontier;
  for (const [x, y] of view.frontiers) circle(ctx, px(x, y), unit * 0.8, false);

  const best = Math.max(1e-9, ...view.candidates.map((c) => c.value));
  for (const c of view.candidates) {
    const [u, v] = px(c.x, c.y);
    const r = unit * (0.5 + 0.6 * c.value / best);
    ctx.fillStyle = COLOURS.candidate;
    ctx.strokeStyle = "#000";
    ctx.beginPath();
    ctx.moveTo(u, v - r); ctx.lineTo(u + r, v); ctx.lineTo(u, v + r); ctx.lineTo(u - r, v); ctx.closePath();
    ctx.fill(); ctx.stroke();
  }

  if (view.path.length > 1) {
    ctx.strokeStyle = COLOURS.path;
    ctx.beginPath();
    view.path.forEach(([x, y], i) => { const [u, v] = px(x, y); if (i) ctx.lineTo(u, v); else ctx.moveTo(u, v); });
    ctx.stroke();
  }

  const font = Math.round(12 * dpr);
  const marks = [];    // rectangles labels keep off: every mark drawn
  const labels = [];   // in order of importance: placed once everything is drawn
  const drawnMarks = [];
  const mark = (u, v, r) => { marks.push([u - r - 2, v - r - 2, u + r + 2, v + r + 2]); return r + 4; };
  const foundLabels = new Set(view.found.map((f) => f.label));
  const targets = mapTargets(view);
  // the map outlives a task: only objects of this task's targets are its detections
  const ours = view.objects.filter((o) => targets.has(o.label));
  const others = view.objects.filter((o) => !targets.has(o.label));
  for (const o of others) {
    const at = px(o.x, o.y);
    const r = unit * 0.6;
    ring(ctx, at, r, COLOURS.other, dpr);
    drawnMarks.push({ label: o.label, kind: "other", u: at[0], v: at[1], r });
    labels.push({ text: o.label, at, clear: mark(...at, r), colour: "#6b7280", numbered: false });
  }
  for (const o of [...ours].sort((a, b) => b.confirmed - a.confirmed)) {
    const at = px(o.x, o.y);
    const r = unit * 0.7;
    const kind = o.confirmed ? "confirmed" : "unconfirmed";
    ring(ctx, at, r, COLOURS[kind], dpr);
    drawnMarks.push({ label: o.label, kind, u: at[0], v: at[1], r });
    const clear = mark(...at, r);
    if (!foundLabels.has(o.label)) labels.push({ text: `${o.label} ×${o.hits}`, at, clear, colour: "#111" });
  }

  const foundAt = [];
  const first = [];
  for (const f of view.found) {
    const [u, v] = px(f.x, f.y);
    const s = unit * 1.2;
    ctx.fillStyle = COLOURS.found;
    ctx.fillRect(u - s, v - s, 2 * s, 2 * s);
    ctx.strokeStyle = "#fff";
    ctx.strokeRect(u - s, v - s, 2 * s, 2 * s);
    first.push({ text: `✓ ${f.label} (step ${f.step})`, at: [u, v], clear: mark(u, v, s), colour: "#111", bold: true });
    foundAt.push(`${f.label}@${Math.round(u)},${Math.round(v)}`);
  }

  if (view.goal && view.robot) {
    const [u, v] = px(view.goal.x, view.goal.y);
    ctx.strokeStyle = COLOURS.goal;
    ctx.setLineDash([6 * dpr, 4 * dpr]);
    ctx.beginPath(); ctx.moveTo(...px(view.robot.x, view.robot.y)); ctx.lineTo(u, v); ctx.stroke();
    ctx.setLineDash([]);
  }
  if (view.goal) {
    ctx.strokeStyle = COLOURS.goal;
    const at = px(view.goal.x, view.goal.y);
    circle(ctx, at, unit * 1.1, false);
    circle(ctx, at, unit * 0.4, false);
    first.push({ text: `goal: ${view.goal.label || view.goal.kind}`, at, clear: mark(...at, unit * 1.1), colour: "#111" });
  }

  if (view.robot) {
    const at = px(view.robot.x, view.robot.y);
    const r = Math.max(unit, view.robot_radius_m * perMetre);
    ctx.fillStyle = COLOURS.robot;
    ctx.strokeStyle = "#fff";
    circle(ctx, at, r, true);
    const tip = [at[0] + Math.cos(view.robot.yaw) * r * 1.8, at[1] - Math.sin(view.robot.yaw) * r * 1.8];
    ctx.strokeStyle = "#000";
    ctx.lineWidth = 3 * dpr;
    ctx.beginPath(); ctx.moveTo(...at); ctx.lineTo(...tip); ctx.stroke();
    marks.push([Math.min(at[0] - r, tip[0]) - 3, Math.min(at[1] - r, tip[1]) - 3,
                Math.max(at[0] + r, tip[0]) + 3, Math.max(at[1] + r, tip[1]) + 3]);
  }
  const { placed, listed } = drawLabels(ctx, [...first, ...labels], marks, font);
  // what was drawn, for people using a screen reader (and for the browser tests)
  canvas.dataset.seq = view.seq;
  canvas.dataset.found = foundAt.join(" ");
  canvas.dataset.robot = view.robot ? `${view.robot.x.toFixed(2)},${view.robot.y.toFixed(2)}` : "";
  canvas.dataset.marks = JSON.stringify(drawnMarks);
  canvas.dataset.labels = JSON.stringify(placed);
  canvas.setAttribute("aria-label", `map of robot ${state.robot}, frame ${view.seq}` +
    (view.found.length ? `; found ${view.found.map((f) => f.label).join(", ")}` : ""));
  $("found-list").textContent = view.found.length
    ? `Found: ${view.found.map((f) => `${f.label} at (${f.x.toFixed(1)}, ${f.y.toFixed(1)}), step ${f.step}`).join("; ")}`
    : "";
  $("map-labels").textContent = listed.length ? `Labels by number: ${listed.join(" · ")}` : "";
}

// The targets of the map's task (its detections are drawn as such): from the task's view when
// the page has it, else the map's layers (the remaining targets) and what the task found.
function mapTargets(view) {
  const task = state.views.get(view.task_id) || state.tasks.get(view.task_id);
  return new Set(task ? task.targets : [...view.layers, ...view.found.map((f) => f.label)]);
}

function circle(ctx, [u, v], r, fill) {
  ctx.beginPath();
  ctx.arc(u, v, r, 0, 2 * Math.PI);
  if (fill) ctx.fill();
  ctx.stroke();
}

// A detection: a coloured ring on a dark one, visible over every colour of the heat map.
function ring(ctx, at, r, colour, dpr) {
  ctx.save();
  ctx.lineWidth = 4 * dpr;
  ctx.strokeStyle = "rgba(20,20,20,0.85)";
  circle(ctx, at, r, false);
  ctx.lineWidth = 2 * dpr;
  ctx.strokeStyle = colour;
  circle(ctx, at, r, false);
  ctx.restore();
}

// -- labels: each beside its mark where it overlaps no other label nor mark and stays inside the
// canvas; farther (with a leader line) within a few label heights; else a number there and its
// text under the map. An earlier task's object with no room keeps no label.
const LABEL_ANGLES = [0, 180, -90, 90, -35, 35, -145, 145, -65, 65, -115, 115, -15, 15, -165, 165]
  .map((d) => d * Math.PI / 180);
const LABEL_REACH = 3;  // label heights

function makePlacer(width, height, avoid) {
  const taken = avoid.map((r) => r.slice());
  const free = (x0, y0, w, h) => x0 >= 0 && y0 >= 0 && x0 + w <= width && y0 + h <= height &&
    !taken.some(([a, b, c, d]) => x0 < c && x0 + w > a && y0 < d && y0 + h > b);
  return (at, w, h, clear, reach) => {
    const step = Math.max(h, 6);
    const far = reach === undefined ? Math.hypot(width, height) : reach;
    let spot = null;
    for (let s = 0; s <= far && !spot; s += step) {
      for (const a of LABEL_ANGLES) {
        const x0 = Math.round(at[0] + Math.cos(a) * (clear + w / 2 + s) - w / 2);
        const y0 = Math.round(at[1] + Math.sin(a) * (clear + h / 2 + s) - h / 2);
        if (free(x0, y0, w, h)) { spot = { rect: [x0, y0, x0 + w, y0 + h], away: s > 0 }; break; }
      }
    }
    if (!spot && reach === undefined) {  // rings are sparse far out: the nearest free spot of a grid
      let best = Infinity;
      for (let y0 = 0; y0 + h <= height; y0 += 4) {
        for (let x0 = 0; x0 + w <= width; x0 += 4) {
          const gap = Math.hypot(Math.max(x0 - at[0], at[0] - x0 - w, 0), Math.max(y0 - at[1], at[1] - y0 - h, 0));
          if (gap >= clear && gap < best && free(x0, y0, w, h)) { best = gap; spot = { rect: [x0, y0, x0 + w, y0 + h], away: true }; }
        }
      }
    }
    if (spot) taken.push(spot.rect);
    return spot;
  };
}

function drawLabels(ctx, items, marks, font) {
  const place = makePlacer(ctx.canvas.width, ctx.canvas.height, marks);
  const pad = Math.round(font * 0.25);
  const h = Math.round(font * 1.35);
  const width = (item, text) => {
    ctx.font = `${item.bold ? "bold " : ""}${font}px system-ui, sans-serif`;
    return Math.ceil(ctx.measureText(text).width) + 2 * pad;
  };
  const drawn = [];
  const unplaced = [];
  for (const item of items) {
    const spot = place(item.at, width(item, item.text), h, item.clear, LABEL_REACH * h);
    if (spot) drawn.push({ ...item, ...spot, shown: item.text });
    else if (item.numbered !== false) unplaced.push(item);
  }
  const listed = unplaced.map((item, i) => {
    const number = String(i + 1);
    const spot = place(item.at, width(item, number), h, item.clear);
    if (spot) drawn.push({ ...item, ...spot, shown: number });
    return `${spot ? number : "–"} ${item.text}`;
  });
  ctx.save();
  ctx.lineWidth = 1;
  ctx.strokeStyle = "#111";
  for (const d of drawn.filter((d) => d.away)) {  // leaders first: no line crosses a label
    const [x0, y0, x1, y1] = d.rect;
    ctx.beginPath();
    ctx.moveTo(...d.at);
    ctx.lineTo(Math.min(Math.max(d.at[0], x0), x1), Math.min(Math.max(d.at[1], y0), y1));
    ctx.stroke();
  }
  ctx.textBaseline = "middle";
  for (const d of drawn) {
    const [x0, y0, x1, y1] = d.rect;
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.fillRect(x0, y0, x1 - x0, y1 - y0);
    ctx.font = `${d.bold ? "bold " : ""}${font}px system-ui, sans-serif`;
    ctx.fillStyle = d.colour;
    ctx.fillText(d.shown, x0 + pad, (y0 + y1) / 2);
  }
  ctx.restore();
  return { placed: drawn.map((d) => ({ text: d.shown, rect: d.rect })), listed };
}

// The legend's swatches take their colours from COLOURS: what it shows is what the map draws.
for (const [name, colour] of Object.entries(COLOURS)) document.documentElement.style.setProperty(`--map-${name}`, colour);

window.addEventListener("resize", drawMap);

// -- start -----------------------------------------------------------------------------------------
renderChips();
every(PERIOD_MS.health, loadHealth);
every(PERIOD_MS.robot, loadRobot);
every(PERIOD_MS.tasks, loadTasks);
every(PERIOD_MS.map, loadMap);
