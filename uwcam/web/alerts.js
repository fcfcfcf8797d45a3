// The alert banner: the alerts the daemon holds raised (GET api/v1/alerts), above the page, most
// severe first, each with its message and since when. Self-contained: app.js only starts it.
// A banner the daemon has not confirmed lately says so, rather than going blank.

const POLL_MS = 2000;
const SEVERITY_ORDER = ["emergency", "alert", "critical", "error", "warning", "notice", "info", "debug"];

function clock(unixSeconds) {
  return new Date(unixSeconds * 1000).toLocaleTimeString([], { hour12: false });
}

export function renderAlerts(banner, active, stale) {
  const sorted = [...active].sort((a, b) => SEVERITY_ORDER.indexOf(a.severity) - SEVERITY_ORDER.indexOf(b.severity));
  banner.replaceChildren(...sorted.map((alert) => {
    const item = document.createElement("div");
    item.className = `alert alert-${alert.severity}`;
    item.dataset.key = alert.key;
    item.textContent = `${alert.severity}: ${alert.message} (since ${clock(alert.since)})`;
    return item;
  }));
  if (stale && sorted.length) {
    const note = document.createElement("div");
    note.className = "alert-stale";
    note.textContent = "alerts not confirmed by the daemon lately";
    banner.append(note);
  }
  banner.hidden = sorted.length === 0;
}

export function startAlertBanner(banner) {
  let active = [];
  async function poll() {
    try {
      const response = await fetch("api/v1/alerts", { headers: { Accept: "application/json" } });
      if (!response.ok) throw new Error(`HTTP ${response.status}`);
      active = (await response.json()).active;
      renderAlerts(banner, active, false);
    } catch (error) {
      renderAlerts(banner, active, true);
    }
    setTimeout(poll, POLL_MS);
  }
  poll();
}
