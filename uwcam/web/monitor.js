// The fleet page of `uwcam monitor`: polls api/fleet and lists every vehicle heard. Rows of
// vehicles unheard for longer than the monitor's --stale-s are greyed (class "stale"), never
// dropped: the last figures stay, with their age, so a lost vehicle's last state is still read.

const POLL_MS = 1000;
const $ = (id) => document.getElementById(id);

function metres(value) {
  return value == null ? "—" : `${value.toFixed(2)} m`;
}

function seconds(value) {
  return value == null ? "—" : value < 60 ? `${value.toFixed(1)} s` : `${Math.round(value / 60)} min`;
}

function cell(row, cls, content) {
  const td = document.createElement("td");
  td.className = cls;
  if (content instanceof Node) td.append(content); else td.textContent = content;
  row.append(td);
  return td;
}

function render(vehicle, previous) {
  const row = document.createElement("tr");
  row.dataset.name = vehicle.name;
  row.className = vehicle.stale ? "stale" : "live";
  let name = document.createTextNode(vehicle.name);
  if (vehicle.page_url) {
    name = document.createElement("a");
    name.href = vehicle.page_url;
    name.target = "_blank";
    name.rel = "noopener";
    name.textContent = vehicle.name;
  }
  cell(row, "name", name);
  cell(row, "num last-seen", `${seconds(vehicle.last_seen_s)} ago`);
  cell(row, "num fps", vehicle.fps == null ? "—" : vehicle.fps.toFixed(1));
  cell(row, "calibration", vehicle.calibration_age_days == null ? (vehicle.calibration || "—")
    : `${vehicle.calibration} (${vehicle.calibration_age_days.toFixed(0)} d)`);
  const devices = document.createElement("span");
  for (const [device, state] of Object.entries(vehicle.devices)) {
    const d = document.createElement("span");
    d.className = `dev-${state}`;
    d.dataset.device = device;
    d.textContent = `${device} ${state} `;
    devices.append(d);
  }
  cell(row, "devices", devices);
  cell(row, "num centre", metres(vehicle.centre_m));
  cell(row, "num minimum", metres(vehicle.minimum_m));
  cell(row, "num range-age", seconds(vehicle.range_age_s));
  const alerts = document.createElement("span");
  for (const alert of vehicle.alerts) {
    const a = document.createElement("span");
    a.className = `alert alert-${alert.severity}`;
    a.dataset.key = alert.key;
    a.textContent = `${alert.severity}: ${alert.message}`;
    alerts.append(a);
  }
  cell(row, "alerts", alerts);
  // The preview is fetched again only when a new one has been heard.
  const img = previous?.querySelector("img") || document.createElement("img");
  const src = `api/fleet/preview.jpg?prefix=${encodeURIComponent(vehicle.prefix)}&n=${vehicle.previews}`;
  if (vehicle.previews > 0 && img.getAttribute("src") !== src) img.setAttribute("src", src);
  img.alt = `preview of ${vehicle.name}`;
  cell(row, "preview", vehicle.previews > 0 ? img : "—");
  return row;
}

async function poll() {
  try {
    const response = await fetch("api/fleet");
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    const fleet = await response.json();
    const body = $("fleet").querySelector("tbody");
    const old = new Map([...body.rows].map((r) => [r.dataset.name, r]));
    body.replaceChildren(...fleet.vehicles.map((v) => render(v, old.get(v.name))));
    $("fleet").hidden = fleet.vehicles.length === 0;
    $("empty").hidden = fleet.vehicles.length > 0;
    $("connection").textContent = `${fleet.vehicles.filter((v) => !v.stale).length} of ${fleet.vehicles.length} live`;
  } catch (error) {
    // Nothing confirmed any more: every row is shown stale rather than as it last was.
    $("connection").textContent = "the monitor does not answer";
    for (const row of $("fleet").querySelector("tbody").rows) row.className = "stale";
  }
  setTimeout(poll, POLL_MS);
}

poll();
