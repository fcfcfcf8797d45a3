"""Stopping the camera while its thread is inside a driver call that blocks (a stalled stream's
read returns only after FFmpeg's timeout, a GenTL open can take tens of seconds): the device is
closed by that thread when the call returns, never from stop() under the call (OpenCV's or an
SDK's release during its read is a native use after free), and the health stays "stopped"."""

from __future__ import annotations

import threading

import pytest

from uwcam.drivers.base import HealthState
from uwcam.drivers.sim import SimulatedCamera, SimulatedRig
from uwcam.drivers.supervisor import SupervisedCamera


@pytest.fixture
def blocking_camera(request):
    serial = f"SIM-{request.node.name[-20:]}"
    driver = SimulatedCamera(SimulatedRig(size=(64, 48), distance=2.0), fps=50.0, serial_number=serial)
    events: list[tuple[str, bool]] = []
    in_read, release_read = threading.Event(), threading.Event()
    read, close = driver.read, driver.close
    calls = []

    def blocking_read(timeout_s):
        calls.append(1)
        if len(calls) > 2:  # two frames, then a read that stalls until the test lets it go
            in_read.set()
            release_read.wait(10.0)
            events.append(("read returned", False))
        return read(timeout_s)

    def recording_close():
        events.append(("close", in_read.is_set() and not release_read.is_set()))
        close()

    driver.read, driver.close = blocking_read, recording_close
    yield driver, events, in_read, release_read
    release_read.set()
    SimulatedCamera.plug(serial)


def test_a_stop_during_a_blocking_read_leaves_the_close_to_the_camera_thread(blocking_camera):
    driver, events, in_read, release_read = blocking_camera
    cam = SupervisedCamera(driver, read_timeout_s=0.5, stop_wait_s=0.2)
    cam.start()
    assert in_read.wait(10.0)
    cam.stop()  # the thread is still in read(): nothing is closed under it
    assert ("close", True) not in events and not any(e == "close" for e, _ in events)
    assert cam.health.state == HealthState.STOPPED
    release_read.set()
    thread = next(t for t in threading.enumerate() if t.name == f"camera-{driver.name}")
    thread.join(5.0)
    assert not thread.is_alive()
    assert [e for e, _ in events] == ["read returned", "close"]  # closed once, by the thread, after its read
    assert cam.health.state == HealthState.STOPPED  # the late read did not report the camera recovering


def test_a_stop_with_the_thread_ended_closes_once(blocking_camera):
    driver, events, in_read, release_read = blocking_camera
    release_read.set()  # reads never stall
    cam = SupervisedCamera(driver, read_timeout_s=0.5)
    cam.start()
    assert cam.get(timeout_s=5.0) is not None
    cam.stop()
    assert [e for e, _ in events if e == "close"] == ["close"]
    assert cam.health.state == HealthState.STOPPED
