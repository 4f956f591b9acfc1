// A run's events (control/observer.py EventKind) as sentences with rounded numbers: one function,
// one entry per kind, a fallback for kinds it does not know.

// A fault's key (the part of a run's message before ": ") in plain words.
export const FAULT_WORDS = {
  no_contact: "the grasp found nothing between the fingertips",
  force_ceiling: "the grip force went too high",
  stale_sensor: "the tactile frames stopped coming",
  dropped: "both contacts were lost; the object is no longer held, or both distal pads stopped reading it",
  stuck: "the rolling kept reversing without turning the object (stuck)",
  joint_error: "the joint controller failed",
  sensor_error: "the tactile sensor's controller failed",
  internal_error: "an unexpected error in sdh2svc (a bug: the log has its traceback)",
};

const PHASES = {
  connecting: "Connecting to the hand",
  "pre-shape": "Moving the fingers to the pre-shape pose",
  grasping: "Grasping",
  rolling: "Rolling",
  releasing: "Releasing: the fingers open to the pre-shape pose",
  done: "Done",
  stopped: "Stopped",
  faulted: "Faulted",
  "e-stopped": "E-stopped",
};

const END_WORDS = {
  completed: "completed", stopped: "was stopped", faulted: "faulted", "e-stopped": "was e-stopped",
  dropped: "lost the object", interrupted: "was interrupted",
};

/** What the recognition made of the run's object (the `end` event's `recognition`), or "". */
function recognised(r) {
  if (!r || !r.object_class) return "";
  const conf = Number.isFinite(r.confidence) ? ` (${Math.round(100 * r.confidence)} %)` : "";
  // the range it turned through (ψ max − min), and where it ended: a stroke there and back ends
  // near its start after turning through many degrees
  const through = Number.isFinite(r.rotation_range_deg)
    ? `, turned through ${r.rotation_range_deg.toFixed(1)}°` : "";
  const end = Number.isFinite(r.rotation_deg) ? Math.abs(r.rotation_deg).toFixed(1) : null;
  let turn = through;
  if (end !== null) {
    turn = through ? `${through} (ends ${end}° from its start)` : `, ends ${end}° from its start`;
  }
  const a = /^[aeiou]/.test(r.object_class) ? "an" : "a";
  return `; recognised ${a} ${r.object_class}${conf}${turn}`;
}

const PARAM_NAMES = {
  delta_phi_deg: ["Δφ", "°"], k: ["k", ""], lambda_gain: ["λ", ""], d_sigma_deg: ["dσ", "°"],
  alpha_deg: ["α", "°"], grasp_force: ["Fd", ""], cycles: ["cycles", ""],
};

const isNum = (v) => typeof v === "number" && Number.isFinite(v);

/** A number rounded for reading: at most `digits` decimals, no trailing zeros. */
export function round(v, digits = 2) {
  if (!isNum(v)) return "–";
  return String(Number(v.toFixed(digits)));
}

function params(p, only = null) {
  if (!p || typeof p !== "object") return "";
  const keys = only ?? Object.keys(PARAM_NAMES).filter((k) => k in p);
  return keys
    .filter((k) => k in p)
    .map((k) => {
      const [name, unit] = PARAM_NAMES[k] ?? [k, ""];
      return `${name} = ${isNum(p[k]) ? round(p[k], 3) : p[k]}${unit}`;
    })
    .join(", ");
}

const words = (s) => String(s).toLowerCase().match(/[\p{L}\p{N}]+/gu) ?? [];

/** Whether `rest` says nothing that `said` does not (the same words, in any order). */
function repeats(said, rest) {
  const have = new Set(words(said));
  return words(rest).every((w) => have.has(w));
}

/**
 * The part of a fault's or run's message a person reads ("no_contact: …" in plain words). The
 * service's own text follows in brackets when it tells more (numbers, a line's name), not when
 * it says the same again ("dropped: both contacts lost: the object is no longer held, or both
 * distal pads stopped reading it").
 */
export function plainMessage(message) {
  const m = String(message || "").trim();
  const i = m.indexOf(": ");
  const plain = FAULT_WORDS[i > 0 ? m.slice(0, i) : m];
  if (!plain) return m;
  const rest = i > 0 ? m.slice(i + 2).trim() : "";
  return rest && !repeats(plain, rest) ? `${plain} (${rest})` : plain;
}

