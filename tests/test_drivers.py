"""Camera drivers under supervision: frames, faults and recovery, against real peers where they exist."""

import os
import time
import warnings

import cv2
import genicam
import numpy as np
import pytest

from tests.waiting import wait_for
from uwcam.drivers import registry
from uwcam.drivers.base import CameraSettings, ConfigurationError, DeviceLost, HealthState
from uwcam.drivers.genicam import GenTLCamera, find_producers
from uwcam.drivers.pixels import BayerWarning, assemble_components, decode, unpack_10p, unpack_12p
from uwcam.drivers.replay import ReplayCamera
from uwcam.drivers.sim import SimulatedCamera, SimulatedRig
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.drivers.v4l2 import V4L2Camera

# Compile the simulator before any test waits for a frame against a clock.
pytestmark = pytest.mark.usefixtures("warm_kernels")

VIKY = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")


@pytest.fixture
def rig():
    return SimulatedRig(size=(64, 48), distance=2.0)


@pytest.fixture
def serial(request):
    s = f"SIM-{request.node.name[-20:]}"
    yield s
    SimulatedCamera.plug(s)
    SimulatedCamera.stall(s, False)


def test_registry_names_drivers_and_explains_unknown_ones():
    assert {"sim", "replay", "genicam", "v4l2", "aravis"} <= set(registry.known("camera"))
    with pytest.raises(ConfigurationError, match="unknown camera driver 'gige'; known camera drivers: aravis, genicam, multi, replay, sim, stream, v4l2"):
        registry.create("camera", "gige")
    with pytest.raises(ConfigurationError, match="camera driver 'sim': .*unexpected keyword argument 'colour'"):
        registry.create("camera", "sim", colour="red")
    assert isinstance(registry.create("camera", "sim", fps=5.0, size=(32, 24)), SimulatedCamera)


def test_simulated_camera_streams_with_metadata(rig, serial):
    with SupervisedCamera(SimulatedCamera(rig, fps=50.0, serial_number=serial)) as cam:
        frames = [cam.get(timeout_s=5.0) for _ in range(5)]
        assert cam.health.state == HealthState.OK
    assert all(f is not None for f in frames)
    assert [f.sequence for f in frames] == sorted(f.sequence for f in frames)
    f = frames[-1]
    assert f.data.shape == (48, 64, 3) and f.data.dtype == np.uint16 and f.lamp_on is True
    assert f.host_monotonic_ns <= time.monotonic_ns() and f.age_s >= 0
    assert cam.health.state == HealthState.STOPPED


def test_the_simulated_sensor_renders_at_the_lowest_priority_and_the_caller_alone_is_lowered(rig, serial):
    """The thread that reads the simulated camera (the supervisor's) renders at nice 19, read
    from the kernel for that thread; the rest of the process keeps its priority."""
    import threading

    cam = SimulatedCamera(rig, fps=100.0, serial_number=serial)
    cam.open()
    cam.start()
    seen = {}

    def read() -> None:
        cam.read(5.0)
        seen["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    reader = threading.Thread(target=read)
    reader.start()
    reader.join(30.0)
    cam.close()
    assert seen["nice"] == 19
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == before


def test_lamp_off_leaves_dark_current_only(rig, serial):
    cam = SimulatedCamera(rig, fps=100.0, serial_number=serial)
    cam.open(); cam.start()
    lit = cam.read(1.0).data.mean()
    rig.lamp_on = False
    dark = cam.read(1.0)
    cam.close()
    assert dark.lamp_on is False and dark.data.mean() < 0.05 * lit
    assert abs(dark.data.mean() - rig.world.camera.dark_level_dn) < 2.0


def test_full_queue_drops_the_oldest_frame(rig, serial):
    with SupervisedCamera(SimulatedCamera(rig, fps=200.0, serial_number=serial), queue_size=2) as cam:
        assert wait_for(lambda: cam.stats.dropped >= 3)
        a, b = cam.get(1.0), cam.get(1.0)
    assert b.sequence > a.sequence > cam.stats.dropped  # the newest survive; the dropped were the oldest


def test_unplugged_camera_recovers_by_itself(rig, serial):
    cam = SupervisedCamera(SimulatedCamera(rig, fps=50.0, serial_number=serial), backoff_s=(0.05, 0.2), lost_after_s=0.5)
    with cam:
        assert cam.get(5.0) is not None
        SimulatedCamera.unplug(serial)
        assert wait_for(lambda: cam.health.state != HealthState.OK)
        assert cam.health.state in (HealthState.RECOVERING, HealthState.LOST)
        assert "unplugged" in cam.health.reason
        assert wait_for(lambda: cam.health.state == HealthState.LOST)
        SimulatedCamera.plug(serial)
        assert wait_for(lambda: cam.health.state == HealthState.OK)
        while cam.get(0.0) is not None:
            pass  # drain what came before
        fresh = cam.get(5.0)
        assert fresh is not None and fresh.age_s < 1.0
        assert cam.stats.reconnects >= 1
        assert cam.device.serial_number == serial


def test_silent_camera_trips_the_watchdog(rig, serial):
    cam = SupervisedCamera(SimulatedCamera(rig, fps=50.0, serial_number=serial), read_timeout_s=0.1, watchdog_s=0.3,
                           backoff_s=(0.05, 0.1))
    with cam:
        assert cam.get(5.0) is not None
        SimulatedCamera.stall(serial)
        assert wait_for(lambda: "no frame for" in cam.health.reason or cam.health.state != HealthState.OK)
        assert cam.health.state != HealthState.OK
        SimulatedCamera.stall(serial, False)
        assert wait_for(lambda: cam.health.state == HealthState.OK)


def test_damaged_frame_is_dropped_and_counted(rig, serial):
    with SupervisedCamera(SimulatedCamera(rig, fps=50.0, serial_number=serial)) as cam:
        assert cam.get(5.0) is not None
        SimulatedCamera.corrupt_next(serial)
        assert wait_for(lambda: cam.stats.corrupt == 1)
        assert cam.get(5.0) is not None and cam.health.state == HealthState.OK


def test_absent_camera_is_a_clear_error_at_start(rig, serial):
    SimulatedCamera.unplug(serial)
    with pytest.raises(DeviceLost, match="unplugged"):
        SupervisedCamera(SimulatedCamera(rig, serial_number=serial)).start()


def test_replay_folder_loops_or_ends(tmp_path):
    for k in range(3):
        np.save(tmp_path / f"f{k}.npy", np.full((4, 5, 3), k, np.uint16))
    with SupervisedCamera(ReplayCamera(str(tmp_path), fps=100.0, loop=True)) as cam:
        values = [int(cam.get(5.0).data[0, 0, 0]) for _ in range(5)]
    assert values == [0, 1, 2, 0, 1]
    with SupervisedCamera(ReplayCamera(str(tmp_path), fps=100.0, loop=False)) as cam:
        assert wait_for(lambda: cam.health.state == HealthState.STOPPED)
        assert "finished (3 frames)" in cam.health.reason
    with pytest.raises(ConfigurationError, match="neither a folder of frames nor a video"):
        ReplayCamera(str(tmp_path / "nothing.xyz"))


def write_video(path, frames=6, size=(32, 24)):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, size)
    assert writer.isOpened()
    for k in range(frames):
        img = np.zeros((size[1], size[0], 3), np.uint8)
        img[..., 2] = 200  # red in BGR
        img[..., 0] = 10 * k
        writer.write(img)
    writer.release()


