"""The native V4L2 path against a fake kernel answering from a real UVC camera's control table.

The table is the Blue Robotics Low-Light HD USB Camera's (tests/data/bluerobotics-lowlight-uvc.txt,
which says where it was published). Expected values come from the V4L2 specification
(``V4L2_CID_EXPOSURE_ABSOLUTE`` counts 100 µs) and from that table, not from the driver.
"""

from __future__ import annotations

import errno
import os
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest

from tests.fake_v4l2 import DATA, FakeUVC, install, parse_table
from uwcam.drivers.base import CameraSettings, ConfigurationError, DeviceLost
from uwcam.drivers.pixels import BayerWarning
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.drivers.v4l2 import V4L2Camera

TABLE = DATA / "bluerobotics-lowlight-uvc.txt"
EXPOSURE = 0x009A0902
EXPOSURE_AUTO = 0x009A0901
AUTO_WB = 0x0098090C
WB_TEMPERATURE = 0x0098091A
GAMMA = 0x00980910
GAIN = 0x00980913


@pytest.fixture
def camera(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    driver = V4L2Camera(device=fake.path)
    yield fake, driver
    driver.close()


def test_the_recorded_table_is_what_the_fake_answers():
    controls, formats = parse_table(TABLE)
    assert (controls[EXPOSURE].minimum, controls[EXPOSURE].maximum, controls[EXPOSURE].default) == (1, 5000, 156)
    assert controls[EXPOSURE_AUTO].menu == {1: "Manual Mode", 3: "Aperture Priority Mode"}
    assert [f.fourcc for f in formats] == ["MJPG", "YUYV"]


def test_exposure_goes_to_the_device_in_100_us_units_and_frames_carry_the_read_back(camera):
    fake, driver = camera
    info = driver.open()
    assert driver.native and "native" in info.model
    report = driver.configure(CameraSettings(exposure_us=10_000.0, gain_db=0.0))
    # 10 ms is 100 units of 100 µs (V4L2 spec); ×10 or ÷10 would leave 1000 or 10 here.
    assert fake.controls[EXPOSURE].value == 100
    assert fake.controls[EXPOSURE_AUTO].value == 1  # manual mode, set before the exposure (else EACCES)
    assert report.applied["exposure_us"] == 10_000.0
    driver.start()
    frame = driver.read(2.0)
    assert frame.exposure_us == 10_000.0 and frame.gain_db == 0.0
    assert frame.device_timestamp_ns is not None and frame.data.shape == (1080, 1920, 3)


def test_pixels_scale_with_the_true_exposure(camera):
    """Twice the exposure doubles the signal the fake renders: units are right in the pixels too."""
    fake, driver = camera
    driver.open()
    means = []
    for exposure_us in (2000.0, 4000.0):
        driver.configure(CameraSettings(exposure_us=exposure_us, region=(0, 0, 640, 480)))
        driver.start()
        frame = driver.read(2.0)
        driver.stop()
        assert frame.exposure_us == exposure_us
        means.append(frame.data[240:, 320:].astype(float).mean(axis=(0, 1)))
    assert np.allclose(means[1] / means[0], 2.0, rtol=0.05)


def test_exposure_beyond_the_range_is_clamped_and_reported_with_the_range(camera):
    fake, driver = camera
    driver.open()
    report = driver.configure(CameraSettings(exposure_us=2_000_000.0))  # 2 s; the camera stops at 500 ms
    assert fake.controls[EXPOSURE].value == 5000
    assert report.applied["exposure_us"] == 500_000.0
    assert "100…500000 µs in steps of 100 µs" in report.details["exposure_us"]
    driver.start()
    assert driver.read(2.0).exposure_us == 500_000.0  # labelled with what the device did, not what was asked


def test_exposure_is_rounded_to_the_device_step(camera):
    fake, driver = camera
    driver.open()
    report = driver.configure(CameraSettings(exposure_us=1234.0))
    assert fake.controls[EXPOSURE].value == 12
    assert report.applied["exposure_us"] == 1200.0 and "asked 1234 µs" in report.details["exposure_us"]


def test_white_balance_is_fixed_and_gamma_set_to_unity(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    driver = V4L2Camera(device=fake.path, white_balance_k=5200.0)
    driver.open()
    report = driver.configure(CameraSettings())
    assert fake.controls[AUTO_WB].value == 0 and fake.controls[WB_TEMPERATURE].value == 5200
    assert report.applied["white_balance_k"] == 5200.0
    assert fake.controls[GAMMA].value == 100
    assert report.radiometry_not_disabled == []
    order = [cid for _, cid, _ in fake.log]
    assert order.index(AUTO_WB) < order.index(WB_TEMPERATURE)  # automatic mode off before the manual value
    driver.close()


def test_white_balance_out_of_range_is_reported_with_the_range(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    driver = V4L2Camera(device=fake.path, white_balance_k=9000.0)
    driver.open()
    report = driver.configure(CameraSettings())
    assert fake.controls[WB_TEMPERATURE].value == 6500
    assert report.applied["white_balance_k"] == 6500.0
    assert "2800…6500 in steps of 1" in report.details["white_balance_k"]
    driver.close()


def test_gain_without_a_unit_is_refused_with_what_the_camera_offers(camera):
    fake, driver = camera
    driver.open()
    report = driver.configure(CameraSettings(gain_db=6.0))
    assert "gain_db" in report.unsupported
    assert "0…100 in steps of 1" in report.details["gain_db"] and "gain_db_per_step" in report.details["gain_db"]
    assert fake.controls[GAIN].value == 0  # left alone


def test_gain_in_db_with_a_known_step(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0"), gain_per_step=0.1))
    driver = V4L2Camera(device=fake.path, gain_db_per_step=0.1)
    driver.open()
    report = driver.configure(CameraSettings(exposure_us=1000.0, gain_db=6.0))
    assert fake.controls[GAIN].value == 60 and report.applied["gain_db"] == pytest.approx(6.0)
    driver.start()
    assert driver.read(2.0).gain_db == pytest.approx(6.0)
    driver.close()


def test_formats_are_enumerated_and_an_absent_one_is_reported_with_the_list(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    driver = V4L2Camera(device=fake.path, fourcc="BYR2")
    driver.open()
    report = driver.configure(CameraSettings(exposure_us=1000.0))
    assert "pixel_format" in report.unsupported
    detail = report.details["pixel_format"]
    assert detail.startswith("BYR2 is not offered") and "MJPG (Motion-JPEG; compressed: 1920×1080" in detail
    assert "YUYV (YUYV 4:2:2: 1920×1080, 1280×720" in detail
    assert fake.format[0] == "YUYV"  # the uncompressed one is preferred over JPEG
    driver.close()


def test_an_unoffered_size_is_reported_with_the_sizes_offered(camera):
    fake, driver = camera
    driver.open()
    report = driver.configure(CameraSettings(region=(0, 0, 1000, 700)))
    assert fake.format[1:] == (1280, 720)
    assert "asked 1000×700, the camera gave 1280×720" in report.details["region"]


def test_yuyv_and_mjpeg_frames_decode_to_rgb(monkeypatch, tmp_path):
    for fourcc in ("YUYV", "MJPG"):
        fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / f"video-{fourcc}")))
        driver = V4L2Camera(device=fake.path, fourcc=fourcc)
        driver.open()
        driver.configure(CameraSettings(exposure_us=10_000.0, region=(0, 0, 320, 240)))
        driver.start()
        frame = driver.read(2.0)
        driver.close()
        assert frame.data.shape == (240, 320, 3) and frame.bit_depth == 8
        expected = np.clip(fake.linear_counts() / 256, 0, 255)
        corner = frame.data[10:100, 10:140].reshape(-1, 3).mean(axis=0)  # the coloured quadrant: R > G > B
        assert np.allclose(corner, expected[10:100, 10:140].reshape(-1, 3).mean(axis=0), atol=4), fourcc


def test_sixteen_bit_bayer_is_enumerated_and_kept_at_full_depth(monkeypatch, tmp_path):
    """A camera offering raw 16-bit Bayer (a synthetic table: these fourccs are V4L2's own)."""
    table = tmp_path / "raw-camera.txt"
    table.write_text(TABLE.read_text().split("[formats]")[0] + "[formats]\n"
                     "YUYV - YUYV 4:2:2: 640x480\n"
                     "BYR2 - 16-bit Bayer BGBG/GRGR: 640x480\n"
                     "GREY - 8-bit Greyscale: 640x480\n")
    fake = install(monkeypatch, FakeUVC(table, str(tmp_path / "video0")))
    driver = V4L2Camera(device=fake.path)
    driver.open()
    driver.configure(CameraSettings(exposure_us=20_000.0))
    assert fake.format[0] == "BYR2"  # the deepest offered is taken when none is asked for
    driver.start()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BayerWarning)
        frame = driver.read(2.0)
    driver.close()
    assert frame.data.dtype == np.uint16 and frame.bit_depth == 16
    truth = np.clip(fake.linear_counts(), 0, 65535)
    inner = (slice(20, 200), slice(20, 280))  # inside the coloured quadrant, away from its edges
    assert np.allclose(frame.data[inner].reshape(-1, 3).mean(axis=0), truth[inner].reshape(-1, 3).mean(axis=0),
                       rtol=0.01)
    # A monochrome format is refused with the reason.
    fake2 = install(monkeypatch, FakeUVC(table, str(tmp_path / "video1")))
    mono = V4L2Camera(device=fake2.path, fourcc="GREY")
    mono.open()
    with pytest.raises(ConfigurationError, match="monochrome"):
        mono.configure(CameraSettings())
    mono.close()


def test_h264_node_is_refused_with_the_stream_driver_named(monkeypatch, tmp_path):
    table = tmp_path / "h264.txt"
    table.write_text(TABLE.read_text().split("[formats]")[0] + "[formats]\nH264 compressed H.264: 1920x1080\n")
    fake = install(monkeypatch, FakeUVC(table, str(tmp_path / "video2")))
    driver = V4L2Camera(device=fake.path, fourcc="H264")
    driver.open()
    with pytest.raises(ConfigurationError, match="cannot be decoded frame by frame.*'stream' camera driver"):
        driver.configure(CameraSettings())
    driver.close()


def test_a_camera_held_by_another_program_says_so(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    fake.busy = True
    driver = V4L2Camera(device=fake.path)
    driver.open()
    driver.configure(CameraSettings())
    with pytest.raises(DeviceLost, match="busy.*mavlink-camera-manager"):
        driver.start()
    driver.close()


def test_supervised_native_camera_streams_and_exposure_changes_while_streaming(monkeypatch, tmp_path):
    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    cam = SupervisedCamera(V4L2Camera(device=fake.path), CameraSettings(exposure_us=5000.0, region=(0, 0, 320, 240)),
                           read_timeout_s=2.0)
    with cam:
        assert cam.get(5.0).exposure_us == 5000.0
        assert cam.driver.exposure_control == "common"
        cam.driver.set_exposure((7000.0,))
        assert fake.controls[EXPOSURE].value == 70
        # A frame captured before the change may still be on its way (a loaded machine): it carries
        # the old exposure, rightly; the frames after it the new one.
        seen = [cam.get(5.0).exposure_us]
        while seen[-1] != 7000.0 and len(seen) < 10:
            seen.append(cam.get(5.0).exposure_us)
        assert seen[-1] == 7000.0 and set(seen) <= {5000.0, 7000.0}, seen
        assert cam.status()["unsupported_settings"] == []


def test_opencv_fallback_converts_exposure_units_too(monkeypatch):
    """OpenCV's CAP_PROP_EXPOSURE on V4L2 is the same 100 µs control: the fallback converts."""
    import cv2

    sent = {}

    class Capture:
        def set(self, prop, value):
            sent[prop] = value
            return True

        def get(self, prop):
            return sent.get(prop, 0)

    driver = V4L2Camera(device="/dev/video9", backend="opencv")
    driver._cap = Capture()
    report = driver.configure(CameraSettings(exposure_us=10_000.0))
    assert sent[cv2.CAP_PROP_EXPOSURE] == 100 and report.applied["exposure_us"] == 10_000.0


def test_option_errors_are_clear():
    with pytest.raises(ConfigurationError, match="unknown V4L2 backend 'gst'"):
        V4L2Camera(backend="gst")
    with pytest.raises(ConfigurationError, match="native' drives V4L2 devices only"):
        V4L2Camera(api="any", backend="native")


def _loopback_device() -> str | None:
    for node in sorted(Path("/sys/class/video4linux").glob("video*")):
        if (node / "name").is_file() and "loopback" in (node / "name").read_text().lower():
            return f"/dev/{node.name}"
    return None


def test_native_path_on_v4l2loopback():
    """With a kernel V4L2 device (v4l2loopback), the native path reads what a writer puts in."""
    device = _loopback_device()
    if device is None:
        try:
            probe = subprocess.run(["modprobe", "v4l2loopback", "exclusive_caps=0"], capture_output=True, text=True,
                                   timeout=30)
            why = (probe.stderr or probe.stdout).strip() or f"modprobe exited {probe.returncode}"
        except FileNotFoundError:
            why = "no modprobe on this machine"
        device = _loopback_device()
        if device is None:
            pytest.skip(f"v4l2loopback is not loaded and cannot be loaded here ({why}); the native path is "
                        "tested against the recorded UVC table instead")
    fd = os.open(device, os.O_RDWR)
    try:
        from linuxpy.video.device import BufferType, set_format

        set_format(fd, BufferType.VIDEO_OUTPUT, 64, 48, "YUYV")
        frame = np.zeros((48, 64, 2), np.uint8)
        frame[..., 0], frame[..., 1] = 180, 128  # grey, Y=180
        os.write(fd, frame.tobytes())
        driver = V4L2Camera(device=device, fourcc="YUYV")
        driver.open()
        assert driver.native
        driver.configure(CameraSettings(region=(0, 0, 64, 48)))
        driver.start()
        for _ in range(3):
            os.write(fd, frame.tobytes())
        got = driver.read(5.0)
        driver.close()
        assert got.data.shape == (48, 64, 3) and abs(float(got.data.mean()) - 180) < 25
    except OSError as exc:
        if exc.errno in (errno.EBUSY, errno.EINVAL):
            pytest.fail(f"v4l2loopback refused the test's format: {exc}")
        raise
    finally:
        os.close(fd)
