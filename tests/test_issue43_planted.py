"""Issue #43, items 30–34: tests for bugs that were planted in the newest modules and got through.
Each test here fails with its item's bug planted (checked by planting it)."""

from __future__ import annotations

import inspect
import time

import numpy as np
import pytest

from uwcam.optics.validity import Reason


# -- 30: the rule that two starts settling apart leave no range runs at the default two passes ----------

def test_blocks_whose_near_and_far_starts_settle_apart_lose_their_ranges_at_the_default_passes(monkeypatch):
    """At the default settings (``iterations`` 2), a block whose near start (the first pass's depth)
    and far start (open water) settle on different depths has no range (reason 3). The passes are
    the code's own; only the far start's answer is replaced, by a depth 50 % beyond the near one
    (both "settled"): every block that had a range loses it. The same run with the far start
    agreeing keeps its ranges, so the rule, not something else, removes them."""
    from tests.test_backscatter_unresolved import murky_cell
    from uwcam.ranging.images import range_images
    from uwcam.water import frame_compensator
    from uwcam.water.frame_compensator import BackscatterCompensator

    assert inspect.signature(BackscatterCompensator).parameters["iterations"].default == 2
    assert inspect.signature(range_images).parameters["iterations"].default == 2
    profile, frames, open_water, _ = murky_cell(distance=5.0, water_name="jerlov-IB")
    settle = BackscatterCompensator._settle

    def run(far_factor: float):
        calls = []

        def fake_settle(self, small, small_ambient, scale, depth, most):
            assert most == frame_compensator.MAX_PASSES  # more than one pass, as 2 iterations ask
            found, settled = settle(self, small, small_ambient, scale, depth, most)
            calls.append(found)
            if len(calls) % 2 == 0:  # the far start: the near one's depths, times far_factor, all settled
                near = calls[-2]
                return near * far_factor, np.ones_like(settled)
            return found, np.ones_like(settled)

        monkeypatch.setattr(BackscatterCompensator, "_settle", fake_settle)
        result = range_images(profile, frames, compensate=True, open_water=open_water)  # default passes
        assert len(calls) == 2, "both starts run at the default two passes"
        return result

    agreeing = run(1.0)
    kept = np.isfinite(agreeing.range)
    assert kept.mean() > 0.5
    apart = run(1.5)
    assert not np.isfinite(apart.range[kept]).any()
    assert np.all(apart.reasons[kept] == Reason.BACKSCATTER_ONLY)


# -- 31: the compiled water-light judge at exactly its limit ------------------------------------------------

@pytest.mark.parametrize("path", ["compiled", "numpy"])
def test_the_water_light_judge_at_exactly_its_limit_agrees_with_the_strict_rule(path):
    """A channel exactly at its limit is not above the water's light (``>``, not ``>=``), and one
    exactly at saturation is not below it: a pixel with one channel above and one exactly at the
    limit loses its range, compiled and in numpy alike, against the rule written out here."""
    from uwcam.water import water_light

    kernel = water_light._judge if path == "compiled" else water_light._judge_py
    if kernel is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(31)
    h, w, n = 6, 7, 3
    saturation = 4000.0
    limit = rng.uniform(100.0, 1000.0, (h, w, n)).astype(np.float32)
    # Per channel: above (limit + 50), exactly at the limit, below (limit − 50), or exactly saturated.
    choice = rng.integers(0, 4, (h, w, n))
    choice[0, 0] = (0, 1, 2)  # one above, one at the limit: loses
    choice[0, 1] = (0, 1, 1)
    choice[0, 2] = (0, 0, 1)  # two above: keeps
    choice[0, 3] = (0, 3, 2)  # one above, one saturated: loses
    frame = np.where(choice == 0, limit + 50, np.where(choice == 1, limit, np.where(choice == 2, limit - 50,
                                                                                  saturation))).astype(np.float32)
    assert np.sum(frame == limit) > 20
    active = np.ones(n, bool)
    range_m = rng.uniform(1.0, 5.0, (h, w)).astype(np.float32)
    variance = np.full((h, w), 0.01, np.float32)
    reasons = np.zeros((h, w), np.uint8)
    reasons[5, :3] = Reason.PATH_OUT_OF_BOUNDS
    reasons[5, 3:] = Reason.BELOW_NOISE_FLOOR
    expected_lost = (((frame > limit) & (frame < saturation)).sum(-1) < 2) & (
        (reasons == Reason.VALID) | (reasons == Reason.PATH_OUT_OF_BOUNDS))
    assert expected_lost[0, 0] and expected_lost[0, 1] and not expected_lost[0, 2] and expected_lost[0, 3]
    r0, q0 = range_m.copy(), reasons.copy()
    kernel(frame.reshape(h, -1), limit.reshape(h, -1), active, saturation, range_m, variance, reasons,
           np.uint8(Reason.BACKSCATTER_ONLY))
    np.testing.assert_array_equal(np.isnan(range_m), expected_lost)
    np.testing.assert_array_equal(np.isnan(variance), expected_lost)
    np.testing.assert_array_equal(reasons, np.where(expected_lost, np.uint8(Reason.BACKSCATTER_ONLY), q0))
    np.testing.assert_array_equal(range_m[~expected_lost], r0[~expected_lost])


