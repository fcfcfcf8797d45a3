// uwcam operator page: live colour and range views, readout, pins, line profile, 3-D, health
// and controls. Talks only to the daemon's public API, always by relative URL (so it works under
// a reverse proxy's path prefix, e.g. BlueOS's /extensionv2/uwcam/).
//
// One module over 500 lines on purpose: its handlers all read and write the page's one `state`
// (the newest frame, colour limits, pins, the status, the patch being drawn), so they stay
// together; what stands alone lives beside it: colour maps, the view stream, the 3-D view, the
// tank calibration panel and the alert banner.

import { COLOUR_MAPS, REASON_COLOURS, cssColour, lut, reasonColour } from "./colormap.js";
import { ViewStream, centreAndMinimum, float16, sample } from "./stream.js";
import { PointCloudView } from "./viewer3d.js";
import { startTank } from "./tank.js";
// --- alert banner (issue 28): begin ---
import { startAlertBanner } from "./alerts.js";
// --- alert banner: end ---

const $ = (id) => document.getElementById(id);
const STALE_AFTER_MS = 1500;
const MAX_PINS = 8;
const REQUEST_TIMEOUT_MS = 15000;

const state = {
  hello: null,
  frame: null,        // newest decoded frame, painted or not
  shown: null,        // the frame on screen
  colourBitmap: null,
  paused: false,
  mode: "side",
  showSigma: false,
  fusedFrames: null,  // median frames per pixel under temporal fusion (status), or null
  table: lut("turbo"),
  limits: { auto: true, min: 0.5, max: 5 },
  autoLimits: null,
  tool: "inspect",
  pointer: null,      // image pixel under the pointer
  pins: [],
  line: null,         // {x0, y0, x1, y1} in image pixels
  patchDraft: null,
  drag: null,
  status: null,
  statusAt: 0,
  config: null,
  csrf: sessionStorage.getItem("uwcam-csrf"),
  session: { token_required: false, signed_in: true },
  // Figures a benchmark or a test reads: frames painted and their age (capture → painted).
  stats: { displayed: 0, lastDisplayed: 0, ages: [], connectedAt: 0 },
};
window.uwcam = state;

// ---------------------------------------------------------------- API helpers

function message(text, ok = false) {
  const el = $("message");
  el.textContent = text;
  el.className = ok ? "ok" : "";
}

async function api(path, { method = "GET", body, type = "application/json" } = {}) {
  const headers = {};
  if (body !== undefined) headers["Content-Type"] = type;
  if (method !== "GET" && state.csrf) headers["X-CSRF-Token"] = state.csrf;
  // Every request the page makes sets a value (none adds to one), so a request that hangs — a
  // tether dropping packets, a stale kept-alive connection — is abandoned after a while and sent
  // once more rather than leaving a control dead.
  let response;
  for (let attempt = 1; ; attempt++) {
    try {
      response = await fetch(path, {
        method, headers, credentials: "same-origin", signal: AbortSignal.timeout(REQUEST_TIMEOUT_MS),
        body: body === undefined ? undefined : type === "application/json" ? JSON.stringify(body) : body,
      });
      break;
    } catch (error) {
      if (error.name !== "TimeoutError" || attempt >= 2) {
        throw new Error(`${method} ${path}: ${error.name === "TimeoutError" ? "no answer from the daemon" : error.message}`);
      }
    }
  }
  const text = await response.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = text; }
  if (!response.ok) {
    if (response.status === 401) { state.session.signed_in = false; renderAuth(); }
    const detail = data && (data.detail || data.error);
    const why = typeof detail === "string" ? detail : JSON.stringify(detail);
    throw new Error(`${method} ${path}: ${response.status} ${why || response.statusText}`);
  }
  return data;
}

async function change(what, path, options) {
  try {
    const result = await api(path, options);
    message(`${what}: done`, true);
    return result;
  } catch (error) {
    message(`${what} failed — ${error.message}`);
    return null;
  }
}

// Lamp intensity: one request at a time, the newest value sent last. A slider dragged across
// fires change after change; requests in flight together may be applied in any order (the API
// serves them on several threads), and the lamp would stay at whichever came last rather than
// where the slider stopped.
let intensityInFlight = false;
let intensityWanted = null;
async function sendIntensity(value) {
  intensityWanted = value;
  if (intensityInFlight) return;
  intensityInFlight = true;
  try {
    while (intensityWanted !== null) {
      const v = intensityWanted;
      intensityWanted = null;
      await change("Lamp intensity", "api/v1/lamp", { method: "PUT", body: { intensity: v } });
    }
  } finally {
    intensityInFlight = false;
  }
}

// ---------------------------------------------------------------- sign-in

function renderAuth() {
  const box = $("auth");
  const locked = state.session.token_required && !state.session.signed_in;
  document.querySelectorAll(".control").forEach((el) => { el.disabled = locked; });
  box.replaceChildren();
  if (!state.session.token_required) return;
  if (state.session.signed_in) {
    const out = document.createElement("button");
    out.textContent = "Sign out";
    out.onclick = async () => {
      await change("Sign out", "api/v1/session", { method: "DELETE" });
      state.csrf = null;
      sessionStorage.removeItem("uwcam-csrf");
      state.session.signed_in = false;
      renderAuth();
    };
    box.append("signed in ", out);
    return;
  }
  const input = document.createElement("input");
  input.type = "password";
  input.placeholder = "token";
  input.id = "token";
  const button = document.createElement("button");
  button.textContent = "Sign in";
  button.id = "sign-in";
  const signIn = async () => {
    const result = await change("Sign in", "api/v1/session", { method: "POST", body: { token: input.value } });
    if (result) {
      state.csrf = result.csrf_token;
      sessionStorage.setItem("uwcam-csrf", state.csrf);
      state.session.signed_in = true;
      renderAuth();
    }
  };
  button.onclick = signIn;
  input.onkeydown = (e) => { if (e.key === "Enter") signIn(); };
  box.append("controls locked: ", input, button);
}

