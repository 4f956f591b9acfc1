// Planar y0z0 sketch of the two coupled fingers (hand-model.md §1–§3, §6).
//
// Frame 0: origin at Finger 1's proximal joint O, z0 along the straightened finger (drawn up),
// y0 towards Finger 2, whose proximal joint O' is at y0 = 66 mm. Angles arrive in degrees.

// The hand's geometry: the packaged defaults until configureHand() gets the service's own
// (GET /api/config: `hand`), so a hand configured differently is drawn as configured.
let BASE = 66.0; // |OO'| mm
let PROXIMAL = 86.5; // |OC| mm
// Fingertip pad profile in frame 3 (§3): flat y3 = 15 for 17.5 < x3 ≤ 33.5, then an arc with
// centre K = (33.5, −45) and R = 60 up to the fingertip's end at x3 = 66.402.
let PAD = { flatStart: 17.5, flatEnd: 33.5, flatY: 15.0, R: 60.0, tipEnd: 66.402 };
const VIEW = { yMin: -95, yMax: 161, zMin: -22, zMax: 190 }; // mm shown
const CONE_LEN = 38; // mm drawn along each cone edge
const D2R = Math.PI / 180;

function padY3(x3) {
  const dx = x3 - PAD.flatEnd;
  if (dx <= 0) return PAD.flatY;
  return PAD.flatY - PAD.R + Math.sqrt(PAD.R * PAD.R - dx * dx);
}

function padSlope(x3) {
  const dx = x3 - PAD.flatEnd;
  if (dx <= 0) return 0;
  return -dx / Math.sqrt(PAD.R * PAD.R - dx * dx);
}

// The distal link's outline in frame 3: a joint hub, the pad (flat, then arc), the back.
function distalOutline() {
  const pts = [[-9, -11], [-9, 11], [PAD.flatStart, PAD.flatY]];
  for (let i = 1; i <= 24; i++) {
    const x3 = PAD.flatStart + ((PAD.tipEnd - PAD.flatStart) * i) / 24;
    pts.push([x3, padY3(x3)]);
  }
  pts.push([PAD.tipEnd - 2, -4], [PAD.tipEnd - 9, -11]);
  return pts;
}
let DISTAL_OUTLINE = distalOutline();
let PAD_SURFACE = DISTAL_OUTLINE.slice(2, 2 + 25);

/** Take the service's hand geometry (the `hand` section of GET /api/config). */
export function configureHand(hand) {
  BASE = hand.base_offset_mm;
  PROXIMAL = hand.proximal_length_mm;
  const p = hand.pad;
  PAD = { flatStart: p.flat_start_x3_mm, flatEnd: p.flat_end_x3_mm, flatY: p.flat_y3_mm,
          R: p.arc_radius_mm, tipEnd: p.tip_end_x3_mm };
  DISTAL_OUTLINE = distalOutline();
  PAD_SURFACE = DISTAL_OUTLINE.slice(2, 2 + 25);
}

/** Distal joint and frame-3 axes of a finger (1 or 2) at its proximal/distal angles (rad). */
export function fingerFrame(finger, prox, dist) {
  const psi = prox + dist;
  if (finger === 1) {
    return {
      base: [0, 0],
      joint: [PROXIMAL * Math.sin(prox), PROXIMAL * Math.cos(prox)],
      ex: [Math.sin(psi), Math.cos(psi)],
      ey: [Math.cos(psi), -Math.sin(psi)],
      proxDir: [Math.sin(prox), Math.cos(prox)],
      proxIn: [Math.cos(prox), -Math.sin(prox)],
    };
  }
  return {
    base: [BASE, 0],
    joint: [BASE - PROXIMAL * Math.sin(prox), PROXIMAL * Math.cos(prox)],
    ex: [-Math.sin(psi), Math.cos(psi)],
    ey: [-Math.cos(psi), -Math.sin(psi)],
    proxDir: [-Math.sin(prox), Math.cos(prox)],
    proxIn: [-Math.cos(prox), -Math.sin(prox)],
  };
}

