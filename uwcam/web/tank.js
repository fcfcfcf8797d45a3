// uwcam operator page: the tank calibration, step by step. Talks only to the daemon's public API
// (api/v1/calibration/session, and api/v1/simulation/plate in the simulated tank), by relative URL.
//
// The page never judges a capture itself: the session's live feedback says whether a capture now
// would be accepted (live.capture_ok) and why not (live.refusals), from the same checks the
// capture applies, so the Capture button and the API's answer never disagree. The session lives
// in the daemon (and on its disk), so a reload or a daemon restart finds it again.

const TANK = "api/v1/calibration/session";
const RAIL = "api/v1/simulation/plate";
const POLL_MS = 700;
const FIT_DISTANCES = [1.0, 1.5, 2.0];  // suggestions only: any three spread over the working range do
const HELD_BACK_DISTANCE = 1.75;

const $ = (id) => document.getElementById(id);
const el = (tag, text, cls) => {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
};
const metres = (v, digits = 3) => (typeof v === "number" ? `${v.toFixed(digits)} m` : "—");

const tank = {
  session: null,    // the session's summary, null when none
  live: null,       // newest live feedback
  liveFor: null,    // the distance and held-back flag the feedback was asked for
  fit: null,        // the fit shown
  fitKey: null,
  busy: false,      // a capture, fit or accept in flight
  rail: null,       // the simulated tank's rail, null on a real rig
};
window.uwcamTank = tank;  // read by tests and benchmarks

let io = null;  // {api, change, message, onProfilesChanged, liveImage}

// ---------------------------------------------------------------- what the engineer reads

function typed() {
  const value = Number($("tank-distance").value);
  return { distance: $("tank-distance").value.trim() !== "" && Number.isFinite(value) ? value : null,
           heldBack: $("tank-held-back").checked };
}

function progress() {
  const caps = tank.session?.captures || [];
  const fitted = [...new Set(caps.filter((c) => !c.held_back).map((c) => c.distance_m))].sort((a, b) => a - b);
  const held = caps.filter((c) => c.held_back).map((c) => c.distance_m);
  return { fitted, held };
}

function nextStep() {
  const { fitted, held } = progress();
  const fit = tank.session?.fit || {};
  if (fitted.length < 3) {
    const next = FIT_DISTANCES.find((d) => !fitted.some((f) => Math.abs(f - d) < 0.05));
    return { n: 1, text: `Capture the plate at three distances (${fitted.length} of 3 so far). Put the plate square to the ` +
      `camera${next ? ` at about ${next} m` : ""}, measure the camera-to-plate distance along the camera's axis, type ` +
      "it below and press Capture once every check is green." };
  }
  if (!held.length) {
    return { n: 2, text: `Capture one more distance between the others (e.g. ${HELD_BACK_DISTANCE} m) with "hold back ` +
      "to check\" ticked: it is kept out of the fit and used to check the new calibration." };
  }
  if (!fit.validation) return { n: 3, text: "Press Fit: it computes the calibration from your captures and checks it on the held-back one." };
  const failed = fit.validation.filter((v) => !v.passed);
  if (failed.length) return { n: 3, text: "The check on the held-back distance failed (see below): measure the distances again, capture again and fit." };
  return { n: 4, text: "The calibration passed its check. Name it and press Accept to use it from now on, or Discard to throw the session away." };
}

function check(ok, text, detail) {
  const li = el("li", undefined, ok === null ? "wait" : ok ? "ok" : "bad");
  li.append(el("span", ok === null ? "…" : ok ? "✓" : "✗", "mark"), el("span", text));
  if (detail) li.append(el("small", detail));
  return li;
}

