// The sdh2svc dashboard: wires the REST API, the telemetry WebSocket, the plots, pads and sketch.

import {
  allFrames, allSamples, allTruth, api, ApiError, getToken, setToken, Telemetry,
} from "/web/api.js";
import { eventSentence, plainMessage } from "/web/events.js";
import { ParamsForm } from "/web/params.js";
import { Pads } from "/web/pads.js";
import { showObject } from "/web/readout.js";
import { MARKERS, Plots } from "/web/plots.js";
import { Replay } from "/web/replay.js";
import { coneAlpha, configureHand, placedTruth, Sketch } from "/web/sketch.js";

const $ = (sel) => document.querySelector(sel);
const ACTIVE = new Set(["idle", "connecting", "pre-shape", "grasping", "rolling", "releasing"]);
const CONTACT_STALE_MS = 1500;
// How a run can end that needs a person to look (status.last_run.status, the `end` event).
// "interrupted": the service was killed or crashed during the run (status.last_run after a restart).
const NOTICE_STATUSES = new Set(["faulted", "dropped", "e-stopped", "stopped", "interrupted"]);
const TOAST_MS = { error: 15000, info: 4000 }; // how long a toast stays, unless renewed
// The browser's note that a ResizeObserver's callback resized something: benign, never an error.
const BENIGN_ERRORS = /ResizeObserver loop/;
const VIEW_FEED_MS = 100; // the 3-D view follows the replay at most this often
const STATUS_PROBE_TIMEOUT_MS = 3000; // a status poll without an answer by then: no service
const SILENT_SOCKET_MS = 5000; // status messages come at 2 Hz: a socket this quiet is suspect

// Counters for tests and the curious (see the browser test).
const sdh2 = (window.sdh2 = {
  samples: 0, tactile: 0, statusMsgs: 0, events: 0, lastError: null,
  ws: "connecting", connects: 0, dropped: 0, runState: null, replaying: null,
  serviceAlive: true, deadSince: null, notice: null, openRequests: 0,
  replayIndex: null, viewerFeeds: 0, toasts: 0, backfilled: null,
});

const state = {
  status: null,
  params: {}, // RollingParams in force (from status)
  liveRunId: null,
  lastSampleAt: 0,
  runKey: "",
  sim: null,
  replayId: null,
  openPending: false, // an Open hand request in flight, or answered and not yet in a status
  openAnsweredAt: 0,
  startPending: false, // a Grasp & roll request in flight, or answered and its run not yet in a status
  startedRun: null, // the run id the start request was answered with
  presets: null, // the simulated object's preset names (GET /api/sim/object), a Set
  objectPuts: 0, // object choices sent and not yet answered: the selector keeps the user's pick
  notice: null, // {id, status, message, opened, openStopped (why an opening stopped), error}
  // (id null: the hand's own, not a run's — an opening that was e-stopped)
  dismissedRun: null,
  // the hand's opening seen (its `open` event), until it ended; `stoppedAt`: when it ended
  // stopped part-way (an e-stop's own event follows that), else null
  opening: null,
  releasedRuns: new Set(), // runs seen in their releasing phase (the fingers opened)
};

// The service's liveness: every message or answer is a sign of life; a closed socket plus a
// status poll that fails means the service is gone (see goDead / revive).
const live = { dead: false, lastHeard: Date.now(), since: 0, timer: 0, delay: 1000, probing: null };
let telemetry = null;

// --- errors -----------------------------------------------------------------------------------

/**
 * A toast under the page: errors stay TOAST_MS.error, notes TOAST_MS.info (or `timeoutMs`).
 * `key` names the problem (the action that failed): clearToasts(key) removes it once that
 * action succeeds. The same text again renews the toast it has (counted) instead of stacking,
 * with the newest details. `timeoutMs: Infinity`: it stays until dismissed or cleared.
 */
function toast(message, { details = [], kind = "error", timeoutMs = 0, key = "" } = {}) {
  const host = $("#errors");
  const expires = Date.now() + (timeoutMs || TOAST_MS[kind] || TOAST_MS.error);
  for (const old of host.children) {
    if (old.dataset.text === message && old.dataset.key === key) {
      const n = Number(old.dataset.count || 1) + 1;
      old.dataset.count = String(n);
      old.dataset.expires = String(expires);
      old.querySelector(".toast-text").textContent = `${message} (×${n})`;
      setDetails(old, details); // the same sentence may come with other details (another field)
      return old;
    }
  }
  const box = document.createElement("div");
  box.className = `toast ${kind}`;
  box.setAttribute("role", kind === "error" ? "alert" : "status");
  box.dataset.text = message;
  box.dataset.key = key;
  box.dataset.expires = String(expires);
  const text = document.createElement("div");
  text.className = "toast-text";
  text.textContent = message;
  box.appendChild(text);
  setDetails(box, details);
  const close = document.createElement("button");
  close.className = "close";
  close.type = "button";
  close.textContent = "×";
  close.title = "dismiss";
  close.addEventListener("click", () => box.remove());
  box.appendChild(close);
  host.appendChild(box);
  while (host.children.length > 6) host.firstElementChild.remove();
  sdh2.toasts = host.children.length;
  return box;
}

/** A toast's list of details, replacing the one it had (none: no list). */
function setDetails(box, details) {
  const old = box.querySelector("ul");
  if (old) old.remove();
  if (!details.length) return;
  const ul = document.createElement("ul");
  for (const d of details) {
    const li = document.createElement("li");
    li.textContent = String(d);
    ul.appendChild(li);
  }
  box.querySelector(".toast-text").after(ul);
}

/** Remove the toasts whose time is up (`now`: a test may pass a later time). */
function expireToasts(now = Date.now()) {
  for (const box of [...$("#errors").children]) {
    if (Number(box.dataset.expires) <= now) box.remove();
  }
  sdh2.toasts = $("#errors").children.length;
}
setInterval(() => expireToasts(), 1000);

/** The problem `key` is gone: its toasts go too. */
function clearToasts(key) {
  for (const box of [...$("#errors").children]) if (box.dataset.key === key) box.remove();
  sdh2.toasts = $("#errors").children.length;
}

function showError(e, context = "") {
  const msg = e instanceof ApiError ? e.error : String((e && e.message) || e);
  const details = e instanceof ApiError ? e.details : [];
  const full = context ? `${context}: ${msg}` : msg;
  sdh2.lastError = details.length ? `${full} — ${details.join("; ")}` : full;
  console.warn("sdh2svc:", sdh2.lastError);
  // no answer at all is the service's problem, whatever asked: cleared when it answers again
  const key = e instanceof ApiError && e.status === 0 ? "service" : context;
  toast(full, { details, key });
  if (e instanceof ApiError && e.status === 401) $("#token-field").hidden = false;
}

/** Run an async UI action; show its error instead of failing silently. */
async function guard(context, fn) {
  try {
    const out = await fn();
    clearToasts(context);
    return out;
  } catch (e) {
    showError(e, context);
    return undefined;
  }
}

window.addEventListener("error", (ev) => {
  if (BENIGN_ERRORS.test(String(ev.message || ""))) {
    ev.stopImmediatePropagation();
    return;
  }
  showError(ev.message || "script error", "dashboard");
});
window.addEventListener("unhandledrejection", (ev) => showError(ev.reason, "dashboard"));

// --- components -------------------------------------------------------------------------------

const sketch = new Sketch($("#sketch"));
const pads = new Pads($("#pads"));
const readout = $("#object-readout");
const replay = new Replay($("#replay-banner"), { onIndex: (i, s) => showReplayIndex(i, s) });
// hovering a plot shows that iteration in the sketch; off the plots, a replay's own iteration
const plots = new Plots({
  windowSize: 2000,
  onCursor: (s) => {
    const shown = s ?? (replay.active ? replay.samples[replay.index] : null);
    sketch.setOverride(shown, replay.active ? replayTruth(shown) : null);
  },
});
const form = new ParamsForm($("#params-form"), {
  onSubmit: (patch) => applyParams(patch),
});

// --- parameters (in a drawer: the plots and pads keep the screen) -----------------------------

/** Open (or with false, close) the parameter drawer; none: toggle. */
function openDrawer(open) {
  const drawer = $("#params-drawer");
  const was = drawer.classList.contains("open");
  const want = open ?? !was;
  drawer.classList.toggle("open", want);
  drawer.setAttribute("aria-hidden", String(!want));
  document.body.classList.toggle("drawer-open", want); // the toasts move clear of its buttons
  $("#params-toggle").setAttribute("aria-expanded", String(want));
  if (want && !was) {
    // the drawer is last in the page: without this, Tab walks the whole page to reach it
    const field = drawer.querySelector(".field.invalid input, .field.invalid select")
      ?? drawer.querySelector("#params-fields input, #params-fields select");
    if (field) field.focus({ preventScroll: true });
  } else if (!want && drawer.contains(document.activeElement)) {
    $("#params-toggle").focus(); // back where the keyboard came from
  }
}
$("#params-toggle").addEventListener("click", () => openDrawer());
$("#params-close").addEventListener("click", () => openDrawer(false));
document.addEventListener("keydown", (ev) => {
  if (ev.key === "Escape" && $("#params-drawer").classList.contains("open")) openDrawer(false);
});

