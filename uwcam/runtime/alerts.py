"""Alert rules, evaluated: pure functions from what the daemon publishes (range summaries, the
status document) to conditions, and :class:`AlertEvaluator`, which turns a stream of conditions
into events — each alert raised once when its condition has held for the rule's time, cleared once
when it has been false for ``clear_s`` — with their time and values.

Nothing here reads a clock, a device or a file: the caller passes the time and the observations
(uwcam.outputs.alert_monitor does, in a thread of its own), so every rule is tested with made-up
inputs (tests/test_alerts.py). Severities are MAVLink's MAV_SEVERITY names, so that STATUSTEXT
carries them unchanged.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field
from datetime import datetime

from uwcam.config import AlertsConfig

SEVERITIES = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4, "notice": 5, "info": 6, "debug": 7}
"""MAV_SEVERITY values by name (MAVLink common.xml)."""
DEVICES = ("camera", "lamp", "rangefinder")
DAY_S = 86400.0


@dataclass(frozen=True)
class Condition:
    """One rule's verdict on one subject at one moment. ``active``: True (the condition holds),
    False (it does not), None (no evidence either way: nothing changes)."""

    rule: str
    subject: str
    active: bool | None
    severity: str
    message: str
    """Short: MAVLink STATUSTEXT carries its first 50 characters, prefix included."""
    for_s: float = 0.0
    """How long the condition must hold before the alert is raised, s."""
    values: dict = field(default_factory=dict)

    @property
    def key(self) -> str:
        return f"{self.rule}/{self.subject}" if self.subject else self.rule


@dataclass(frozen=True)
class AlertEvent:
    """An alert raised or cleared: ``time`` is Unix seconds; ``since`` when the condition began
    (raised) or ended (cleared), Unix seconds; ``values`` the figures at that moment."""

    key: str
    rule: str
    subject: str
    state: str  # "raised" or "cleared"
    severity: str
    message: str
    time: float
    since: float
    values: dict

    def as_dict(self) -> dict:
        return asdict(self)


def _round(value: float | None, digits: int = 4) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), digits)


# -- the rules: observations → conditions ----------------------------------------------------------
def range_condition(config: AlertsConfig, summary: dict | None) -> list[Condition]:
    """Collision warning from a range summary (``minimum_m``, m): below ``range.below_m``. A frame
    without a minimum (too few valid pixels) is no evidence."""
    rule = config.range
    if rule is None or summary is None:
        return []
    minimum = summary.get("minimum_m")
    if minimum is None:
        return [Condition("range", "", None, "critical", "range unknown", rule.for_s)]
    values = {"minimum_m": _round(minimum), "below_m": rule.below_m, "frame": summary.get("frame")}
    return [Condition("range", "", minimum < rule.below_m, "critical",
                      f"range {minimum:.2f} m < {rule.below_m:g} m" if minimum < rule.below_m
                      else f"range {minimum:.2f} m", rule.for_s, values)]


def device_conditions(config: AlertsConfig, status: dict) -> list[Condition]:
    """A configured device lost or recovering (``status[device].health.state``)."""
    rule = config.device
    if rule is None:
        return []
    out = []
    for device in DEVICES:
        entry = status.get(device)
        health = entry.get("health") if isinstance(entry, dict) else None
        if not isinstance(health, dict):
            continue  # not configured
        state = health.get("state")
        down = state in ("lost", "recovering")
        out.append(Condition("device", device, down, "error", f"{device} {state}: {health.get('reason', '')}",
                             rule.for_s, {"state": state, "reason": health.get("reason"), "for_s": health.get("for_s")}))
    return out


def calibration_conditions(config: AlertsConfig, status: dict, now_wall: float) -> list[Condition]:
    """The calibration's age (days since ``calibration.created``) and the patch-tracked drift of
    each channel's attenuation difference against the profile's uncertainty of it."""
    rule = config.calibration
    if rule is None:
        return []
    calibration = status.get("calibration") or {}
    out = []
    if rule.max_age_days is not None:
        created = calibration.get("created")
        try:
            made = datetime.fromisoformat(created).timestamp() if created else None
        except ValueError:
            made = None  # an unreadable date is no evidence, not an old calibration
        if made is not None:
            age_days = (now_wall - made) / DAY_S
            out.append(Condition("calibration_age", "", age_days > rule.max_age_days, "notice",
                                 f"calibration {age_days:.0f} days old (max {rule.max_age_days:g})", 0.0,
                                 {"age_days": _round(age_days, 2), "max_age_days": rule.max_age_days,
                                  "name": calibration.get("name"), "created": created}))
    tracking = calibration.get("tracking")
    if rule.drift_sigmas is not None and isinstance(tracking, dict) and tracking.get("accepted"):
        drift, std = tracking.get("drift") or {}, tracking.get("drift_std") or {}
        judged = {c: abs(d) / std[c] for c, d in drift.items() if std.get(c, 0) > 0 and math.isfinite(d)}
        if judged:
            worst = max(judged, key=judged.get)
            sigmas = judged[worst]
            out.append(Condition("attenuation_drift", "", sigmas > rule.drift_sigmas, "notice",
                                 f"attenuation {worst} drift {sigmas:.1f} sigma", rule.drift_for_s,
                                 {"channel": worst, "drift_per_m": _round(drift[worst], 5),
                                  "std_per_m": _round(std[worst], 5), "sigmas": _round(sigmas, 2),
                                  "limit_sigmas": rule.drift_sigmas}))
    return out


def disk_condition(config: AlertsConfig, status: dict) -> list[Condition]:
    """Free space on the recordings' disk below ``disk_free_below_percent`` of its size."""
    limit = config.disk_free_below_percent
    recording = status.get("recording")
    if limit is None or not isinstance(recording, dict):
        return []
    free, total = recording.get("disk_free_bytes"), recording.get("disk_total_bytes")
    if free is None or not total:
        return []
    percent = 100.0 * free / total
    return [Condition("disk", "", percent < limit, "warning", f"recording disk {percent:.1f} % free", 0.0,
                      {"free_percent": _round(percent, 2), "free_bytes": free, "below_percent": limit})]