async function loadSession() {
  try {
    state.session = await api("api/v1/session");
    // A signed-in browser gets its CSRF token back: a second tab shares the session cookie.
    state.csrf = state.session.csrf_token || null;
    if (state.csrf) sessionStorage.setItem("uwcam-csrf", state.csrf);
  } catch (error) {
    message(error.message);
  }
  renderAuth();
}

// ---------------------------------------------------------------- drawing

function percentileLimits(range) {
  // 2nd and 98th percentile of valid ranges from a histogram of every 7th pixel (1 cm bins).
  const bins = new Uint32Array(6600);
  let count = 0;
  const data = range.data, base = range.invalid_base;
  for (let i = 0; i < data.length; i += 7) {
    const v = data[i];
    if (v < base) { bins[(v / 10) | 0]++; count++; }
  }
  if (count < 20) return null;
  let acc = 0, lo = null, hi = null;
  for (let b = 0; b < bins.length; b++) {
    acc += bins[b];
    if (lo === null && acc >= 0.02 * count) lo = b / 100;
    if (acc >= 0.98 * count) { hi = (b + 1) / 100; break; }
  }
  if (hi - lo < 0.05) { lo -= 0.025; hi += 0.025; }
  return { min: Math.max(0, lo), max: hi };
}

function currentLimits(frame) {
  if (state.showSigma) {
    return state.sigmaLimits || { min: 0, max: 0.05 };
  }
  if (!state.limits.auto) return state.limits;
  const fresh = percentileLimits(frame.range);
  if (fresh) {
    // Smoothed so that the colours do not flicker from frame to frame.
    const a = state.autoLimits;
    state.autoLimits = a ? { min: a.min + 0.3 * (fresh.min - a.min), max: a.max + 0.3 * (fresh.max - a.max) } : fresh;
  }
  return state.autoLimits || state.limits;
}

let rangeImage = null, sigmaCanvas = null, sigmaImage = null;
const SIGMA_BINS = 10001;  // σ histogram: 1 mm bins to 10 m, the last holds everything above
const sigmaBins = new Uint32Array(SIGMA_BINS);
const reasonTable = new Uint32Array(64).map((_, code) => reasonColour(code));

function drawRange(frame) {
  const canvas = $("range");
  const r = frame.range;
  if (canvas.width !== r.width || canvas.height !== r.height) {
    canvas.width = r.width; canvas.height = r.height;
    $("marks").width = r.width; $("marks").height = r.height;
    rangeImage = null;
  }
  const ctx = canvas.getContext("2d");
  const limits = currentLimits(frame);
  const table = state.table;
  if (state.showSigma) {
    const s = frame.sigma;
    if (!sigmaCanvas || sigmaCanvas.width !== s.width || sigmaCanvas.height !== s.height) {
      sigmaCanvas = new OffscreenCanvas(s.width, s.height);
      sigmaImage = new ImageData(s.width, s.height);
    }
    const out = new Uint32Array(sigmaImage.data.buffer);
    const lo = limits.min * 1000, scale = 255 / Math.max((limits.max - limits.min) * 1000, 1e-6);
    // The next frame's scale: the 98th percentile of σ, so that a few wild pixels (edges, the
    // image border) do not squeeze every other pixel into the first colour. Every pixel counts,
    // in 1 mm bins (a sample on a fixed stride would keep hitting the same border columns).
    const bins = sigmaBins.fill(0);
    let n = 0;
    for (let i = 0; i < s.data.length; i++) {
      const v = float16(s.data[i]);
      if (Number.isNaN(v)) { out[i] = reasonTable[1]; continue; }
      bins[v < SIGMA_BINS - 1 ? v | 0 : SIGMA_BINS - 1]++;
      n++;
      let t = ((v - lo) * scale) | 0;
      out[i] = table[t < 0 ? 0 : t > 255 ? 255 : t];
    }
    if (n >= 20) {
      let b = 0;
      for (let acc = bins[0]; acc < 0.98 * n; acc += bins[++b]);
      const top = Math.max((b + 1) / 1000, 0.001);
      const a = state.sigmaLimits;
      state.sigmaLimits = { min: 0, max: a ? a.max + 0.3 * (top - a.max) : top };
    }
    sigmaCanvas.getContext("2d").putImageData(sigmaImage, 0, 0);
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(sigmaCanvas, 0, 0, r.width, r.height);
  } else {
    if (!rangeImage) rangeImage = new ImageData(r.width, r.height);
    const out = new Uint32Array(rangeImage.data.buffer);
    const data = r.data, base = r.invalid_base;
    const lo = limits.min * 1000, scale = 255 / Math.max((limits.max - limits.min) * 1000, 1);
    for (let i = 0; i < data.length; i++) {
      const v = data[i];
      if (v >= base) { out[i] = reasonTable[v - base]; continue; }
      let t = ((v - lo) * scale) | 0;
      out[i] = table[t < 0 ? 0 : t > 255 ? 255 : t];
    }
    ctx.putImageData(rangeImage, 0, 0);
  }
  drawColourbar(limits);
}