// How close ω was to the cone's edge 90° ± α (degrees; negative: beyond it).
const coneMargin = (omega, alpha) => (isNum(omega) && isNum(alpha) ? alpha - Math.abs(omega - 90) : null);

function reversal(d, ctx) {
  const s = ctx.sample || {};
  let text;
  switch (d.reason) {
    case "cone_A":
    case "cone_B": {
      const finger = d.reason === "cone_A" ? 1 : 2;
      const m = coneMargin(d.reason === "cone_A" ? s.omega_A : s.omega_B, ctx.alpha);
      text = `Reversed at the friction cone of finger ${finger}`;
      if (m !== null) text += ` (margin ${round(m, 1)}°)`;
      break;
    }
    case "wedge": {
      const w = isNum(s.omega_A) && isNum(s.omega_B) ? (s.omega_A + s.omega_B) / 2 - 90 : null;
      text = "Reversed at the pads' wedge limit";
      if (w !== null) text += ` (wedge ${round(w, 1)}°)`;
      break;
    }
    case "workspace":
      text = "Reversed at the joint limits";
      break;
    case "ik_unreachable":
      text = "Reversed: finger 1 cannot reach the next contact point";
      break;
    case "contact_edge":
      text = "Reversed: a contact reached the pad's edge";
      break;
    case "contact_lost":
      text = "Reversed: a contact force fell to the contact threshold";
      break;
    default:
      text = `Reversed (${d.reason ?? "no reason given"})`;
  }
  if (isNum(ctx.since)) text += ` after ${ctx.since} iteration${ctx.since === 1 ? "" : "s"}`;
  if (isNum(d.half_strokes)) text += `; half stroke ${d.half_strokes}`;
  return text;
}

/** Anything else: its kind and its detail, numbers rounded, no JSON. */
function fallback(kind, d) {
  const parts = Object.entries(d).map(([k, v]) => {
    if (isNum(v)) return `${k} ${round(v)}`;
    if (v && typeof v === "object") return `${k} (${Object.keys(v).length} values)`;
    return `${k} ${v}`;
  });
  return `${kind[0].toUpperCase()}${kind.slice(1)}${parts.length ? `: ${parts.join(", ")}` : ""}`;
}

/**
 * One event as a sentence. `m`: {kind, detail, run_id, iteration}; `ctx`: what the sentence may
 * quote beyond the event: `sample` (the sample of the event's iteration), `alpha` (α in force,
 * degrees), `since` (iterations since the previous reversal).
 */
export function eventSentence(m, ctx = {}) {
  const d = m.detail && typeof m.detail === "object" ? m.detail : {};
  const run = m.run_id ?? "–";
  switch (m.kind) {
    case "start": {
      const p = params(d.params, ["delta_phi_deg", "k", "grasp_force", "cycles"]);
      return `Run ${run} started${p ? ` (${p})` : ""}`;
    }
    case "phase":
      return PHASES[d.phase] ?? `Phase: ${d.phase}`;
    case "params": {
      const p = params(d.params);
      return p ? `New parameters took effect: ${p}` : "New parameters took effect";
    }
    case "grasped": {
      let text = `Grasped with F = ${round(d.F)}`;
      if (isNum(d.wedge_deg)) text += ` (pads' wedge ${round(d.wedge_deg, 1)}°)`;
      return text;
    }
    case "reversal":
      return reversal(d, ctx);
    case "fault":
      return `Fault: ${plainMessage(d.fault ? `${d.fault}: ${d.message ?? ""}` : d.message)}`;
    case "estop":
      return "Emergency stop: the motors were switched off";
    case "end": {
      const why = plainMessage(d.message);
      const how = END_WORDS[d.status] ?? `ended (${d.status ?? "no status"})`;
      return `Run ${run} ${how}${why ? `: ${why}` : ""}${recognised(d.recognition)}`;
    }
    case "recognition_failed":
      return `The object's recognition failed${d.message ? ` (${d.message})` : ""}: the rolling ` +
        "goes on without an estimate";
    case "open":
      return "Opening the hand";
    case "opened":
      return d.completed === false
        ? `Opening the hand stopped${d.message && d.message !== "stopped" ? `: ${plainMessage(d.message)}` : ""}`
        : "The hand is open";
    default:
      return fallback(String(m.kind ?? "event"), d);
  }
}