function renderChecks(live) {
  const list = [];
  const ids = live.markers_found || [];
  const ignored = live.markers_ignored?.length ? `; left out (not the plate's): ${live.markers_ignored.join(", ")}` : "";
  list.push(check(live.plate_found, live.plate_found ? `Plate found: ${ids.length} markers` : `Plate not found: ${ids.length} of its markers in view (3 needed)`,
    `marker ids ${ids.length ? ids.join(", ") : "none"}${ignored}`));
  if (live.plate_found) {
    list.push(check(live.target_in_view, live.target_in_view ? "Whole target region in view" : "The target region runs off the image"));
    list.push(check(live.tilt_deg <= 10, `Plate ${live.tilt_deg <= 3 ? "square to the camera" : `tilted ${live.tilt_deg.toFixed(1)}°`}`,
      "within 10° is fine; square is best"));
    const tol = live.tolerance_m;
    if (live.typed_distance_m === null || live.typed_distance_m === undefined) {
      list.push(check(false, `Type the distance: the markers put the plate at ${metres(live.marker_distance_m)}`));
    } else {
      const diff = live.typed_difference_m;
      list.push(check(live.typed_agrees, `Distance typed ${metres(live.typed_distance_m, 2)}, markers ${metres(live.marker_distance_m)}`,
        `differ by ${(Math.abs(diff) * 100).toFixed(1)} cm; up to ${(tol * 100).toFixed(1)} cm allowed`));
    }
    if (live.rangefinder_m !== null && live.rangefinder_m !== undefined) {
      list.push(check(live.rangefinder_agrees ?? null, `Rangefinder reads ${metres(live.rangefinder_m)}`,
        live.rangefinder_difference_m === undefined ? "" : `differs from the markers by ${(Math.abs(live.rangefinder_difference_m) * 100).toFixed(1)} cm`));
    }
    const sat = live.saturated_fraction;
    list.push(check(sat <= live.saturation_limit, `Saturated: ${(sat * 100).toFixed(2)} % of the plate`, `at most ${live.saturation_limit * 100} % allowed`));
  }
  $("tank-checks").replaceChildren(...list);
}

function renderBars(live) {
  const box = $("tank-bars");
  if (!live.channels) { box.replaceChildren(); return; }
  box.replaceChildren(el("div", "Signal on the plate per channel (the green band is acceptable: above the noise floor, below saturation)", "muted"),
    ...Object.entries(live.channels).map(([name, c]) => {
      const full = Math.max(c.full_scale_dn, 1);
      const row = el("div", undefined, "tank-bar");
      const track = el("div", undefined, "track");
      const band = el("div", undefined, "band");
      band.style.left = `${Math.min(100, (c.floor_dn / full) * 100)}%`;
      band.style.right = "0%";
      const fill = el("div", undefined, c.above_floor && c.saturated_fraction <= live.saturation_limit ? "fill ok" : "fill bad");
      fill.style.width = `${Math.min(100, Math.max(0, (c.signal_dn / full) * 100))}%`;
      track.append(band, fill);
      row.title = `${name}: signal ${c.signal_dn.toFixed(0)} DN, noise floor ${c.floor_dn.toFixed(0)} DN, full scale ${full.toFixed(0)} DN`;
      row.append(el("span", name, "name"), track,
        el("span", `${c.signal_dn.toFixed(0)} DN${c.saturated_fraction > 0 ? ` · ${(c.saturated_fraction * 100).toFixed(1)} % sat.` : ""}`, "value"));
      row.dataset.channel = name;
      return row;
    }));
}

