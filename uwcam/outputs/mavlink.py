"""MAVLink output: range to an autopilot as DISTANCE_SENSOR, OBSTACLE_DISTANCE and HEARTBEAT.

A subscriber of the frame loop. The loop's callback only stores the newest published frame
(one slot, newest wins); this output's own thread, at the configured rate, takes the newest
frame, reduces its range map to what the autopilot needs and sends it over UDP, TCP or a
serial line.

Field semantics follow MAVLink's common.xml:

* DISTANCE_SENSOR ``current_distance``: a robust statistic (median, or the smallest median
  over small tiles as the "minimum") of the valid pixels' distance along the optical axis in the configured
  region, cm. ``min_distance``/``max_distance``: the processing path-length bounds turned
  into camera range on the axis (ArduPilot keeps them in int16 cm, so at most 32767); the
  maximum is lowered to the range the profile can measure where that can be known: the longest
  range at which two channels of different attenuation still return more than the profile's
  noise floor from the surface the rangefinder measured (absolute attenuations and the surface
  scale of docs/physics.md §8–9), so that ArduSub's RNGFND1_MAX can be set from it.
  ``covariance``: the per-pixel variance of those pixels (median), cm²; UINT8_MAX when
  unknown or too large for a byte. ``signal_quality``: the valid fraction of the region in
  percent, never below 2 for a reading that is sent (0 means unknown, 1 invalid).
  ``horizontal_fov``/``vertical_fov``: the region's angular size from the intrinsics, rad (0
  unknown). Nothing is sent while the newest frame is stale or the region holds too few
  valid pixels: ArduPilot then times the rangefinder out (500 ms) instead of trusting it.
* OBSTACLE_DISTANCE: 72 sectors spanning the camera's horizontal field of view (body frame
  FRD, clockwise positive, ``angle_offset`` the centre of sector 0), each the robust minimum
  horizontal distance of its valid pixels in cm; UINT16_MAX where unknown, ``max_distance +
  1`` where the sector's pixels saw only lit water (no obstacle within range).
* STATUSTEXT for each alert raised or cleared (uwcam.runtime.alerts), with the alert's MAV_SEVERITY
  (cleared: INFO), its text cut to the message's 50 characters; queued while the link is down
  (the newest 16 kept).
* Received: the autopilot's HEARTBEAT (status), and its ATTITUDE (roll, pitch and yaw rates) and
  LOCAL_POSITION_NED (velocity), which temporal fusion reads to start afresh when the vehicle
  moves (:meth:`MavlinkOutput.motion`; docs/physics.md §11).
* HEARTBEAT at 1 Hz as an onboard controller, so the autopilot and ground station see the
  component; ``system_status`` ACTIVE while distances are sent, STANDBY otherwise. 1 Hz also
  while the link is being re-opened: a reconnect does not send one of its own.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from uwcam.config import MavlinkConfig
from uwcam.drivers.threads import StoppableThread
from uwcam.outputs.mavlink_links import LinkDown, open_transport
from uwcam.outputs.mavlink_measure import (
    Measurement,
    PixelRays,
    covariance_cm2,
    distance_limits_cm,
    measure,
    reach_of,
    signal_quality,
)
from uwcam.runtime.published import Published

log = logging.getLogger(__name__)

HEARTBEAT_PERIOD_S = 1.0
STATUSTEXT_BYTES = 50
"""STATUSTEXT's text field (a longer text would need MAVLink 2's chunks, which not every ground station joins)."""
MOTION_MAX_AGE_S = 1.0
"""ATTITUDE and LOCAL_POSITION_NED older than this (s) say nothing about the vehicle's motion now."""
STATUSTEXT_QUEUE = 16
# MAVLink enum values used here (common.xml), named so the code reads like the spec.
MAV_DISTANCE_SENSOR_UNKNOWN = 4
MAV_FRAME_BODY_FRD = 12
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_STANDBY, MAV_STATE_ACTIVE = 3, 4