function drawColourbar(limits) {
  const bar = $("colourbar");
  if (bar.drawnTable !== state.table) {  // the gradient changes only with the colour map
    const ctx = bar.getContext("2d");
    for (let x = 0; x < bar.width; x++) {
      ctx.fillStyle = cssColour(state.table[Math.round((x / (bar.width - 1)) * 255)]);
      ctx.fillRect(x, 0, 1, bar.height);
    }
    bar.drawnTable = state.table;
  }
  const digits = limits.max - limits.min < 0.5 ? 3 : 2;
  $("bar-min").textContent = limits.min.toFixed(digits);
  $("bar-max").textContent = limits.max.toFixed(digits);
  $("bar-unit").textContent = state.showSigma ? "σ, m" : "range, m";
  $("range-label").textContent = rangeLabel();
}

// "range", and over how many frames the median pixel's range is fused while temporal fusion is on.
function rangeLabel() {
  const what = state.showSigma ? "σ of range" : "range";
  const n = state.fusedFrames;
  return n ? `${what} · fused over ${n} frame${n === 1 ? "" : "s"}` : what;
}

function drawColour() {
  if (!state.colourBitmap) return;
  const canvas = $("colour");
  const bitmap = state.colourBitmap;
  if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
    canvas.width = bitmap.width; canvas.height = bitmap.height;
  }
  canvas.getContext("2d").drawImage(bitmap, 0, 0);
}

function drawMarks() {
  const canvas = $("marks");
  const frame = state.shown;
  if (!frame) return;
  const step = frame.range.step;
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.lineWidth = Math.max(1, canvas.width / 640);
  ctx.font = `${Math.round(canvas.width / 60)}px sans-serif`;
  state.pins.forEach((p, i) => {
    const x = p.x / step, y = p.y / step;
    ctx.strokeStyle = "#fff"; ctx.fillStyle = "#fff";
    ctx.beginPath(); ctx.arc(x, y, canvas.width / 160, 0, 2 * Math.PI); ctx.stroke();
    ctx.fillText(String(i + 1), x + canvas.width / 120, y - canvas.width / 120);
  });
  const line = state.line;
  if (line) {
    ctx.strokeStyle = "#ff0"; ctx.beginPath();
    ctx.moveTo(line.x0 / step, line.y0 / step); ctx.lineTo(line.x1 / step, line.y1 / step); ctx.stroke();
  }
  const patch = state.patchDraft || state.patchRegion;
  if (patch) {
    ctx.strokeStyle = state.patchDraft ? "#0ff" : "rgba(0,255,255,.6)";
    ctx.setLineDash(state.patchDraft ? [6, 4] : []);
    ctx.strokeRect(patch[0] / step, patch[1] / step, patch[2] / step, patch[3] / step);
    ctx.setLineDash([]);
  }
}

function formatReading(reading) {
  if (reading.range === null) {
    const name = state.hello?.reasons?.[reading.reason];
    return `no range: ${PLAIN_REASONS[name] || name || `reason ${reading.reason}`}`;
  }
  return `${reading.range.toFixed(3)} m ± ${reading.sigma.toFixed(3)} m`;
}

function updateReadout() {
  const frame = state.shown;
  const el = $("readout");
  if (!frame || !state.pointer) return;
  const reading = sample(frame, state.pointer.x, state.pointer.y);
  const { x, y } = reading;  // the pixel actually read (the map holds every step-th pixel)
  el.textContent = `${formatReading(reading)} · px (${x}, ${y}) · frame ${frame.number}`;
  el.dataset.frame = frame.number;
  el.dataset.x = x; el.dataset.y = y;
}

function updatePins() {
  // Rebuilt only when the pins change (a button replaced every frame could not be clicked).
  $("pins").replaceChildren(...state.pins.map((p, i) => {
    const li = document.createElement("li");
    const reading = document.createElement("span");
    reading.className = "pin-reading";
    const remove = document.createElement("button");
    remove.textContent = "×";
    remove.title = "remove this pin";
    remove.onclick = () => { state.pins.splice(i, 1); updatePins(); drawMarks(); };
    li.append(reading, " ", remove);
    return li;
  }));
  updatePinReadings();
}

function updatePinReadings() {
  const frame = state.shown;
  const spans = $("pins").querySelectorAll(".pin-reading");
  state.pins.forEach((p, i) => {
    if (spans[i]) spans[i].textContent = `(${p.x}, ${p.y}) ${frame ? formatReading(sample(frame, p.x, p.y)) : ""}`;
  });
}

