"""Aravis against its Fake camera, and GigE Vision over loopback with arv-fake-gv-camera-0.8."""

import shutil
import subprocess

import numpy as np
import pytest

from tests.waiting import wait_for
from uwcam.drivers.aravis import AravisCamera
from uwcam.drivers.base import CameraSettings, ConfigurationError, HealthState
from uwcam.drivers.supervisor import SupervisedCamera

FAKE_GV = "arv-fake-gv-camera-0.8"


def test_fake_camera_streams_rgb8_at_full_depth():
    driver = AravisCamera(fake=True, device_id="Fake_1")
    settings = CameraSettings(pixel_format="RGB8", exposure_us=2000.0, frame_rate=50.0)
    with SupervisedCamera(driver, settings, read_timeout_s=2.0) as cam:
        frames = [cam.get(10.0) for _ in range(3)]
        report = cam.report
    assert all(f is not None for f in frames)
    f = frames[-1]
    assert f.data.shape == (512, 512, 3) and f.data.dtype == np.uint8 and f.bit_depth == 8
    assert f.sequence > frames[0].sequence and f.device_timestamp_ns
    assert report.applied["PixelFormat"] == "RGB8" and report.applied["exposure_us"] == pytest.approx(2000.0)
    assert f.exposure_us == pytest.approx(2000.0) and f.gain_db is not None


def test_fake_camera_refuses_mono16_and_unknown_formats():
    driver = AravisCamera(fake=True, device_id="Fake_1")
    driver.open()
    try:
        with pytest.raises(ConfigurationError, match="pixel format Mono16 is monochrome"):
            driver.configure(CameraSettings(pixel_format="Mono16"))
        with pytest.raises(ConfigurationError, match="does not offer pixel format RGB12p; it offers .*RGB8, Mono16"):
            driver.configure(CameraSettings(pixel_format="RGB12p"))
    finally:
        driver.close()


@pytest.fixture
def fake_gv():
    """A GigE Vision camera on 127.0.0.1, started (and restartable) by the test."""
    assert shutil.which(FAKE_GV), f"{FAKE_GV} is missing: install Debian's aravis-tools (.ci/run does)"
    procs = []

    def start():
        proc = subprocess.Popen([FAKE_GV, "-i", "127.0.0.1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(proc)
        assert wait_for(lambda: any(d.serial_number == "GV01" for d in AravisCamera.list_devices()), 15.0)
        return proc

    yield start
    for proc in procs:
        proc.kill()
        proc.wait()


def test_gige_camera_over_loopback_recovers_after_it_vanishes(fake_gv):
    proc = fake_gv()
    driver = AravisCamera(serial_number="GV01")
    cam = SupervisedCamera(driver, CameraSettings(pixel_format="RGB8"), read_timeout_s=0.5, watchdog_s=1.0,
                           backoff_s=(0.1, 0.5))
    with cam:
        assert cam.get(10.0) is not None and cam.health.state == HealthState.OK
        assert cam.device.serial_number == "GV01"
        proc.kill()
        proc.wait()
        assert wait_for(lambda: cam.health.state != HealthState.OK, 15.0)
        assert cam.health.state in (HealthState.RECOVERING, HealthState.LOST)
        fake_gv()
        assert wait_for(lambda: cam.health.state == HealthState.OK, 30.0)
        while cam.get(0.0) is not None:
            pass
        frame = cam.get(10.0)
        assert frame is not None and frame.data.shape[-1] == 3 and frame.age_s < 2.0
        assert cam.stats.reconnects >= 1