// the header's height (the drawer sits below it) and where the stage starts (below the header
// and whichever banners show): the stage fills the rest of the first screen
const layoutWatch = new ResizeObserver(() => requestAnimationFrame(() => {
  const root = document.documentElement.style;
  root.setProperty("--header-h", `${$("#controls").offsetHeight}px`);
  root.setProperty("--stage-top", `${$(".stage").getBoundingClientRect().top + window.scrollY}px`);
}));
for (const sel of ["#controls", "#dead-banner", "#estop-banner", "#run-notice"]) {
  layoutWatch.observe($(sel));
}

async function applyParams(patch) {
  form.clearErrors();
  if (!Object.keys(patch).length) {
    toast("No parameter changed.", { kind: "info", timeoutMs: 3000 });
    return;
  }
  try {
    const now = await api.patchParams(patch);
    form.setValues(now, true);
    state.params = now;
    clearToasts("parameters");
    toast(`Parameters applied: ${Object.keys(patch).join(", ")}`, { kind: "info", timeoutMs: 3000 });
  } catch (e) {
    if (e instanceof ApiError && e.status === 422) {
      form.showServerErrors(e.details, e.error);
      openDrawer(true);
      // the drawer may have been open, scrolled to its buttons: the first field in error,
      // into view with the keyboard on it
      const bad = $("#params-drawer").querySelector(".field.invalid input, .field.invalid select");
      if (bad) {
        bad.focus({ preventScroll: true });
        bad.scrollIntoView({ block: "center" });
      }
    }
    showError(e, "parameters");
  }
}

// --- run control ------------------------------------------------------------------------------

async function startRun() {
  if (state.startPending) return; // a double click: one request
  const body = {};
  const { patch, blocked } = form.collect(true);
  if (blocked) {
    showError("fix the marked parameter fields first", "start");
    openDrawer(true);
    return;
  }
  if (Object.keys(patch).length) body.params = patch;
  const object = objectToSend();
  if (object) body.object = object;
  form.clearErrors();
  // Grasp & roll stays disabled from the click until a status shows the run (or the refusal)
  state.startPending = true;
  state.startedRun = null;
  updateControls();
  try {
    const r = await api.startRun(body);
    state.startedRun = r.run_id;
    clearToasts("start");
    toast(`Run ${r.run_id} started`, { kind: "info", timeoutMs: 3000 });
    plots.resetLive();
    state.liveRunId = r.run_id;
    if (plots.replaying) backToLive();
  } catch (e) {
    state.startPending = false;
    if (e instanceof ApiError && e.status === 422) {
      form.showServerErrors(e.details, e.error);
      openDrawer(true);
    }
    showError(e, "start");
  }
  updateControls();
}

/**
 * The `object` Grasp & roll asks for: the preset picked, unless it is the current object
 * already (its PUT is answered). None: the run uses the current object, whatever it is — a
 * custom one's name is no preset and must never be sent as one.
 */
function objectToSend() {
  if (!state.sim || !state.presets) return null;
  const picked = $("#object-select").value;
  const current = state.status && state.status.object ? state.status.object.name : null;
  return state.presets.has(picked) && picked !== current ? picked : null;
}

$("#start").addEventListener("click", startRun);
$("#stop").addEventListener("click", () => guard("stop", async () => {
  const r = await api.stopRun();
  const what = r.run_id == null ? "Stopping the opening: the fingers hold where they are"
    : `Stopping run ${r.run_id} (${r.state})`;
  toast(what, { kind: "info", timeoutMs: 3000 });
}));
$("#estop").addEventListener("click", estop);
$("#open-hand").addEventListener("click", openHand);
$("#notice-open-hand").addEventListener("click", openHand);
$("#notice-dismiss").addEventListener("click", () => {
  if (state.notice && state.notice.id != null) state.dismissedRun = state.notice.id;
  hideNotice();
});

async function openHand() {
  state.openPending = true;
  state.openAnsweredAt = 0;
  sdh2.openRequests += 1;
  setNoticeError("");
  updateControls();
  try {
    await api.openHand();
    clearToasts("open hand");
    state.openAnsweredAt = Date.now();
    // until the opening ends, however it ends (opened, stopped, e-stopped, a fault)
    toast("Opening the hand…", { kind: "info", timeoutMs: 30000, key: "opening" });
  } catch (e) {
    state.openPending = false;
    showError(e, "open hand");
    const msg = e instanceof ApiError ? e.error : String(e);
    setNoticeError(`Open hand was refused: ${msg}`);
  }
  updateControls();
}
$("#estop-release").addEventListener("click", () => guard("release e-stop", async () => {
  await api.release();
  clearEstopAnswer();
  renderEstopBanner();
  renderEstop(false);
  refreshStatus();
}));

// --- e-stop -----------------------------------------------------------------------------------

const USE_SWITCH = "use the hand's own emergency-stop switch";

// What POST /api/estop could not do (its answer's hand_reached / recorded false), shown in
// #estop-banner until a status says otherwise: status.estop.hand_reached (the service's word on
// the power-off, for every page) and status.estop.recorded; the release ends both. `latched`: a
// status since the answer showed the e-stop latched (a later one that does not is the release);
// `seq`: the statuses rendered before the answer came (only a later one overrules it).
const NO_ESTOP_ANSWER = Object.freeze(
  { unreached: false, unrecorded: false, detail: "", latched: false, seq: 0 });
const estopAnswer = { ...NO_ESTOP_ANSWER };
let statusSeq = 0; // statuses rendered so far (from either the socket or GET /api/status)

// status.estop.recorded: the latch is in the hand, not (yet) in the run database
const DISK_NOTES = {
  pending: "The e-stop is latched, but not on disk yet: the run database is busy (another " +
    "program holds it locked); until it is written, a restart of the service would not keep it.",
  no: "The e-stop is latched in the hand, but not on disk (the run database did not take it; " +
    "the service's log says why): a restart of the service would not keep it.",
};

/**
 * E-STOP: always sent, even when the page believes the service is gone (it may only be slow).
 * The answer may say the hand or the disk did not take it; a failure says to use the hand's
 * own switch, in a toast that stays.
 */
async function estop() {
  try {
    const r = await api.estop(); // no token needed: stopping is always allowed
    heard();
    clearToasts("e-stop");
    takeEstopAnswer(r || {});
    renderEstop(true);
    refreshStatus();
  } catch (e) {
    if (e instanceof ApiError && e.status !== 0) heard(); // it answered, with an error
    const msg = e instanceof ApiError ? e.error : String((e && e.message) || e);
    sdh2.lastError = `e-stop: ${msg}`;
    console.warn("sdh2svc:", sdh2.lastError);
    toast(`The E-STOP did not go through (${msg}): ${USE_SWITCH}.`,
      { key: "e-stop", timeoutMs: Infinity });
  }
}

function takeEstopAnswer(r) {
  const st = state.status || {};
  estopAnswer.unreached = r.hand_reached === false;
  estopAnswer.unrecorded = r.recorded === false;
  estopAnswer.detail = r.detail ? String(r.detail) : "";
  estopAnswer.seq = statusSeq;
  estopAnswer.latched = Boolean(st.estopped);
  renderEstopBanner();
}

function clearEstopAnswer() {
  Object.assign(estopAnswer, NO_ESTOP_ANSWER);
}

/** The e-stop banner from the last status and the last e-stop answer. */
function renderEstopBanner() {
  const st = state.status || {};
  const a = estopAnswer;
  if (st.estopped) a.latched = true;
  else if (a.latched) clearEstopAnswer(); // released (here or elsewhere)
  const confirmed = st.estop ? st.estop.hand_reached : undefined;
  if (typeof confirmed === "boolean" && statusSeq > a.seq) a.unreached = !confirmed; // its word
  const recorded = st.estop ? st.estop.recorded : undefined;
  if (a.unrecorded && st.estop && !DISK_NOTES[recorded]) a.unrecorded = false; // on disk now
  const hand = a.unreached
    ? `The hand has not confirmed the e-stop: the motors may still be on — ${USE_SWITCH}.` : "";
  const disk = DISK_NOTES[recorded] || (a.unrecorded ? DISK_NOTES.pending : "");
  const detail = (a.unreached || a.unrecorded) && a.detail ? `The service says: ${a.detail}.` : "";
  for (const [sel, text] of [["#estop-hand", hand], ["#estop-disk", disk], ["#estop-detail", detail]]) {
    $(sel).textContent = text;
    $(sel).hidden = !text;
  }
  $("#estop-banner").hidden = !hand && !disk;
}

/** The E-STOP button: latched or not in its text and aria-pressed too, not only its colour;
 * never disabled. */
