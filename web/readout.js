// The "object" readout: what the recognition makes of the object while it rolls — class and
// confidence, sizes, rotation so far, what touches each distal pad — from a Sample's fields
// (docs/api.md), live and in a replay.

// Every value not known (none yet, null, not a finite number) reads "–", in every field; no
// field is ever left blank.
const UNKNOWN = "–";
const num = (v) => typeof v === "number" && Number.isFinite(v);
const mm = (v) => (num(v) ? v.toFixed(1) : UNKNOWN);
const deg = (v) => (num(v) ? `${v.toFixed(1)}°` : UNKNOWN);
const pct = (v) => (num(v) ? `${Math.round(100 * v)} %` : `${UNKNOWN} %`);

// how each class names its two sizes (control/recognition.py, Recognition)
const SIZES = {
  circle: (a) => `r ${mm(a)} mm`,
  ellipse: (a, b) => `a ${mm(a)} · b ${mm(b)} mm`,
  box: (a, b) => `${mm(a)} × ${mm(b)} mm`,
  stick: (a, b) => `L ${mm(a)} · ⌀ ${mm(b)} mm`,
  polygon: (a, b) => `R ${mm(a)} · side ${mm(b)} mm`,
};

function contact(name, kind, radius) {
  if (!kind) return `${name} ${UNKNOWN}`;
  return kind === "curved" ? `${name} curved, r ${mm(radius)} mm` : `${name} ${kind}`;
}

/** Show sample `s`'s recognition in `el` (#object-readout); null: nothing known. In simulation,
 * `trueTurnDeg` is how far the object truly turned since the run's first rolling sample (null:
 * not known now), shown beside the estimate; left out (undefined) where there is no truth (a
 * real hand, a real hand's run replayed). */
export function showObject(el, s, trueTurnDeg = undefined) {
  const v = s || {};
  const cls = v.object_class || "";
  el.querySelector(".obj-class").textContent = cls ? `${cls} ${pct(v.class_confidence)}`
    : `object ${UNKNOWN}`;
  el.querySelector(".obj-size").textContent = cls && SIZES[cls] ? SIZES[cls](v.size_a, v.size_b)
    : `size ${UNKNOWN}`;
  const truly = trueTurnDeg === undefined ? "" : ` (true ${deg(trueTurnDeg)})`;
  el.querySelector(".obj-rot").textContent = `turned ${deg(v.rotation_est)}${truly}`;
  el.querySelector(".obj-contacts").textContent =
    `${contact("A", v.contact1_kind, v.radius1)} · ${contact("B", v.contact2_kind, v.radius2)}`;
  el.dataset.class = cls;
  if (s && s.iteration != null) el.dataset.iteration = String(s.iteration);
  else delete el.dataset.iteration;
}