const toFrame0 = (f, [x3, y3]) => [
  f.joint[0] + x3 * f.ex[0] + y3 * f.ey[0],
  f.joint[1] + x3 * f.ex[1] + y3 * f.ey[1],
];

/** Unit normal of the pad (pointing out of the pad) at the pad point nearest to P. */
export function padNormalAt(f, P) {
  const rel = [P[0] - f.joint[0], P[1] - f.joint[1]];
  const x3 = rel[0] * f.ex[0] + rel[1] * f.ex[1];
  const m = padSlope(Math.min(Math.max(x3, PAD.flatStart), PAD.tipEnd - 0.01));
  const n = [f.ey[0] - m * f.ex[0], f.ey[1] - m * f.ex[1]];
  const len = Math.hypot(n[0], n[1]);
  return [n[0] / len, n[1] / len];
}

const rotate = ([x, y], a) => [x * Math.cos(a) - y * Math.sin(a), x * Math.sin(a) + y * Math.cos(a)];
const isNum = (v) => typeof v === "number" && Number.isFinite(v);
// the cones' half-angle (deg) for a sample: the one it recorded (α as the run widened it to what
// the grasp and the contacts held), else the run's configured α
export const coneAlpha = (sample, alpha) => (sample && isNum(sample.alpha) && sample.alpha > 0 ? sample.alpha : alpha);

/** A recorded iteration's truth (GET /api/runs/{id}/truth: the run's `outline`, one of its
 * `truth` rows) as the live `sim` message's: the outline placed at the iteration's y, z, ψ. */
export function placedTruth(outline, row) {
  const c = Math.cos(row.psi);
  const s = Math.sin(row.psi);
  return {
    object: outline.object, size_mm: outline.size_mm, held: row.held, dropped: row.dropped,
    in_fixture: row.in_fixture, pose: [row.y, row.z, row.psi], slips: row.slips,
    outline: outline.points.map(([x, y]) => [row.y + c * x - s * y, row.z + s * x + c * y]),
    contacts: [],
  };
}

/** What became of the true object: "released" when it fell as the fingers let go of it on
 * purpose (`released`: said by the page, the sim's truth has only `dropped`), "dropped" when it
 * fell before, else held or not. */
export function objectFate(truth) {
  if (!truth) return "";
  if (truth.released) return "released";
  return truth.dropped ? "dropped" : truth.held ? "held" : "not held";
}

export class Sketch {
  constructor(canvas) {
    this.canvas = canvas;
    this.angles = null; // [φ2, φ3, φ4, φ5] deg
    this.contact = null; // a Sample with A, B, ω …
    this.truth = null; // sim truth
    this.alpha = 22;
    this.override = null; // a Sample under the plot cursor (replay / inspection)
    this.overrideTruth = null; // the sim truth recorded with it (a replay in simulation)
    this.frame = 0;
    // fitted in the next frame, not in the observer's callback: no "ResizeObserver loop"
    new ResizeObserver(() => requestAnimationFrame(() => this.fit())).observe(canvas);
    this.fit();
  }

  fit() {
    const r = this.canvas.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(200, Math.round(r.width * dpr));
    const h = Math.max(160, Math.round(r.height * dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    this.schedule();
  }

  setAngles(deg) {
    if (deg && deg.every(isNum)) this.angles = deg;
    this.schedule();
  }

  setContact(sample) {
    this.contact = sample;
    this.schedule();
  }

  setTruth(truth) {
    this.truth = truth;
    this.schedule();
  }

  setAlpha(alphaDeg) {
    if (isNum(alphaDeg) && alphaDeg !== this.alpha) {
      this.alpha = alphaDeg;
      this.schedule();
    }
  }

  /** Show one sample (angles and contacts) and the truth recorded with it (null: none) instead
   * of the live state; null: back to live. */
  setOverride(sample, truth = null) {
    this.override = sample;
    this.overrideTruth = sample ? truth : null;
    if (sample && sample.iteration != null) this.canvas.dataset.iteration = String(sample.iteration);
    else delete this.canvas.dataset.iteration;
    // the recorded object's pose shown (y, z mm; ψ rad), for tests and the curious
    if (this.overrideTruth) this.canvas.dataset.objectPose = this.overrideTruth.pose.join(",");
    else delete this.canvas.dataset.objectPose;
    this.schedule();
  }

  schedule() {
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      this.draw();
    });
  }

