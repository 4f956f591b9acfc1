// The six tactile pads as heat maps (from `tactile` messages; raw counts, 4095 = full scale).
//
// Matrix order 0…5 as in the config's axes.*_matrix. Row 0 is at the fingertip's end (distal
// pads) or at the distal joint (proximal pads), so it is drawn at the top: the fingertip is "up".
// In simulation, pressing and holding a cell presses the simulated pad there (see pressable).

import { request } from "/web/api.js";

export const PAD_LABELS = ["F1 prox", "F1 dist", "thumb prox", "thumb dist", "F2 prox", "F2 dist"];
const SHAPES = [[14, 6], [13, 6], [14, 6], [13, 6], [14, 6], [13, 6]]; // rows × cols
const FULL_SCALE = 4095;
const CELL = 13; // px per taxel
export const ZERO_COLOR = [24, 27, 38]; // colour of a taxel reading 0

// A perceptual ramp (roughly "inferno"): dark → purple → orange → pale yellow.
const STOPS = [
  [0.0, ZERO_COLOR],
  [0.02, [40, 11, 84]],
  [0.25, [120, 28, 109]],
  [0.5, [212, 72, 66]],
  [0.75, [251, 155, 6]],
  [1.0, [252, 255, 164]],
];
const LUT = buildLut(256);

function buildLut(n) {
  const out = [];
  for (let i = 0; i < n; i++) {
    const v = i / (n - 1);
    let k = 1;
    while (k < STOPS.length - 1 && STOPS[k][0] < v) k++;
    const [v0, c0] = STOPS[k - 1];
    const [v1, c1] = STOPS[k];
    const f = v1 > v0 ? Math.min(1, Math.max(0, (v - v0) / (v1 - v0))) : 0;
    const c = c0.map((x, j) => Math.round(x + f * (c1[j] - x)));
    out.push(`rgb(${c[0]},${c[1]},${c[2]})`);
  }
  return out;
}

function colour(count) {
  if (!(count > 0)) return LUT[0];
  const v = Math.min(1, count / FULL_SCALE);
  return LUT[Math.max(1, Math.round(v * (LUT.length - 1)))];
}

export class Pads {
  /** container: the #pads element; six figures with a canvas each are created in it. */
  constructor(container) {
    this.canvases = [];
    this.infos = [];
    this.latest = null;
    this.frame = 0;
    this.container = container;
    container.innerHTML = "";
    SHAPES.forEach(([rows, cols], i) => {
      const fig = document.createElement("figure");
      fig.className = "pad";
      // fingers side by side (F1, thumb, F2), the distal pad above the proximal one
      fig.style.gridColumn = String(Math.floor(i / 2) + 1);
      fig.style.gridRow = String(i % 2 === 1 ? 1 : 2);
      const cap = document.createElement("figcaption");
      cap.textContent = `${PAD_LABELS[i]} (${i})`;
      const canvas = document.createElement("canvas");
      canvas.width = cols * CELL;
      canvas.height = rows * CELL;
      canvas.dataset.matrix = String(i);
      canvas.title = `${PAD_LABELS[i]}: matrix ${i}, ${rows}×${cols}, top = fingertip side`;
      const info = document.createElement("div");
      info.className = "pad-info";
      info.textContent = "–";
      fig.append(cap, canvas, info);
      container.appendChild(fig);
      this.canvases.push(canvas);
      this.infos.push(info);
      this.draw(i, null);
      this.pressable(i);
    });
    const scale = document.createElement("div");
    scale.className = "pad-scale";
    const stops = STOPS.map(([v, c]) => `rgb(${c[0]},${c[1]},${c[2]}) ${(v * 100).toFixed(0)}%`);
    scale.innerHTML = `<span>0</span><div class="bar"></div><span>${FULL_SCALE}</span>`;
    scale.querySelector(".bar").style.background = `linear-gradient(to right, ${stops.join(", ")})`;
    container.appendChild(scale);
  }

  /** Keep the newest frame; draw it at the next animation frame. `iteration`: the recorded
   * iteration it belongs to (a replay), or null (live); shown as the container's data-iteration. */
  update(matrices, iteration = null) {
    this.latest = matrices;
    if (iteration === null) delete this.container.dataset.iteration;
    else this.container.dataset.iteration = String(iteration);
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      const m = this.latest;
      if (!m) return;
      for (let i = 0; i < this.canvases.length; i++) this.draw(i, m[i] || null);
    });
  }

  /**
   * Press-and-hold on pad i presses the simulated pad under the pointer (POST /api/sim/press,
   * 2 N over a 4 mm disc, position in mm from the cell frame: x across, y along from the tip);
   * letting go lifts it (DELETE). A real hand answers 404: its pads stay read-only.
   */
  pressable(i) {
    const PITCH_MM = 3.4; // the config's tactile.texel_pitch_mm
    const canvas = this.canvases[i];
    const [rows, cols] = SHAPES[i];
    canvas.style.cursor = "crosshair";
    canvas.addEventListener("pointerdown", (e) => {
      if (this.readOnly || e.button !== 0) return;
      canvas.setPointerCapture(e.pointerId);
      const box = canvas.getBoundingClientRect();
      const x = ((e.clientX - box.left) / box.width) * cols * PITCH_MM;
      const y = ((e.clientY - box.top) / box.height) * rows * PITCH_MM;
      const press = { pad: i, x_mm: +x.toFixed(2), y_mm: +y.toFixed(2), force_n: 2, radius_mm: 4,
        duration_s: 60 };
      // resolves to whether the press is on, so that letting go early still lifts it
      this.pressing = request("POST", "/api/sim/press", press).then(
        () => true,
        (err) => {
          if (err.status === 404) {
            this.readOnly = true;
            this.canvases.forEach((c) => (c.style.cursor = ""));
          } else this.infos[i].textContent = err.message;
          return false;
        },
      );
    });
    const lift = async () => {
      const pressing = this.pressing;
      this.pressing = null;
      if (pressing && (await pressing)) request("DELETE", "/api/sim/press", {}).catch(() => {});
    };
    canvas.addEventListener("pointerup", lift);
    canvas.addEventListener("pointercancel", lift);
  }

  draw(i, matrix) {
    const canvas = this.canvases[i];
    const ctx = canvas.getContext("2d");
    const [rows, cols] = SHAPES[i];
    let max = 0;
    let sum = 0;
    for (let r = 0; r < rows; r++) {
      const row = matrix ? matrix[r] : null;
      for (let c = 0; c < cols; c++) {
        const v = row ? row[c] : 0;
        if (v > max) max = v;
        sum += v || 0;
        ctx.fillStyle = colour(v);
        ctx.fillRect(c * CELL, r * CELL, CELL - 1, CELL - 1);
      }
    }
    this.infos[i].textContent = matrix ? `max ${max} · Σ ${sum}` : "no data";
  }
}
