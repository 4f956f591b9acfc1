// The rolling-parameter form, built from GET /api/params/schema (ranges, descriptions).
//
// Client-side checks (min/max, exclusive bounds, integers) show a message next to a field as
// you type; the server stays the judge: its 422 `details` lines are put next to the fields they
// name, and lines naming no field go under the form.

const LABELS = {
  mode: "mode",
  delta_phi_deg: "Δφ (deg)",
  k: "k",
  lambda_gain: "λ",
  d_sigma_deg: "dσ (deg)",
  alpha_deg: "α (deg)",
  grasp_force: "Fd",
  contact_force_min: "contact F min",
  force_deadband: "force deadband",
  force_band_low: "force band low (× Fd)",
  force_band_high: "force band high (× Fd)",
  delta_lambda_inc_mm: "ΔΛ_inc (mm)",
  delta_lambda_dec_mm: "ΔΛ_dec (mm)",
  force_reverse: "force reverse (× Fd)",
  finger1_max_step_deg: "Finger 1's step at most (deg)",
  min_half_stroke_deg: "half stroke at least (deg)",
  wedge_limit_deg: "pads' wedge at most (deg)",
  recentre_strokes: "re-centre within (strokes)",
  route: "Finger 2's route",
  cycles: "cycles (strokes)",
};

function rangeText(name, p) {
  const lo = p.exclusiveMinimum ?? p.minimum;
  const hi = p.exclusiveMaximum ?? p.maximum;
  const parts = [];
  if (lo !== undefined) parts.push(`${lo} ${p.exclusiveMinimum !== undefined ? "<" : "≤"} `);
  parts.push(name);
  if (hi !== undefined) parts.push(` ${p.exclusiveMaximum !== undefined ? "<" : "≤"} ${hi}`);
  return parts.join("");
}

/** Client-side check of one value against its schema; an error string or "". */
export function checkValue(name, p, raw) {
  if (p.enum) return p.enum.includes(raw) ? "" : `${name}: choose one of ${p.enum.join(", ")}`;
  if (raw === "" || raw === null || raw === undefined) return `${name}: enter a number`;
  const v = Number(raw);
  if (!Number.isFinite(v)) return `${name}: "${raw}" is not a number`;
  if (p.type === "integer" && !Number.isInteger(v)) return `${name}: must be a whole number`;
  const bad =
    (p.minimum !== undefined && v < p.minimum) ||
    (p.maximum !== undefined && v > p.maximum) ||
    (p.exclusiveMinimum !== undefined && v <= p.exclusiveMinimum) ||
    (p.exclusiveMaximum !== undefined && v >= p.exclusiveMaximum);
  return bad ? `${name} = ${raw}: out of range (allowed: ${rangeText(name, p)})` : "";
}

export class ParamsForm {
  /** form: #params-form; onSubmit(patch) is called with the changed fields. */
  constructor(form, { onSubmit, onReset }) {
    this.form = form;
    this.fieldsEl = form.querySelector("#params-fields");
    this.formError = form.querySelector("#params-form-error");
    this.schema = null;
    this.server = {}; // values the server has in force
    this.inputs = {};
    form.addEventListener("submit", (ev) => {
      ev.preventDefault();
      const { patch, blocked } = this.collect(true);
      if (blocked) return;
      onSubmit(patch);
    });
    form.querySelector("#params-reset").addEventListener("click", () => {
      this.setValues(this.server, true);
      if (onReset) onReset();
    });
  }

  build(schema) {
    this.schema = schema;
    this.fieldsEl.innerHTML = "";
    this.inputs = {};
    for (const [name, p] of Object.entries(schema.properties || {})) {
      const row = document.createElement("div");
      row.className = "field";
      row.dataset.field = name;
      const label = document.createElement("label");
      label.htmlFor = `param-${name}`;
      label.textContent = LABELS[name] ?? p.title ?? name;
      let input;
      if (p.enum) {
        input = document.createElement("select");
        for (const v of p.enum) input.add(new Option(v, v));
      } else {
        input = document.createElement("input");
        input.type = "number";
        input.step = p.type === "integer" ? "1" : "any";
        if (p.minimum !== undefined) input.min = String(p.minimum);
        if (p.maximum !== undefined) input.max = String(p.maximum);
      }
      input.id = `param-${name}`;
      input.name = name;
      input.title = `${p.description ?? ""} (${p.enum ? p.enum.join(" | ") : rangeText(name, p)})`;
      const desc = document.createElement("div");
      desc.className = "desc";
      desc.textContent = `${p.description ?? ""}${p.enum ? "" : ` — ${rangeText(name, p)}`}`;
      desc.id = `param-${name}-desc`;
      const err = document.createElement("div");
      err.className = "field-error";
      err.id = `param-${name}-error`;
      err.dataset.errorFor = name;
      input.setAttribute("aria-describedby", desc.id);
      input.addEventListener("input", () => this.onInput(name));
      input.addEventListener("change", () => this.onInput(name));
      row.append(label, input, desc, err);
      this.fieldsEl.appendChild(row);
      this.inputs[name] = { input, row, err, desc, p };
    }
  }