function drawProfile() {
  const canvas = $("profile");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const frame = state.shown, line = state.line;
  ctx.fillStyle = "#7f95a5"; ctx.font = "11px sans-serif";
  if (!frame || !line) { ctx.fillText("choose the line tool and drag across the range view", 8, 20); return; }
  const length = Math.hypot(line.x1 - line.x0, line.y1 - line.y0);
  const n = Math.max(2, Math.min(400, Math.round(length / frame.range.step)));
  const values = [];
  for (let i = 0; i < n; i++) {
    const t = i / (n - 1);
    values.push(sample(frame, Math.round(line.x0 + t * (line.x1 - line.x0)), Math.round(line.y0 + t * (line.y1 - line.y0))).range);
  }
  const valid = values.filter((v) => v !== null);
  if (!valid.length) { ctx.fillText("no valid range along the line", 8, 20); return; }
  let lo = Math.min(...valid), hi = Math.max(...valid);
  if (hi - lo < 0.01) { lo -= 0.005; hi += 0.005; }
  const left = 44, bottom = canvas.height - 16, top = 8, right = canvas.width - 6;
  ctx.strokeStyle = "#2e4a5e"; ctx.strokeRect(left, top, right - left, bottom - top);
  ctx.fillText(`${hi.toFixed(2)} m`, 2, top + 8);
  ctx.fillText(`${lo.toFixed(2)} m`, 2, bottom);
  ctx.fillText(`0 … ${Math.round(length)} px along the line`, left, canvas.height - 3);
  ctx.strokeStyle = "#4fc3f7"; ctx.lineWidth = 1.5; ctx.beginPath();
  let pen = false;
  values.forEach((v, i) => {
    if (v === null) { pen = false; return; }
    const x = left + (i / (n - 1)) * (right - left), y = bottom - ((v - lo) / (hi - lo)) * (bottom - top);
    if (pen) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    pen = true;
  });
  ctx.stroke();
}

// Why a pixel has no range, as a pilot would say it.
const PLAIN_REASONS = {
  "below noise floor": "too dark",
  "saturated": "too bright",
  "backscatter only": "only murky water",
  "too few channels": "too dark in some colours",
  "path out of bounds": "out of range",
  "vehicle": "our vehicle",
};
const REASON_HELP = {
  "below noise floor": "too little light came back for a range: closer, or more lamp",
  "saturated": "the camera clipped: less lamp or a shorter exposure",
  "backscatter only": "the light there is the water's own glow (backscatter), not a surface",
  "too few channels": "red is absorbed first: too few colours were bright enough to compare",
  "path out of bounds": "the colour ratio gives a range outside the configured limits",
  "vehicle": "part of the vehicle (bracket, skids) is masked here",
};

function drawLegend() {
  const reasons = state.hello?.reasons || {};
  $("legend").replaceChildren(...Object.entries(reasons).filter(([code]) => code !== "0").map(([code, name]) => {
    const li = document.createElement("li");
    const swatch = document.createElement("i");
    const c = REASON_COLOURS[code] || [128, 128, 128];
    swatch.style.background = `rgb(${c.join(",")})`;
    li.append(swatch, PLAIN_REASONS[name] || name);
    li.title = `${name} (reason ${code}): ${REASON_HELP[name] || ""}`;
    return li;
  }));
}

// ---------------------------------------------------------------- frames

let paintScheduled = false;
let cloud = null;
let cloudUpdatedAt = 0;

// A frame's age in ms, without comparing this computer's clock with the vehicle's: the daemon's
// own capture → encode time, plus the time since the frame arrived here.
function frameAge(frame) {
  return (frame.header.encoded_time_ns - frame.header.capture_time_ns) / 1e6 + (performance.now() - frame.arrivedAt);
}

function onFrame(frame) {
  frame.arrivedAt = performance.now();
  state.frame = frame;
  if (state.paused) return;  // not acknowledged: the daemon stops sending until Resume
  createImageBitmap(frame.colour.blob).then((bitmap) => {
    if (state.frame !== frame || state.paused) { bitmap.close(); return; }  // a newer frame arrived meanwhile
    state.pending?.bitmap.close();
    state.pending = { frame, bitmap };
    if (!paintScheduled) { paintScheduled = true; requestAnimationFrame(paint); }
  }, () => stream.ack(frame.number));
}

function paint() {
  paintScheduled = false;
  const pending = state.pending;
  state.pending = null;
  if (!pending || state.paused) { pending?.bitmap.close(); return; }
  const { frame, bitmap } = pending;
  if (state.shown && frame.number <= state.shown.number) { bitmap.close(); return; }
  state.colourBitmap?.close();
  state.colourBitmap = bitmap;
  state.shown = frame;
  if (state.mode !== "range" && state.mode !== "cloud") drawColour();
  if (state.mode !== "cloud") drawRange(frame);
  else if (performance.now() - cloudUpdatedAt > 400) { cloudUpdatedAt = performance.now(); cloud?.update(frame, state.colourBitmap, state.hello); }
  drawMarks();
  updateReadout();
  updatePinReadings();
  if (state.line) drawProfile();
  const stats = state.stats;
  stats.displayed++;
  stats.lastDisplayed = frame.number;
  // Capture → painted by the wall clock: exact where page and daemon share a machine (benchmarks).
  stats.ages.push(Date.now() - frame.captureMs);
  if (stats.ages.length > 100000) stats.ages.splice(0, 50000);
  if (stats.displayed % 3 === 1) {  // ten times a second is plenty for digits
    const m = centreAndMinimum(frame.range);
    $("centre-range").textContent = m.centre === null ? "—" : `${m.centre.toFixed(2)} m`;
    $("minimum-range").textContent = m.minimum === null ? "—" : `${m.minimum.toFixed(2)} m`;
    state.digitsFrame = frame;
  }
  showAges();
  stream.ack(frame.number);
}