function drawView(live) {
  const canvas = $("tank-view");
  const ctx = canvas.getContext("2d");
  const [w, h] = live?.image_size || [canvas.width, canvas.height];
  const bitmap = io.liveImage?.();
  const scale = canvas.width / w;
  canvas.height = Math.round(h * scale);
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  try { if (bitmap) ctx.drawImage(bitmap, 0, 0, canvas.width, canvas.height); } catch { /* closed by a newer frame */ }
  if (!live?.plate_found) {
    ctx.fillStyle = "#ef5350";
    ctx.font = "14px system-ui";
    ctx.fillText("no plate found", 8, 20);
    return;
  }
  const outline = (points, colour, dash) => {
    ctx.beginPath();
    points.forEach(([x, y], i) => (i ? ctx.lineTo(x * scale, y * scale) : ctx.moveTo(x * scale, y * scale)));
    ctx.closePath();
    ctx.setLineDash(dash);
    ctx.lineWidth = 2;
    ctx.strokeStyle = colour;
    ctx.stroke();
  };
  outline(live.plate_outline_px, "#4fc3f7", []);
  outline(live.target_outline_px, live.capture_ok ? "#3ecf8e" : "#f0b429", [6, 4]);
  ctx.setLineDash([]);
}

function renderCaptures() {
  const caps = tank.session?.captures || [];
  const table = $("tank-captures");
  if (!caps.length) { table.replaceChildren(); return; }
  const head = el("tr");
  ["distance", "markers say", "frames", "use"].forEach((t) => head.append(el("th", t)));
  table.replaceChildren(head, ...caps.map((c) => {
    const tr = el("tr");
    tr.append(el("td", `${c.distance_m} m`), el("td", metres(c.marker_distance_m)), el("td", String(c.frames)),
      el("td", c.held_back ? "held back (check)" : "fit"));
    return tr;
  }));
}

function renderFit(result) {
  const box = $("tank-fit-result");
  if (!result || !result.channels) { box.replaceChildren(); return; }
  const parts = [el("h3", "Fit")];
  const warnings = result.warnings || [];
  if (warnings.length) {
    const w = el("div", undefined, "tank-warnings");
    w.append(el("b", "This fit may be poor:"), ...warnings.map((t) => el("p", t)));
    parts.push(w);
  } else {
    parts.push(el("p", `Good fit: ${result.distances_m.length} distances spanning ` +
      `${(Math.max(...result.distances_m) - Math.min(...result.distances_m)).toFixed(2)} m, residuals small.`, "ok-text"));
  }
  const att = el("table");
  const head = el("tr");
  ["channel", "attenuation difference (1/m)", "± σ"].forEach((t) => head.append(el("th", t)));
  att.append(head);
  for (const [name, c] of Object.entries(result.channels)) {
    const tr = el("tr");
    tr.append(el("td", name), el("td", c.attenuation_difference.toFixed(4)), el("td", c.attenuation_difference_std.toFixed(4)));
    att.append(tr);
  }
  parts.push(att);
  const res = el("table");
  const names = Object.keys(result.residuals || {});
  const rh = el("tr");
  rh.append(el("th", "residual at"));
  names.forEach((n) => rh.append(el("th", n)));
  res.append(rh);
  (result.distances_m || []).forEach((d, i) => {
    const tr = el("tr");
    tr.append(el("td", `${d} m`));
    names.forEach((n) => tr.append(el("td", `${(result.residuals[n][i] * 100).toFixed(2)} %`)));
    res.append(tr);
  });
  parts.push(res);
  for (const v of result.validation || []) {
    const ok = v.passed;
    const text = v.median_range_error_m === undefined
      ? `Held back at ${v.distance_m} m: FAILED — ${v.reason}`
      : `Held back at ${v.distance_m} m: the new calibration ranges the plate ${(v.median_range_error_m * 100).toFixed(1)} cm ` +
        `(${(v.relative_error * 100).toFixed(2)} %) off; ${(v.allowed_m * 100).toFixed(1)} cm allowed — ${ok ? "passed" : "FAILED"}`;
    parts.push(el("p", text, ok ? "ok-text validation" : "bad-text validation"));
  }
  if (!(result.validation || []).length) parts.push(el("p", "No held-back distance yet: capture one (tick \"hold back\") and fit again before accepting.", "bad-text"));
  const link = el("a", "Download the report (HTML)");
  link.href = `${TANK}/report.html`;
  link.download = "";
  link.id = "tank-report";
  parts.push(el("p"));
  parts.at(-1).append(link);
  const plots = el("div", undefined, "tank-plots");
  for (const src of result.plots || []) {
    const img = el("img");
    img.src = `${TANK}/${src}?t=${Date.now()}`;
    img.alt = src.replace(/^plots\/|\.png$/g, "");
    img.loading = "lazy";
    plots.append(img);
  }
  parts.push(plots);
  box.replaceChildren(...parts);
}

