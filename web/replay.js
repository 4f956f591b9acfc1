// The replay's one time scrubber: play/pause, speed, drag; the iteration and time shown. Whoever
// shows a recorded run (plots, pads, sketch, the 3-D view) follows `onIndex(i, sample)`.

const SPEEDS = [0.25, 0.5, 1, 2, 5, 10];
const FALLBACK_DT_S = 0.02; // between samples without a time (never in a recorded run)

export class Replay {
  /** bar: the #replay-banner element (its controls are looked up inside it). */
  constructor(bar, { onIndex }) {
    this.bar = bar;
    this.onIndex = onIndex;
    this.samples = [];
    this.index = 0;
    this.speed = 1;
    this.playing = false;
    this.raf = 0;
    this.slider = bar.querySelector("#replay-scrubber");
    this.playBtn = bar.querySelector("#replay-play");
    this.speedSel = bar.querySelector("#replay-speed");
    this.at = bar.querySelector("#replay-at");
    this.speedSel.innerHTML = "";
    for (const v of SPEEDS) this.speedSel.add(new Option(`${v}×`, String(v), v === 1, v === 1));
    this.slider.addEventListener("input", () => {
      this.pause();
      this.seek(Number(this.slider.value));
    });
    this.playBtn.addEventListener("click", () => this.toggle());
    this.speedSel.addEventListener("change", () => this.setSpeed(Number(this.speedSel.value)));
    // keys while a replay is shown (not while typing): space plays/pauses, ← → step (⇧: 10)
    document.addEventListener("keydown", (ev) => {
      if (!this.active) return;
      const arrow = ev.key === "ArrowRight" || ev.key === "ArrowLeft";
      // a focused field keeps its own keys (typing, a list's arrows), and a button its space;
      // the arrows step the replay from a button and from the scrubber too (⇧: ten)
      const own = ev.target.closest("input, select, textarea, button");
      const ours = own === this.slider || (own && own.tagName === "BUTTON" && arrow);
      if (own && !ours) return;
      const step = ev.shiftKey ? 10 : 1;
      if (ev.key === " ") this.toggle();
      else if (arrow) {
        this.pause();
        this.seek(this.index + (ev.key === "ArrowRight" ? step : -step));
      } else return;
      ev.preventDefault();
    });
  }

  get active() {
    return this.samples.length > 0;
  }

  /** Start on a run's samples (at the first). */
  load(samples) {
    this.pause();
    this.samples = samples;
    this.slider.min = "0";
    this.slider.max = String(Math.max(0, samples.length - 1));
    this.slider.disabled = samples.length < 2;
    this.playBtn.disabled = samples.length < 2;
    this.seek(0);
  }

  clear() {
    this.pause();
    this.samples = [];
  }

  time(i) {
    const t = this.samples[i] && this.samples[i].t;
    return typeof t === "number" ? t : i * FALLBACK_DT_S;
  }

  seek(i) {
    if (!this.samples.length) return;
    const idx = Math.max(0, Math.min(this.samples.length - 1, Math.round(i)));
    this.index = idx;
    this.slider.value = String(idx);
    const s = this.samples[idx];
    const it = s.iteration ?? idx;
    this.at.textContent = `iteration ${it} · ${this.time(idx).toFixed(2)} s`;
    this.bar.dataset.iteration = String(it);
    this.onIndex(idx, s);
  }

  /** Seek to the sample of iteration `it` (the nearest at or before it). */
  seekIteration(it) {
    let lo = 0;
    let hi = this.samples.length - 1;
    while (lo < hi) {
      const mid = (lo + hi + 1) >> 1;
      if ((this.samples[mid].iteration ?? mid) <= it) lo = mid;
      else hi = mid - 1;
    }
    this.seek(lo);
  }

  setSpeed(v) {
    if (!(v > 0)) return;
    this.speed = v;
    this.speedSel.value = String(v);
    if (this.playing) this.play(); // go on from here at the new speed
  }

  toggle() {
    if (this.playing) this.pause();
    else this.play();
  }

  /** Play in the run's own time × speed, from the shown sample (from the start at the end). */
  play() {
    if (this.samples.length < 2) return;
    if (this.index >= this.samples.length - 1) this.seek(0);
    cancelAnimationFrame(this.raf);
    this.playing = true;
    this.playBtn.textContent = "❚❚ Pause";
    this.bar.dataset.playing = "true";
    const t0 = this.time(this.index);
    const wall0 = performance.now();
    const step = (now) => {
      if (!this.playing) return;
      const target = t0 + ((now - wall0) / 1000) * this.speed;
      let i = this.index;
      while (i < this.samples.length - 1 && this.time(i + 1) <= target) i++;
      if (i !== this.index) this.seek(i);
      if (i >= this.samples.length - 1) {
        this.pause();
        return;
      }
      this.raf = requestAnimationFrame(step);
    };
    this.raf = requestAnimationFrame(step);
  }

  pause() {
    this.playing = false;
    cancelAnimationFrame(this.raf);
    this.raf = 0;
    this.playBtn.textContent = "▶ Play";
    this.bar.dataset.playing = "false";
  }
}
