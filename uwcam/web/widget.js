// Cockpit widget: centre and minimum range in large digits over the pilot's video, a small
// false-colour strip of the range map, transparent background. Quarter resolution is plenty.

import { lut } from "./colormap.js";
import { ViewStream } from "./stream.js";

const $ = (id) => document.getElementById(id);
const table = lut("turbo");
let latest = null;
const state = { frame: null, centre: null, minimum: null };
window.uwcamWidget = state;

function centreAndMinimum(range) {
  // Centre: median of valid ranges in the middle 10 % of the image; minimum: 2nd percentile of
  // all valid ranges (one noisy pixel must not read as an obstacle).
  const { data, width, height, invalid_base: base } = range;
  const centre = [], all = [];
  const x0 = Math.floor(width * 0.45), x1 = Math.ceil(width * 0.55), y0 = Math.floor(height * 0.45), y1 = Math.ceil(height * 0.55);
  for (let y = 0; y < height; y++) {
    for (let x = 0; x < width; x++) {
      const v = data[y * width + x];
      if (v >= base) continue;
      all.push(v);
      if (x >= x0 && x < x1 && y >= y0 && y < y1) centre.push(v);
    }
  }
  const pick = (values, q) => {
    if (!values.length) return null;
    values.sort((a, b) => a - b);
    return values[Math.min(values.length - 1, Math.floor(q * values.length))] / 1000;
  };
  return { centre: pick(centre, 0.5), minimum: pick(all, 0.02), low: pick(all.slice(), 0.02), high: pick(all, 0.98) };
}

function drawStrip(range, low, high) {
  const canvas = $("strip");
  canvas.width = range.width; canvas.height = range.height;
  const ctx = canvas.getContext("2d");
  const image = ctx.createImageData(range.width, range.height);
  const out = new Uint32Array(image.data.buffer);
  const lo = (low ?? 0) * 1000, scale = 255 / Math.max(((high ?? 1) - (low ?? 0)) * 1000, 1);
  for (let i = 0; i < range.data.length; i++) {
    const v = range.data[i];
    if (v >= range.invalid_base) { out[i] = 0x80000000; continue; }  // invalid: translucent black
    const t = ((v - lo) * scale) | 0;
    out[i] = table[t < 0 ? 0 : t > 255 ? 255 : t];
  }
  ctx.putImageData(image, 0, 0);
}

function paint() {
  const frame = latest;
  latest = null;
  if (!frame) return;
  const m = centreAndMinimum(frame.range);
  state.frame = frame.number; state.centre = m.centre; state.minimum = m.minimum;
  $("centre").textContent = m.centre === null ? "—" : `${m.centre.toFixed(2)} m`;
  $("minimum").textContent = m.minimum === null ? "—" : `${m.minimum.toFixed(2)} m`;
  drawStrip(frame.range, m.low, m.high);
  stream.ack(frame.number);
}

const stream = new ViewStream({
  step: 4,
  onFrame: (frame) => {
    if (!latest) requestAnimationFrame(paint);
    latest = frame;
    state.captureMs = frame.captureMs;
  },
  onState: (s) => { $("note").textContent = s === "connected" ? "" : "uwcam: reconnecting…"; },
});

setInterval(() => {
  const stale = !state.captureMs || Date.now() - state.captureMs > 1500;
  $("digits").classList.toggle("stale", stale);
  if (stale && state.captureMs) $("note").textContent = `stale: last frame ${((Date.now() - state.captureMs) / 1000).toFixed(1)} s old`;
  else if (!stale && $("note").textContent.startsWith("stale")) $("note").textContent = "";
}, 500);