function render() {
  const running = ["positioning", "fitted"].includes(tank.session?.state);
  $("tank-intro").hidden = running;
  $("tank-steps").hidden = !running;
  $("tank-rail").hidden = !tank.rail;
  if (tank.rail) {
    const moving = tank.rail.moving_to_m;
    $("tank-rail-state").textContent = moving !== null ? `moving the plate to ${moving} m…` : `plate at ${tank.rail.distance_m} m`;
    $("tank-rail-move").disabled = moving !== null;
  }
  if (!running) return;
  const step = nextStep();
  $("tank-now").textContent = `Step ${step.n} of 4 — ${step.text}`;
  [...$("tank-progress").children].forEach((li, i) => { li.className = i + 1 < step.n ? "done" : i + 1 === step.n ? "now" : ""; });
  const live = tank.live;
  const want = typed();
  const current = live && tank.liveFor && tank.liveFor.distance === want.distance && tank.liveFor.heldBack === want.heldBack;
  if (live) { renderChecks(live); renderBars(live); drawView(live); }
  const ok = Boolean(current && live.capture_ok && !tank.busy && (tank.rail?.moving_to_m ?? null) === null);
  $("tank-capture").disabled = !ok;
  $("tank-why-not").textContent = ok || tank.busy ? "" : !current ? "checking…" : (live.refusals || []).join(" · ");
  renderCaptures();
  const { fitted } = progress();
  $("tank-fit").disabled = tank.busy || fitted.length < 2;
  $("tank-fit").title = fitted.length < 2 ? "capture at two or more distances first (three are better)" : "";
  const passed = tank.session.state === "fitted" && (tank.session.fit?.validation || []).length &&
    tank.session.fit.validation.every((v) => v.passed);
  $("tank-accept").disabled = tank.busy || !passed;
  // Redrawn only when the fit changes (each poll brings a fresh copy; the plots would reload).
  const fitKey = tank.session.state === "fitted" ? `${tank.session.id} ${JSON.stringify(tank.session.fit)}` : null;
  if (fitKey !== tank.fitKey) { tank.fitKey = fitKey; tank.fit = fitKey ? tank.session.fit : null; renderFit(tank.fit); }
}

// ---------------------------------------------------------------- talking to the daemon

let sent = 0, applied = 0, polls = 0;
async function poll() {
  // Polls overlap (typing polls at once): an answer older than one already shown is dropped.
  const seq = ++sent;
  // The rail changes only when moved: asked while a move goes on, else every few polls (another client).
  if (tank.rail && (tank.rail.moving_to_m !== null || ++polls % 5 === 0)) {
    try { tank.rail = await io.api(RAIL); } catch { /* the daemon away for a moment */ }
  }
  if (!tank.session) {
    // No session known: the status says whether one is open (asking the session itself would be a 404).
    try {
      const status = await io.api("api/v1/status");
      if (seq < applied) return;
      if (!status.calibration_session) { applied = seq; tank.live = null; render(); return; }
    } catch { return; }  // the daemon away for a moment
  }
  const want = typed();
  const query = new URLSearchParams({ held_back: want.heldBack });
  if (want.distance !== null && want.distance >= 0.05 && want.distance <= 100) query.set("distance", want.distance);
  try {
    const answer = await io.api(`${TANK}?${query}`);
    if (seq < applied) return;
    applied = seq;
    tank.session = answer.session;
    tank.live = answer.live;
    tank.liveFor = want;
  } catch (error) {
    // 404: no session (none started, or accepted or cancelled elsewhere); otherwise the daemon is away
    // for a moment (a restart): keep what is shown, try again.
    if (seq < applied) return;
    if (/ 404 /.test(error.message)) { tank.session = null; tank.live = null; }
  }
  render();
}