  draw() {
    const { canvas } = this;
    const ctx = canvas.getContext("2d");
    const W = canvas.width;
    const H = canvas.height;
    const s = Math.min(W / (VIEW.yMax - VIEW.yMin), H / (VIEW.zMax - VIEW.zMin));
    const ox = (W - s * (VIEW.yMax - VIEW.yMin)) / 2 - s * VIEW.yMin;
    const oz = H - (H - s * (VIEW.zMax - VIEW.zMin)) / 2 + s * VIEW.zMin;
    const px = ([y, z]) => [ox + s * y, oz - s * z];
    const dpr = window.devicePixelRatio || 1;

    ctx.clearRect(0, 0, W, H);
    ctx.fillStyle = "#fbfbfd";
    ctx.fillRect(0, 0, W, H);
    ctx.lineJoin = "round";
    ctx.font = `${12 * dpr}px system-ui, sans-serif`;

    this.drawFrame(ctx, px, s, dpr);

    const shown = this.override;
    const angles = shown && isNum(shown.phi2)
      ? [shown.phi2, shown.phi3, shown.phi4, shown.phi5]
      : this.angles;
    const contact = shown ?? this.contact;
    const truth = shown ? this.overrideTruth : this.truth;

    // the true object (simulation only), behind the fingers
    if (truth && Array.isArray(truth.outline) && truth.outline.length > 2) {
      ctx.beginPath();
      truth.outline.forEach((p, i) => {
        const [x, y] = px(p);
        if (i === 0) ctx.moveTo(x, y);
        else ctx.lineTo(x, y);
      });
      ctx.closePath();
      ctx.fillStyle = truth.released ? "rgba(120,120,120,0.15)"
        : truth.dropped ? "rgba(214,39,40,0.15)" : "rgba(255,193,7,0.28)";
      ctx.fill();
      ctx.strokeStyle = "#b8860b";
      ctx.lineWidth = 1.5 * dpr;
      ctx.setLineDash([4 * dpr, 3 * dpr]);
      ctx.stroke();
      ctx.setLineDash([]);
    }

    // the object as the recognition reconstructs it (sent with the sample: the server's
    // control.recognition.outline, never worked out here), over the true one
    const est = contact && Array.isArray(contact.estimate_outline) ? contact.estimate_outline : [];
    if (est.length > 2) {
      ctx.beginPath();
      est.forEach((p, i) => (i ? ctx.lineTo(...px(p)) : ctx.moveTo(...px(p))));
      ctx.closePath();
      ctx.fillStyle = "rgba(11,111,168,0.08)";
      ctx.fill();
      ctx.strokeStyle = "#0b6fa8";
      ctx.lineWidth = 2 * dpr;
      ctx.stroke();
    }
    this.canvas.dataset.estimatePoints = String(est.length);

    let frames = null;
    if (angles) {
      const [p2, p3, p4, p5] = angles.map((a) => a * D2R);
      frames = [fingerFrame(1, p2, p3), fingerFrame(2, p4, p5)];
      frames.forEach((f, i) => this.drawFinger(ctx, px, s, dpr, f, i === 0 ? "C" : "D"));
    }

    if (contact && isNum(contact.Ay) && isNum(contact.By)) {
      const A = [contact.Ay, contact.Az];
      const B = [contact.By, contact.Bz];
      // contacts from the sample's own angles where it has them
      const cf = isNum(contact.phi2)
        ? [fingerFrame(1, contact.phi2 * D2R, contact.phi3 * D2R),
           fingerFrame(2, contact.phi4 * D2R, contact.phi5 * D2R)]
        : frames;
      if (cf) {
        const alpha = coneAlpha(contact, this.alpha);
        this.drawCone(ctx, px, s, dpr, A, padNormalAt(cf[0], A), contact.omega_A, alpha);
        this.drawCone(ctx, px, s, dpr, B, padNormalAt(cf[1], B), contact.omega_B, alpha);
      }
      ctx.strokeStyle = "#111";
      ctx.lineWidth = 2.5 * dpr;
      ctx.beginPath();
      ctx.moveTo(...px(A));
      ctx.lineTo(...px(B));
      ctx.stroke();
      for (const [P, name, col] of [[A, "A", "#1f77b4"], [B, "B", "#d62728"]]) {
        const [x, y] = px(P);
        ctx.fillStyle = col;
        ctx.beginPath();
        ctx.arc(x, y, 4.5 * dpr, 0, 2 * Math.PI);
        ctx.fill();
        ctx.fillText(name, x + (name === "A" ? -16 : 8) * dpr, y - 6 * dpr);
      }
    }
    this.drawLegend(ctx, dpr, angles, contact, shown, truth);
  }

