// REST and WebSocket access to the sdh2svc service (docs/api.md).
//
// Every REST error answer is JSON {"error": "...", "details": [...]}; `request` turns it into an
// ApiError carrying both, so callers can show the sentence and put field details next to fields.

const TOKEN_KEY = "sdh2svc.token";

export class ApiError extends Error {
  constructor(status, error, details) {
    super(error);
    this.status = status;
    this.error = error;
    this.details = Array.isArray(details) ? details : [];
  }
}

export function getToken() {
  try {
    return localStorage.getItem(TOKEN_KEY) || "";
  } catch {
    return "";
  }
}

export function setToken(token) {
  try {
    if (token) localStorage.setItem(TOKEN_KEY, token);
    else localStorage.removeItem(TOKEN_KEY);
  } catch {
    /* private mode: the token lives for this page only */
  }
}

const MUTATING = new Set(["POST", "PUT", "PATCH"]);

/**
 * One REST call; resolves to the parsed JSON (or null), rejects with an ApiError.
 *
 * Every mutating request carries a JSON body (`{}` when there is nothing to say) and
 * `Content-Type: application/json`: the service answers 415 otherwise. Options: `timeoutMs`
 * (the call fails as "does not answer" after it), `auth` (false: no Authorization header).
 */
export async function request(method, path, body, { timeoutMs = 0, auth = true } = {}) {
  const headers = {};
  const token = auth ? getToken() : "";
  if (token) headers["Authorization"] = `Bearer ${token}`;
  const init = { method, headers, cache: "no-store" };
  if (body !== undefined || MUTATING.has(method)) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body === undefined ? {} : body);
  }
  if (timeoutMs > 0) init.signal = AbortSignal.timeout(timeoutMs);
  let resp;
  let text;
  try {
    resp = await fetch(path, init);
    text = await resp.text();
  } catch (e) {
    const why = e && e.name === "TimeoutError" ? `no answer within ${timeoutMs / 1000} s` : e.message;
    throw new ApiError(0, `${method} ${path}: the service does not answer (${why})`, []);
  }
  let data = null;
  if (text) {
    try {
      data = JSON.parse(text);
    } catch {
      data = null;
    }
  }
  if (!resp.ok) {
    const msg = (data && data.error) || `${method} ${path}: HTTP ${resp.status} ${text.slice(0, 200)}`;
    throw new ApiError(resp.status, msg, data && data.details);
  }
  return data;
}

/**
 * The e-stop needs no token (stopping is always allowed): it goes with the stored token if
 * there is one (older services want it), and once more without it if that token is refused.
 */
async function estop() {
  try {
    return await request("POST", "/api/estop", {}, { timeoutMs: 5000 });
  } catch (e) {
    if (e instanceof ApiError && e.status === 401 && getToken()) {
      return request("POST", "/api/estop", {}, { timeoutMs: 5000, auth: false });
    }
    throw e;
  }
}

export const api = {
  status: (timeoutMs = 0) => request("GET", "/api/status", undefined, { timeoutMs }),
  params: () => request("GET", "/api/params"),
  paramsSchema: () => request("GET", "/api/params/schema"),
  patchParams: (patch) => request("PATCH", "/api/params", patch),
  startRun: (body) => request("POST", "/api/runs", body),
  stopRun: () => request("POST", "/api/runs/stop", {}),
  runs: (limit) => request("GET", `/api/runs?limit=${limit}`),
  deleteRun: (id) => request("DELETE", `/api/runs/${id}`, {}),
  run: (id) => request("GET", `/api/runs/${id}`),
  /** Samples by iteration: from `from` on, one iteration in `every`; the page's `next` goes on. */
  samplesFrom: (id, from, limit, { every = 1, outline = false } = {}) => request("GET",
    `/api/runs/${id}/samples?from=${from}&limit=${limit}&every=${every}` +
    (outline ? "&outline=true" : "")),
  frames: (id, from, limit, every = 1) =>
    request("GET", `/api/runs/${id}/frames?from=${from}&limit=${limit}&every=${every}`),
  truth: (id, from, limit, every = 1) =>
    request("GET", `/api/runs/${id}/truth?from=${from}&limit=${limit}&every=${every}`),
  exportUrl: (id, format) => `/api/runs/${id}/export?format=${format}`,
  showReplay: (runId, iteration) =>
    request("PUT", "/api/viewer/replay", { run_id: runId, iteration }, { timeoutMs: 10000 }),
  endReplay: () => request("DELETE", "/api/viewer/replay", {}, { timeoutMs: 5000 }),
  estop,
  release: () => request("POST", "/api/estop/release", {}),
  openHand: () => request("POST", "/api/hand/open", {}),
  simObject: () => request("GET", "/api/sim/object"),
  putSimObject: (name) => request("PUT", "/api/sim/object", { name }),
  viewer: () => request("GET", "/api/viewer"),
  config: () => request("GET", "/api/config"),
};

