"""The frame loop's queue policy: fresh queued frames are ranged in order, stale ones skipped."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.synthetic import make_profile
from tests.waiting import wait_for
from tests.queued_camera import QueuedCamera
from uwcam.config import ProcessingConfig
from uwcam.drivers.base import Frame
from uwcam.runtime import pipeline as pipeline_module
from uwcam.runtime.pipeline import QUEUED_FRAME_BUDGET_S, FramePipeline

BUDGET_S = 2.0
"""The budget the tests run with: far above any scheduling delay of a loaded test machine, so
"fresh" and "stale" are decided by the ages the tests give, not by how busy the machine is."""


def frame(sequence: int, age_s: float) -> Frame:
    data = np.full((8, 8, 3), (2000, 9000, 12000), np.uint16)
    return Frame(data=data, sequence=sequence, host_monotonic_ns=time.monotonic_ns() - int(age_s * 1e9),
                 wall_time=time.time(), lamp_on=True)


def run_with(ages_s: list[float]) -> tuple[list[int], list[tuple[int, str]]]:
    """Frames 1, 2, … of these ages queued at once, as after a stall; (ranged, unranged) sequences."""
    camera = QueuedCamera()
    pipeline = FramePipeline(camera, make_profile([0.46, 0.11, 0.06], [0, 0, 0]), ProcessingConfig())
    ranged, unranged = [], []
    pipeline.subscribe(lambda p: ranged.append(p.frame.sequence))
    pipeline.subscribe_unranged(lambda f, why: unranged.append((f.sequence, why)))
    frames = [frame(k, age) for k, age in enumerate(ages_s, start=1)]  # made after the set-up's compilation
    camera.put(*frames)
    pipeline.start()
    try:
        assert wait_for(lambda: len(ranged) + len(unranged) == len(frames), 10.0)
    finally:
        pipeline.stop()
    return ranged, unranged


@pytest.fixture(autouse=True)
def budget(monkeypatch):
    monkeypatch.setattr(pipeline_module, "QUEUED_FRAME_BUDGET_S", BUDGET_S)


def test_the_budget_keeps_latency_within_the_daemons_goal():
    assert 0.0 < QUEUED_FRAME_BUDGET_S < 0.05  # p99 capture → send < 50 ms


def test_fresh_queued_frames_are_all_ranged_in_order():
    # A stall of a few milliseconds left three frames queued, each younger than the budget.
    ranged, unranged = run_with([0.0, 0.0, 0.0])
    assert ranged == [1, 2, 3] and unranged == []


def test_stale_frames_are_skipped_for_the_newest_and_counted():
    stale = 3 * BUDGET_S
    ranged, unranged = run_with([stale, stale, 0.0])
    assert ranged == [3]
    assert unranged == [(1, "skipped for newer"), (2, "skipped for newer")]


def test_a_stale_frame_with_nothing_newer_is_still_ranged():
    ranged, unranged = run_with([3 * BUDGET_S])
    assert ranged == [1] and unranged == []


def test_an_open_water_request_takes_only_frames_captured_after_it_and_before_its_deadline():
    """A loop that fell behind still holds frames captured before the request (the camera may not
    have faced open water yet): they are ranged, not averaged into the open-water frame. A frame
    captured after the deadline lapses the request however soon it is processed."""
    camera = QueuedCamera()
    pipeline = FramePipeline(camera, make_profile([0.46, 0.11, 0.06], [0, 0, 0]), ProcessingConfig())
    ranged = []
    pipeline.subscribe(lambda p: ranged.append(p.frame.sequence))
    pipeline.start()
    try:
        before = [frame(k, 0.05) for k in (1, 2)]  # captured 50 ms before the request
        done = pipeline.request_open_water(frames=2, timeout_s=30.0)
        camera.put(*before)
        assert wait_for(lambda: len(ranged) == 2, 10.0)
        assert not done.is_set() and pipeline.backscatter_status()["capture"] == "capturing"
        camera.put(frame(3, 0.0), frame(4, 0.0))  # after it: these two make the open-water frame
        assert done.wait(10.0)
        assert pipeline.open_water_info["frames"] == 2
        assert np.array_equal(pipeline.open_water, before[0].data.astype(np.float32))

        pipeline.request_open_water(frames=2, timeout_s=0.2)
        late = frame(5, 0.0)
        late.host_monotonic_ns += int(0.5e9)  # stamped 0.3 s past the deadline (a clock seen ahead)
        camera.put(late)
        assert wait_for(lambda: 5 in ranged, 10.0)
        assert pipeline.backscatter_status()["capture"].startswith("lapsed: 0 of 2 lamp-lit frames came within 0.2 s")
    finally:
        pipeline.stop()