  drawFrame(ctx, px, s, dpr) {
    // palm line, axes, joints O and O'
    ctx.strokeStyle = "#bbb";
    ctx.lineWidth = 1 * dpr;
    ctx.beginPath();
    ctx.moveTo(...px([-40, -6]));
    ctx.lineTo(...px([BASE + 40, -6]));
    ctx.stroke();
    // frame-0 axes at the bottom left: y0 to the right, z0 up
    ctx.strokeStyle = "#888";
    ctx.fillStyle = "#888";
    const [ax, az] = px([-80, 4]);
    ctx.beginPath();
    ctx.moveTo(ax, az);
    ctx.lineTo(ax + 18 * s, az);
    ctx.moveTo(ax, az);
    ctx.lineTo(ax, az - 18 * s);
    ctx.stroke();
    ctx.fillText("y0", ax + 19 * s, az + 4 * dpr);
    ctx.fillText("z0", ax - 4 * dpr, az - 19 * s);
    // 20 mm scale bar, bottom right
    const [bx, by] = px([VIEW.yMax - 30, 2]);
    ctx.strokeStyle = "#555";
    ctx.lineWidth = 2 * dpr;
    ctx.beginPath();
    ctx.moveTo(bx, by);
    ctx.lineTo(bx + 20 * s, by);
    ctx.stroke();
    ctx.fillStyle = "#555";
    ctx.textAlign = "right"; // ends where the bar ends: inside the view however narrow it is
    ctx.fillText("20 mm", bx + 20 * s, by + 14 * dpr);
    ctx.textAlign = "left";
    ctx.fillStyle = "#444";
    for (const [P, name] of [[[0, 0], "O"], [[BASE, 0], "O'"]]) {
      const [x, y] = px(P);
      ctx.beginPath();
      ctx.arc(x, y, 5 * dpr, 0, 2 * Math.PI);
      ctx.fill();
      ctx.fillText(name, x - 6 * dpr, y + 18 * dpr);
    }
  }

