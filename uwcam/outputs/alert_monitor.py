"""The alert monitor: feeds :mod:`uwcam.runtime.alerts` from the frame loop and the daemon's status, in a
thread of its own, and hands each event to the alert outputs (the REST API reads
:meth:`AlertMonitor.snapshot`; Zenoh ``alerts`` and MAVLink STATUSTEXT get a callback).

The frame loop's callback only keeps the newest published frame (one slot, newest wins); the
thread turns it into a range summary a few times a second, reads the status once a second, and
evaluates. Nothing here runs on the frame loop or the API's event loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from uwcam.runtime.alerts import (AlertEvaluator, AlertEvent, DropWindow, calibration_conditions, device_conditions,
                          disk_condition, dropped_condition, range_condition)
from uwcam.config import AlertsConfig
from uwcam.drivers.threads import StoppableThread
from uwcam.runtime.published import Published

log = logging.getLogger(__name__)

RANGE_PERIOD_S = 0.2
"""The range rule looks at the newest frame this often (a summary costs ~1 ms on 320 columns)."""
STATUS_PERIOD_S = 1.0
"""The other rules read the daemon's status this often."""

Sink = Callable[[AlertEvent, list[AlertEvent]], None]
"""Called with each event and the alerts active after it, in the monitor's thread."""


class AlertMonitor:
    def __init__(self, pipeline, config: AlertsConfig, status: Callable[[], dict], sinks: list[Sink] | None = None) -> None:
        self.pipeline = pipeline
        self.config = config
        self._status_fn = status
        self.sinks: list[Sink] = list(sinks or [])
        self._evaluator = AlertEvaluator(config)
        self._drops = DropWindow(config.frames_dropped.window_s) if config.frames_dropped else None
        self._lock = threading.Lock()  # guards the slot and the snapshot below
        self._slot: Published | None = None
        self._active: list[AlertEvent] = []
        self._history: list[AlertEvent] = []
        self._worker = StoppableThread(self._run, "alert-monitor")
        self.evaluations = 0
        self.error: str | None = None

    def start(self) -> None:
        self._worker.start()
        if self.config.range is not None:
            self.pipeline.subscribe(self._on_published)

    def close(self) -> None:
        self.pipeline.unsubscribe(self._on_published)
        self._worker.stop()

    def _on_published(self, published: Published) -> None:  # the frame loop's thread: hand-off only
        with self._lock:
            self._slot = published

    def snapshot(self) -> dict:
        """The active alerts and the recent events (newest last), as JSON-ready dicts."""
        with self._lock:
            return {"active": [e.as_dict() for e in self._active], "history": [e.as_dict() for e in self._history],
                    "rules": self.config.model_dump(exclude={"history"}), "error": self.error}

    def status(self) -> dict:
        """What /api/v1/status carries: the active alerts, briefly."""
        with self._lock:
            return {"active": [{"key": e.key, "severity": e.severity, "message": e.message, "time": e.time}
                               for e in self._active], "error": self.error}

    def _run(self) -> None:
        from uwcam.outputs.zenoh_publisher import range_summary

        next_status = 0.0
        while not self._worker.stopping.wait(RANGE_PERIOD_S):
            try:
                conditions = []
                with self._lock:
                    published, self._slot = self._slot, None
                if published is not None:
                    conditions += range_condition(self.config, range_summary(published))
                now = time.monotonic()
                if now >= next_status:
                    next_status = now + STATUS_PERIOD_S
                    status, wall = self._status_fn(), time.time()
                    conditions += device_conditions(self.config, status)
                    conditions += calibration_conditions(self.config, status, wall)
                    conditions += disk_condition(self.config, status)
                    conditions += dropped_condition(self.config, self._drops, status, now)
                self._evaluate(conditions, now)
            except Exception as exc:  # keep watching; say what went wrong
                log.exception("alert evaluation failed")
                with self._lock:
                    self.error = f"{type(exc).__name__}: {exc}"

    def _evaluate(self, conditions, now: float) -> None:
        events = self._evaluator.update(conditions, now, time.time())
        active = self._evaluator.active()
        with self._lock:
            self._active = active
            self._history = list(self._evaluator.history)
            self.evaluations += 1
            self.error = None
        for event in events:
            (log.warning if event.state == "raised" else log.info)("alert %s: %s", event.state, event.message)
            for sink in self.sinks:
                try:
                    sink(event, active)
                except Exception:  # one output failing must not keep the alert from the others
                    log.exception("alert output failed")