class DropWindow:
    """Frames captured and dropped over the last ``window_s`` seconds, from the status's running
    counters (a counter that goes back — a restarted camera — starts the window afresh)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._samples: deque[tuple[float, int, int]] = deque()

    def add(self, now: float, captured: int, dropped: int) -> tuple[float, int] | None:
        """(share dropped, frames captured) over the window; None until it spans ``window_s``."""
        if self._samples and (captured < self._samples[-1][1] or dropped < self._samples[-1][2]):
            self._samples.clear()
        self._samples.append((now, captured, dropped))
        while len(self._samples) > 2 and self._samples[1][0] <= now - self.window_s:
            self._samples.popleft()
        t0, c0, d0 = self._samples[0]
        if now - t0 < self.window_s * 0.999:
            return None
        # A frame the camera's queue dropped may not count as captured: the share is of the larger.
        lost = dropped - d0
        total = max(captured - c0, lost)
        return (lost / total if total else 0.0), total


def dropped_condition(config: AlertsConfig, window: DropWindow | None, status: dict, now: float) -> list[Condition]:
    """Share of frames dropped over the window above ``frames_dropped.above_percent``. No frames
    captured at all over the window is the device rule's business, not this one's."""
    rule = config.frames_dropped
    frames = status.get("frames")
    if rule is None or window is None or not isinstance(frames, dict):
        return []
    share = window.add(now, int(frames.get("captured", 0)), int(frames.get("dropped", 0)))
    if share is None or share[1] == 0:
        return []
    percent = 100.0 * share[0]
    return [Condition("frames_dropped", "", percent > rule.above_percent, "warning",
                      f"{percent:.0f} % of frames dropped", 0.0,
                      {"dropped_percent": _round(percent, 2), "above_percent": rule.above_percent,
                       "window_s": rule.window_s, "frames": share[1]})]


# -- raised once, cleared once ---------------------------------------------------------------------
@dataclass
class _Track:
    since: float | None = None  # monotonic s: when the condition began (inactive) or ended (active)
    since_wall: float | None = None
    active: bool = False
    raised: AlertEvent | None = None
    last: Condition | None = None


class AlertEvaluator:
    """Conditions in, events out. An alert is raised when its condition has been true for the
    rule's ``for_s`` (a false reading in between starts the wait afresh), and cleared when it has
    been false for ``clear_s`` (a true reading in between keeps it raised); a condition without
    evidence (``active`` None) changes nothing. Not thread-safe: one owner feeds it."""

    def __init__(self, config: AlertsConfig) -> None:
        self.config = config
        self._tracks: dict[str, _Track] = {}
        self.history: deque[AlertEvent] = deque(maxlen=config.history)

    def update(self, conditions: list[Condition], now: float, wall: float) -> list[AlertEvent]:
        """``now``: monotonic seconds; ``wall``: Unix seconds of the same moment."""
        events = []
        for c in conditions:
            track = self._tracks.setdefault(c.key, _Track())
            if c.active is None:
                continue
            track.last = c
            if c.active == track.active:  # as it stands: no transition pending
                track.since = track.since_wall = None
                continue
            if track.since is None:
                track.since, track.since_wall = now, wall
            hold = c.for_s if c.active else self.config.clear_s
            if now - track.since < hold:
                continue
            track.active = c.active
            event = AlertEvent(c.key, c.rule, c.subject, "raised" if c.active else "cleared", c.severity,
                               f"{c.message}" if c.active else f"cleared: {c.message}", wall, track.since_wall,
                               dict(c.values))
            track.raised = event if c.active else None
            track.since = track.since_wall = None
            self.history.append(event)
            events.append(event)
        return events

    def active(self) -> list[AlertEvent]:
        """The alerts raised and not cleared, in the order they were raised."""
        return sorted((t.raised for t in self._tracks.values() if t.raised is not None), key=lambda e: e.time)

    def current(self, key: str) -> Condition | None:
        """The newest condition with evidence for ``key`` (what the alert's figures are now)."""
        track = self._tracks.get(key)
        return None if track is None else track.last