  drawFinger(ctx, px, s, dpr, f, jointName) {
    // proximal link: a bar from the base to the distal joint, its pad on the inner side
    const half = 9;
    const a = f.base;
    const b = f.joint;
    const n = f.proxIn;
    const poly = [
      [a[0] - half * n[0], a[1] - half * n[1]], [b[0] - half * n[0], b[1] - half * n[1]],
      [b[0] + half * n[0], b[1] + half * n[1]], [a[0] + half * n[0], a[1] + half * n[1]],
    ];
    ctx.fillStyle = "#c9ced6";
    ctx.strokeStyle = "#6b7280";
    ctx.lineWidth = 1.2 * dpr;
    ctx.beginPath();
    poly.forEach((p, i) => (i ? ctx.lineTo(...px(p)) : ctx.moveTo(...px(p))));
    ctx.closePath();
    ctx.fill();
    ctx.stroke();
    const d = f.proxDir;
    ctx.strokeStyle = "#e2a03f";
    ctx.lineWidth = 3 * dpr;
    ctx.beginPath();
    ctx.moveTo(...px([a[0] + 12 * d[0] + half * n[0], a[1] + 12 * d[1] + half * n[1]]));
    ctx.lineTo(...px([a[0] + 76 * d[0] + half * n[0], a[1] + 76 * d[1] + half * n[1]]));
    ctx.stroke();

    // distal link with its pad profile
    ctx.fillStyle = "#d7dbe2";
    ctx.strokeStyle = "#6b7280";
    ctx.lineWidth = 1.2 * dpr;
    tracePath(ctx, DISTAL_OUTLINE.map((p) => px(toFrame0(f, p))));
    ctx.closePath();
    ctx.fill();
    ctx.stroke();
    ctx.strokeStyle = "#e2a03f";
    ctx.lineWidth = 3 * dpr;
    tracePath(ctx, PAD_SURFACE.map((p) => px(toFrame0(f, p))));
    ctx.stroke();

    const [jx, jy] = px(f.joint);
    ctx.fillStyle = "#444";
    ctx.beginPath();
    ctx.arc(jx, jy, 4 * dpr, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillText(jointName, jx + (jointName === "C" ? -16 : 8) * dpr, jy + 4 * dpr);
  }

  drawCone(ctx, px, s, dpr, P, normal, omega, alpha) {
    const a = alpha * D2R;
    const e1 = rotate(normal, a);
    const e2 = rotate(normal, -a);
    // colour by the margin to the cone's edge: green, amber when < α/2 left, red outside
    let col = "44,160,44";
    if (isNum(omega)) {
      const margin = alpha - Math.abs(omega - 90);
      if (margin < 0) col = "214,39,40";
      else if (margin < alpha / 2) col = "255,152,0";
    }
    const tip1 = [P[0] + CONE_LEN * e1[0], P[1] + CONE_LEN * e1[1]];
    const tip2 = [P[0] + CONE_LEN * e2[0], P[1] + CONE_LEN * e2[1]];
    ctx.fillStyle = `rgba(${col},0.18)`;
    ctx.strokeStyle = `rgba(${col},0.9)`;
    ctx.lineWidth = 1.2 * dpr;
    ctx.beginPath();
    ctx.moveTo(...px(P));
    ctx.lineTo(...px(tip1));
    ctx.lineTo(...px(tip2));
    ctx.closePath();
    ctx.fill();
    ctx.beginPath();
    ctx.moveTo(...px(tip1));
    ctx.lineTo(...px(P));
    ctx.lineTo(...px(tip2));
    ctx.stroke();
    // the pad normal, dotted
    ctx.setLineDash([2 * dpr, 3 * dpr]);
    ctx.beginPath();
    ctx.moveTo(...px(P));
    ctx.lineTo(...px([P[0] + CONE_LEN * normal[0], P[1] + CONE_LEN * normal[1]]));
    ctx.stroke();
    ctx.setLineDash([]);
  }

  drawLegend(ctx, dpr, angles, contact, shown, truth) {
    const lines = [];
    if (shown) lines.push(`inspecting iteration ${shown.iteration}`);
    if (angles) lines.push(`φ2…φ5 = ${angles.map((a) => a.toFixed(1)).join(", ")}°`);
    else lines.push("no joint angles yet");
    if (contact && isNum(contact.Lambda)) {
      const sig = isNum(contact.sigma) ? contact.sigma.toFixed(2) : "–";
      lines.push(`Λ = ${contact.Lambda.toFixed(1)} mm, σ = ${sig}°`);
      const wa = isNum(contact.omega_A) ? contact.omega_A.toFixed(1) : "–";
      const wb = isNum(contact.omega_B) ? contact.omega_B.toFixed(1) : "–";
      const alpha = Math.round(10 * coneAlpha(contact, this.alpha)) / 10;
      lines.push(`ωA = ${wa}°, ωB = ${wb}° (cone 90 ± ${alpha}°)`);
    }
    const fate = objectFate(truth);
    if (fate) lines.push(`object ${truth.object ?? "?"}: ${fate}`);
    if (fate && !shown) this.canvas.dataset.object = fate;
    else delete this.canvas.dataset.object;
    ctx.fillStyle = "#333";
    lines.forEach((l, i) => ctx.fillText(l, 8 * dpr, (16 + 15 * i) * dpr));
  }
}

/** Begin a path through canvas points (no fill or stroke). */
function tracePath(ctx, points) {
  ctx.beginPath();
  points.forEach((q, i) => (i ? ctx.lineTo(...q) : ctx.moveTo(...q)));
}
