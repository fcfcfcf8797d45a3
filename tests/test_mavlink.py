"""MAVLink output against a real pymavlink listener on loopback.

The listener is a UDP socket (or a TCP server) that decodes what arrives with pymavlink's
MAVLink 2 parser. Expected distances come from the simulated seabed (a plane square to the
optical axis at a known distance) and from a naive reduction of the very frames the daemon
published, written here apart from the output's code.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from tests.waiting import wait_for
from uwcam.config import CameraConfig, DaemonConfig, DeviceConfig, MavlinkConfig, ProcessingConfig
from uwcam.runtime.daemon import Daemon
from uwcam.drivers.sim import SimulatedCamera
from uwcam.fileio import UserInputError
from uwcam.config import load_config

SEABED_M = 2.0
LAMP = (0.3, 0.0, 0.0)
W, H = 160, 120


class Listener:
    """A MAVLink endpoint on loopback (UDP, like a router's UDP server) decoding every message."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.parser = mavlink2.MAVLink(None)
        self.messages: list[tuple[float, object]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-listener")

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, _ = self.sock.recvfrom(65536)
            except socket.timeout:
                continue
            for msg in self.parser.parse_buffer(data) or []:
                with self._lock:
                    self.messages.append((time.monotonic(), msg))

    def of(self, kind: str, since: float = 0.0) -> list:
        with self._lock:
            return [m for t, m in self.messages if m.get_type() == kind and t >= since]

    def __enter__(self) -> "Listener":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def rig_config(port: int, scene: str = "seabed-patch", **mavlink) -> DaemonConfig:
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 20.0, "serial_number": "SIM-MAV"}, watchdog_s=0.5),
        lamp=DeviceConfig(driver="sim"),
        simulation={"scene": scene, "distance": SEABED_M, "size": [W, H], "water": "jerlov-IB",
                    "lamp_offset": list(LAMP), "material": "grey"},
        mavlink=MavlinkConfig(connection=f"udpout:127.0.0.1:{port}", **mavlink),
    )


