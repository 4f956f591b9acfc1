// The "object" readout: what the recognition makes of the object while it rolls — class and
// confidence, sizes, rotation so far, what touches each distal pad — from a Sample's fields
// (docs/api.md), live and in a replay.

const num = (v) => typeof v === "number" && Number.isFinite(v);
const mm = (v) => (num(v) ? v.toFixed(1) : "–");

// how each class names its two sizes (control/recognition.py, Recognition)
const SIZES = {
  circle: (a) => `r ${mm(a)} mm`,
  ellipse: (a, b) => `a ${mm(a)} · b ${mm(b)} mm`,
  box: (a, b) => `${mm(a)} × ${mm(b)} mm`,
  stick: (a, b) => `L ${mm(a)} · ⌀ ${mm(b)} mm`,
  polygon: (a, b) => `R ${mm(a)} · side ${mm(b)} mm`,
};

function contact(name, kind, radius) {
  if (!kind) return `${name} –`;
  return kind === "curved" && num(radius) ? `${name} curved, r ${mm(radius)} mm` : `${name} ${kind}`;
}

/** Show sample `s`'s recognition in `el` (#object-readout); null: nothing known. In simulation,
 * `trueTurnDeg` is how far the object truly turned since the run's first rolling sample (null:
 * not known here), shown beside the estimate. */
export function showObject(el, s, trueTurnDeg = null) {
  const cls = (s && s.object_class) || "";
  const conf = s && num(s.class_confidence) ? ` ${Math.round(100 * s.class_confidence)} %` : "";
  el.querySelector(".obj-class").textContent = cls ? `${cls}${conf}` : "object –";
  const size = cls && SIZES[cls] ? SIZES[cls](s.size_a, s.size_b) : "";
  el.querySelector(".obj-size").textContent = size;
  const truly = num(trueTurnDeg) ? ` (true ${trueTurnDeg.toFixed(1)}°)` : "";
  const rot = s && num(s.rotation_est) ? `turned ${s.rotation_est.toFixed(1)}°${truly}` : "";
  el.querySelector(".obj-rot").textContent = rot;
  el.querySelector(".obj-contacts").textContent = s
    ? `${contact("A", s.contact1_kind, s.radius1)} · ${contact("B", s.contact2_kind, s.radius2)}`
    : "A – · B –";
  el.dataset.class = cls;
  if (s && s.iteration != null) el.dataset.iteration = String(s.iteration);
  else delete el.dataset.iteration;
}