// ---------------------------------------------------------------- staleness

// Every value from a frame says how old it is, and greys out once it is stale: the header's
// digits and frame line keep counting when frames stop coming.
function showAges() {
  const shown = state.shown, digits = state.digitsFrame;
  $("frame-info").textContent = shown ? `frame ${shown.number} · ${ageText(frameAge(shown))} old` : "";
  $("frame-info").classList.toggle("stale", !!shown && frameAge(shown) > STALE_AFTER_MS);
  const digitsStale = !digits || frameAge(digits) > STALE_AFTER_MS;
  for (const id of ["centre-box", "minimum-box"]) $(id).classList.toggle("stale", digitsStale);
  // Readings of the shown frame (pointer, pins) grey out with it, unless the pilot paused on it.
  const readingsStale = !!shown && !state.paused && frameAge(shown) > STALE_AFTER_MS;
  for (const id of ["readout", "pins"]) $(id).classList.toggle("stale", readingsStale);
}

function ageText(ms) {
  return ms < 1000 ? `${Math.round(ms)} ms` : ago(ms / 1000);
}

function checkStale() {
  showAges();
  const age = state.shown ? frameAge(state.shown) : Infinity;
  const camera = state.status?.camera?.health;
  const stale = $("stale");
  let text = "";
  if (state.paused && state.shown) text = `PAUSED — frame ${state.shown.number}`;
  else if (!state.shown) text = "waiting for the first frame…";
  else if (age > STALE_AFTER_MS) text = `STALE — last frame ${(age / 1000).toFixed(1)} s old`;
  if (camera && camera.state !== "ok") text += `${text ? " · " : ""}camera ${camera.state}: ${camera.reason}`;
  stale.hidden = !text;
  stale.textContent = text;
  $("panes").classList.toggle("stale-view", !state.paused && age > STALE_AFTER_MS);
  const statusAge = Date.now() - state.statusAt;
  $("health-box").classList.toggle("stale", statusAge > 3000);
  $("health-age").textContent = statusAge > 3000 ? `no answer for ${(statusAge / 1000).toFixed(0)} s` : "";
}

// ---------------------------------------------------------------- health

function cell(text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  return td;
}

function ago(seconds) {
  if (seconds === null || seconds === undefined) return "";
  return seconds < 60 ? `${seconds.toFixed(seconds < 10 ? 1 : 0)} s` : seconds < 3600 ? `${(seconds / 60).toFixed(0)} min` : `${(seconds / 3600).toFixed(1)} h`;
}

function renderHealth(s) {
  const rows = [];
  const device = (name, health) => {
    const tr = document.createElement("tr");
    if (!health) { tr.append(cell(name), cell("not configured", "muted")); return tr; }
    tr.append(cell(name), cell(health.state, `state-${health.state}`), cell(`${health.reason} · ${ago(health.for_s)}`, "muted"));
    return tr;
  };
  rows.push(device("camera", s.camera?.health));
  rows.push(device("lamp", s.lamp?.health));
  rows.push(device("rangefinder", s.rangefinder?.health));
  $("devices").replaceChildren(...rows);

  const figures = [];
  const add = (term, value, cls, help) => {
    const dt = document.createElement("dt"); dt.textContent = term;
    if (help) { dt.title = help; dt.classList.add("has-help"); }
    const dd = document.createElement("dd"); dd.textContent = value;
    if (cls) dd.className = cls;
    figures.push(dt, dd);
  };
  const f = s.frames;
  add("frame rate", `${f.fps.toFixed(1)} fps`, f.fps === 0 ? "state-lost" : "");
  add("frames", `${f.processed} processed · ${f.dropped} dropped`);
  if (s.latency_ms) add("latency", `p50 ${s.latency_ms.p50} ms · p99 ${s.latency_ms.p99} ms`);
  const cal = s.calibration;
  if (cal) {
    const created = cal.created ? new Date(cal.created) : null;
    add("calibration", `${cal.name}${created ? ` · ${ago((Date.now() - created) / 1000)} old` : ""}`);
    if (cal.tracking) {
      const diffs = Object.entries(cal.tracking.attenuation_differences)
        .map(([k, v]) => `${k} ${v.toFixed(4)} (${cal.tracking.drift[k] >= 0 ? "+" : ""}${cal.tracking.drift[k].toFixed(4)})`).join(", ");
      add("water check", `${cal.tracking.state} · ${diffs} 1/m`, "",
          "The reference patch on the bracket, at a known distance, is watched in every frame: how much faster " +
          "the water absorbs each colour than red (attenuation difference, 1/m) and its drift since calibration. " +
          "Ranging follows the water as it changes.");
      if (cal.tracking.region && !state.patchDraft) state.patchRegion = cal.tracking.region;
    }
    if (cal.reflectance) add("surface colour", cal.reflectance.state, "",
      "The seabed's own colour is measured where the sonar points (its range is known there), so a surface " +
      "redder or bluer than the calibration plate does not bias the range.");
  }
  const rf = s.rangefinder;
  if (rf) {
    const stale = rf.age_s === null || rf.age_s > 2;
    add("rangefinder", rf.range_m === null ? "no reading" :
      `${rf.range_m.toFixed(2)} m · confidence ${rf.confidence === null ? "?" : Math.round(rf.confidence * 100)} % · ${ago(rf.age_s)} old`, stale ? "stale" : "");
  }
  const lamp = s.lamp;
  if (lamp) {
    add("lamp", lamp.on === null ? "unknown" : `${lamp.on ? "on" : "off"} · ${lamp.percent ?? "?"} %`);
    $("lamp-state").textContent = lamp.on === null ? "" : lamp.on ? "on" : "off";
    if (document.activeElement !== $("lamp-intensity") && lamp.percent !== null) {
      $("lamp-intensity").value = lamp.percent;
      $("lamp-intensity-value").textContent = Math.round(lamp.percent);
    }
  }
  const t = s.temporal;
  state.fusedFrames = t && t.enabled ? t.median_frames : null;
  if (t && t.enabled) {
    add("fusion", t.median_frames ? `${t.median_frames} frames per pixel (median, at most ${t.max_frames})` +
      ` · ${(t.changed_fraction * 100).toFixed(1)} % changed in the last frame` : "no range yet", "",
      "Temporal fusion: each pixel's range is made from the frames over which it held still, so its noise " +
      "is √N smaller; a pixel whose light changes more than its noise allows starts afresh from the newest frame.");
  }
  $("range-label").textContent = rangeLabel();
  $("figures").replaceChildren(...figures);
  renderRecording(s.recording);
  renderBackscatter(s.backscatter);
}

