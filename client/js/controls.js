// Parameter sliders, built from the axes the server declares (nothing about any scene is
// hard-coded here): one range input per axis with its name, current value, range, tick marks at
// the training values (a <datalist> for the browser, drawn ticks for the eye) and a number
// field for an exact value.

import { clamp } from "./state.js";

let uid = 0;

/** Format a parameter value compactly but without hiding differences between training values. */
export function formatValue(value, axis) {
  if (!Number.isFinite(value)) return "–";
  const span = Math.abs(axis.max - axis.min) || Math.abs(value) || 1;
  const digits = clamp(Math.ceil(-Math.log10(span)) + 3, 0, 6);
  return Number(value.toFixed(digits)).toString();
}

/** A step that gives about 200 keyboard steps across the range, rounded to 1, 2 or 5 x 10^k. */
export function sliderStep(axis) {
  const span = axis.max - axis.min;
  if (!(span > 0)) return "any";
  const raw = span / 200;
  const p = 10 ** Math.floor(Math.log10(raw));
  const m = raw / p;
  const nice = m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10;
  return nice * p;
}

/**
 * Build the sliders of one parameter set into `container`.
 * @param {HTMLElement} container
 * @param {Array<{name, min, max, values, default}>} axes
 * @param {{set: "A"|"B", onInput: (name, value, {interactive, inputTime}) => void}} options
 * @returns {{update: (values: Object<string, number>) => void}}
 */
export function buildParamControls(container, axes, { set, onInput }) {
  container.replaceChildren();
  const rows = new Map();
  if (!axes.length) {
    const p = document.createElement("p");
    p.className = "muted";
    p.textContent = "This scene has no parameters: only the view can change.";
    container.append(p);
  }
  for (const axis of axes) {
    const row = buildRow(axis, set, onInput);
    rows.set(axis.name, row);
    container.append(row.element);
  }
  return {
    update(values) {
      for (const [name, row] of rows) row.show(values[name]);
    },
  };
}

function buildRow(axis, set, onInput) {
  uid += 1;
  const id = `param-${set}-${uid}`;
  const span = axis.max - axis.min;
  const values = (axis.values || []).filter((v) => Number.isFinite(v));

  const row = document.createElement("div");
  row.className = "param";
  row.dataset.param = axis.name;
  row.dataset.set = set;

  const head = document.createElement("div");
  head.className = "param-head";
  const label = document.createElement("label");
  label.htmlFor = id;
  label.className = "param-name";
  label.textContent = axis.name;
  const number = document.createElement("input");
  number.type = "number";
  number.className = "param-number";
  number.min = String(axis.min);
  number.max = String(axis.max);
  number.step = "any";
  number.setAttribute("aria-label", `${axis.name} exact value (set ${set})`);
  head.append(label, number);

  const listId = `${id}-ticks`;
  const datalist = document.createElement("datalist");
  datalist.id = listId;
  for (const v of values) {
    const option = document.createElement("option");
    option.value = String(v);
    datalist.append(option);
  }

  const range = document.createElement("input");
  range.type = "range";
  range.id = id;
  range.name = axis.name;
  range.className = "param-range";
  range.min = String(axis.min);
  range.max = String(axis.max);
  range.step = String(sliderStep(axis));
  range.setAttribute("list", listId);
  range.dataset.set = set;
  range.setAttribute(
    "aria-describedby",
    `${id}-range`,
  );

  // Drawn ticks: one per training value, positioned where the slider thumb centre would be.
  const ticks = document.createElement("div");
  ticks.className = "param-ticks";
  ticks.setAttribute("aria-hidden", "true");
  for (const v of values) {
    const tick = document.createElement("span");
    tick.className = "tick";
    tick.dataset.value = String(v);
    tick.style.setProperty("--pos", String(span > 0 ? (v - axis.min) / span : 0.5));
    tick.title = `trained at ${formatValue(v, axis)}`;
    ticks.append(tick);
  }

  const foot = document.createElement("div");
  foot.className = "param-range-text";
  foot.id = `${id}-range`;
  const lo = document.createElement("span");
  lo.className = "param-min";
  lo.textContent = formatValue(axis.min, axis);
  const mid = document.createElement("span");
  mid.className = "param-trained";
  mid.textContent = values.length ? `${values.length} trained values (ticks)` : "";
  const hi = document.createElement("span");
  hi.className = "param-max";
  hi.textContent = formatValue(axis.max, axis);
  foot.append(lo, mid, hi);
  const srRange = document.createElement("span");
  srRange.className = "sr-only";
  srRange.textContent = ` range ${formatValue(axis.min, axis)} to ${formatValue(axis.max, axis)}`;
  foot.append(srRange);

  const track = document.createElement("div");
  track.className = "param-track";
  track.append(range, ticks);
  row.append(head, track, datalist, foot);

  let current = NaN;
  const show = (value) => {
    if (!Number.isFinite(value)) return;
    current = value;
    const text = formatValue(value, axis);
    // The slider shows the position; the exact value lives in the state and the number field.
    if (document.activeElement !== range) range.value = String(value);
    if (document.activeElement !== number) number.value = text;
    range.setAttribute("aria-valuetext", `${axis.name} ${text}`);
    row.classList.toggle("at-training-value", values.some((v) => Math.abs(v - value) <= 1e-9 * (span || 1)));
  };

  range.addEventListener("input", (event) => {
    onInput(axis.name, Number(range.value), { interactive: true, inputTime: event.timeStamp });
  });
  // Keyboard steps fire input and change together: both count as interaction (previews, then one
  // full frame when the keys stop), so holding an arrow key never queues full-quality renders.
  range.addEventListener("change", (event) => {
    onInput(axis.name, Number(range.value), { interactive: true, inputTime: event.timeStamp });
  });
  // Page Up/Down jump a tenth of the range (browsers differ on this for range inputs).
  range.addEventListener("keydown", (event) => {
    if (event.key !== "PageUp" && event.key !== "PageDown") return;
    event.preventDefault();
    const delta = (event.key === "PageUp" ? 1 : -1) * span * 0.1;
    onInput(axis.name, clamp(current + delta, axis.min, axis.max), {
      interactive: true,
      inputTime: event.timeStamp,
    });
  });

  const commitNumber = (event) => {
    const v = Number(number.value);
    if (number.value.trim() === "" || !Number.isFinite(v)) {
      number.value = formatValue(current, axis);
      return;
    }
    const inside = clamp(v, axis.min, axis.max);
    onInput(axis.name, inside, { interactive: false, inputTime: event.timeStamp });
    number.value = formatValue(inside, axis);
    range.value = String(inside);
  };
  number.addEventListener("change", commitNumber);
  number.addEventListener("keydown", (event) => {
    if (event.key === "Enter") commitNumber(event);
  });

  return { element: row, show };
}
