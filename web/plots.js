// Live and replayed plots of the thesis's figures (uPlot, vendored; global `uPlot`).
//
// Samples are appended to column buffers (a rolling window); the charts are redrawn at most once
// per animation frame, and only those whose data changed.

const C = {
  phi2: "#1f77b4", phi3: "#ff7f0e", phi4: "#2ca02c", phi5: "#d62728",
  F: "#222222", dF: "#9467bd", F1: "#8c564b", F2: "#e377c2", limit: "#d62728", ref: "#7f7f7f",
  a: "#1f77b4", b: "#d62728", d: "#2ca02c",
};
const DASH = [6, 4];
// Event markers on the iteration axis: colour and dash per event kind.
export const MARKERS = {
  reversal: { color: "rgba(214,39,40,0.55)", dash: [] },
  grasped: { color: "rgba(46,125,50,0.8)", dash: [4, 3] },
  fault: { color: "rgba(198,40,40,0.95)", dash: [], width: 2 },
  estop: { color: "rgba(198,40,40,0.95)", dash: [2, 2], width: 2 },
  params: { color: "rgba(107,114,128,0.8)", dash: [2, 3] },
};

const num = (v) => (v === null || v === undefined || Number.isNaN(v) ? null : v);
const field = (k) => (s) => num(s[k]);

// One entry per chart: container id, title, y unit, and its series (value from sample s and the
// parameters p in force for it).
export const PLOTS = [
  {
    id: "plot-joints", title: "joint angles φ2…φ5 (dashed: targets)", unit: "deg",
    series: [
      { label: "φ2", color: C.phi2, value: field("phi2") },
      { label: "φ3", color: C.phi3, value: field("phi3") },
      { label: "φ4", color: C.phi4, value: field("phi4") },
      { label: "φ5", color: C.phi5, value: field("phi5") },
      { label: "φ2d", color: C.phi2, dash: DASH, value: field("phi2_d") },
      { label: "φ3d", color: C.phi3, dash: DASH, value: field("phi3_d") },
      { label: "φ4d", color: C.phi4, dash: DASH, value: field("phi4_d") },
      { label: "φ5d", color: C.phi5, dash: DASH, value: field("phi5_d") },
    ],
  },
  {
    id: "plot-force", title: "force F, ΔF (Fd and the [0.25, 2.5]·Fd band)", unit: "lib. units",
    series: [
      { label: "F", color: C.F, width: 2, value: field("F") },
      { label: "ΔF", color: C.dF, value: field("dF") },
      { label: "F1", color: C.F1, width: 1, value: field("F1"), show: false },
      { label: "F2", color: C.F2, width: 1, value: field("F2"), show: false },
      { label: "Fd", color: C.ref, dash: DASH, value: (s, p) => num(p.grasp_force) },
      { label: "0.25·Fd", color: C.limit, dash: [2, 4], width: 1,
        value: (s, p) => (p.grasp_force == null ? null : 0.25 * p.grasp_force) },
      { label: "2.5·Fd", color: C.limit, dash: [2, 4], width: 1,
        value: (s, p) => (p.grasp_force == null ? null : 2.5 * p.grasp_force) },
    ],
  },
  {
    id: "plot-sigma", title: "inclination σ of AB", unit: "deg",
    series: [
      { label: "σ", color: C.a, width: 2, value: field("sigma") },
      { label: "σd", color: C.b, dash: DASH, value: field("sigma_d") },
    ],
  },
  {
    id: "plot-s", title: "contact positions S1, S2 on the pads", unit: "mm",
    series: [
      { label: "S1", color: C.a, width: 2, value: field("S1") },
      { label: "S2", color: C.b, width: 2, value: field("S2") },
    ],
  },
  {
    id: "plot-omega", title: "ωA, ωB and the friction cone 90° ± α", unit: "deg",
    series: [
      { label: "ωA", color: C.a, width: 2, value: field("omega_A") },
      { label: "ωB", color: C.b, width: 2, value: field("omega_B") },
      { label: "90−α", color: C.limit, dash: DASH, width: 1,
        value: (s, p) => (p.alpha_deg == null ? null : 90 - p.alpha_deg) },
      { label: "90+α", color: C.limit, dash: DASH, width: 1,
        value: (s, p) => (p.alpha_deg == null ? null : 90 + p.alpha_deg) },
    ],
  },
  {
    id: "plot-lambda", title: "held distance Λ = |AB| and Λad", unit: "mm",
    series: [
      { label: "Λ", color: C.a, width: 2, value: field("Lambda") },
      { label: "Λad", color: C.d, dash: DASH, value: field("Lambda_ad") },
    ],
  },
];

/** Column buffers for all charts: x (iteration) plus one column per series. */
class Buffers {
  constructor(limit) {
    this.limit = limit;
    this.clear();
  }