function renderBackscatter(b) {
  const el = $("backscatter-state");
  if (!b) { el.textContent = ""; return; }
  const water = b.open_water;
  const from = water ? `open-water frame ${water.source}${water.age_s !== undefined ? ` ${ago(water.age_s)} ago` : ""}`
    : "no open-water frame: the calibration's black-patch measurements alone";
  // Where the calibration measured the water's light it is always subtracted (a range with it left
  // in reads short): the box shows it ticked and cannot be unticked, and says why.
  const box = $("backscatter-on");
  const always = b.enabled && !b.configured;
  box.checked = b.enabled;
  box.disabled = always;
  box.title = always ? "always on: this calibration measured the water's own light, and a range with it left in reads short" : "";
  const parts = [b.enabled ? `on${always ? " (always, with this calibration)" : ""} · ${b.iterations} iterations${b.ms_per_frame !== null ? ` · ${b.ms_per_frame} ms per frame` : ""}` : "off", from];
  if (b.capture && b.capture !== "done") parts.push(b.capture);
  el.textContent = parts.join(" · ");
}

// How long the disk lasts at the recording budget (or the measured rate).
function diskOutlook(r) {
  if (r.hours_left === null || r.hours_left === undefined) return "";
  return ` · disk holds ${r.hours_left < 1 ? `${Math.round(r.hours_left * 60)} min` : `${r.hours_left.toFixed(1)} h`}` +
    (r.budget_mb_s ? ` at ${r.budget_mb_s} MB/s` : "");
}

function renderRecording(r) {
  const el = $("record-state");
  if (!r) { el.textContent = "no recorder"; return; }
  if (r.state === "recording") {
    const mb = (r.bytes / 1e6).toFixed(1);
    const kept = r.raw_kept_ratio === null || r.raw_kept_ratio === undefined ? "" : ` · raw frames kept ${Math.round(r.raw_kept_ratio * 100)} %`;
    el.textContent = `recording ${r.file ?? ""} · ${ago(r.duration_s)} · ${mb} MB · ${r.frames_written} frames${kept}` +
      (r.frames_dropped ? ` · ${r.frames_dropped} dropped` : "") + (r.frames_lost ? ` · ${r.frames_lost} lost` : "") +
      diskOutlook(r);
    el.className = r.frames_lost ? "state-lost" : "state-recovering";
  } else {
    el.textContent = (r.last_stop_reason ? `idle — last recording: ${r.last_stop_reason}` : "idle") + diskOutlook(r);
    el.className = "muted";
  }
  el.title = r.budget_mb_s ? `recording.budget_mb_s = ${r.budget_mb_s} MB/s: raw frames beyond it are left out ` +
    "(every frame's summary and the preview are always kept)" : "";
}

async function pollStatusNow() {
  try {
    state.status = await api("api/v1/status");
    state.statusAt = Date.now();
    renderHealth(state.status);
  } catch (error) {
    // the age shown in the health box says how long the daemon has not answered
  }
}

async function pollStatus() {
  await pollStatusNow();
  setTimeout(pollStatus, 1000);
}

// ---------------------------------------------------------------- controls

async function loadConfig() {
  try {
    state.config = await api("api/v1/config");
  } catch (error) { message(error.message); return; }
  const c = state.config;
  const channels = state.hello?.channels || [];
  const pair = $("pair");
  const options = [["fuse", "all channels fused"]];
  for (let i = 0; i < channels.length; i++) {
    for (let j = i + 1; j < channels.length; j++) options.push([`${channels[i]},${channels[j]}`, `${channels[i]}/${channels[j]} pair`]);
  }
  pair.replaceChildren(...options.map(([value, label]) => new Option(label, value)));
  pair.value = c.pair ? c.pair.join(",") : "fuse";
  $("smoothing").value = c.smoothing;
  $("smoothing-stage").value = c.smoothing_stage;
  $("lamp-off-interval").value = c.lamp_off_interval;
  // Disabled: always on with this calibration (renderBackscatter), whatever the settings say.
  $("backscatter-on").checked = (c.backscatter !== null && c.backscatter !== undefined) || $("backscatter-on").disabled;
  if (c.patch?.path_length_m) $("patch-path").value = c.patch.path_length_m;
  $("temporal-on").checked = c.temporal !== null && c.temporal !== undefined;
}