def test_replay_video_plays_in_rgb_order(tmp_path):
    video = tmp_path / "dive.avi"
    write_video(video)
    with SupervisedCamera(ReplayCamera(str(video), fps=200.0)) as cam:
        frame = cam.get(5.0)
    assert frame.data.shape == (24, 32, 3) and frame.data[..., 0].mean() > 150  # red first


def test_v4l2_driver_logic_on_a_file(tmp_path):
    """No video device here: the same driver code runs against OpenCV's file backend."""
    video = tmp_path / "uvc.avi"
    write_video(video)
    driver = V4L2Camera(device=str(video), api="any")
    cam = SupervisedCamera(driver, CameraSettings(exposure_us=1000.0, gain_db=2.0), backoff_s=(0.05, 0.1))
    with cam:
        frame = cam.get(5.0)
        assert frame.data.shape == (24, 32, 3) and frame.channel_names == ("R", "G", "B")
        # A file has no exposure control: all of it is reported, nothing silently ignored.
        assert "auto exposure" in cam.report.radiometry_not_disabled
        assert {"exposure_us", "gain_db"} <= set(cam.report.unsupported)
    with pytest.raises(DeviceLost, match="does not exist"):
        V4L2Camera(device="/dev/video-absent").open()
    with pytest.raises(ConfigurationError, match="unknown OpenCV api 'gst'"):
        V4L2Camera(api="gst")


def test_genicam_streams_from_the_gentl_simulator():
    devices = GenTLCamera.list_devices(cti=VIKY)
    assert len(devices) >= 1 and all(d.serial_number for d in devices)
    driver = GenTLCamera(cti=VIKY, serial_number=devices[0].serial_number)
    with SupervisedCamera(driver, CameraSettings(pixel_format="RGBa8", exposure_us=500.0), read_timeout_s=3.0) as cam:
        frames = [cam.get(10.0) for _ in range(3)]
        report = cam.report
    assert all(f is not None for f in frames)
    f = frames[-1]
    assert f.data.ndim == 3 and f.data.shape[-1] == 3 and f.data.dtype == np.uint8  # alpha dropped
    assert frames[-1].sequence > frames[0].sequence
    assert report.applied["PixelFormat"] == "RGBa8"
    assert f.exposure_us is None and f.gain_db is None  # the simulator has neither node
    assert "ExposureTime" in report.unsupported  # the simulator has no exposure node, and we say so
    # Nor exposure selectors: no per-channel exposure, and no exposure control at all (nor HDR).
    assert driver.exposure_control == "" and f.channel_exposure_us is None