function renderEstop(latched = Boolean(state.status && state.status.estopped)) {
  const b = $("#estop");
  const e = (state.status && state.status.estop) || {};
  b.classList.toggle("latched", latched);
  b.textContent = latched ? "E-STOP (latched)" : "E-STOP";
  b.setAttribute("aria-pressed", String(latched));
  let title = "POST /api/estop: motors off at once";
  if (latched) {
    const since = wallTime(e.since);
    title = `The e-stop is latched${since ? ` since ${since}` : ""}` +
      `${e.reason ? ` (${e.reason})` : ""}: the motors are off until it is released. ` +
      "A click sends it again.";
  }
  if (live.dead) title = `The service is not answering: a click tries all the same; ${USE_SWITCH}.`;
  b.title = title;
  renderLatchLine(latched, e);
}

/** Next to the E-STOP while it is latched, always in sight (a tooltip is not, on a touch
 * screen): since when, why, whether the hand confirmed the power-off and the disk took it. */
function renderLatchLine(latched, e) {
  const line = $("#estop-latch");
  let text = "";
  if (latched) {
    const since = wallTime(e.since);
    const at = since ? ` ${since}` : "";
    const parts = [`latched${at}${e.reason ? ` — ${e.reason}` : ""}`];
    if (e.hand_reached === true) parts.push("hand confirmed");
    else if (e.hand_reached === false) parts.push("hand NOT confirmed yet");
    if (e.recorded === "no") parts.push("not on disk");
    else if (e.recorded === "pending") parts.push("not on disk yet");
    text = parts.join(" · ");
  }
  line.textContent = text;
  line.hidden = !text;
  line.classList.toggle("unconfirmed", latched && e.hand_reached === false);
}

// --- token ------------------------------------------------------------------------------------

$("#token").value = getToken();
$("#token").addEventListener("change", () => setToken($("#token").value.trim()));

// --- object (simulation) ----------------------------------------------------------------------

// The custom entry's value: no preset's name (a custom object's name is not one the API takes).
const CUSTOM = "";

async function loadObject() {
  const sel = $("#object-select");
  try {
    const info = await api.simObject();
    state.sim = true;
    state.presets = new Set(info.presets || []);
    sel.innerHTML = "";
    for (const name of state.presets) sel.add(new Option(name, name));
    syncObject(info.object);
    updateControls();
  } catch (e) {
    if (e instanceof ApiError && e.status === 404) {
      state.sim = false; // a real hand: no object choice
      $("#object-field").hidden = true;
    } else {
      showError(e, "object");
    }
  }
}

/**
 * The selector shows the current object (`obj`: status.object or an answer's): its preset, or
 * one "NAME (custom)" entry for any other (set by another client, `--object-file`). Left alone
 * while the user's own pick is on its way.
 */
function syncObject(obj) {
  const sel = $("#object-select");
  if (!state.presets || !obj || state.objectPuts > 0) return;
  const name = obj.name || "";
  let custom = sel.querySelector("option[data-custom]");
  if (state.presets.has(name)) {
    if (custom) custom.remove();
  } else {
    const label = `${name || obj.kind || "object"} (custom)`;
    if (!custom) {
      custom = new Option(label, CUSTOM);
      custom.dataset.custom = "true";
      sel.add(custom);
    }
    if (custom.textContent !== label) custom.textContent = label;
  }
  const want = state.presets.has(name) ? name : CUSTOM;
  if (sel.value !== want) sel.value = want;
}

$("#object-select").addEventListener("change", async (ev) => {
  const sel = ev.target;
  if (!state.presets || !state.presets.has(sel.value)) return; // the custom entry: current already
  state.objectPuts += 1;
  let now = null;
  try {
    const r = await api.putSimObject(sel.value);
    now = (r && (r.object ?? r)) || null;
    clearToasts("object");
    toast(`Object: ${(now && now.name) || sel.value}`, { kind: "info", timeoutMs: 2500 });
  } catch (e) {
    showError(e, "object");
  } finally {
    state.objectPuts -= 1;
  }
  syncObject(now ?? (state.status && state.status.object)); // refused: back to the current
});

// --- status -----------------------------------------------------------------------------------

function fmt(v, digits = 1) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(digits);
  return String(v);
}

// a line's state, and why it is down (the status's links.*_down: silent, the port gone, …)
function linkState(up, why) {
  return up ? "connected" : `down${why ? `: ${why}` : ""}`;
}

function renderBus(st) {
  const t = st.links && st.links.tactile;
  const hub = st.telemetry || {};
  const rows = [];
  if (t) {
    rows.push(
      ["mode", t.mode],
      ["frames/s", fmt(t.frames_per_s)],
      ["line utilisation", `${fmt(t.line_utilisation_pct)} %`],
      ["frame age", `${fmt(t.frame_age_ms)} ms`],
      ["frames", fmt(t.frames)],
      ["CRC errors", fmt(t.crc_errors), t.crc_errors > 0],
      ["resyncs", fmt(t.resyncs), t.resyncs > 0],
      ["timeouts", fmt(t.timeouts), t.timeouts > 0],
      ["bad frames", fmt(t.bad_frames), t.bad_frames > 0],
      ["reconnects", fmt(t.reconnects), t.reconnects > 0],
      ["tactile link", linkState(t.connected && !t.silent, st.links.tactile_down),
       !t.connected || t.silent],
    );
  } else {
    rows.push(["tactile link", "not open", true]);
  }
  const j = st.hand && st.hand.connected;
  rows.push(["joint link", linkState(j && j.joints, st.links && st.links.joints_down),
             !(j && j.joints)]);
  rows.push(["telemetry clients", fmt(hub.clients)]);
  if (hub.dropped !== undefined) rows.push(["messages dropped", fmt(hub.dropped)]);
  const dl = $("#bus-stats");
  dl.innerHTML = "";
  for (const [k, v, bad] of rows) {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    if (bad) dd.className = "bad";
    dl.append(dt, dd);
  }
  dl.title = `DSA ${st.links?.dsa_url ?? "?"} · SDH ${st.links?.sdh_url ?? "?"}`;
}

function renderStatus(st) {
  const wasLatched = Boolean(state.status && state.status.estopped);
  state.status = st;
  statusSeq += 1;
  if (wasLatched && !st.estopped) forgetTrueTurn(); // the e-stop is released
  // the view's process ended: its note instead of a frame saying "Connecting…" for ever
  if (st.viewer === false && $("#viewer").dataset.url) loadViewer();
  const run = st.run;
  // a run the e-stop ended stays "e-stopped" in the status after the release: from the
  // status that says the e-stop is released, the header says so (not the latched red state)
  const released = Boolean(run && run.state === "e-stopped" && !st.estopped);
  const runState = run ? (released ? "e-stop released" : run.state) : "no run";
  sdh2.runState = run ? run.state : null;
  const rs = $("#run-state");
  rs.textContent = runState;
  rs.dataset.state = run ? (released ? "estop-released" : run.state) : "";
  rs.title = released ? `run ${run.id} was e-stopped; the e-stop has been released since` : "";
  $("#run-id").textContent = run ? String(run.id) : "–";
  $("#stroke").textContent = run ? `${run.stroke} of ${run.strokes_total}` : "–";
  $("#iteration").textContent = run ? String(run.iteration) : "–";
  // the run history's row of the running run counts along (the table loads at starts and ends)
  const row = run && run.status === "running" ? $(`#runs tr[data-run-id="${run.id}"]`) : null;
  if (row && row.cells[5]) row.cells[5].textContent = String(run.iteration);
  const msg = run && run.message ? run.message : "";
  $("#run-message").textContent = msg;
  $("#run-message").title = msg;

  // an Open hand answered 202 is pending until a status produced after the answer says so
  if (state.openPending && state.openAnsweredAt && Date.now() - state.openAnsweredAt > 600) {
    state.openPending = false;
  }
  // a start answered 201 is pending until a status shows its run
  if (state.startPending && state.startedRun != null && run && run.id >= state.startedRun) {
    state.startPending = false;
  }
  updateControls();
  renderEstopBanner();

  $("#mode-badge").textContent = st.sim ? "simulated hand" : "real hand";
  renderLinks(st.hand && st.hand.connected);
  if (st.auth_required) $("#token-field").hidden = false;

  if (st.params) {
    state.params = st.params;
    form.setValues(st.params);
    sketch.setAlpha(st.params.alpha_deg);
  }
  if (state.sim) syncObject(st.object);
  if (st.hand && Array.isArray(st.hand.angles_deg)) setPose(st.hand.angles_deg);
  noticeFromStatus(st);
  if (run && run.state !== "rolling" && Date.now() - state.lastSampleAt > CONTACT_STALE_MS) {
    sketch.setContact(null);
  }
  renderBus(st);

  // refresh the history when a run starts or ends
  const key = run ? `${run.id}:${ACTIVE.has(run.state)}` : "";
  if (key !== state.runKey) {
    state.runKey = key;
    loadRuns();
  }
}

