"""A camera that survives real hardware: one acquisition thread per camera.

The thread reads frames from the driver into a bounded queue; when the queue is full the
oldest frame is dropped and counted, never the newest. Failures never escape the thread:

* CorruptFrame: the frame is dropped and counted, the stream goes on;
* FrameTimeout: tolerated until no frame has arrived for ``watchdog_s``, then the device is
  treated as lost;
* DeviceLost or any unexpected SDK error: the device is closed, health says RECOVERING with
  the reason (LOST once it has been gone ``lost_after_s``), and the thread retries with
  exponential backoff: open the same device by serial number, re-apply the settings, check
  that automatic exposure/gain/white balance/gamma are still off, start, and report OK
  only when frames flow again.

All waiting is on events and monotonic clocks, never sleep-polling.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, CorruptFrame,
                                DeviceInfo, EndOfStream, Frame, FrameTimeout, Health, HealthState, HealthTracker)
from uwcam.drivers.threads import StoppableThread

log = logging.getLogger(__name__)


@dataclass
class CameraStats:
    """What the camera's thread has counted since it started.

    ``captured``: frames the driver delivered whole; ``dropped``: frames pushed out of the full
    queue, oldest first; ``corrupt``: frames the driver reported damaged, not passed on;
    ``timeouts``: reads that waited the read timeout for no frame; ``reconnects``: times the
    driver was opened and started, the first time included.
    """

    captured: int = 0
    dropped: int = 0
    corrupt: int = 0
    timeouts: int = 0
    reconnects: int = 0


class SupervisedCamera:
    """Runs a :class:`CameraDriver` in its own thread; consumers call :meth:`get`."""

    def __init__(
        self,
        driver: CameraDriver,
        settings: CameraSettings | None = None,
        *,
        queue_size: int = 4,
        read_timeout_s: float = 0.5,
        watchdog_s: float = 2.0,
        lost_after_s: float = 10.0,
        backoff_s: tuple[float, float] = (0.1, 5.0),
        on_frame: Callable[[Frame], None] | None = None,
        stop_wait_s: float = 10.0,
    ) -> None:
        if queue_size < 1:
            raise ConfigurationError("queue_size must be at least 1")
        self.driver = driver
        self.settings = settings or CameraSettings()
        self.read_timeout_s = read_timeout_s
        self.watchdog_s = watchdog_s
        self.lost_after_s = lost_after_s
        self.backoff_s = backoff_s
        self.on_frame = on_frame
        self.stop_wait_s = stop_wait_s
        """How long stop() waits for the acquisition thread to end before leaving it to close the device itself."""
        self.stats = CameraStats()
        self.device: DeviceInfo | None = None
        self.report: ConfigureReport | None = None
        self._health = HealthTracker()
        self._queue: collections.deque[Frame] = collections.deque(maxlen=queue_size)
        # One condition guards the queue: the acquisition thread notifies, consumers wait.
        self._ready = threading.Condition()
        self._worker = StoppableThread(self._run, f"camera-{driver.name}", wake=self._ready)
        self._connected = False
        self._exposure_lock = threading.Lock()
        self._pending_exposure: tuple[tuple[float, ...], tuple[float, ...] | None] | None = None
        self.exposure_error: str | None = None
        """Why the last exposure change failed (None: it did not)."""

    # -- consumer side -------------------------------------------------------------------
    @property
    def health(self) -> Health:
        return self._health.current

    def get(self, timeout_s: float | None = None) -> Frame | None:
        """The oldest queued frame, waiting up to ``timeout_s``; None if none came."""
        with self._ready:
            if not self._queue:
                self._ready.wait_for(lambda: bool(self._queue) or self._worker.stopping.is_set(), timeout=timeout_s)
            return self._queue.popleft() if self._queue else None

    @property
    def exposure_control(self) -> str:
        """"per-channel", "common" or "" (see :attr:`CameraDriver.exposure_control`)."""
        return getattr(self.driver, "exposure_control", "")

    def set_exposure(self, exposure_us: tuple[float, ...], gain_db: tuple[float, ...] | None = None) -> None:
        """Ask for new per-channel exposure (µs) and gain (dB); the acquisition thread applies them
        before its next read (the driver is not thread-safe) and keeps them for reconnections.
        Returns at once; a later request replaces one not yet applied."""
        with self._exposure_lock:
            self._pending_exposure = (tuple(float(v) for v in exposure_us), None if gain_db is None else tuple(map(float, gain_db)))

    def _apply_exposure(self) -> None:
        with self._exposure_lock:
            pending, self._pending_exposure = self._pending_exposure, None
        if pending is None:
            return
        exposure, gain = pending
        try:
            self.driver.set_exposure(exposure, gain)
        except Exception as exc:  # a value the device refuses: keep streaming at the old exposure
            self.exposure_error = f"{type(exc).__name__}: {exc}"
            log.warning("exposure change to %s µs refused: %s", list(exposure), exc)
            return
        self.exposure_error = None
        self.settings = replace(self.settings, channel_exposure_us=exposure,
                                channel_gain_db=gain if gain is not None else self.settings.channel_gain_db)

    def status(self) -> dict:
        return {
            "health": self.health.as_dict(),
            "device": None if self.device is None else vars(self.device),
            "stats": vars(self.stats).copy(),
            "radiometry_not_disabled": [] if self.report is None else list(self.report.radiometry_not_disabled),
            "unsupported_settings": [] if self.report is None else list(self.report.unsupported),
            "settings_details": {} if self.report is None else dict(self.report.details),
        }

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        """Open and configure once in the caller's thread, so a configuration that can never work
        fails here, clearly; then stream in the background."""
        self._connect()
        self._worker.start()

    def stop(self) -> None:
        # The acquisition thread closes the device itself when it ends: a driver call that outlasts
        # the wait (a stream's read or a GenTL open may block for tens of seconds) must not have
        # the device released under it from here (native use after free in OpenCV or an SDK).
        if self._worker.stop(self.stop_wait_s):
            if self._connected:  # opened by start(), the thread never ran
                self._disconnect()
        else:
            log.warning("camera %s: still in a driver call after the wait; it is closed when that call returns",
                        self.driver.serial_number)
        self._health.set(HealthState.STOPPED, "stopped")

    def __enter__(self) -> "SupervisedCamera":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- acquisition thread --------------------------------------------------------------
    def _connect(self) -> None:
        self.device = self.driver.open()
        if self.driver.serial_number is None:
            self.driver.serial_number = self.device.serial_number  # reconnect to this very device
        self.report = self.driver.configure(self.settings)
        if self.report.radiometry_not_disabled:
            log.warning("%s: could not turn off %s; intensity ratios will suffer", self.device.id,
                        ", ".join(self.report.radiometry_not_disabled))
        for name, detail in self.report.details.items():
            log.warning("%s: %s: %s", self.device.id, name, detail)
        self.driver.start()
        self._connected = True

    def _disconnect(self) -> None:
        try:
            self.driver.stop()
        except Exception:  # the device may already be gone; closing is best effort
            pass
        try:
            self.driver.close()
        except Exception:
            pass
        self._connected = False

    def _push(self, frame: Frame) -> None:
        with self._ready:
            if len(self._queue) == self._queue.maxlen:
                self.stats.dropped += 1
            self._queue.append(frame)
            self._ready.notify_all()
        if self.on_frame is not None:
            self.on_frame(frame)

    def _report(self, state: HealthState, reason: str) -> None:
        """Health from the acquisition thread; once stopping, stop() has said the last word."""
        if not self._worker.stopping.is_set():
            self._health.set(state, reason)

    def _run(self) -> None:
        try:
            self._acquire()
        finally:
            if self._connected and self._worker.stopping.is_set():
                self._disconnect()

    def _acquire(self) -> None:
        last_frame = time.monotonic()
        lost_since: float | None = None
        delay = self.backoff_s[0]
        fresh = False
        self._report(HealthState.RECOVERING, "started, waiting for the first frame")
        while not self._worker.stopping.is_set():
            if not self._connected:
                try:
                    self._connect()
                    self.stats.reconnects += 1
                    last_frame = time.monotonic()
                    fresh = True  # no frame yet since this open
                except Exception as exc:  # absent device, SDK error: retry later
                    gone = time.monotonic() - (lost_since or time.monotonic())
                    state = HealthState.LOST if gone >= self.lost_after_s else HealthState.RECOVERING
                    self._report(state, f"reconnecting to {self.driver.serial_number or 'the camera'}: {exc}")
                    self._disconnect()
                    self._worker.stopping.wait(delay)
                    delay = min(delay * 2, self.backoff_s[1])
                    continue
            try:
                self._apply_exposure()
                frame = self.driver.read(self.read_timeout_s)
            except CorruptFrame as exc:
                self.stats.corrupt += 1
                log.debug("corrupt frame dropped: %s", exc)
                continue
            except FrameTimeout:
                self.stats.timeouts += 1
                silent = time.monotonic() - last_frame
                if silent < self.watchdog_s:
                    continue
                reason = f"no frame for {silent:.1f} s (watchdog {self.watchdog_s:g} s)"
            except EndOfStream as exc:
                self._health.set(HealthState.STOPPED, str(exc))
                self._disconnect()
                break
            except Exception as exc:  # DeviceLost and anything an SDK may raise
                reason = f"{type(exc).__name__}: {exc}"
            else:
                self.stats.captured += 1
                last_frame = time.monotonic()
                lost_since = None
                fresh = False
                delay = self.backoff_s[0]
                self._report(HealthState.OK, "streaming")
                self._push(frame)
                continue
            # The device is gone or silent: close it and rebuild.
            lost_since = lost_since or time.monotonic()
            self._report(HealthState.RECOVERING, reason)
            log.warning("camera %s: %s; reconnecting", self.driver.serial_number, reason)
            self._disconnect()
            if fresh:  # lost again before a frame since it opened (a stream that ends at once): back off
                self._worker.stopping.wait(delay)
                delay = min(delay * 2, self.backoff_s[1])