async function pollLoop() {
  await poll();
  setTimeout(pollLoop, POLL_MS);
}

async function loadRail() {
  try {
    tank.rail = (await io.api("api/v1/simulation")).tank ? await io.api(RAIL) : null;
  } catch { tank.rail = null; }
  if (tank.rail) $("tank-rail-distance").value = tank.rail.distance_m;
  render();
}

async function act(what, path, options) {
  tank.busy = true;
  render();
  try {
    return await io.change(what, path, options);
  } finally {
    tank.busy = false;
    await poll();
  }
}

function wire() {
  $("tank-start").onclick = async () => {
    await act("Start tank calibration", TANK, { method: "POST", body: { rig: $("tank-rig").value } });
  };
  $("tank-capture").onclick = async () => {
    const { distance, heldBack } = typed();
    const done = await act(`Capture at ${distance} m${heldBack ? " (held back)" : ""}`, `${TANK}/captures`,
      { method: "POST", body: { distance_m: distance, held_back: heldBack } });
    if (done && heldBack) $("tank-held-back").checked = false;
  };
  $("tank-fit").onclick = () => act("Fit", `${TANK}/fit`, { method: "POST" });
  $("tank-accept").onclick = async () => {
    const name = $("tank-name").value.trim();
    if (!/^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$/.test(name)) { io.message("name the new calibration with letters, digits, '.', '_' or '-' (up to 64), starting with a letter or digit"); return; }
    const done = await act(`Accept ${name}`, `${TANK}/accept`, { method: "POST", body: { name } });
    if (done) { io.message(`Calibration ${name} is active: the camera ranges with it from now on.`, true); io.onProfilesChanged?.(); }
  };
  let armed = null;
  $("tank-cancel").onclick = async () => {
    // Two presses: the captures are thrown away for good.
    if (!armed) {
      $("tank-cancel").textContent = "Press again to discard";
      armed = setTimeout(() => { armed = null; $("tank-cancel").textContent = "Discard session"; }, 4000);
      return;
    }
    clearTimeout(armed);
    armed = null;
    $("tank-cancel").textContent = "Discard session";
    await act("Discard tank calibration", TANK, { method: "DELETE" });
  };
  $("tank-rail-move").onclick = async () => {
    const d = Number($("tank-rail-distance").value);
    const [lo, hi] = tank.rail?.rail_m || [0, 0];
    if (!(Number.isFinite(d) && d >= lo && d <= hi)) { io.message(`the rail puts the plate ${lo} to ${hi} m from the camera`); return; }
    // The daemon answers at once and renders the moved plate meanwhile; the poll follows the move.
    const answer = await io.change(`Move the plate to ${d} m`, RAIL, { method: "PUT", body: { distance_m: d } });
    if (answer) tank.rail = answer;
    render();
  };
  for (const id of ["tank-distance", "tank-held-back"]) $(id).addEventListener("input", () => { render(); poll(); });
  const today = new Date().toISOString().slice(0, 10);
  if (!$("tank-name").value) $("tank-name").value = `tank-${today}`;
}

/** Start the tank calibration panel. ``api(path, options)`` returns the answer or throws with the
 * daemon's reason; ``change(what, path, options)`` does the same and reports it in the page's
 * message line (null on failure); ``liveImage()`` returns the newest colour image (an ImageBitmap
 * or canvas) to draw the plate's outline on, or null. */
export function startTank({ api, change, message, onProfilesChanged, liveImage }) {
  io = { api, change, message, onProfilesChanged, liveImage };
  wire();
  loadRail();
  pollLoop();
}