@dataclass
class MavlinkStats:
    sent: dict[str, int] = field(default_factory=lambda: {"HEARTBEAT": 0, "DISTANCE_SENSOR": 0, "OBSTACLE_DISTANCE": 0,
                                                          "STATUSTEXT": 0})
    send_errors: int = 0
    reconnects: int = 0
    frames_measured: int = 0
    frames_skipped_for_newer: int = 0
    """Frames replaced by a newer one before a message was due: never measured (newest wins)."""


class MavlinkOutput:
    """Sends the newest frame's distance to an autopilot; start/stop it with the frame loop.

    ``pipeline``: the :class:`uwcam.runtime.pipeline.FramePipeline` (its ``profile`` and ``processing``
    are read for intrinsics, lamp position and path-length bounds at every frame).
    """

    def __init__(self, config: MavlinkConfig, pipeline) -> None:
        from pymavlink.dialects.v20 import common as mavlink2

        self.config = config
        self.pipeline = pipeline
        self.stats = MavlinkStats()
        self._mavlink2 = mavlink2
        # MAVLink 2 framing: OBSTACLE_DISTANCE (id 330) and DISTANCE_SENSOR's extension fields need it.
        self._mav = mavlink2.MAVLink(self, srcSystem=config.source_system, srcComponent=config.source_component)
        self._mav.robust_parsing = True
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True
        self._slot: Published | None = None  # newest frame not yet measured (one slot, newest wins)
        self._slot_lock = threading.Lock()
        self._texts: deque[tuple[int, bytes]] = deque(maxlen=STATUSTEXT_QUEUE)  # guarded by _slot_lock
        self._worker = StoppableThread(self._run, "output-mavlink")
        self._transport = None
        self._retry_at = 0.0
        self._retry_delay = 0.2
        self._rays = PixelRays()
        self.measurement: Measurement | None = None
        self.max_distance_from = "processing.path_length_bounds"
        self.autopilot_heartbeat_monotonic: float | None = None
        # The vehicle's motion as the autopilot reports it, (monotonic s, value), or None; each a
        # tuple swapped whole, so that another thread reads one consistent reading.
        self._turn_rate: tuple[float, float] | None = None
        """Angular speed (rad/s) from ATTITUDE's roll, pitch and yaw rates."""
        self._speed: tuple[float, float] | None = None
        """Speed (m/s) from LOCAL_POSITION_NED's velocity."""
        self._state_lock = threading.Lock()
        self._state = ("stopped", "not started", time.time())
        self.connected = False

    # -- frame loop side: hand-off only ------------------------------------------------------
    def offer(self, published: Published) -> None:
        """Called by the frame loop for every published frame: keep the newest, nothing more."""
        with self._slot_lock:
            if self._slot is not None:
                self.stats.frames_skipped_for_newer += 1
            self._slot = published

    def offer_statustext(self, severity: str, text: str) -> None:
        """Queue a STATUSTEXT (severity: a MAV_SEVERITY name such as "critical"; text: cut to 50
        bytes of UTF-8) for this output's thread; any thread may call it."""
        from uwcam.runtime.alerts import SEVERITIES

        data = text.encode("utf-8")[:STATUSTEXT_BYTES].decode("utf-8", "ignore").encode("utf-8")
        with self._slot_lock:
            self._texts.append((SEVERITIES[severity], data))

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self._set_state("connecting", f"opening {self.config.connection}")
        self._worker.start()
        self.pipeline.subscribe(self.offer)

    def stop(self) -> None:
        self.pipeline.unsubscribe(self.offer)
        self._worker.stop(timeout_s=5.0)
        self._close()
        self._set_state("stopped", "stopped")

    # -- the output's thread -------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        """pymavlink's file interface: every message goes out through the transport."""
        self._transport.send(data)

    def _set_state(self, state: str, reason: str) -> None:
        with self._state_lock:
            if self._state[:2] != (state, reason):
                self._state = (state, reason, time.time())

    def _close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        self.connected = False

    def _connect(self, now: float) -> bool:
        if self._transport is not None:
            return True
        if now < self._retry_at:
            return False
        transport = open_transport(self.config)
        try:
            transport.open()
        except LinkDown as exc:
            self._link_down(str(exc), now)
            return False
        self._transport = transport
        self.connected = True
        self._retry_delay = 0.2
        return True

    def _link_down(self, reason: str, now: float) -> None:
        self.stats.send_errors += 1
        self._close()
        self._retry_at = now + self._retry_delay
        self._retry_delay = min(self._retry_delay * 2, 5.0)
        self.stats.reconnects += 1
        self._set_state("disconnected", reason)

    def _run(self) -> None:
        period = 1.0 / self.config.rate_hz
        next_send = next_heartbeat = time.monotonic()
        while not self._worker.stopping.wait(max(0.0, min(next_send, next_heartbeat) - time.monotonic())):
            now = time.monotonic()
            if now >= next_send:
                # Only the newest frame, and only when a message is due: the work is bounded by
                # rate_hz whatever the camera's frame rate.
                self._take_newest()
            if not self._connect(now):
                next_send = max(now + period, self._retry_at)
                next_heartbeat = max(next_heartbeat, self._retry_at)
                continue
            try:
                self._receive()
                if now >= next_heartbeat:
                    # Due a period after the last attempt, sent or failed: a link that fails and
                    # reopens every 0.2 s (a UDP peer that is not there yet) still gets 1 Hz.
                    next_heartbeat = now + HEARTBEAT_PERIOD_S
                    self._send_heartbeat()
                if now >= next_send:
                    next_send = max(next_send + period, now)
                    self._send_distance(now)
                self._send_texts()
            except LinkDown as exc:
                self._link_down(str(exc), now)
            except Exception as exc:  # never let the output die: report and go on
                log.exception("MAVLink output failed")
                self._link_down(f"{type(exc).__name__}: {exc}", now)

    def _take_newest(self) -> None:
        with self._slot_lock:
            published, self._slot = self._slot, None
        if published is None:
            return
        processing = self.pipeline.processing
        profile = self.pipeline.profile
        reach, self.max_distance_from = reach_of(profile, getattr(self.pipeline, "corrector", None))
        self.measurement = measure(published, self.config, profile, processing.path_length_bounds, self._rays, reach)
        self.stats.frames_measured += 1

    def _receive(self) -> None:
        data = self._transport.receive()
        if not data:
            return
        try:
            messages = self._parser.parse_buffer(data) or []
        except Exception:  # robust parsing: garbage on the link is not our problem
            return
        for msg in messages:
            kind = msg.get_type()
            if kind == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID:
                self.autopilot_heartbeat_monotonic = time.monotonic()
            elif kind == "ATTITUDE":
                rate = math.sqrt(msg.rollspeed**2 + msg.pitchspeed**2 + msg.yawspeed**2)
                if math.isfinite(rate):
                    self._turn_rate = (time.monotonic(), rate)
            elif kind == "LOCAL_POSITION_NED":
                speed = math.sqrt(msg.vx**2 + msg.vy**2 + msg.vz**2)
                if math.isfinite(speed):
                    self._speed = (time.monotonic(), speed)

    def motion(self, max_age_s: float = MOTION_MAX_AGE_S) -> tuple[float | None, float | None]:
        """(angular speed rad/s, speed m/s) of the vehicle from the autopilot's latest ATTITUDE and
        LOCAL_POSITION_NED, each None when none came in the last ``max_age_s`` seconds. Any thread."""
        now = time.monotonic()
        turn, speed = self._turn_rate, self._speed
        return (turn[1] if turn is not None and now - turn[0] <= max_age_s else None,
                speed[1] if speed is not None and now - speed[0] <= max_age_s else None)

    def _send_texts(self) -> None:
        while True:
            with self._slot_lock:
                if not self._texts:
                    return
                severity, text = self._texts[0]
            self._mav.statustext_send(severity, text)  # LinkDown leaves it queued for the next link
            with self._slot_lock:
                if self._texts and self._texts[0] == (severity, text):
                    self._texts.popleft()
            self.stats.sent["STATUSTEXT"] += 1

    def _send_heartbeat(self) -> None:
        status = MAV_STATE_ACTIVE if self.sending else MAV_STATE_STANDBY
        self._mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, status)
        self.stats.sent["HEARTBEAT"] += 1

    def _send_distance(self, now: float) -> None:
        m = self.measurement
        if m is None:
            self._set_state("stale", "no frame processed yet")
            return
        age = now - m.capture_monotonic_ns / 1e9
        if age > self.config.max_age_s:
            self._set_state("stale", f"newest frame is {age:.2f} s old (limit {self.config.max_age_s:g} s)")
            return
        min_cm, max_cm = distance_limits_cm(m.min_distance_m, m.max_distance_m)
        if m.distance_m is not None:
            cm = int(round(m.distance_m * 100))
            if not min_cm <= cm <= max_cm:
                self._set_state("invalid", f"distance {cm} cm outside {min_cm}–{max_cm} cm")
            else:
                self._mav.distance_sensor_send(
                    (m.capture_monotonic_ns // 1_000_000) % (1 << 32), min_cm, max_cm, cm, MAV_DISTANCE_SENSOR_UNKNOWN,
                    self.config.sensor_id, self.config.orientation_value, covariance_cm2(m.variance_m2),
                    m.horizontal_fov_rad, m.vertical_fov_rad, [0.0, 0.0, 0.0, 0.0], signal_quality(m.valid_fraction))
                self.stats.sent["DISTANCE_SENSOR"] += 1
                self._set_state("sending", f"DISTANCE_SENSOR at {self.config.rate_hz:g} Hz")
        else:
            self._set_state("invalid", m.reason)
        if m.sectors_cm is not None:
            self._mav.obstacle_distance_send(
                int(m.wall_time * 1e6), MAV_DISTANCE_SENSOR_UNKNOWN, [int(v) for v in m.sectors_cm],
                max(1, min(255, int(round(m.sector_increment_deg)))), min_cm, max_cm, m.sector_increment_deg,
                m.sector_offset_deg, MAV_FRAME_BODY_FRD)
            self.stats.sent["OBSTACLE_DISTANCE"] += 1

    # -- health --------------------------------------------------------------------------------
    @property
    def sending(self) -> bool:
        with self._state_lock:
            return self._state[0] == "sending"

    def status(self) -> dict:
        with self._state_lock:
            state, reason, since = self._state
        m = self.measurement
        beat = self.autopilot_heartbeat_monotonic
        return {
            "connection": self.config.connection,
            "state": state, "reason": reason, "since": since,
            "connected": self.connected, "sending": state == "sending",
            "sent": dict(self.stats.sent), "send_errors": self.stats.send_errors,
            "frames_measured": self.stats.frames_measured,
            "frames_skipped_for_newer": self.stats.frames_skipped_for_newer,
            "distance_m": None if m is None or m.distance_m is None else round(m.distance_m, 4),
            "min_distance_m": None if m is None else distance_limits_cm(m.min_distance_m, m.max_distance_m)[0] / 100,
            "max_distance_m": None if m is None else distance_limits_cm(m.min_distance_m, m.max_distance_m)[1] / 100,
            "max_distance_from": self.max_distance_from,
            "valid_fraction": None if m is None else round(m.valid_fraction, 4),
            "autopilot_heartbeat_age_s": None if beat is None else round(time.monotonic() - beat, 3),
            "obstacle_distance": None if not self.config.obstacle_distance else (
                "sending" if m is not None and m.sectors_cm is not None else
                "no frame yet" if m is None else
                "not sent: the calibration profile has no camera intrinsics (fx, fy, cx, cy)"),
        }