/** The links badge, its tooltip naming the line that is down (goDead's tooltip never stays). */
function renderLinks(conn) {
  const ok = Boolean(conn && conn.joints && conn.tactile);
  const down = [];
  if (!(conn && conn.joints)) down.push("the joint line");
  if (!(conn && conn.tactile)) down.push("the tactile line");
  const ls = $("#links-state");
  ls.textContent = ok ? "links up" : "links down";
  ls.className = `badge ${ok ? "links-ok" : "links-bad"}`;
  ls.title = ok ? "the hand's two links: the joint line and the tactile line are up"
    : `${down.join(" and ")} ${down.length > 1 ? "are" : "is"} down (see the tactile bus card)`;
}

async function refreshStatus() {
  const st = await guard("status", () => api.status(STATUS_PROBE_TIMEOUT_MS));
  if (st) {
    heard();
    renderStatus(st);
  }
}

function runActive(st) {
  const run = st && st.run;
  return Boolean(run && (run.status === "running" || ACTIVE.has(run.state)));
}

/** `why`: the tooltip while disabled; `title`: while enabled, if not the button's own. */
function setButton(sel, disabled, why = "", title = "") {
  const b = $(sel);
  b.disabled = disabled;
  if (!b.dataset.title) b.dataset.title = b.title;
  b.title = disabled && why ? why : title || b.dataset.title;
}

/** Every control's enabled state, from the last status, the liveness and pending requests. */
function updateControls() {
  const st = state.status || {};
  const dead = live.dead;
  const active = runActive(st);
  const estopped = Boolean(st.estopped);
  const handOpening = Boolean(st.hand && st.hand.opening);
  const opening = handOpening || state.openPending;
  const gone = "the service is not answering";
  setButton("#start", dead || active || estopped || opening || state.startPending,
    dead ? gone : estopped ? "release the e-stop first" : active ? "a run is active"
      : opening ? "the hand is opening" : "the run is being started");
  // Stop halts an opening too (POST /api/runs/stop): the fingers hold where they are
  setButton("#stop", dead || !(active || handOpening),
    dead ? gone : "no run is active and the hand is not opening",
    !active && handOpening ? "POST /api/runs/stop: halt the opening; the fingers hold where they are" : "");
  renderEstop(); // never disabled: a page that thinks the service is gone may be wrong
  setButton("#estop-release", dead || !estopped, dead ? gone : "the e-stop is not latched");
  let why = "";
  if (dead) why = gone;
  else if (estopped) why = "Release the e-stop first: the motors are off.";
  else if (active) why = "A run is active: stop it first.";
  else if (opening) why = "The hand is opening…";
  for (const sel of ["#open-hand", "#notice-open-hand"]) setButton(sel, Boolean(why), why);
  const hint = $("#open-hand-hint");
  hint.textContent = !dead && estopped ? "release the e-stop first to open the hand"
    : !dead && opening ? "opening…" : "";
  // with the hand e-stopped nothing changes its world: the object stays (the API refuses too)
  setButton("#object-select", dead || active || estopped || state.sim === false,
    dead ? gone : estopped ? "Release the e-stop first: while it is latched the object stays as it is."
      : active ? "A run is active: the object cannot change during it." : "");
  $("#params-apply").disabled = dead;
  $("#runs-refresh").disabled = dead;
  if (state.notice) renderNotice();
}

// --- what happened to the last run, and what to do next ---------------------------------------

function sentence(text) {
  const t = text.trim();
  return !t || /[.!?…]$/.test(t) ? t : `${t}.`;
}

/** Who stopped a run, from its message ("as the service shut down", …); Stop is "on request". */
function stoppedBy(message) {
  const why = plainMessage(message || "").split(";")[0].trim();
  return !why || why.startsWith("through the API") ? "on request" : why;
}

function noticeFromStatus(st) {
  if (runActive(st)) {
    // a new run: what happened before is history
    if (state.notice && st.run && st.run.id !== state.notice.id) hideNotice();
    return;
  }
  if (state.notice && state.notice.id == null) return; // the hand's own says what came after
  const last = st.last_run;
  // the newest run the service knows: a run that has just ended is `run` before its end is
  // written and `last_run` names it; an older run's notice is history by then
  const newest = Math.max(st.run ? st.run.id : -1, last ? last.id : -1);
  if (state.notice && state.notice.id < newest) hideNotice();
  if (!last || last.id < newest) return;
  if (!NOTICE_STATUSES.has(last.status) || last.id === state.dismissedRun) return;
  if (state.notice && state.notice.id === last.id && state.notice.status === last.status) return;
  showNotice({ id: last.id, status: last.status, message: last.message || "" });
}

function showNotice(n) {
  const prev = state.notice && state.notice.id === n.id ? state.notice : {};
  state.notice = { opened: false, openStopped: "", error: "", ...prev, ...n };
  renderNotice();
}

function hideNotice() {
  state.notice = null;
  sdh2.notice = null;
  $("#run-notice").hidden = true;
}

function setNoticeError(text) {
  if (!state.notice) return;
  state.notice.error = text;
  renderNotice();
}

function renderNotice() {
  const n = state.notice;
  if (!n) return;
  const st = state.status || {};
  const estopped = Boolean(st.estopped);
  const released = state.releasedRuns.has(n.id);
  let title;
  let body;
  let next;
  switch (n.status) {
    case "faulted":
      title = `Run ${n.id} faulted:`;
      body = sentence(plainMessage(n.message) || "the safety supervisor stopped it");
      if (released) next = "The fingers moved back to the open pre-shape pose; check the object.";
      else if (String(n.message).startsWith("no_contact")) {
        next = "The fingers are holding still where the grasp gave up.";
      } else next = "The fingers are holding still; the object may still be held.";
      break;
    case "dropped":
      title = `Run ${n.id} lost the object:`;
      body = sentence(plainMessage(n.message) || "both contacts were lost");
      next = "The fingers are holding still; check where the object is before the next run.";
      break;
    case "e-stopped":
      title = `Run ${n.id} was e-stopped:`;
      body = "the motors were switched off at once.";
      next = "The fingers are not driven; the object may still be held.";
      break;
    case "open-e-stopped": // the hand's own: Open hand, e-stopped part-way
      title = "Opening the hand was e-stopped:";
      body = "the motors were switched off at once, part-way open.";
      next = "The fingers are not driven; the object may still be held.";
      break;
    case "interrupted": // the service was killed or crashed: nothing ended the run
      title = `Run ${n.id} was interrupted:`;
      body = "the service stopped during it (it was killed or crashed).";
      next = "The fingers stopped where they were; the object may still be held.";
      break;
    default: // stopped: by Stop (the API), from the 3-D view, as the service shut down
      title = `Run ${n.id} was stopped`;
      body = `${stoppedBy(n.message)}; the fingers released the object.`;
      next = "";
  }
  // an Open hand stopped part-way (Stop, an e-stop) left the fingers where they were
  const toOpen = !n.opened && (n.status !== "stopped" || Boolean(n.openStopped));
  if (n.openStopped) {
    const why = n.openStopped === "stopped" ? "" : ` (${n.openStopped})`;
    next = `Opening the hand was stopped part-way${why}: the fingers hold where ` +
      "they are; the object may still be held.";
  }
  if (n.opened) {
    next = "The hand is open now.";
  } else if (estopped) {
    next = `${next} Release the e-stop when it is safe, then open the hand.`.trim();
  } else if (toOpen) {
    next = `${next} Open the hand to let go of whatever it holds, or start the next run.`.trim();
  }
  $("#run-notice-title").textContent = title;
  $("#run-notice-body").textContent = body;
  $("#run-notice-next").textContent = next;
  const err = $("#run-notice-error");
  err.textContent = n.error || "";
  err.hidden = !n.error;
  const box = $("#run-notice");
  box.dataset.status = n.status;
  box.classList.toggle("resolved", !toOpen);
  // after a stop the run itself opened the fingers; Open hand stays in the control bar
  $("#notice-open-hand").hidden = !toOpen;
  box.hidden = false;
  sdh2.notice = `${title} ${body} ${next}`;
}

// --- is the service there? --------------------------------------------------------------------

/**
 * A wall-clock time as the page shows every one (the run history, the e-stop's latch, the
 * service's silence): local time, "YYYY-MM-DD HH:MM:SS". `t`: milliseconds since the epoch, or
 * the API's ISO time ("…+0000" too); null when there is none or it is not a time.
 */
function wallTime(t) {
  if (t === null || t === undefined || t === "") return null;
  const d = new Date(typeof t === "number" ? t : String(t).replace(/\+0000$/, "Z"));
  if (Number.isNaN(d.getTime())) return null;
  const two = (x) => String(x).padStart(2, "0");
  return `${d.getFullYear()}-${two(d.getMonth() + 1)}-${two(d.getDate())} ` +
    `${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}`;
}

/** A sign of life from the service (a message, an answer). */
function heard() {
  live.lastHeard = Date.now();
  if (live.dead) revive();
}