async function patchConfig(what, body) {
  const result = await change(what, "api/v1/config", { method: "PATCH", body });
  await loadConfig();
  return result;
}

async function loadProfiles() {
  let profiles;
  try { profiles = await api("api/v1/calibration/profiles"); } catch (error) { message(error.message); return; }
  $("profiles").replaceChildren(...profiles.map((p) => {
    const li = document.createElement("li");
    li.textContent = `${p.name} (${p.channels.join(", ")}) `;
    if (p.active) {
      const b = document.createElement("b"); b.textContent = "active"; li.append(b);
    } else {
      const button = document.createElement("button");
      button.textContent = "activate";
      button.className = "control";
      button.onclick = async () => {
        await change(`Activate ${p.name}`, `api/v1/calibration/profiles/${encodeURIComponent(p.name)}/activate`, { method: "POST" });
        loadProfiles();
      };
      li.append(button);
    }
    return li;
  }));
  renderAuth();
}

function wireControls() {
  $("record-start").onclick = async () => {
    const r = await change("Start recording", "api/v1/recordings/start", { method: "POST" });
    if (r) pollStatusNow();
  };
  $("record-stop").onclick = async () => {
    const r = await change("Stop recording", "api/v1/recordings/stop", { method: "POST" });
    if (r) pollStatusNow();
  };
  $("lamp-on").onclick = () => change("Lamp on", "api/v1/lamp", { method: "PUT", body: { on: true } });
  $("lamp-off").onclick = () => change("Lamp off", "api/v1/lamp", { method: "PUT", body: { on: false } });
  $("lamp-intensity").oninput = () => { $("lamp-intensity-value").textContent = $("lamp-intensity").value; };
  $("lamp-intensity").onchange = () => sendIntensity(Number($("lamp-intensity").value));
  $("pair").onchange = () => {
    const v = $("pair").value;
    patchConfig("Channels", v === "fuse" ? { fuse: true } : { pair: v.split(",") });
  };
  $("smoothing").onchange = () => patchConfig("Smoothing", { smoothing: $("smoothing").value });
  $("smoothing-stage").onchange = () => patchConfig("Smoothing stage", { smoothing_stage: $("smoothing-stage").value });
  $("lamp-off-interval").onchange = () => {
    const n = Number($("lamp-off-interval").value);
    if (!Number.isInteger(n) || n < 0) { message("the lamp-off interval is a whole number of frames, 0 or more"); return; }
    patchConfig("Lamp-off interval", { lamp_off_interval: n });
  };
  $("temporal-on").onchange = () => patchConfig("Temporal fusion", { temporal: $("temporal-on").checked ? {} : null });
  $("backscatter-on").onchange = () => patchConfig("Backscatter", { backscatter: $("backscatter-on").checked ? { iterations: 2 } : null });
  $("open-water").onclick = async () => {
    if (await change("Take open-water frame", "api/v1/backscatter/open-water", { method: "POST", body: { frames: 4 } })) pollStatusNow();
  };
  $("open-water-forget").onclick = async () => {
    if (await change("Forget open-water frame", "api/v1/backscatter/open-water", { method: "DELETE" })) pollStatusNow();
  };
  $("profile-upload").onclick = async () => {
    const file = $("profile-file").files[0];
    const name = $("profile-name").value.trim() || file?.name.replace(/\.(ya?ml|json)$/, "");
    if (!file || !name) { message("choose a profile file (YAML or JSON) and a name"); return; }
    const type = file.name.endsWith(".json") ? "application/json" : "application/x-yaml";
    await change(`Upload ${name}`, `api/v1/calibration/profiles/${encodeURIComponent(name)}`, { method: "PUT", body: await file.text(), type });
    loadProfiles();
  };
  $("patch-apply").onclick = async () => {
    const region = state.patchDraft;
    const path = Number($("patch-path").value);
    if (!region || !(path > 0)) { message("drag a patch region and give its path length in metres"); return; }
    const result = await patchConfig("Patch region", { patch: { region, path_length_m: path } });
    if (result) { state.patchRegion = region; state.patchDraft = null; $("patch-form").hidden = true; drawMarks(); }
  };
  $("patch-cancel").onclick = () => { state.patchDraft = null; $("patch-form").hidden = true; drawMarks(); };
}

// ---------------------------------------------------------------- view settings and pointer tools

