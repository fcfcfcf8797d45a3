"""One ranging path: ``uwcam range``, the daemon's frame loop and ``uwcam reprocess`` give the same
frame, with the same profile and settings, bit-identical range, variance and reasons — with
backscatter compensated (the command line used to leave out the model's uncertainty the loop has)
and with the water's own light judged per pixel (an open-water frame's)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.waiting import wait_for
from tests.queued_camera import QueuedCamera
from uwcam.recording import format as rec
from uwcam.cli import main
from uwcam.config import BackscatterConfig, ProcessingConfig, RecordingConfig
from uwcam.drivers.base import Frame
from uwcam.recording.recorder import Recorder
from uwcam.runtime.pipeline import FramePipeline
from uwcam.calibration.profile import save_profile
from uwcam.recording.reprocess import reprocess
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
from uwcam.simulation.tank import calibrate_in_simulation

SIZE = (80, 60)
WATER = water_preset("jerlov-II", [675.0, 575.0, 475.0])
LAMP = Lamp(position=(0.3, 0.0, 0.0))


@pytest.fixture(scope="module")
def setting():
    """A profile calibrated in jerlov-II with the lamp 0.3 m aside, a seabed 4 m away and an open-water frame."""
    profile = calibrate_in_simulation(WATER, LAMP, SIZE, CameraModel(), frames_per_distance=2)
    scene = SimulatedWorld(scene="seabed", distance=4.0, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                           material="grey", seed=5)
    water = SimulatedWorld(scene="open-water", distance=4.0, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                           fixed_exposure=scene.exposure, seed=6)
    return profile, scene.frame(0), water.frame(0), water.frame(1)


def image(msg):
    """A foxglove.RawImage decoded from its documented layout."""
    dtype = {"32FC1": "<f4", "mono8": "u1"}[msg.encoding]
    return np.frombuffer(msg.data, dtype=dtype).reshape(msg.height, msg.width)


def decoded(path, topic):
    with open(path, "rb") as fh:
        reader = rec.open_reader(fh)
        return [(m.log_time, d) for _s, _c, m, d in reader.iter_decoded_messages(topics=[topic])]


@pytest.mark.slow
@pytest.mark.parametrize("compensate, smoothing", [(False, "none"), (True, "none"), (False, "adaptive")],
                         ids=["plain", "compensated", "adaptive-windows"])
def test_cli_loop_and_reprocess_give_bit_identical_results(setting, tmp_path, compensate, smoothing, capsys):
    profile, frame, open_water, _ = setting
    save_profile(profile, tmp_path / "p.yaml")
    np.save(tmp_path / "f.npy", frame)
    np.save(tmp_path / "ow.npy", open_water)
    args = ["range", str(tmp_path / "p.yaml"), str(tmp_path / "f.npy"), "-o", str(tmp_path / "r.npy"),
            "--variance", str(tmp_path / "v.npy"), "--reasons", str(tmp_path / "c.npy"), "--open-water", str(tmp_path / "ow.npy")]
    # Adaptive windows with a target most of this seabed's pixels miss alone: most are ranged from windows.
    adaptive = ["--smoothing", "adaptive", "--smoothing-target", "0.01"] if smoothing == "adaptive" else []
    assert main(args + (["--compensate-backscatter"] if compensate else []) + adaptive) == 0, capsys.readouterr().err
    cli = [np.load(tmp_path / n) for n in ("r.npy", "v.npy", "c.npy")]

    camera = QueuedCamera()
    processing = ProcessingConfig(backscatter=BackscatterConfig() if compensate else None, smoothing=smoothing,
                                  smoothing_target=0.01)
    pipeline = FramePipeline(camera, profile, processing)
    pipeline.set_open_water(open_water.astype(np.float32))  # raw, no ambient light here
    published = []
    pipeline.subscribe(published.append)
    # results: true, so the live depth, variance and reasons are in the file to compare with.
    recorder = Recorder(pipeline, RecordingConfig(folder=str(tmp_path / "rec"), chunk_kb=64, results=True))
    path = str(tmp_path / "dive.mcap")
    recorder.start(path)
    pipeline.start()
    try:
        camera.put(*(Frame(data=frame.copy(), sequence=k, host_monotonic_ns=time.monotonic_ns(),
                           wall_time=time.time() + k * 1e-3, lamp_on=True) for k in range(2)))
        assert wait_for(lambda: len(published) == 2, 60.0)
    finally:
        pipeline.stop()
        recorder.stop()
    loop = published[-1].result
    assert published[-1].water_source == "open-water frame"
    for a, b in zip(cli, (loop.range, loop.variance, loop.reasons)):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
    assert np.isfinite(loop.range).mean() > 0.5
    if smoothing == "adaptive":  # the windows were used: the maps differ from the pixels' own
        single = main(args[:5] + ["--variance", str(tmp_path / "v1.npy"), "--open-water", str(tmp_path / "ow.npy")])
        assert single == 0 and not np.array_equal(np.load(tmp_path / "v1.npy"), cli[1], equal_nan=True)

    out = str(tmp_path / "again.mcap")
    reprocess([path], out, progress=False)
    for topic in (rec.DEPTH, rec.VARIANCE, rec.REASONS):
        live, again = decoded(path, topic), decoded(out, topic)
        assert len(live) == 2 and [t for t, _ in live] == [t for t, _ in again]
        for (_, a), (_, b) in zip(live, again):
            assert np.array_equal(image(a), image(b), equal_nan=True)
    reasons = image(decoded(out, rec.REASONS)[-1][1])
    assert np.array_equal(reasons, cli[2])


def test_range_fuses_several_images_and_refuses_mismatched_ones(setting, tmp_path, capsys):
    """`uwcam range PROFILE A B C`: one map from the frames' mean; the same frame given three times
    is that frame with a third of its temporal noise variance (the fixed pattern's stays), so its
    variance falls by less than 3; images of another size are refused with one line."""
    profile, frame, _, _ = setting
    save_profile(profile, tmp_path / "p.yaml")
    np.save(tmp_path / "a.npy", frame)
    np.save(tmp_path / "small.npy", frame[:-2])
    out = [str(tmp_path / n) for n in ("r.npy", "v.npy")]
    assert main(["range", str(tmp_path / "p.yaml"), str(tmp_path / "a.npy"), "-o", out[0], "--variance", out[1]]) == 0
    one = [np.load(p) for p in out]
    assert main(["range", str(tmp_path / "p.yaml"), *[str(tmp_path / "a.npy")] * 3, "-o", out[0], "--variance", out[1]]) == 0
    three = [np.load(p) for p in out]
    both = np.isfinite(one[0]) & np.isfinite(three[0])
    assert both.mean() > 0.5
    # The channels' weights shift (the fixed pattern's share differs by channel), so the fused range
    # moves a little where the channels disagree (this water's light); the variance falls, by at most 3.
    np.testing.assert_allclose(three[0][both], one[0][both], rtol=0.05)
    ratio = one[1][both] / three[1][both]
    assert np.all(ratio > 1.0) and np.all(ratio <= 3.0 * (1 + 1e-5)), (ratio.min(), ratio.max())
    capsys.readouterr()
    assert main(["range", str(tmp_path / "p.yaml"), str(tmp_path / "a.npy"), str(tmp_path / "small.npy"), "-o", out[0]]) == 2
    err = capsys.readouterr().err.strip()
    assert "image 2 is 80×58" in err and "image 1 is 80×60" in err and len(err.splitlines()) == 1


def test_a_compensator_built_for_a_profile_replaced_meanwhile_is_not_kept(setting, monkeypatch):
    """A frame in flight builds the compensator of its own profile (slow on a loaded machine); a new
    profile put in use meanwhile brings its own, which that build must not replace: else the new
    profile ranges with the old one's water light from then on."""
    import threading

    profile, frame, _, _ = setting
    pipeline = FramePipeline(QueuedCamera(), profile, ProcessingConfig())
    old_profile, old_processing, old_estimator = pipeline.profile, pipeline.processing, pipeline.estimator
    assert pipeline._compensator is None  # no frame yet: the loop builds it on the first
    make, building, release = pipeline._make_compensator, threading.Event(), threading.Event()

    def slow(*args):
        building.set()
        assert release.wait(30.0)
        return make(*args)

    monkeypatch.setattr(pipeline, "_make_compensator", slow)
    incoming = Frame(data=frame.copy(), sequence=1, host_monotonic_ns=time.monotonic_ns(), wall_time=time.time(), lamp_on=True)
    in_flight = threading.Thread(target=pipeline._compensation, args=(incoming, old_processing, old_profile, old_estimator, None))
    in_flight.start()
    assert building.wait(30.0)
    monkeypatch.setattr(pipeline, "_make_compensator", make)
    pipeline._frame_shape = frame.shape  # frames have come: set_profile builds its compensator ahead
    replacement = profile.model_copy(update={"name": "replacement"})
    pipeline.set_profile(replacement)
    ours = pipeline._compensator
    assert ours is not None and ours.built_from[0] is replacement
    release.set()
    in_flight.join(30.0)
    assert pipeline._compensator is ours


@pytest.mark.slow
def test_a_captured_open_water_mean_keeps_its_count_in_the_loop_and_in_reprocessing(setting, tmp_path):
    """The daemon's open-water capture keeps the mean of its frames and how many there were: the
    loop finds each pixel's response from it, the recording says the count, and reprocessing
    ranges the frame bit-identically with it; the same mean taken for a single frame ranges otherwise."""
    import json

    profile, frame, _, _ = setting
    view = SimulatedWorld(scene="open-water", distance=4.0, size=SIZE, water=WATER, lamp=LAMP, camera=CameraModel(),
                          fixed_exposure=SimulatedWorld(scene="seabed", distance=4.0, size=SIZE, water=WATER, lamp=LAMP,
                                                        camera=CameraModel()).exposure, seed=6)
    mean = np.mean([view.frame(i) for i in range(8)], axis=0).astype(np.float32)

    def live(info: dict, folder: str):
        camera = QueuedCamera()
        pipeline = FramePipeline(camera, profile, ProcessingConfig(backscatter=BackscatterConfig()))
        pipeline.set_open_water(mean, info)
        published = []
        pipeline.subscribe(published.append)
        recorder = Recorder(pipeline, RecordingConfig(folder=str(tmp_path / folder), chunk_kb=64, results=True))
        path = str(tmp_path / f"{folder}.mcap")
        recorder.start(path)
        pipeline.start()
        try:
            camera.put(Frame(data=frame.copy(), sequence=0, host_monotonic_ns=time.monotonic_ns(), wall_time=time.time(),
                             lamp_on=True))
            assert wait_for(lambda: len(published) == 1, 60.0)
        finally:
            pipeline.stop()
            recorder.stop()
        assert (pipeline._compensator.model.response is not None) == (info.get("frames", 1) > 1)
        return published[0], path

    eight, path = live({"frames": 8, "source": "test"}, "eight")
    one, _ = live({"source": "test"}, "one")
    assert eight.open_water_frames == 8 and one.open_water_frames == 1
    assert not np.array_equal(eight.result.range, one.result.range, equal_nan=True)
    records = [json.loads(d) if isinstance(d, (bytes, str)) else d for _, d in decoded(path, rec.RANGING)]
    assert records and all(r["open_water_frames"] == 8 for r in records)
    out = str(tmp_path / "again.mcap")
    reprocess([path], out, progress=False)
    for topic in (rec.DEPTH, rec.VARIANCE, rec.REASONS):
        (_, a), = decoded(path, topic)
        (_, b), = decoded(out, topic)
        assert np.array_equal(image(a), image(b), equal_nan=True)