function goDead() {
  if (live.dead) return;
  live.dead = true;
  live.since = live.lastHeard;
  sdh2.serviceAlive = false;
  sdh2.deadSince = wallTime(live.since);
  document.body.classList.add("service-dead");
  $("#dead-text").textContent =
    `The service is not answering (since ${sdh2.deadSince}) — the hand's state is unknown.`;
  $("#dead-banner").hidden = false;
  if (sdh2.ws !== "open") $("#ws-state").textContent = "no service";
  const ls = $("#links-state");
  ls.textContent = "links unknown";
  ls.className = "badge links-unknown";
  ls.title = "the service does not answer: nothing is known about the hand's links";
  state.startPending = false; // its run may never show (a restarted service numbers anew)
  const rs = $("#run-state");
  const lastSeen = rs.textContent;
  rs.textContent = "unknown";
  rs.dataset.state = "unknown";
  rs.title = `last seen: ${lastSeen}`;
  sketch.setContact(null);
  updateControls();
  console.warn(`sdh2svc: the service is not answering (since ${sdh2.deadSince})`);
}

function revive() {
  live.dead = false;
  sdh2.serviceAlive = true;
  sdh2.deadSince = null;
  document.body.classList.remove("service-dead");
  $("#dead-banner").hidden = true;
  $("#run-state").title = "";
  clearToasts("service");
  toast(`The service answers again (it was gone since ${wallTime(live.since)}).`,
    { kind: "info", timeoutMs: 5000 });
  updateControls();
  loadRuns();
  if (state.sim === null) loadObject(); // the page loaded while the service was gone
}

/** Ask for the status once: true if the service answered (even with an error). */
function probe() {
  if (live.probing) return live.probing;
  live.probing = (async () => {
    try {
      const st = await api.status(STATUS_PROBE_TIMEOUT_MS);
      heard();
      renderStatus(st);
      if (telemetry) telemetry.kick();
      return true;
    } catch (e) {
      if (e instanceof ApiError && e.status !== 0) {
        heard(); // it answered, with an error
        return true;
      }
      goDead();
      return false;
    } finally {
      live.probing = null;
    }
  })();
  return live.probing;
}

/** While the socket is down: poll the status (every 3 s; with backoff up to 10 s when gone). */
function pollWhileClosed(now = false) {
  clearTimeout(live.timer);
  live.timer = setTimeout(async () => {
    const ok = await probe();
    live.delay = ok ? 1000 : Math.min(live.delay * 2, 10000);
    if (sdh2.ws !== "open") pollWhileClosed();
  }, now ? 0 : live.dead ? live.delay : 3000);
}

// A socket that stays open but goes silent (a frozen service) is checked over REST too.
setInterval(() => {
  if (sdh2.ws !== "open" || live.probing || Date.now() - live.lastHeard < SILENT_SOCKET_MS) return;
  probe().then((ok) => {
    if (!ok && telemetry) telemetry.drop(`no message for ${SILENT_SOCKET_MS / 1000} s`);
  });
}, 1000);

// Wire axes of φ2…φ5: SDH2 defaults until GET /api/config gives the service's [axes].
let poseAxes = [1, 2, 5, 6];

function setPose(angles) {
  if (angles.length >= 7) sketch.setAngles(poseAxes.map((i) => angles[i]));
}

// --- telemetry --------------------------------------------------------------------------------

// The sim's object falls when the fingers open (a run's releasing, Open hand) as when it slips
// out mid-run: its truth says `dropped` both times. Whether the fingers were letting go when
// it first fell tells a release from a drop (kept until the object is placed again).
const fate = { dropped: false, released: false };

function lettingGo() {
  const st = state.status || {};
  const run = st.run || {};
  return Boolean(st.hand && st.hand.opening) || state.opening !== null || state.openPending ||
    ["releasing", "done", "stopped"].includes(run.state) ||
    (run.id != null && state.releasedRuns.has(run.id));
}

/** The sim's truth, `released` added when the fingers let go of the object on purpose. */
function withFate(truth) {
  if (!truth) return truth;
  if (!truth.dropped) fate.released = false;
  else if (!fate.dropped) fate.released = lettingGo(); // it fell just now
  fate.dropped = Boolean(truth.dropped);
  return { ...truth, released: fate.released };
}

// What an event's sentence may quote: the samples of recent iterations (the reversal's own
// comes right after it), α in force, the iteration of the run's previous reversal.
const recent = { samples: new Map(), lastReversal: new Map(), pending: [] };

function rememberSample(runId, s) {
  recent.samples.set(s.iteration, s);
  if (recent.samples.size > 400) recent.samples.delete(recent.samples.keys().next().value);
  // a reversal waits for its iteration's sample (at most a moment): its margin is in it
  while (recent.pending.length && recent.pending[0].iteration <= s.iteration) {
    const p = recent.pending.shift();
    clearTimeout(p.timer);
    p.done();
  }
}

const MAX_EVENTS = 60; // in the list, newest first

/** An event's list item (its sentence written by `writeEvent`). */
function eventItem(m) {
  const li = document.createElement("li");
  li.className = m.kind;
  li.dataset.kind = m.kind;
  return li;
}

/** The event as a sentence (`ctx`: see eventSentence) and where it happened. */
function writeEvent(li, m, ctx) {
  const where = m.run_id != null ? `run ${m.run_id}${m.iteration != null ? `, it ${m.iteration}` : ""}` : "hand";
  li.textContent = `${eventSentence(m, ctx)} `;
  const small = document.createElement("small");
  small.textContent = `(${where})`;
  li.appendChild(small);
}

/** The event on the live plots' iteration axis, if it is of the live run and has a marker. */
function markEvent(m) {
  if (m.run_id != null && m.run_id === state.liveRunId && m.iteration != null && MARKERS[m.kind]) {
    plots.markLive({ x: m.iteration, kind: m.kind, text: m.kind });
  }
}

/** A live event at the top of the list. */
function addEvent(m) {
  const li = eventItem(m);
  const ol = $("#events");
  ol.prepend(li);
  if (m.run_id != null) shownLive(m);
  while (ol.children.length > MAX_EVENTS) ol.lastElementChild.remove();
  const write = () => {
    const sample = recent.samples.get(m.iteration);
    const ctx = { alpha: coneAlpha(sample, state.params.alpha_deg), sample };
    if (m.kind === "reversal" && m.run_id != null && m.iteration != null) {
      const prev = recent.lastReversal.get(m.run_id);
      if (prev !== undefined) ctx.since = m.iteration - prev;
      recent.lastReversal.set(m.run_id, m.iteration);
    }
    writeEvent(li, m, ctx);
  };
  if (m.kind === "reversal" && m.iteration != null && !recent.samples.has(m.iteration)) {
    const p = { iteration: m.iteration, done: write, timer: 0 };
    p.timer = setTimeout(() => {
      recent.pending = recent.pending.filter((x) => x !== p);
      write();
    }, 500);
    recent.pending.push(p);
  } else {
    write();
  }
  markEvent(m);
  eventNotice(m);
}

/** An event from the run's record, below those listed (`samples`: the recorded ones by
 * iteration; `since`: iterations since the previous reversal). */
function addOlderEvent(m, samples, since) {
  markEvent(m);
  const ol = $("#events");
  if (ol.children.length >= MAX_EVENTS) return;
  const li = eventItem(m);
  li.dataset.backfilled = "true";
  ol.append(li);
  const sample = samples.get(m.iteration);
  const ctx = { alpha: coneAlpha(sample, state.params.alpha_deg), sample };
  if (since !== undefined) ctx.since = since;
  writeEvent(li, m, ctx);
}

/** Events that change what the notice says (`fault` comes before the run's `end`). */
function eventNotice(m) {
  const d = (m.detail && typeof m.detail === "object") ? m.detail : {};
  if (m.kind === "phase" && d.phase === "releasing" && m.run_id != null) {
    state.releasedRuns.add(m.run_id);
  } else if (m.kind === "fault" && m.run_id != null) {
    const status = d.fault === "dropped" ? "dropped" : "faulted";
    const message = d.fault ? `${d.fault}: ${d.message ?? ""}` : String(d.message ?? "");
    if (m.run_id !== state.dismissedRun) showNotice({ id: m.run_id, status, message });
  } else if (m.kind === "end" && m.run_id != null && NOTICE_STATUSES.has(d.status)) {
    if (m.run_id !== state.dismissedRun) {
      showNotice({ id: m.run_id, status: d.status, message: d.message ?? "" });
    }
  } else if (m.kind === "estop" && m.run_id != null && m.run_id !== state.dismissedRun) {
    showNotice({ id: m.run_id, status: "e-stopped", message: "emergency stop" });
  } else if (m.kind === "estop" && m.run_id == null && openingEstopped()) {
    openEstopNotice();
  } else if (m.kind === "open") {
    state.opening = { stoppedAt: null };
    if (state.notice) {
      state.notice.openStopped = ""; // opening (again)
      renderNotice();
    }
  } else if (m.kind === "opened") {
    // `completed: false`: stopped part-way (Stop, an e-stop): the hand is not open
    const done = d.completed !== false;
    state.opening = done ? null : { stoppedAt: Date.now() };
    if (!done && state.status && state.status.estopped) {
      openEstopNotice(); // (else the e-stop's own event, which follows, says it)
    } else if (state.notice) {
      state.notice.opened = done;
      state.notice.openStopped = done ? "" : plainMessage(d.message) || "stopped";
      state.notice.error = "";
      renderNotice();
    }
  }
  if (m.kind === "opened" || m.kind === "fault" || (m.kind === "estop" && m.run_id == null)) {
    if (m.kind === "fault") state.opening = null;
    state.openPending = false;
    clearToasts("opening"); // however the opening ended
    updateControls();
  }
}

