// Cockpit widget: centre and minimum range in large digits over the pilot's video, a small
// false-colour strip of the range map, transparent background. Quarter resolution is plenty.

import { lut } from "./colormap.js";
import { ViewStream, centreAndMinimum } from "./stream.js";

const $ = (id) => document.getElementById(id);
const table = lut("turbo");
let latest = null;
const state = { frame: null, centre: null, minimum: null };
window.uwcamWidget = state;

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
  drawStrip(frame.range, m.minimum, m.centre === null ? null : Math.max(m.centre * 1.5, (m.minimum ?? 0) + 0.5));
  stream.ack(frame.number);
}

const stream = new ViewStream({
  step: 4,
  colour: false,
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