def test_genicam_refuses_mono_and_missing_producers(monkeypatch, tmp_path):
    driver = GenTLCamera(cti=VIKY)
    driver.open()
    try:
        with pytest.raises(ConfigurationError, match="pixel format Mono8 is monochrome; ranging needs two or more colour"):
            driver.configure(CameraSettings(pixel_format="Mono8"))
        with pytest.raises(ConfigurationError, match="does not offer pixel format RGB12p; it offers RGBa8, Mono8"):
            driver.configure(CameraSettings(pixel_format="RGB12p"))
    finally:
        driver.close()
    with pytest.raises(ConfigurationError, match="GenTL producer /nope.cti does not exist"):
        GenTLCamera(cti="/nope.cti")
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(tmp_path))
    with pytest.raises(ConfigurationError, match="no GenTL producer: set 'cti'"):
        find_producers()
    monkeypatch.setenv("GENICAM_GENTL64_PATH", os.path.dirname(VIKY))
    assert find_producers() == [VIKY]


def pack_10p(values):
    v = np.asarray(values, np.uint64).reshape(-1, 4)
    word = v[:, 0] | (v[:, 1] << 10) | (v[:, 2] << 20) | (v[:, 3] << 30)
    return np.stack([(word >> (8 * k)) & 0xFF for k in range(5)], axis=1).astype(np.uint8).reshape(-1)


def pack_12p(values):
    v = np.asarray(values, np.uint32).reshape(-1, 2)
    word = v[:, 0] | (v[:, 1] << 12)
    return np.stack([(word >> (8 * k)) & 0xFF for k in range(3)], axis=1).astype(np.uint8).reshape(-1)


def test_packed_formats_unpack_exactly():
    rng = np.random.default_rng(0)
    v10 = rng.integers(0, 1024, 4 * 30)
    v12 = rng.integers(0, 4096, 2 * 45)
    np.testing.assert_array_equal(unpack_10p(pack_10p(v10), v10.size), v10)
    np.testing.assert_array_equal(unpack_12p(pack_12p(v12), v12.size), v12)
    rgb = rng.integers(0, 4096, (6, 5, 3))
    img, bits = decode("RGB12p", pack_12p(rgb.reshape(-1)), 5, 6)
    assert bits == 12 and np.array_equal(img, rgb)


def test_formats_keep_rgb_order_and_depth():
    bgr = np.array([[[1, 2, 3]]], np.uint8)
    img, bits = decode("BGR8", bgr.reshape(-1), 1, 1)
    assert img.tolist() == [[[3, 2, 1]]] and bits == 8
    rgb16 = np.array([[[1000, 40000, 65535]]], np.uint16)
    img, bits = decode("RGB16", rgb16.view(np.uint8).reshape(-1), 1, 1)
    assert img.dtype == np.uint16 and img.tolist() == [[[1000, 40000, 65535]]]
    mosaic = np.full((4, 4), 100, np.uint8)
    with pytest.warns(BayerWarning, match="Bayer mosaic"):
        img, _ = decode("BayerRG8", mosaic.reshape(-1), 4, 4)
    assert img.shape == (4, 4, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert assemble_components([np.zeros((3, 4), np.uint16)] * 3).shape == (3, 4, 3)


def test_multi_sensor_camera_assembles_one_frame_from_three_gentl_devices():
    """The GenTL simulator's three devices stand in for a 3-chip camera's sensors."""
    serials = [d.serial_number for d in GenTLCamera.list_devices(cti=VIKY)][:3]
    sensors = [{"driver": "genicam", "cti": VIKY, "serial_number": s, "channel": k} for k, s in enumerate(serials)]
    driver = registry.create("camera", "multi", sensors=sensors, channel_names=("R", "G", "B"), max_skew_ms=200.0)
    with SupervisedCamera(driver, CameraSettings(pixel_format="RGBa8"), read_timeout_s=3.0) as cam:
        frame = cam.get(15.0)
        assert cam.device.serial_number == "+".join(serials)
    assert frame is not None and frame.data.shape[-1] == 3 and frame.channel_names == ("R", "G", "B")
    with pytest.raises(ConfigurationError, match="needs two or more sensors"):
        registry.create("camera", "multi", sensors=[{"driver": "sim"}])
    with pytest.raises(ConfigurationError, match="sensor 1 needs a 'driver'"):
        registry.create("camera", "multi", sensors=[{"driver": "sim"}, {"channel": 1}])


def test_genicam_recovers_when_the_sdk_fails_mid_stream():
    """An SDK error mid-stream (fault injected at harvesters' fetch) is survived: close, reopen by serial, stream."""
    driver = GenTLCamera(cti=VIKY)
    cam = SupervisedCamera(driver, CameraSettings(pixel_format="RGBa8"), read_timeout_s=3.0, backoff_s=(0.05, 0.2))
    with cam:
        assert cam.get(10.0) is not None
        serial = cam.device.serial_number

        def broken(**_):
            raise RuntimeError("transport layer error (cable pulled)")

        driver._acquirer.fetch = broken
        assert wait_for(lambda: cam.stats.reconnects >= 1 and cam.health.state == HealthState.OK, 20.0)
        while cam.get(0.0) is not None:
            pass
        assert cam.get(10.0) is not None
        assert cam.device.serial_number == serial