// an opening that ended stopped part-way this long before the hand's e-stop event was stopped by it
const OPENING_ESTOP_MS = 5000;

/** The hand's e-stop came while it opened (its `opened` said stopped part-way just before, or
 * it has not ended yet). */
function openingEstopped() {
  const o = state.opening;
  return Boolean(o) && (o.stoppedAt === null || Date.now() - o.stoppedAt < OPENING_ESTOP_MS);
}

/** An opening e-stopped part-way: a notice of its own (not a line of the last run's, which it
 * replaces: what came after). */
function openEstopNotice() {
  state.opening = null;
  if (state.notice && state.notice.id != null) state.dismissedRun = state.notice.id;
  state.notice = null;
  showNotice({ id: null, status: "open-e-stopped", message: "" });
}

// --- joining a run mid-way ----------------------------------------------------------------------

const BACKFILL_PAGE = 1000; // samples per request (the API's limit is 10 000)
// the recorder writes every 50 ms: how often, and how long, to wait for what it has not written
const BACKFILL_WAITS = 20;
const BACKFILL_WAIT_MS = 100;
const backfilled = { runId: null, busy: false };
// the events shown live, per run (the last few runs), so that the record's copy is not shown twice
const liveEvents = new Map();
const eventKey = (m) => `${m.kind}|${m.iteration}|${m.t}`;

function shownLive(m) {
  if (!liveEvents.has(m.run_id)) {
    liveEvents.set(m.run_id, new Set());
    if (liveEvents.size > 3) liveEvents.delete(liveEvents.keys().next().value);
  }
  liveEvents.get(m.run_id).add(eventKey(m));
}

/**
 * The run's iterations before `first` (the first live sample seen, at time `t0`) and its events
 * before that, from its record: a page opened or reloaded mid-run shows the whole run (as far
 * as the plots' window goes), not only what came after it loaded. The live samples come
 * before the recorder's next write (every 50 ms): the record is read until it reaches `first`.
 */
async function backfill(runId, first, t0) {
  if (backfilled.busy) return;
  backfilled.busy = true;
  try {
    const older = [];
    let from = Math.max(0, first - plots.live.limit); // the plots' window of iterations
    for (let waits = 0; waits < BACKFILL_WAITS; ) {
      const page = await api.samplesFrom(runId, from, BACKFILL_PAGE);
      const got = page.samples.filter((x) => x.iteration < first);
      older.push(...got);
      if (got.length) from = got[got.length - 1].iteration + 1;
      // the record reaches the first live sample: it holds every one before it (in order)
      if (got.length < page.samples.length) break;
      if (page.samples.length < BACKFILL_PAGE) { // the newest are not written yet
        waits += 1;
        await new Promise((done) => setTimeout(done, BACKFILL_WAIT_MS));
      }
    }
    const run = await api.run(runId);
    recordedPsi0(runId).catch(() => {}); // optional: the backfill does not wait for it
    if (state.liveRunId !== runId) return; // another run began meanwhile
    plots.prependLive(older, state.params);
    const bySample = new Map(older.map((x) => [x.iteration, x]));
    const seen = liveEvents.get(runId) ?? new Set();
    const events = [];
    let last; // the iteration of the previous reversal, for each reversal's "since"
    for (const e of run.events || []) {
      if (e.t > t0) break;
      const m = { type: "event", run_id: runId, ...e };
      const since = m.kind === "reversal" && last !== undefined ? m.iteration - last : undefined;
      if (m.kind === "reversal") last = m.iteration;
      if (!seen.has(eventKey(m))) events.push({ m, since });
    }
    for (const { m, since } of events.reverse()) { // newest first, below those already listed
      addOlderEvent(m, bySample, since);
    }
    if (last !== undefined && !recent.lastReversal.has(runId)) recent.lastReversal.set(runId, last);
    sdh2.backfilled = { samples: older.length, events: events.length };
  } catch (e) {
    showError(e, "backfill");
  } finally {
    backfilled.busy = false;
  }
}

function onMessage(m) {
  heard();
  switch (m.type) {
    case "hello":
    case "status":
      sdh2.statusMsgs += 1;
      renderStatus(m.status);
      break;
    case "sample": {
      sdh2.samples += 1;
      const s = m.sample;
      if (m.run_id !== state.liveRunId) {
        state.liveRunId = m.run_id;
        plots.resetLive();
      }
      if (m.run_id !== backfilled.runId) {
        backfilled.runId = m.run_id;
        // the page may have joined mid-run (opened or reloaded): what it missed, from the record
        backfill(m.run_id, s.iteration, s.t);
      }
      plots.push(s, state.params);
      rememberSample(m.run_id, s);
      state.lastSampleAt = Date.now();
      state.lastSample = s;
      sketch.setContact(s);
      if (m.run_id !== liveTurn.runId) { // ψ at the grasp: only from the run's first samples
        liveTurn.runId = m.run_id;
        liveTurn.psi0 = s.iteration <= 1 ? liveTurn.psi : null;
      }
      liveTurn.atSample = turnedDeg(liveTurn.psi, liveTurn.psi0);
      if (!replay.active) showObject(readout, s, liveTrueTurn());
      break;
    }
    case "tactile":
      sdh2.tactile += 1;
      state.lastTactile = m.matrices;
      if (!replay.active) pads.update(m.matrices); // a replay shows its own frames
      break;
    case "pose":
      setPose(m.angles_deg || []);
      break;
    case "sim":
      sketch.setTruth(withFate(m.truth));
      liveTurn.psi = m.truth && m.truth.pose ? m.truth.pose[2] : null;
      break;
    case "event":
      sdh2.events += 1;
      addEvent(m);
      break;
    case "dropped":
      sdh2.dropped = m.count;
      $("#ws-state").textContent = `live (${m.count} dropped)`;
      $("#ws-state").title = `telemetry WebSocket: ${m.count} messages dropped for this page ` +
        "(the page could not keep up; the oldest go first)";
      break;
    default:
      break;
  }
}

function onWsState(s, info) {
  const was = sdh2.ws;
  sdh2.ws = s;
  const el = $("#ws-state");
  el.className = `badge ws-${s}`;
  if (s === "open") {
    sdh2.connects += 1;
    el.textContent = "live";
    el.title = "telemetry WebSocket";
    heard();
    if (sdh2.connects > 1) loadViewer(); // the service may be another one, or its view gone
    clearTimeout(live.timer);
    live.delay = 1000;
  } else if (s === "connecting") {
    el.textContent = live.dead ? "no service — trying…" : "connecting…";
  } else {
    // counted down each second until the retry (the state changes then)
    const retryAt = Date.now() + info.retryInS * 1000;
    const countdown = () => {
      if (sdh2.ws !== s || el.dataset.retryAt !== String(retryAt)) return;
      const left = Math.ceil(Math.max(0, retryAt - Date.now()) / 1000);
      el.textContent = `${live.dead ? "no service" : "disconnected"} — retry in ${left} s`;
      if (left > 0) setTimeout(countdown, 250);
    };
    el.dataset.retryAt = String(retryAt);
    countdown();
    el.title = `telemetry WebSocket closed (${info.reason})`;
    // is the service still there? ask at once when the socket has just closed, then keep the
    // status fresh over REST while the socket is down
    if (was === "open" || !live.timer) pollWhileClosed(was === "open");
  }
}

// --- run history and replay -------------------------------------------------------------------

function cell(tr, text, cls) {
  const td = document.createElement("td");
  td.textContent = text ?? "–";
  if (cls) td.className = cls;
  tr.appendChild(td);
  return td;
}

// One load at a time; a load asked for while one is in flight runs again after it, so a click
// on Refresh always gets an answer the server gave after the click (not one an earlier load,
// started by a run's start or end, brings back).
let runsLoading = null;
let runsAgain = false;
const RUNS_PAGE = 50; // runs listed at first, and more with each "Older runs"
const RUNS_MOST = 999; // listed at most (the API gives 1000 a page: one more tells of older)
let runsShown = RUNS_PAGE;
async function loadRuns() {
  if (runsLoading) {
    runsAgain = true;
    return runsLoading;
  }
  runsLoading = (async () => {
    try {
      do {
        runsAgain = false;
        try {
          const runs = (await api.runs(runsShown + 1)) || []; // one more: are there older?
          clearToasts("run history");
          renderRuns(runs.slice(0, runsShown));
          $("#runs-older").hidden = runs.length <= runsShown || runsShown >= RUNS_MOST;
        } catch (e) {
          showError(e, "run history");
        }
      } while (runsAgain);
    } finally {
      runsLoading = null;
    }
  })();
  return runsLoading;
}