class Recorder:
    """Keeps every published frame by its capture time in ms, as DISTANCE_SENSOR stamps it."""

    def __init__(self) -> None:
        self.frames: dict[int, object] = {}

    def __call__(self, published) -> None:
        self.frames[(published.frame.host_monotonic_ns // 1_000_000) % (1 << 32)] = published


def axial_distance(range_map: np.ndarray, fov_deg: float = 60.0) -> np.ndarray:
    """Range along each ray → distance along the optical axis, for the simulator's pinhole
    (principal point at the centre, square pixels, horizontal field of view fov_deg)."""
    h, w = range_map.shape
    f = (w / 2) / math.tan(math.radians(fov_deg) / 2)
    x = (np.arange(w) - (w - 1) / 2) / f
    y = (np.arange(h) - (h - 1) / 2) / f
    return range_map / np.sqrt(1 + x[None, :] ** 2 + y[:, None] ** 2)


@pytest.mark.slow
def test_downward_distance_sensor_matches_the_seabed_and_the_published_frames():
    region = (0, 0, 70, 120)  # the left part: seabed only, the patch bracket is at the lower right
    with Listener() as ear:
        d = Daemon(rig_config(ear.port, region=region, rate_hz=10.0))
        recorder = Recorder()
        try:
            d.start()
            d.pipeline.subscribe(recorder)
            assert wait_for(lambda: len(ear.of("DISTANCE_SENSOR")) >= 5, 30.0), d.status()["mavlink"]
            t0 = time.monotonic()
            time.sleep(3.0)
            window = ear.of("DISTANCE_SENSOR", since=t0)
            beats = ear.of("HEARTBEAT", since=t0)
            status = d.status()["mavlink"]
        finally:
            d.pipeline and d.pipeline.unsubscribe(recorder)
            d.stop()
    # 10 Hz and 1 Hz over 3 s, with slack for a loaded machine.
    assert 20 <= len(window) <= 32 and 2 <= len(beats) <= 4
    beat = beats[-1]
    assert (beat.type, beat.autopilot) == (mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID)
    assert beat.get_srcSystem() == 1 and beat.get_srcComponent() == 158 and beat.system_status == mavlink2.MAV_STATE_ACTIVE
    far_cm = math.ceil(100 * (100.0 ** 2 - sum(c * c for c in LAMP)) / (2 * 100.0))  # path bound 100 m on the axis
    checked = 0
    for msg in window:
        assert msg.get_srcSystem() == 1 and msg.get_srcComponent() == 158
        assert (msg.orientation, msg.id, msg.type) == (25, 0, mavlink2.MAV_DISTANCE_SENSOR_UNKNOWN)
        assert (msg.min_distance, msg.max_distance) == (0, far_cm)
        assert msg.current_distance == pytest.approx(100 * SEABED_M, abs=12)  # the simulated seabed, ranging error
        assert msg.horizontal_fov == pytest.approx(math.radians(60.0) * 70 / W, rel=0.05)
        published = recorder.frames.get(msg.time_boot_ms)
        if published is None:
            continue
        x, y, w, h = region
        z = axial_distance(published.result.range)[y:y + h, x:x + w]
        fraction = np.isfinite(z).mean()
        assert msg.current_distance == round(100 * np.nanmedian(z))
        assert msg.signal_quality == max(2, round(100 * fraction))
        # covariance: the per-pixel variance in cm², checked against the spread of the distances
        # over the flat seabed (all at one true distance), which it must describe.
        spread_cm2 = np.nanvar(z) * 1e4
        assert msg.covariance < 255 and 0.25 < msg.covariance / spread_cm2 < 4.0
        checked += 1
    assert checked >= 5
    assert status["state"] == "sending" and status["connected"] and status["sent"]["DISTANCE_SENSOR"] >= len(window)


@pytest.mark.slow
def test_nothing_is_sent_while_the_range_is_stale_and_heartbeats_go_on():
    with Listener() as ear:
        d = Daemon(rig_config(ear.port, max_age_s=0.3))
        try:
            d.start()
            assert wait_for(lambda: len(ear.of("DISTANCE_SENSOR")) >= 3, 30.0)
            SimulatedCamera.stall("SIM-MAV")
            assert wait_for(lambda: d.status()["mavlink"]["state"] == "stale", 5.0)
            assert "old (limit 0.3 s)" in d.status()["mavlink"]["reason"]
            quiet = time.monotonic() + 0.2  # a message already on its way may still land
            time.sleep(1.5)
            assert ear.of("DISTANCE_SENSOR", since=quiet) == []
            assert len(ear.of("HEARTBEAT", since=quiet)) >= 1
            assert ear.of("HEARTBEAT")[-1].system_status == mavlink2.MAV_STATE_STANDBY
            SimulatedCamera.stall("SIM-MAV", False)
            resumed = time.monotonic()
            assert wait_for(lambda: len(ear.of("DISTANCE_SENSOR", since=resumed)) >= 3, 15.0)
            assert d.status()["mavlink"]["state"] == "sending"
        finally:
            SimulatedCamera.stall("SIM-MAV", False)
            d.stop()


def naive_sectors(range_map: np.ndarray, rows: slice, max_cm: int, block: int = 8, fov_deg: float = 60.0) -> list[int]:
    """OBSTACLE_DISTANCE distances the long way: each column's azimuth from the pinhole, the
    horizontal distance of every pixel, then per sector the smallest median over tiles of
    ``block`` rows (at least half valid)."""
    h, w = range_map.shape
    f = (w / 2) / math.tan(math.radians(fov_deg) / 2)
    left, increment = -fov_deg / 2, fov_deg / 72
    out = []
    for i in range(72):
        cols = [c for c in range(w)
                if left + i * increment <= math.degrees(math.atan((c - (w - 1) / 2) / f)) < left + (i + 1) * increment]
        if i == 71:
            cols += [c for c in range(w) if math.degrees(math.atan((c - (w - 1) / 2) / f)) >= -left]
        best = None
        for r0 in range(rows.start, rows.stop, block):
            values = []
            for r in range(r0, min(r0 + block, rows.stop)):
                for c in cols:
                    x, y = (c - (w - 1) / 2) / f, (r - (h - 1) / 2) / f
                    values.append(range_map[r, c] * math.sqrt(1 + x * x) / math.sqrt(1 + x * x + y * y))
            good = [v for v in values if np.isfinite(v)]
            if values and 2 * len(good) >= len(values):
                m = float(np.median(good))
                best = m if best is None else min(best, m)
        out.append(65535 if best is None else min(max_cm, round(100 * best)))
    return out


@pytest.mark.slow
def test_forward_camera_obstacle_distance_sectors_follow_the_intrinsics():
    """Camera looking forward at a wall (the seabed plane, square to the axis) 2 m ahead."""
    rows = slice(10, 60)
    with Listener() as ear:
        d = Daemon(rig_config(ear.port, region=(0, rows.start, 60, rows.stop - rows.start), orientation="NONE",
                              statistic="minimum", obstacle_distance=True))
        frames: dict[int, object] = {}
        try:
            d.start()
            d.pipeline.subscribe(lambda p: frames.__setitem__(int(p.frame.wall_time * 1e6), p))
            assert wait_for(lambda: any(m.time_usec in frames for m in ear.of("OBSTACLE_DISTANCE")), 30.0)
            msg = next(m for m in reversed(ear.of("OBSTACLE_DISTANCE")) if m.time_usec in frames)
            distance = ear.of("DISTANCE_SENSOR")[-1]
            truth = d.rig.world.camera_range
        finally:
            d.stop()
    half = 30.0  # the simulator's horizontal field of view is 60°
    increment = 2 * half / 72
    assert msg.increment_f == pytest.approx(increment, rel=1e-5) and msg.increment == 1
    assert msg.angle_offset == pytest.approx(-half + increment / 2, abs=1e-4)
    assert msg.frame == mavlink2.MAV_FRAME_BODY_FRD and len(msg.distances) == 72
    assert distance.orientation == 0 and distance.current_distance == pytest.approx(200, abs=25)
    # Exactly the reduction of the frame it came from...
    assert list(msg.distances) == naive_sectors(frames[msg.time_usec].result.range, rows, msg.max_distance)
    # ...and the wall's geometry: the nearest point of the wall in the sector at azimuth θ lies
    # 2 m / cos θ away. The simulated ranging itself reads short towards the image edges (about
    # 8 % in the median there; a tile minimum goes lower), so this bound is loose on purpose.
    for value, expected in zip(msg.distances, naive_sectors(truth, rows, msg.max_distance)):
        assert value == pytest.approx(expected, rel=0.2)
    assert naive_sectors(truth, rows, msg.max_distance)[0] == pytest.approx(200 / math.cos(math.radians(half - increment)), abs=3)


@pytest.mark.slow
def test_no_distance_when_no_pixel_is_valid_and_sectors_unknown():
    """Path-length bounds of 0.5–2 m leave the seabed (about 4 m of light path) out: every pixel
    is invalid, so no DISTANCE_SENSOR goes out and every sector is unknown."""
    config = rig_config(1, orientation="YAW_90", obstacle_distance=True, region=(0, 0, W, 50))  # above the patch
    with Listener() as ear:
        config = config.model_copy(update={
            "processing": ProcessingConfig(path_length_bounds=(0.5, 2.0)),
            "mavlink": config.mavlink.model_copy(update={"connection": f"udpout:127.0.0.1:{ear.port}"})})
        d = Daemon(config)
        try:
            d.start()
            assert wait_for(lambda: len(ear.of("OBSTACLE_DISTANCE")) >= 3, 30.0), d.status()["mavlink"]
            status = d.status()["mavlink"]
        finally:
            d.stop()
    msg = ear.of("OBSTACLE_DISTANCE")[-1]
    assert status["obstacle_distance"] == "sending"
    assert ear.of("DISTANCE_SENSOR") == []
    assert status["state"] == "invalid" and status["reason"].startswith("0.0 % of the region's pixels have a range")
    assert list(msg.distances) == [65535] * 72  # UINT16_MAX: unknown
    # Camera range on the axis for path lengths 0.5 m and 2 m with the lamp 0.3 m to the side:
    # d_c = (d_T² − |S|²) / (2 d_T).
    assert (msg.min_distance, msg.max_distance) == (math.floor(100 * (0.25 - 0.09) / 1.0), math.ceil(100 * (4 - 0.09) / 4))
    # YAW_90: the camera looks to starboard, so sector 0's centre is 90° − 30° + half a sector.
    assert msg.angle_offset == pytest.approx(90 - 30 + 60 / 144, abs=1e-4)


def test_sectors_that_saw_only_water_report_no_obstacle():
    from uwcam.optics.validity import Reason
    from uwcam.outputs.mavlink_measure import sector_distances

    horizontal = np.full((16, 72), np.nan)
    reasons = np.full((16, 72), Reason.BELOW_NOISE_FLOOR, dtype=np.uint8)
    horizontal[:, 0] = 1.234                 # sector 0: a surface at 1.234 m
    reasons[:, 0] = Reason.VALID
    reasons[:, 1] = Reason.BACKSCATTER_ONLY  # sector 1: lit water, nothing in range
    horizontal[:9, 2] = 0.5                  # sector 2: 9 of 16 valid, 0.5 m, the rest water
    reasons[:9, 2] = Reason.VALID
    reasons[9:, 2] = Reason.BACKSCATTER_ONLY
    horizontal[:, 3] = np.linspace(3.0, 1.5, 16)  # sector 3: nearer downwards; tile medians 2.65, 1.85
    reasons[:, 3] = Reason.VALID
    out = sector_distances(horizontal, reasons, np.arange(72), 10, 1000, 8)
    assert out[0] == 123 and out[1] == 1001 and out[3] == 185
    assert out[2] == 50  # the top tile is fully valid
    assert list(out[4:]) == [65535] * 68


@pytest.mark.slow
def test_tcp_link_reconnects_after_the_peer_goes_away():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(20.0)
    port = server.getsockname()[1]
    config = rig_config(1).model_copy(update={"mavlink": MavlinkConfig(connection=f"tcp:127.0.0.1:{port}")})
    d = Daemon(config)
    parser = mavlink2.MAVLink(None)

    def received(conn, seconds: float) -> list:
        conn.settimeout(0.2)
        out, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data = conn.recv(65536)
            except socket.timeout:
                continue
            if not data:
                break
            out += parser.parse_buffer(data) or []
        return out

    try:
        d.start()
        conn, _ = server.accept()
        kinds = {m.get_type() for m in received(conn, 2.0)}
        assert {"HEARTBEAT", "DISTANCE_SENSOR"} <= kinds
        # The autopilot's heartbeat coming back is noticed.
        hb = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        conn.sendall(hb.heartbeat_encode(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(hb))
        assert wait_for(lambda: d.status()["mavlink"]["autopilot_heartbeat_age_s"] is not None, 5.0)
        conn.close()
        assert wait_for(lambda: d.status()["mavlink"]["state"] == "disconnected", 10.0)
        assert "closed the connection" in d.status()["mavlink"]["reason"] or "failed" in d.status()["mavlink"]["reason"]
        conn, _ = server.accept()  # it comes back by itself
        assert "DISTANCE_SENSOR" in {m.get_type() for m in received(conn, 2.0)}
        assert d.status()["mavlink"]["connected"] and d.status()["mavlink"]["send_errors"] >= 1
        conn.close()
    finally:
        d.stop()
        server.close()


def test_mavlink_configuration_is_checked(tmp_path):
    cases = {
        "connection: udp:1.2.3.4:14550": "is not udpout:HOST:PORT, tcp:HOST:PORT or a serial device path",
        "connection: udpout:127.0.0.1:70000": "port 70000 is not 1–65535",
        "rate_hz: .nan": "key 'mavlink.rate_hz'",
        "rate_hz: 80": "less than or equal to 50",
        "orientation: SIDEWAYS": "unknown orientation 'SIDEWAYS'",
        "{orientation: PITCH_270, obstacle_distance: true}": "obstacle_distance needs a camera looking horizontally",
        "source_system: 0": "key 'mavlink.source_system'",
        "statistic: mean": "key 'mavlink.statistic'",
        "colour: red": "unknown key",
    }
    for body, message in cases.items():
        path = tmp_path / "rig.yaml"
        text = body if body.startswith("{") else "{" + body + "}"
        path.write_text(f"mavlink: {text}\n")
        with pytest.raises(UserInputError, match=message.replace("(", r"\(").replace(")", r"\)")):
            load_config(path)
    path.write_text("mavlink: {orientation: mav_sensor_rotation_none, connection: /dev/ttyACM0}\n")
    assert load_config(path).mavlink.orientation_value == 0


class _NoFrames:
    """Stands in for the frame loop: the output subscribes, no frame ever comes."""

    processing = None
    profile = None

    def subscribe(self, fn) -> None:
        pass

    def unsubscribe(self, fn) -> None:
        pass


def test_udp_peer_that_is_not_listening_is_reported():
    from uwcam.outputs.mavlink import MavlinkOutput

    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens there now: the kernel answers with "port unreachable"
    out = MavlinkOutput(MavlinkConfig(connection=f"udpout:127.0.0.1:{port}", rate_hz=20), _NoFrames())
    out.start()
    try:
        assert wait_for(lambda: out.status()["state"] == "disconnected", 10.0), out.status()
        assert out.status()["reason"] == f"nothing listens at udp 127.0.0.1:{port} (connection refused)"
        assert out.status()["send_errors"] >= 1 and not out.status()["connected"]
    finally:
        out.stop()
    assert out.status()["state"] == "stopped"


@pytest.mark.slow
def test_mavlink_benchmark_runs():
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "bench" / "bench_mavlink.py"
    out = subprocess.run([sys.executable, str(script), "--size", "160x120", "--repeat", "2"],
                         check=True, capture_output=True, text=True, timeout=300).stdout
    assert "× memcopy" in out and "obstacle sectors" in out