  clear() {
    this.samples = [];
    this.cols = PLOTS.map((p) => [[], ...p.series.map(() => [])]);
    this.markers = []; // {x: iteration, kind, text}
  }

  mark(marker) {
    if (MARKERS[marker.kind] && Number.isFinite(marker.x)) this.markers.push(marker);
    const first = this.cols[0][0][0];
    if (this.limit && first !== undefined && this.markers.length > 200) {
      this.markers = this.markers.filter((m) => m.x >= first);
    }
  }

  push(sample, params) {
    const x = num(sample.iteration) ?? num(sample.t) ?? this.samples.length;
    this.samples.push(sample);
    PLOTS.forEach((p, i) => {
      const cols = this.cols[i];
      cols[0].push(x);
      p.series.forEach((s, j) => cols[j + 1].push(s.value(sample, params)));
    });
    if (this.limit && this.samples.length > this.limit) {
      const n = this.samples.length - this.limit;
      this.samples.splice(0, n);
      for (const cols of this.cols) for (const c of cols) c.splice(0, n);
    }
  }

  /** The data index of iteration `it` (the nearest at or before it), or -1. */
  indexOf(it) {
    const xs = this.cols[0][0];
    let lo = 0;
    let hi = xs.length - 1;
    if (hi < 0 || it < xs[0]) return -1;
    while (lo < hi) {
      const mid = (lo + hi + 1) >> 1;
      if (xs[mid] <= it) lo = mid;
      else hi = mid - 1;
    }
    return lo;
  }

  get length() {
    return this.samples.length;
  }
}

export class Plots {
  /** onCursor(sample|null): the sample under the (synchronised) cursor, for the sketch. */
  constructor({ windowSize = 2000, onCursor = null } = {}) {
    this.live = new Buffers(windowSize);
    this.replay = null; // Buffers while a past run is shown
    this.onCursor = onCursor;
    this.dirty = false;
    this.frame = 0;
    this.pinned = null; // the data index the replay scrubber shows (the cursor rests there)
    this.pinning = false; // pin() moving the cursors: not the user's hover
    this.charts = PLOTS.map((p) => this.makeChart(p));
    // resized in the next frame, not in the observer's callback: no "ResizeObserver loop"
    const ro = new ResizeObserver(() => requestAnimationFrame(() => this.resize()));
    for (const p of PLOTS) ro.observe(document.getElementById(p.id));
  }

  makeChart(p) {
    const el = document.getElementById(p.id);
    el.innerHTML = "";
    const title = document.createElement("div");
    title.className = "plot-title";
    title.textContent = p.title;
    el.appendChild(title);
    const opts = {
      width: Math.max(200, el.clientWidth - 14),
      height: 150,
      legend: { live: true },
      cursor: { sync: { key: "sdh2" }, drag: { x: true, y: false } },
      scales: { x: { time: false } },
      axes: [
        { label: "iteration", size: 36, labelSize: 14 },
        { label: p.unit, size: 52, labelSize: 14 },
      ],
      series: [
        { label: "it" },
        ...p.series.map((s) => ({
          label: s.label,
          stroke: s.color,
          width: s.width ?? 1.5,
          dash: s.dash,
          show: s.show ?? true,
          spanGaps: false,
          points: { show: false },
          // no value at that iteration (e.g. no targets once the rolling ended): uPlot's "--"
          // as with no iteration at all, not blank
          value: (u, v) => (v == null ? "--" : uPlot.fmtNum(v)),
        })),
      ],
      hooks: {
        setCursor: [
          (u) => {
            if (!this.onCursor || this.pinning) return;
            const idx = u.cursor.idx;
            const buf = this.current();
            this.onCursor(idx == null ? null : buf.samples[idx] ?? null);
          },
        ],
        draw: [(u) => this.drawMarkers(u)],
      },
    };
    const chart = new uPlot(opts, [[], ...p.series.map(() => [])], el);
    chart._container = el;
    // the legend shows the values at the cursor; off the plot, the newest (or the pinned) ones
    chart.over.addEventListener("mouseleave", () => requestAnimationFrame(() => this.restLegends()));
    return chart;
  }

  /** Vertical lines at the events' iterations (reversals, grasp, faults, …). */
  drawMarkers(u) {
    const buf = this.current();
    const { ctx, bbox } = u;
    const [lo, hi] = [u.scales.x.min, u.scales.x.max];
    let drawn = 0;
    let reversals = 0;
    ctx.save();
    for (const m of buf.markers) {
      if (lo == null || m.x < lo || m.x > hi) continue;
      const style = MARKERS[m.kind];
      const x = Math.round(u.valToPos(m.x, "x", true)) + 0.5;
      ctx.strokeStyle = style.color;
      ctx.lineWidth = (style.width ?? 1) * devicePixelRatio;
      ctx.setLineDash(style.dash.map((v) => v * devicePixelRatio));
      ctx.beginPath();
      ctx.moveTo(x, bbox.top);
      ctx.lineTo(x, bbox.top + bbox.height);
      ctx.stroke();
      drawn += 1;
      if (m.kind === "reversal") reversals += 1;
    }
    ctx.restore();
    u._container.dataset.markers = String(drawn);
    u._container.dataset.reversals = String(reversals);
  }