/** The samples of a recorded run (one iteration in `every`), fetched page by page. */
export async function allSamples(id, onProgress, pageSize = 5000, every = 1) {
  const out = [];
  let from = 0;
  while (from !== null && from !== undefined) {
    const page = await api.samplesFrom(id, from, pageSize, { every });
    for (const s of page.samples) out.push(s);
    if (onProgress) onProgress(out.length, Math.ceil(page.total / every));
    from = page.next;
  }
  return out;
}

/** A recorded frame's texels (base64 of little-endian uint16) as matrices of rows, as a live
 * `tactile` message carries them (`shapes`: rows × columns per matrix, in index order). */
export function decodeFrame(b64, shapes) {
  const bytes = atob(b64);
  const counts = new Uint16Array(bytes.length >> 1);
  for (let i = 0; i < counts.length; i++) {
    counts[i] = bytes.charCodeAt(2 * i) | (bytes.charCodeAt(2 * i + 1) << 8);
  }
  const matrices = [];
  let at = 0;
  for (const [rows, cols] of shapes) {
    const m = [];
    for (let r = 0; r < rows; r++, at += cols) m.push(counts.subarray(at, at + cols));
    matrices.push(m);
  }
  return matrices;
}

/** The tactile frames of a recorded run (one iteration in `every`), page by page: Map
 * iteration → matrices. */
export async function allFrames(id, onProgress, pageSize = 2000, every = 1) {
  const out = new Map();
  let from = 0;
  while (from !== null && from !== undefined) {
    const page = await api.frames(id, from, pageSize, every);
    for (const f of page.frames) out.set(f.iteration, decodeFrame(f.texels, page.shapes));
    if (onProgress) onProgress(out.size, Math.ceil(page.total / every));
    from = page.next;
  }
  return out;
}

/** A recorded run's truth (simulation; one iteration in `every`), page by page: `{outline,
 * rows: Map iteration → row}`; a real hand's run: outline null, no rows. */
export async function allTruth(id, pageSize = 10000, every = 1) {
  const rows = new Map();
  let outline = null;
  let from = 0;
  while (from !== null && from !== undefined) {
    const page = await api.truth(id, from, pageSize, every);
    outline = page.outline;
    for (const r of page.truth) rows.set(r.iteration, r);
    from = page.next;
  }
  return { outline, rows };
}

/**
 * The telemetry WebSocket with reconnection (exponential backoff, 0.5 s … 10 s).
 * onMessage(msg) gets every parsed message; onState(state, info) gets
 * "connecting" | "open" | "closed" (info: seconds until the next try).
 */
export class Telemetry {
  constructor({ onMessage, onState, query = "" }) {
    this.onMessage = onMessage;
    this.onState = onState;
    this.query = query;
    this.delay = 500;
    this.ws = null;
    this.timer = null;
    this.stopped = false;
  }

  url() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    return `${proto}//${location.host}/ws/telemetry${this.query}`;
  }

  start() {
    this.stopped = false;
    this.connect();
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
    if (this.ws) this.ws.close();
  }

  /** The service answers again: try now instead of at the end of the backoff. */
  kick() {
    if (this.stopped || this.ws) return;
    clearTimeout(this.timer);
    this.delay = 500;
    this.connect();
  }

  /** Give up on a socket that went silent (the next try follows the backoff). */
  drop(reason) {
    const ws = this.ws;
    if (!ws) return;
    this.ws = null;
    ws.onclose = null;
    ws.close();
    if (!this.stopped) this.retry(reason);
  }

  connect() {
    this.onState("connecting");
    let ws;
    try {
      ws = new WebSocket(this.url());
    } catch (e) {
      this.retry(String(e));
      return;
    }
    this.ws = ws;
    ws.onopen = () => {
      this.delay = 500;
      this.onState("open");
    };
    ws.onmessage = (ev) => {
      if (this.ws !== ws) return;
      let msg;
      try {
        msg = JSON.parse(ev.data);
      } catch {
        return;
      }
      this.onMessage(msg);
    };
    ws.onclose = (ev) => {
      if (this.ws !== ws) return;
      this.ws = null;
      if (!this.stopped) this.retry(ev.reason || `code ${ev.code}`);
    };
    ws.onerror = () => {
      /* onclose follows and schedules the retry */
    };
  }

  retry(reason) {
    const wait = this.delay;
    this.delay = Math.min(this.delay * 2, 10000);
    this.onState("closed", { retryInS: wait / 1000, reason });
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.connect(), wait);
  }
}
