"""MAVLink output received by pymavlink's own ``mavutil`` (what MAVProxy is built on) on loopback:
the rate, the heartbeat's 1 Hz also while the peer is missing, numeric orientations, and the
maximum distance the profile can measure."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from tests.test_mavlink import SEABED_M, rig_config
from tests.waiting import wait_for
from uwcam.config import DeviceConfig, MavlinkConfig, load_config
from uwcam.runtime.daemon import Daemon
from uwcam.optics.orientation import channel_reach_m, measurable_range_m, transfer


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def receive(conn, seconds: float) -> list:
    """Every message mavutil decodes in ``seconds`` (wall clock), as (monotonic time, message)."""
    got, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        msg = conn.recv_match(blocking=True, timeout=min(left, 0.2))
        if msg is not None and msg.get_type() != "BAD_DATA":
            got.append((time.monotonic(), msg))
    return got


@pytest.fixture
def mavutil(monkeypatch):
    monkeypatch.setenv("MAVLINK20", "1")  # DISTANCE_SENSOR's extension fields are MAVLink 2 only
    from pymavlink import mavutil as module

    return module


@pytest.mark.slow
def test_mavutil_receives_distance_at_the_rate_and_heartbeats_at_1_hz_also_while_the_peer_was_missing(mavutil):
    port = free_udp_port()  # nothing listens there yet: every send is refused
    config = rig_config(port, region=(0, 0, 70, 120), rate_hz=10.0, orientation=25)
    config = config.model_copy(update={"rangefinder": DeviceConfig(driver="sim-ping1d", options={"rate_hz": 20})})
    d = Daemon(config)
    try:
        d.start()
        assert wait_for(lambda: d.status()["mavlink"]["send_errors"] >= 2, 30.0), d.status()["mavlink"]
        before, t0 = d.status()["mavlink"]["sent"]["HEARTBEAT"], time.monotonic()
        time.sleep(4.0)
        missing_s = time.monotonic() - t0
        beats_while_missing = d.status()["mavlink"]["sent"]["HEARTBEAT"] - before
        conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
        try:
            assert wait_for(lambda: conn.recv_match(type="DISTANCE_SENSOR", blocking=True, timeout=0.5) is not None, 30.0)
            window_s = 5.0
            got = receive(conn, window_s)
            status = d.status()["mavlink"]
        finally:
            conn.close()
    finally:
        d.stop()
    # 1 Hz (not one per reconnect, every 0.2 s) while nobody listened; slack for a loaded machine.
    assert beats_while_missing <= missing_s + 1.5, (beats_while_missing, missing_s)
    ours = [m for _, m in got if m.get_srcSystem() == 1 and m.get_srcComponent() == 158]
    beats = [m for m in ours if m.get_type() == "HEARTBEAT"]
    distances = [m for m in ours if m.get_type() == "DISTANCE_SENSOR"]
    assert window_s - 1.5 <= len(beats) <= window_s + 1.5
    assert 0.6 * 10 * window_s <= len(distances) <= 10 * window_s + 3
    assert status["max_distance_from"].startswith("the profile's noise floor")
    for m in distances:
        assert m.orientation == 25  # PITCH_270, configured as a number
        assert m.min_distance == round(100 * status["min_distance_m"])
        # The reach follows the surface scale, re-measured with every rangefinder reading: it moves by a centimetre or so.
        assert m.max_distance == pytest.approx(100 * status["max_distance_m"], rel=0.02)
        assert m.min_distance <= m.current_distance <= m.max_distance
        assert m.current_distance == pytest.approx(100 * SEABED_M, abs=12)
        assert 0 < m.covariance < 255
    # The profile's reach, not the path-length bound (100 m): a few metres in this water.
    assert SEABED_M < status["max_distance_m"] < 50.0


def test_channel_reach_solves_the_model():
    # No attenuation, a point lamp: s/d² = floor, d = sqrt(s/floor) exactly.
    assert channel_reach_m(0.0, 400.0, 4.0) == pytest.approx(10.0, rel=1e-9)
    # With attenuation the model (orientation.transfer, square to the lamp) is at the floor there.
    d = channel_reach_m(0.3, 5e4, 20.0)
    assert transfer([0.3], 5e4, d, 1.0)[0] == pytest.approx(20.0, rel=1e-6)
    assert channel_reach_m(0.3, 5e4, 0.0) == math.inf and channel_reach_m(0.3, 1.0, 1e7) == 0.0
    # A lamp of radius r: s/(d + r)² = floor.
    assert channel_reach_m(0.0, 400.0, 4.0, lamp_radius=1.0) == pytest.approx(9.0, rel=1e-9)


def test_measurable_range_is_the_second_longest_reach_of_distinct_attenuations():
    # Reaches 10, 5 and 2.5 m (no attenuation, floors chosen for them): two channels to 5 m.
    assert measurable_range_m([0.0, 0.1, 0.2], [100.0, 100.0, 100.0], [1.0, 4.0, 16.0]) == pytest.approx(
        channel_reach_m(0.1, 100.0, 4.0))
    # Two channels of the same attenuation count once: a ratio between them says nothing.
    assert measurable_range_m([0.1, 0.1], [100.0, 100.0], [1.0, 1.0]) == 0.0
    assert measurable_range_m(np.array([0.05, 0.3]), [1e4, 1e4], [0.0, 0.0]) == math.inf


@pytest.mark.parametrize(("given", "name", "value"), [(25, "PITCH_270", 25), ("25", "PITCH_270", 25), (0, "NONE", 0),
                                                      ("MAV_SENSOR_ROTATION_YAW_90", "YAW_90", 2)])
def test_orientation_by_name_or_number(given, name, value):
    config = MavlinkConfig(orientation=given)
    assert (config.orientation, config.orientation_value) == (name, value)


def test_orientation_number_from_yaml_and_a_wrong_one(tmp_path):
    path = tmp_path / "uwcam.yaml"
    path.write_text("version: 1\nmavlink: {connection: 'udpout:127.0.0.1:14550', orientation: 25}\n")
    assert load_config(path).mavlink.orientation_value == 25
    for wrong in (99, -1, True):
        with pytest.raises(ValueError, match="orientation"):
            MavlinkConfig(orientation=wrong)