function renderRuns(runs) {
  const tbody = $("#runs tbody");
  tbody.innerHTML = "";
  if (!runs.length) {
    const tr = document.createElement("tr");
    cell(tr, "no runs recorded yet").colSpan = 9;
    tbody.appendChild(tr);
    return;
  }
  for (const r of runs) {
    const tr = document.createElement("tr");
    tr.dataset.runId = String(r.id);
    if (r.id === state.replayId) tr.className = "replaying";
    const sum = r.summary || {};
    const meta = r.meta || {};
    cell(tr, String(r.id));
    cell(tr, wallTime(r.started ?? r.started_at));
    cell(tr, wallTime(r.finished ?? r.ended_at));
    cell(tr, r.status, `status-${r.status}`);
    cell(tr, meta.object ? meta.object.name ?? meta.object.kind : "–");
    cell(tr, fmt(r.iterations ?? sum.iterations));
    cell(tr, fmt(sum.strokes));
    const bits = [];
    if (sum.message) bits.push(sum.message);
    if (sum.force && typeof sum.force.mean === "number") {
      bits.push(`F ${fmt(sum.force.mean, 2)}±${fmt(sum.force.sd, 2)}`);
    }
    if (sum.loop_hz) bits.push(`${fmt(sum.loop_hz)} Hz`);
    const rec = sum.recognition;
    if (rec && rec.object_class) {
      bits.push(`${rec.object_class} ${Math.round(100 * (rec.confidence ?? 0))} %`);
    }
    const est = rec && typeof rec.rotation_range_deg === "number" ? rec.rotation_range_deg : null;
    const truly = sum.truth && typeof sum.truth.rotation_range_deg === "number"
      ? sum.truth.rotation_range_deg : null;
    // a run that never rolled (no iteration) turned nothing: no rotation said
    const rolled = Number(r.iterations ?? sum.iterations) > 0;
    const trueRot = truly !== null ? ` (true ${fmt(truly)}°)` : "";
    if (rolled && est !== null) bits.push(`rot ${fmt(est)}°${trueRot}`);
    else if (rolled && truly !== null) bits.push(`true rot ${fmt(truly)}°`);
    cell(tr, bits.join(" · "));
    const td = cell(tr, "", "actions");
    const replay = document.createElement("button");
    replay.className = "btn small secondary replay";
    replay.type = "button";
    replay.textContent = "Replay";
    replay.setAttribute("aria-label", `Replay run ${r.id}`); // a screen reader tells the rows apart
    replay.addEventListener("click", () => replayRun(r));
    td.appendChild(replay);
    for (const f of ["csv", "mcap"]) {
      const a = document.createElement("a");
      a.href = api.exportUrl(r.id, f);
      a.textContent = f.toUpperCase();
      a.setAttribute("download", `run-${r.id}.${f}`);
      a.setAttribute("aria-label", `run ${r.id} as ${f.toUpperCase()}`);
      a.className = `export-${f}`;
      td.appendChild(a);
    }
    if (r.status !== "running") {
      const del = document.createElement("button");
      del.className = "btn small secondary delete";
      del.type = "button";
      del.textContent = "Delete";
      del.setAttribute("aria-label", `Delete run ${r.id}`);
      del.title = `DELETE /api/runs/${r.id}`;
      del.addEventListener("click", () => deleteRun(r));
      td.appendChild(del);
    }
    tbody.appendChild(tr);
  }
}

/** Delete a recorded run, once the person has said so (nothing of it can be had back). */
async function deleteRun(r) {
  const what = `Delete run ${r.id} (${r.status}, ${r.iterations ?? 0} iterations) and ` +
    "everything recorded with it? It cannot be undone.";
  if (!window.confirm(what)) return;
  const done = await guard(`delete run ${r.id}`, () => api.deleteRun(r.id));
  if (done && state.replayId === r.id) backToLive();
  await loadRuns(); // also after a refusal: the list shows what is there now
}

const replayData = { runId: null, frames: new Map(), truth: null, viewer: false, psi0: null };

// In simulation, the object's true angle ψ (rad): the newest, and the live run's at its grasp;
// and how far (°) it had turned at the run's newest sample, which the readout shows
const liveTurn = { runId: null, psi: null, psi0: null, atSample: null };

/** A page that joined mid-run missed ψ at the grasp: it takes the truth recorded with the run's
 * first sample, as a replay does (simulation only: a real hand's run has no truth). */
async function recordedPsi0(runId) {
  if (liveTurn.runId !== runId || liveTurn.psi0 !== null) return;
  const page = await api.truth(runId, 0, 1);
  const row = page.truth && page.truth[0];
  if (row && liveTurn.runId === runId && liveTurn.psi0 === null) liveTurn.psi0 = row.psi;
}

/** How far the object truly turned from ψ0 to ψ (rad), in degrees; null: either unknown. */
function turnedDeg(psi, psi0) {
  return typeof psi === "number" && typeof psi0 === "number" ? ((psi - psi0) * 180) / Math.PI : null;
}

/** The e-stop was released: the fingers are driven again and the object may have fallen or
 * been put back meanwhile, so the truth no longer belongs to the run whose last sample the
 * readout shows; its true turn is not known any more ("–", not the value at the e-stop). A
 * new run's first samples give it again. */
function forgetTrueTurn() {
  liveTurn.runId = null;
  liveTurn.psi0 = null;
  liveTurn.atSample = null;
  if (!replay.active) showObject(readout, state.lastSample ?? null, liveTrueTurn());
}

/** The live run's true turn at the sample the readout shows: in simulation a number or null
 * (not known); undefined on a real hand, which has no truth. Not the newest ψ's: after the run
 * the object is let go, put back or swapped for another, and the readout still shows the run's
 * last sample. */
function liveTrueTurn() {
  return state.sim ? liveTurn.atSample : undefined;
}

/** The sim truth recorded with sample `s` of the replayed run, as the live `sim` message's
 * (null: none recorded, e.g. a real hand's run). */
function replayTruth(s) {
  const t = replayData.truth;
  const row = s && t && t.outline ? t.rows.get(s.iteration) : undefined;
  return row ? placedTruth(t.outline, row) : null;
}

/** The scrubber moved to sample `idx`: the plots' cursors and legends, the pads, the sketch and
 * (through the service) the 3-D view show that iteration. */
function showReplayIndex(idx, s) {
  sdh2.replayIndex = idx;
  plots.pin(idx);
  const it = s.iteration ?? idx;
  const frame = replayData.frames.get(it);
  if (frame) pads.update(frame, it);
  else pads.update([], it);
  const truth = replayTruth(s);
  sketch.setOverride(s, truth);
  // a real hand's run has no truth at all (no outline): the readout leaves it out
  const truly = truth ? turnedDeg(truth.pose[2], replayData.psi0) : null;
  showObject(readout, s, replayData.truth && replayData.truth.outline ? truly : undefined);
  feedOutline(idx);
  feedViewer(replayData.runId, it);
}

// The sketch's reconstructed outline in a replay: the shown iteration's, made by the service
// (control.recognition.outline, milliseconds each: asked for one at a time, the newest wanted,
// kept with the sample once had).
const outlineFeed = { want: null, busy: false };

async function feedOutline(idx) {
  outlineFeed.want = idx;
  if (outlineFeed.busy) return;
  outlineFeed.busy = true;
  try {
    while (outlineFeed.want !== null) {
      const i = outlineFeed.want;
      outlineFeed.want = null;
      const runId = replayData.runId;
      const s = replay.samples[i];
      if (runId === null || !s || s.estimate_outline !== undefined) continue;
      if (!s.object_class) {
        s.estimate_outline = []; // no class: nothing reconstructed
        continue;
      }
      const got = (await api.samplesFrom(runId, s.iteration, 1, { outline: true })).samples[0];
      if (replayData.runId !== runId) continue; // back to live (or another run) meanwhile
      s.estimate_outline = got && got.iteration === s.iteration ? got.estimate_outline : [];
      if (replay.index === i) sketch.setOverride(s, replayTruth(s));
    }
  } catch (e) {
    showError(e, "replay outline");
  } finally {
    outlineFeed.busy = false;
  }
}

// The 3-D view follows the scrubber: the newest iteration, at most every VIEW_FEED_MS, one
// request at a time.
const viewFeed = { want: null, busy: false, sentAt: 0, timer: 0 };

function feedViewer(runId, iteration) {
  if (!replayData.viewer) return;
  viewFeed.want = { runId, iteration };
  pumpViewFeed();
}