function wireView() {
  const mapSelect = $("colour-map");
  mapSelect.replaceChildren(...COLOUR_MAPS.map((name) => new Option(name, name)));
  mapSelect.onchange = () => { state.table = lut(mapSelect.value); repaint(); };
  $("mode").onchange = () => {
    state.mode = $("mode").value;
    $("panes").className = `mode-${state.mode}`;
    $("cloud-pane").hidden = state.mode !== "cloud";
    $("opacity-box").hidden = state.mode !== "overlay";
    if (state.mode === "cloud" && !cloud) cloud = new PointCloudView($("cloud"));
    $("range").style.opacity = state.mode === "overlay" ? $("opacity").value : "";
    $("colour-pane").querySelector(".pane-label").hidden = state.mode === "overlay";
    stream.setWidth();
    repaint();
  };
  $("opacity-box").hidden = true;
  // Only the range picture fades: pins, line and the stale notice stay legible.
  $("opacity").oninput = () => { if (state.mode === "overlay") $("range").style.opacity = $("opacity").value; };
  $("show-sigma").onchange = () => { state.showSigma = $("show-sigma").checked; repaint(); };
  $("limits").onchange = () => {
    state.limits.auto = $("limits").value === "auto";
    $("fixed-limits").hidden = state.limits.auto;
    repaint();
  };
  const setFixed = () => {
    const lo = Number($("limit-min").value), hi = Number($("limit-max").value);
    if (!(Number.isFinite(lo) && Number.isFinite(hi) && hi > lo && lo >= 0)) { message("fixed limits need 0 ≤ lowest < highest"); return; }
    state.limits.min = lo; state.limits.max = hi; repaint();
  };
  $("limit-min").onchange = setFixed;
  $("limit-max").onchange = setFixed;
  $("tool").onchange = () => { state.tool = $("tool").value; };
  $("pause").onclick = () => {
    state.paused = !state.paused;
    $("pause").textContent = state.paused ? "Resume" : "Pause";
    if (!state.paused && state.frame) stream.ack(state.frame.number);  // frames flow again
    checkStale();
  };
  $("clear-pins").onclick = () => { state.pins = []; updatePins(); drawMarks(); };

  const pane = $("range-pane");
  const toImage = (event) => {
    const canvas = $("range");
    const rect = canvas.getBoundingClientRect();
    const frame = state.shown;
    if (!frame) return null;
    const w = frame.header.image_width, h = frame.header.image_height;
    const x = Math.floor(((event.clientX - rect.left) / rect.width) * w);
    const y = Math.floor(((event.clientY - rect.top) / rect.height) * h);
    return { x: Math.min(w - 1, Math.max(0, x)), y: Math.min(h - 1, Math.max(0, y)) };
  };
  pane.addEventListener("pointermove", (event) => {
    const p = toImage(event);
    if (!p) return;
    state.pointer = p;
    updateReadout();
    if (state.drag) {
      const d = state.drag;
      if (state.tool === "line") state.line = { x0: d.x, y0: d.y, x1: p.x, y1: p.y };
      if (state.tool === "patch") {
        state.patchDraft = [Math.min(d.x, p.x), Math.min(d.y, p.y), Math.max(1, Math.abs(p.x - d.x)), Math.max(1, Math.abs(p.y - d.y))];
      }
      drawMarks();
      if (state.tool === "line") drawProfile();
    }
  });
  pane.addEventListener("pointerdown", (event) => {
    const p = toImage(event);
    if (!p) return;
    state.pointer = p;  // a tap on a touch screen reads out like a hover
    updateReadout();
    if (state.tool === "inspect") {
      if (state.pins.length >= MAX_PINS) state.pins.shift();
      state.pins.push(p);
      updatePins(); drawMarks();
      return;
    }
    state.drag = p;
    pane.setPointerCapture(event.pointerId);
  });
  pane.addEventListener("pointerup", () => {
    if (state.drag && state.tool === "patch" && state.patchDraft) {
      $("patch-form").hidden = false;
      $("patch-region").textContent = `x ${state.patchDraft[0]}, y ${state.patchDraft[1]}, ${state.patchDraft[2]} × ${state.patchDraft[3]} px`;
    }
    state.drag = null;
  });
  pane.addEventListener("pointerleave", () => {
    if (state.drag) return;
    state.pointer = null;
    $("readout").classList.add("left");
  });
  pane.addEventListener("pointerenter", () => $("readout").classList.remove("left"));
}

function repaint() {
  if (!state.shown) return;
  if (state.mode !== "cloud") { drawColour(); drawRange(state.shown); }
  else cloud?.update(state.shown, state.colourBitmap, state.hello);
  drawMarks();
}

// ---------------------------------------------------------------- start

// The pixels the range map is drawn across (the 3-D view: its pane): the daemon sends each frame
// at the coarsest resolution that still fills them (?step=1 in the address forces full resolution).
function drawnWidth() {
  const element = state.mode === "cloud" ? $("cloud") : $("range");
  return element.getBoundingClientRect().width * (window.devicePixelRatio || 1);
}

const stream = new ViewStream({
  step: Number(new URLSearchParams(location.search).get("step")) || null,
  width: drawnWidth,
  onHello: (hello) => {
    state.hello = hello;
    drawLegend();
    loadConfig();
  },
  onFrame,
  onState: (s) => {
    const badge = $("connection");
    badge.textContent = s === "connected" ? "live" : "reconnecting…";
    badge.className = `badge ${s === "connected" ? "live" : "down"}`;
    if (s === "connected") state.stats.connectedAt = Date.now();
  },
});

wireView();
wireControls();
startTank({ api, change, message, onProfilesChanged: loadProfiles, liveImage: () => state.colourBitmap });
drawProfile();
loadSession();
loadProfiles();
pollStatus();
setInterval(checkStale, 250);
// --- alert banner (issue 28): begin ---
startAlertBanner($("alert-banner"));
// --- alert banner: end ---

window.addEventListener("resize", () => stream.setWidth());
