"""The stream camera driver against a real RTSP server (GStreamer's gst-rtsp-server, started here)
streaming simulated frames of an 8-bit sRGB camera encoded as H.264 (x264) or MJPEG.

Needs Debian's gir1.2-gst-rtsp-server-1.0, gstreamer1.0-plugins-good and -ugly (see .ci/run).
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.waiting import wait_for
from uwcam.drivers.base import CameraSettings, HealthState
from uwcam.drivers.stream import StreamCamera
from uwcam.drivers.supervisor import SupervisedCamera
from uwcam.ranging.estimator import RangeEstimator
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation
from tests.ports import free_port

SERVER = Path(__file__).parent / "rtsp_server.py"
SIZE = (160, 120)
WATER = water_preset("jerlov-IB", [675.0, 575.0, 475.0])
LAMP = Lamp(position=(0.3, 0.0, 0.0))
CAMERA = CameraModel(bits=8, response="srgb")


class Server:
    """One gst-rtsp-server process; stop() and start() again on the same port."""

    def __init__(self, frames: Path, codec: str = "h264") -> None:
        self.frames, self.codec, self.port = frames, codec, free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"rtsp://127.0.0.1:{self.port}/cam"

    def start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, str(SERVER), str(self.port), str(self.frames), self.codec],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        ready, _, _ = select.select([self.proc.stdout], [], [], 30.0)
        line = self.proc.stdout.readline() if ready else ""
        if not line.startswith("ready"):
            self.stop()
            pytest.fail(f"the RTSP server did not start: {line.strip() or 'no answer in 30 s'}")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=10)
            self.proc.stdout.close()
            self.proc = None


@pytest.fixture(scope="module")
def plate(tmp_path_factory):
    """Four noisy frames of the grey plate at 1.5 m from an 8-bit sRGB camera, and the truth."""
    world = SimulatedWorld(scene="plate", distance=1.5, size=SIZE, water=WATER, lamp=LAMP, camera=CAMERA, seed=9)
    frames = np.stack([world.frame(k) for k in range(4)])
    path = tmp_path_factory.mktemp("rtsp") / "plate.npy"
    np.save(path, frames)
    return path, frames, world.camera_range


@pytest.fixture
def server(plate):
    s = Server(plate[0])
    s.start()
    yield s
    s.stop()


def test_frames_arrive_from_an_h264_rtsp_stream(server, plate):
    _, frames, _ = plate
    driver = StreamCamera(server.url, open_timeout_s=5.0, exposure_us=8000.0)
    with SupervisedCamera(driver, CameraSettings(), read_timeout_s=5.0, watchdog_s=10.0) as cam:
        got = [cam.get(20.0) for _ in range(5)]
        assert all(f is not None for f in got)
        assert cam.health.state == HealthState.OK and "h264 stream 160×120" in cam.device.model
    f = got[-1]
    assert f.data.shape == (120, 160, 3) and f.data.dtype == np.uint8 and f.exposure_us == 8000.0
    assert [g.sequence for g in got] == sorted(g.sequence for g in got)
    # The picture is the one sent: per-channel means within 2 codes of the source's (x264 at 4 Mbit/s).
    assert np.allclose(f.data.reshape(-1, 3).mean(0), frames.reshape(-1, 3).mean(0), atol=2.0)


@pytest.mark.slow
def test_stream_comes_back_after_the_server_restarts(server):
    driver = StreamCamera(server.url, open_timeout_s=3.0)
    cam = SupervisedCamera(driver, CameraSettings(), read_timeout_s=3.0, watchdog_s=6.0, backoff_s=(0.2, 1.0))
    with cam:
        assert cam.get(20.0) is not None
        server.stop()
        assert wait_for(lambda: cam.health.state != HealthState.OK, timeout_s=30.0), cam.health
        server.start()
        assert wait_for(lambda: cam.health.state == HealthState.OK, timeout_s=60.0), cam.health
        while cam.get(0.0) is not None:  # drop what was queued before the restart
            pass
        assert cam.get(30.0) is not None


@pytest.mark.slow
def test_a_plate_ranged_through_the_stream_is_within_the_codec_error(server, plate):
    """8-bit sRGB frames, H.264 at 4 Mbit/s: the profile's response curve linearises the decoded
    frames; range is expected within 1 % of that of the frames before encoding, and within 4 % of
    the truth (the uncompressed frames' own error is about 2 % here, see bench/gamma_accuracy.py)."""
    _, frames, truth = plate
    profile = calibrate_in_simulation(WATER, LAMP, SIZE, CAMERA, frames_per_distance=3)
    assert profile.response is not None
    estimator = RangeEstimator(profile)
    centre = (slice(40, 80), slice(60, 100))
    with SupervisedCamera(StreamCamera(server.url, open_timeout_s=5.0), CameraSettings(), read_timeout_s=5.0,
                          watchdog_s=10.0) as cam:
        streamed = [cam.get(20.0) for _ in range(4)]
    sent = np.nanmedian(estimator(frames[0]).range[centre])
    got = np.median([np.nanmedian(estimator(f.data).range[centre]) for f in streamed])
    expected = float(np.median(truth[centre]))
    assert abs(got / sent - 1) < 0.01, (got, sent)
    assert abs(got / expected - 1) < 0.04, (got, expected)


def test_mjpeg_over_rtsp_arrives_too(plate):
    s = Server(plate[0], codec="mjpeg")
    s.start()
    try:
        with SupervisedCamera(StreamCamera(s.url, open_timeout_s=5.0), CameraSettings(), read_timeout_s=5.0,
                              watchdog_s=10.0) as cam:
            frame = cam.get(20.0)
        assert frame is not None and frame.data.shape == (120, 160, 3)
        assert np.allclose(frame.data.reshape(-1, 3).mean(0), plate[1].reshape(-1, 3).mean(0), atol=3.0)
    finally:
        s.stop()


def test_stream_options_are_checked():
    from uwcam.drivers.base import ConfigurationError

    with pytest.raises(ConfigurationError, match="must start with one of rtsp://"):
        StreamCamera("/dev/video0")
    with pytest.raises(ConfigurationError, match="unknown RTSP transport 'quic'"):
        StreamCamera("rtsp://x/y", transport="quic")
    assert os.environ.get("OPENCV_FFMPEG_CAPTURE_OPTIONS") is None  # nothing left behind in the environment


def test_a_stream_rig_configuration_validates():
    from uwcam.drivers import registry
    from uwcam.drivers.base import ConfigurationError

    options = {"url": "rtsp://127.0.0.1:8554/video_stream_0", "transport": "tcp", "exposure_us": 10000}
    assert registry.validate_options("camera", "stream", options) == options
    with pytest.raises(ConfigurationError, match="camera driver 'stream'.*exposure_us"):
        registry.validate_options("camera", "stream", {"url": "rtsp://x:1/y", "exposure_us": -5})
    with pytest.raises(ConfigurationError, match="camera driver 'v4l2'.*white_balance_k"):
        registry.validate_options("camera", "v4l2", {"white_balance_k": 50})