  current() {
    return this.replay ?? this.live;
  }

  /** Each chart fills its box: the width, and the height left by its title and legend. */
  resize() {
    for (const c of this.charts) {
      const el = c._container;
      const title = el.querySelector(".plot-title");
      const legend = el.querySelector(".u-legend");
      // the box's padding (4 + 4 px), the title's margin and uPlot's own few pixels
      const room = el.clientHeight - (title ? title.offsetHeight : 0) -
        (legend ? legend.offsetHeight : 0) - 20;
      c._legendH = legend ? legend.offsetHeight : 0;
      const w = Math.max(200, el.clientWidth - 14); // inside the padding (6 + 6 px)
      const h = Math.max(80, Math.min(260, Math.floor(room)));
      if (Math.abs(w - c.width) > 2 || Math.abs(h - c.height) > 2) c.setSize({ width: w, height: h });
    }
  }

  /** Legends (and cursors) off the plots: at the pinned index in a replay, else the newest. */
  restLegends() {
    const buf = this.current();
    // a cursor the mouse put on a plot (uPlot parks it at left < 0 otherwise) stays
    if (this.charts.some((c) => c.cursor.left >= 0 && c.cursor.left !== c._pinnedAt)) return;
    if (this.pinned !== null && this.replay) {
      this.pin(this.pinned);
      return;
    }
    const last = buf.length - 1;
    for (const c of this.charts) if (last >= 0) c.setLegend({ idx: last }, false);
  }

  /** Put every chart's cursor on data index `idx` of the shown buffer (the replay scrubber);
   * the legends show that iteration's values. */
  pin(idx) {
    this.pinned = idx;
    const buf = this.current();
    const x = buf.cols[0][0][idx];
    if (x === undefined) return;
    this.pinning = true;
    try {
      for (const c of this.charts) {
        const left = c.valToPos(x, "x");
        if (Number.isFinite(left)) c.setCursor({ left, top: c.bbox.height / devicePixelRatio / 2 }, true, false);
        c._pinnedAt = c.cursor.left;
        c._container.dataset.cursorIteration = String(buf.samples[idx]?.iteration ?? x);
      }
    } finally {
      this.pinning = false;
    }
  }

  /** An event of the live run at its iteration. */
  markLive(marker) {
    this.live.mark(marker);
    if (!this.replay) this.schedule();
  }

  /** Append a live sample (params: the RollingParams in force). */
  push(sample, params) {
    this.live.push(sample, params || {});
    if (!this.replay) this.schedule();
  }

  /** Put a live run's earlier samples (in iteration order, all before the first live one)
   * ahead of those already shown, within the live window; its markers stay. */
  prependLive(samples, params) {
    const now = this.live.samples;
    const markers = this.live.markers;
    this.live.clear();
    for (const s of [...samples, ...now]) this.live.push(s, params || {});
    for (const m of markers) this.live.mark(m);
    if (!this.replay) this.schedule();
  }

  /** Start a new live series (a new run). */
  resetLive() {
    this.live.clear();
    if (!this.replay) this.schedule();
  }

  /** Show a recorded run instead of the live data; `markers`: its events ({x, kind, text}). */
  showReplay(samples, params, markers = []) {
    const buf = new Buffers(0);
    for (const s of samples) buf.push(s, params || {});
    for (const m of markers) buf.mark(m);
    this.replay = buf;
    this.pinned = null;
    this.schedule();
  }

  showLive() {
    this.replay = null;
    this.pinned = null;
    for (const c of this.charts) {
      delete c._container.dataset.cursorIteration;
      // park the replay's cursor off the plot (as uPlot does when the mouse leaves): left on
      // it, it would read as a hover and hold the legends and the sketch on an old iteration
      c.setCursor({ left: -10, top: -10 }, false, false);
      c._pinnedAt = undefined;
    }
    this.onCursor?.(null);
    this.schedule();
  }

  get replaying() {
    return this.replay !== null;
  }

  schedule() {
    this.dirty = true;
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      if (!this.dirty) return;
      this.dirty = false;
      const buf = this.current();
      this.charts.forEach((c, i) => c.setData(buf.cols[i]));
      // after uPlot has taken the new data (it commits in a microtask, queued before this one):
      // a replay's cursor pinned before, at its open, sits on the new scale (index 0 too)
      queueMicrotask(() => this.restLegends());
      // values that wrap the legend onto another line take room from the chart
      if (this.charts.some((c) => c._container.querySelector(".u-legend")?.offsetHeight !== c._legendH)) {
        this.resize();
      }
    });
  }
}