async function pumpViewFeed() {
  if (viewFeed.busy || !viewFeed.want) return;
  const wait = viewFeed.sentAt + VIEW_FEED_MS - Date.now();
  if (wait > 0) {
    clearTimeout(viewFeed.timer);
    viewFeed.timer = setTimeout(pumpViewFeed, wait);
    return;
  }
  const { runId, iteration } = viewFeed.want;
  viewFeed.want = null;
  viewFeed.busy = true;
  viewFeed.sentAt = Date.now();
  try {
    await api.showReplay(runId, iteration);
    sdh2.viewerFeeds += 1;
    clearToasts("3-D view replay");
  } catch (e) {
    if (e instanceof ApiError && e.status === 409) replayData.viewer = false; // the view is off
    else if (e instanceof ApiError && e.status === 0) console.warn("sdh2svc:", e.error); // busy
    else showError(e, "3-D view replay");
  } finally {
    viewFeed.busy = false;
  }
  if (replayData.runId === null) endViewerReplay(); // back to live meanwhile
  else pumpViewFeed();
}

function endViewerReplay() {
  viewFeed.want = null;
  clearTimeout(viewFeed.timer);
  if (!replayData.viewer || viewFeed.busy) return;
  replayData.viewer = false;
  api.endReplay().catch((e) => showError(e, "3-D view replay"));
}

// At most about this many iterations of a run are loaded for its replay (≈ 3 kB of JSON and
// 1 kB of texels each: a run of hours would not fit in the page); a longer run is shown at one
// iteration in `every`, the same ones of its samples, frames and truth.
const REPLAY_MAX_SAMPLES = 10000;

/** 2 → "2nd", 3 → "3rd", 11 → "11th", 21 → "21st". */
function ordinal(n) {
  const teen = n % 100 >= 11 && n % 100 <= 13;
  return `${n}${teen ? "th" : ["th", "st", "nd", "rd"][n % 10] ?? "th"}`;
}

async function replayRun(r) {
  const banner = $("#replay-banner");
  banner.hidden = false;
  $("#replay-text").textContent = `Loading run ${r.id}…`;
  try {
    const total = Number.isFinite(r.iterations) ? r.iterations
      : (await api.samplesFrom(r.id, 0, 1)).total;
    const every = Math.max(1, Math.ceil(total / REPLAY_MAX_SAMPLES));
    const [samples, run] = await Promise.all([
      allSamples(r.id, (n, of) => {
        $("#replay-text").textContent = `Loading run ${r.id}: ${n} of ${of} samples…`;
      }, 5000, every),
      api.run(r.id),
    ]);
    const frames = await allFrames(r.id, (n, of) => {
      $("#replay-text").textContent = `Loading run ${r.id}: ${n} of ${of} tactile frames…`;
    }, 2000, every);
    const truth = await allTruth(r.id, 10000, every);
    const params = (r.meta && r.meta.params) || state.params;
    const events = (run && run.events) || [];
    const markers = events
      .filter((e) => MARKERS[e.kind] && e.iteration != null)
      .map((e) => ({ x: e.iteration, kind: e.kind, text: eventSentence(e) }));
    plots.showReplay(samples, params, markers);
    if (params && params.alpha_deg !== undefined) sketch.setAlpha(params.alpha_deg);
    state.replayId = r.id;
    sdh2.replaying = r.id;
    replayData.runId = r.id;
    replayData.frames = frames;
    replayData.truth = truth;
    const first = samples.length ? replayTruth(samples[0]) : null; // ψ at the grasp
    replayData.psi0 = first ? first.pose[2] : null;
    replayData.viewer = !$("#viewer").hidden && Boolean($("#viewer").dataset.url);
    const reversals = markers.filter((m) => m.kind === "reversal").length;
    const shown = every > 1 ? ` (every ${ordinal(every)} shown)` : "";
    $("#replay-text").textContent = `Run ${r.id} (${r.status}): ` +
      `${every > 1 ? total : samples.length} iterations${shown}, ` +
      `${reversals} reversal${reversals === 1 ? "" : "s"}`;
    banner.dataset.every = String(every);
    for (const tr of document.querySelectorAll("#runs tbody tr")) {
      tr.classList.toggle("replaying", tr.dataset.runId === String(r.id));
    }
    replay.load(samples);
    clearToasts(`replay run ${r.id}`);
    window.scrollTo({ top: 0, left: 0 }); // the stage: plots, pads and sketch follow the scrubber
  } catch (e) {
    if (!replay.active) banner.hidden = true;
    showError(e, `replay run ${r.id}`);
  }
}

function backToLive() {
  replay.clear();
  replayData.runId = null;
  replayData.frames = new Map();
  replayData.truth = null;
  endViewerReplay();
  plots.showLive();
  sketch.setOverride(null);
  showObject(readout, state.lastSample ?? null, liveTrueTurn());
  pads.update(state.lastTactile ?? [], null);
  if (state.params.alpha_deg !== undefined) sketch.setAlpha(state.params.alpha_deg);
  state.replayId = null;
  sdh2.replaying = null;
  sdh2.replayIndex = null;
  $("#replay-banner").hidden = true;
  for (const tr of document.querySelectorAll("#runs tbody tr.replaying")) tr.classList.remove("replaying");
}

// a page closed mid-replay: the 3-D view goes live again (the service also times it out)
window.addEventListener("pagehide", () => {
  if (replayData.viewer && replayData.runId !== null) {
    const headers = { "Content-Type": "application/json" };
    const token = getToken();
    if (token) headers.Authorization = `Bearer ${token}`;
    fetch("/api/viewer/replay", { method: "DELETE", headers, body: "{}", keepalive: true });
  }
});

$("#back-to-live").addEventListener("click", backToLive);
$("#runs-refresh").addEventListener("click", () => loadRuns());
$("#runs-older").addEventListener("click", () => {
  runsShown = Math.min(runsShown + RUNS_PAGE, RUNS_MOST);
  loadRuns();
});

// --- 3-D view ---------------------------------------------------------------------------------

const VIEWER_OFF = "The 3-D view is not available: the service was started with --no-viewer, " +
  "viser is missing, or the view's process ended (the service's log says which; a restart of " +
  "the service starts the view again).";
// The iframe loads when its card first scrolls into sight; from then on a new address loads at once.
const viewerLoad = { observer: null, seen: false };

/** GET /api/viewer, at start and at every reconnection: the view may have gone, or come. */
async function loadViewer() {
  const frame = $("#viewer");
  const note = $("#viewer-note");
  const link = $("#viewer-link");
  try {
    const v = await api.viewer();
    if (!v || !v.url) {
      note.textContent = VIEWER_OFF;
      note.hidden = false;
      frame.hidden = true;
      frame.dataset.url = "";
      if (frame.getAttribute("src") !== "about:blank") frame.src = "about:blank"; // not a frozen view
      link.hidden = true;
      replayData.viewer = false;
      return;
    }
    const url = new URL(v.url);
    // a viewer bound to a wildcard or loopback address: reach it on the host this page came from
    const local = ["0.0.0.0", "::", "[::]", "127.0.0.1", "localhost"];
    if (local.includes(url.hostname) && !local.includes(location.hostname)) {
      url.hostname = location.hostname;
    }
    note.hidden = true;
    link.href = url.toString();
    link.hidden = false;
    if (frame.dataset.url === url.toString() && !frame.hidden) return; // the same view: kept
    frame.hidden = false;
    frame.dataset.url = url.toString();
    showViewer(frame);
  } catch (e) {
    note.textContent = "The 3-D view's address is unknown (GET /api/viewer failed).";
    note.hidden = false;
    showError(e, "3-D view");
  }
}

/** The WebGL view is heavy (a software renderer can starve a small machine): load it when its
 * card first scrolls into sight, and keep it from then on. */
function showViewer(frame) {
  if (viewerLoad.seen) {
    frame.src = frame.dataset.url;
    return;
  }
  if (viewerLoad.observer) return; // still out of sight: it loads dataset.url when seen
  viewerLoad.observer = new IntersectionObserver((entries) => {
    if (!entries.some((e) => e.isIntersecting)) return;
    viewerLoad.observer.disconnect();
    viewerLoad.observer = null;
    viewerLoad.seen = true;
    frame.src = frame.dataset.url;
  }, { rootMargin: "80px" });
  viewerLoad.observer.observe(frame);
}

// --- start ------------------------------------------------------------------------------------

async function init() {
  const [schema, config] = await Promise.all([
    guard("parameter schema", api.paramsSchema),
    guard("configuration", api.config),
    loadObject(),
  ]);
  if (config) {
    configureHand(config.hand);
    const a = config.axes;
    poseAxes = [a.phi2, a.phi3, a.phi4, a.phi5];
  }
  if (schema) form.build(schema);
  const params = await guard("parameters", api.params);
  if (params) {
    state.params = params;
    form.setValues(params, true);
    sketch.setAlpha(params.alpha_deg);
  }
  await refreshStatus();
  loadViewer();
  loadRuns();
  telemetry = new Telemetry({ onMessage, onState: onWsState });
  // onMessage: feed a telemetry message as if it came from the socket (tests);
  // status(): the last status rendered
  // replay: the scrubber; expireToasts(now): toasts past their time at `now` go
  window.sdh2debug = { telemetry, plots, pads, sketch, form, onMessage, replay, expireToasts,
    toast, status: () => state.status, liveTurn };
  telemetry.start();
}

init();