  onInput(name) {
    const f = this.inputs[name];
    const msg = checkValue(name, f.p, f.input.value);
    this.setFieldError(name, msg);
    f.row.classList.toggle("dirty", this.isDirty(name));
  }

  isDirty(name) {
    const f = this.inputs[name];
    const sv = this.server[name];
    if (sv === undefined) return false;
    if (f.p.enum) return f.input.value !== sv;
    return f.input.value === "" || Number(f.input.value) !== Number(sv);
  }

  /**
   * New server values: a field the user changed keeps what they typed while it differs from
   * the server's value; once the server's value is what they typed (sent with Grasp & roll,
   * now in force) it is no longer marked changed. Other fields show the server's value, the
   * focused one too (the drawer focuses its first field when it opens).
   */
  setValues(values, force = false) {
    this.server = { ...values };
    for (const [name, f] of Object.entries(this.inputs)) {
      if (!(name in values)) continue;
      const typed = f.row.classList.contains("dirty") && this.isDirty(name);
      if (force || !typed) {
        if (f.input.value !== String(values[name])) f.input.value = String(values[name]);
        f.row.classList.remove("dirty");
        if (force) this.setFieldError(name, "");
      }
    }
    if (force) this.formError.textContent = "";
  }

  /**
   * The changed fields as a patch. Values out of range are sent anyway (the server answers
   * with its own 422 message); values that are not numbers block the request.
   */
  collect(showErrors) {
    const patch = {};
    let blocked = false;
    for (const [name, f] of Object.entries(this.inputs)) {
      if (!this.isDirty(name)) continue;
      const raw = f.input.value;
      const msg = checkValue(name, f.p, raw);
      if (showErrors) this.setFieldError(name, msg);
      if (f.p.enum) patch[name] = raw;
      else if (raw === "" || !Number.isFinite(Number(raw))) blocked = true;
      else patch[name] = f.p.type === "integer" && Number.isInteger(Number(raw))
        ? parseInt(raw, 10) : Number(raw);
    }
    return { patch, blocked };
  }

  get dirtyCount() {
    return Object.keys(this.inputs).filter((n) => this.isDirty(n)).length;
  }

  setFieldError(name, msg) {
    const f = this.inputs[name];
    if (!f) return;
    f.err.textContent = msg;
    f.row.classList.toggle("invalid", Boolean(msg));
    // a screen reader says the field is wrong, and why, with the field
    if (msg) f.input.setAttribute("aria-invalid", "true");
    else f.input.removeAttribute("aria-invalid");
    f.input.setAttribute("aria-describedby", msg ? `${f.err.id} ${f.desc.id}` : f.desc.id);
  }

  clearErrors() {
    for (const name of Object.keys(this.inputs)) this.setFieldError(name, "");
    this.formError.textContent = "";
  }

  /** Put the server's 422 detail lines next to the fields they name. */
  showServerErrors(details, fallback) {
    const rest = [];
    for (const line of details || []) {
      const name = this.fieldOf(String(line));
      if (name) this.setFieldError(name, String(line));
      else rest.push(String(line));
    }
    if (rest.length || !(details || []).length) {
      this.formError.textContent = rest.length ? rest.join("; ") : fallback;
    }
  }

  fieldOf(line) {
    const names = Object.keys(this.inputs);
    // "k = 0.5: …" (params validation) or "body.params.k: …" (request validation)
    const m = line.match(/^\s*([A-Za-z_][A-Za-z0-9_]*)\s*[=:]/);
    if (m && names.includes(m[1])) return m[1];
    const path = line.split(":")[0];
    for (const seg of path.split(/[.\s]/).reverse()) if (names.includes(seg)) return seg;
    return null;
  }

  /** The values the form shows (for the record; numbers where numeric). */
  values() {
    const out = {};
    for (const [name, f] of Object.entries(this.inputs)) {
      out[name] = f.p.enum ? f.input.value : Number(f.input.value);
    }
    return out;
  }
}