# -- 32: the Zenoh preview waits for the bucket's level, not its capacity -------------------------------------

def test_no_zenoh_preview_before_the_bucket_holds_its_size():
    """The budget's bucket starts empty (no burst on joining): a preview is sent only once the
    bucket's level holds what it costs, however large its capacity."""
    from tests.test_zenoh import synthetic_published
    from uwcam.config import ZenohConfig
    from uwcam.outputs.zenoh_publisher import ZenohOutput

    class Session:
        def __init__(self):
            self.puts = []

        def put(self, key, payload, encoding=None):
            self.puts.append((key, len(payload)))

    out = ZenohOutput(None, ZenohConfig(key_prefix="t"))
    out._session = session = Session()
    r = np.full((120, 160), 3.0)
    published = synthetic_published(r, np.full_like(r, 0.01))
    wait = out._publish_preview(published, 100.0)
    assert session.puts == [] and out.previews == 0 and out._bucket.level == 0.0
    assert wait > 0
    size_bound = out._bucket.capacity  # the preview fits the capacity: only the level holds it back
    # Once the bucket has filled, the preview goes.
    wait = out._publish_preview(published, 100.0 + 2 * size_bound / out._bucket.rate)
    assert out.previews == 1 and {k for k, _ in session.puts} == {"t/range/preview/range", "t/range/preview/colour"}


# -- 33: a V4L2 camera left at its own exposure labels frames in µs ---------------------------------------------

def test_a_native_v4l2_camera_left_at_its_own_exposure_labels_frames_in_microseconds(monkeypatch, tmp_path):
    """No ``exposure_us`` configured: the exposure the camera holds is read back in 100 µs units
    (V4L2 spec) and frames are labelled with it in µs, not 100× short."""
    from tests.fake_v4l2 import FakeUVC, install
    from tests.test_v4l2_native import EXPOSURE, TABLE
    from uwcam.drivers.base import CameraSettings
    from uwcam.drivers.v4l2 import V4L2Camera

    fake = install(monkeypatch, FakeUVC(TABLE, str(tmp_path / "video0")))
    driver = V4L2Camera(device=fake.path)
    try:
        driver.open()
        assert driver.native
        driver.configure(CameraSettings(region=(0, 0, 320, 240)))
        held = fake.controls[EXPOSURE].value
        assert held == 156  # the table's default
        driver.start()
        frame = driver.read(2.0)
        assert frame.exposure_us == pytest.approx(held * 100.0)
    finally:
        driver.close()


# -- 34: a stream's end is a lost stream, promptly, and its reads back off ----------------------------------------

def test_a_stream_that_ends_leaves_ok_promptly_and_its_reads_back_off(monkeypatch):
    """A stream that ends (FFmpeg's read says no frame at once, every time: end of file, a server
    that closes) is not a timeout to sit out for the watchdog period: health leaves OK within a
    fraction of it, and the thread, reopening a stream that ends again at once, backs off instead
    of spinning (55,871 failed reads in 2 s were seen)."""
    import cv2

    from uwcam.drivers import stream as stream_module
    from uwcam.drivers.base import HealthState
    from uwcam.drivers.stream import StreamCamera
    from uwcam.drivers.supervisor import SupervisedCamera

    counts = {"reads": 0, "opens": 0}
    good = {"left": 5}

    class Capture:
        def __init__(self, *args, **kwargs):
            counts["opens"] += 1

        def isOpened(self):
            return True

        def get(self, prop):
            return 0.0

        def read(self):
            counts["reads"] += 1
            if good["left"] > 0:
                good["left"] -= 1
                return True, np.zeros((8, 8, 3), np.uint8)
            return False, None

        def release(self):
            pass

    monkeypatch.setattr(stream_module, "backend_available", lambda name: True)
    monkeypatch.setattr(stream_module.cv2, "VideoCapture", Capture)
    assert stream_module.cv2 is cv2
    cam = SupervisedCamera(StreamCamera("rtsp://127.0.0.1:1/x"), watchdog_s=2.0, backoff_s=(0.1, 5.0))
    cam.start()
    try:
        assert cam.get(2.0) is not None  # the stream ran (health OK) before it ended
        start = time.monotonic()
        while cam.health.state == HealthState.OK and time.monotonic() - start < 3.0:
            time.sleep(0.01)
        left_ok = time.monotonic() - start
        assert cam.health.state != HealthState.OK and left_ok < 0.5, left_ok
        reads = counts["reads"]
        time.sleep(1.5)
        # Backing off from 0.1 s, doubling: a handful of reopen-and-read cycles in 1.5 s, not thousands.
        assert counts["reads"] - reads <= 10, counts
        assert cam.health.state != HealthState.OK
    finally:
        cam.stop()
