"""recording.budget_mb_s: raw frames decimated to fit the disk budget, every frame's metadata and
ranging record and the previews kept, decimation counted, and the hours the disk holds."""

from __future__ import annotations

import json
import shutil

import pytest
from mcap.reader import make_reader

from tests.test_recording import recording_config, running
from tests.waiting import wait_for
from uwcam.recording import format as rec
from uwcam.recording.disk import DiskBudget
from uwcam.recording.records import BUDGET
from uwcam.recording.reprocess import ranged_frame_count, reprocess

RAW_FRAME_BYTES = 160 * 120 * 3 * 2  # the test rig's 16-bit RGB frames


def test_the_bucket_accrues_on_capture_time_and_caps_at_its_burst():
    b = DiskBudget(1000.0, burst_s=2.0)
    assert b.tokens == 2000.0
    b.accrue(10**9)
    b.spend(1500.0)
    b.accrue(10**9 + 500_000_000)  # half a second later: 500 bytes more
    assert b.tokens == pytest.approx(1000.0) and b.affords(1000.0) and not b.affords(1000.1)
    b.accrue(10**9 + 60 * 10**9)  # a minute later: full, not 60 000
    assert b.tokens == 2000.0
    b.accrue(10**9)  # a frame out of order does not give time back
    assert b.tokens == 2000.0


@pytest.mark.slow
def test_a_budget_below_the_raw_rate_decimates_counts_and_keeps_every_summary(tmp_path):
    budget_mb_s = 0.6  # a quarter of the raw 2.3 MB/s at 20 frames/s
    path = tmp_path / "dive.mcap"
    cfg = recording_config(tmp_path, start_file=str(path), results=False, budget_mb_s=budget_mb_s, preview_rate_hz=2.0)
    with running(cfg) as d:
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 100, 90.0)
        during = d.recorder.status()
        final = d.recorder.stop()
    topics: dict[str, list] = {}
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            topics.setdefault(channel.topic, []).append(message)
    metadata = [json.loads(m.data) for m in topics[rec.IMAGE_METADATA]]
    images = topics[rec.IMAGE]
    # Every frame has its summary; only the kept ones their raw image, and the count says so.
    assert len(metadata) == final["frames_written"]
    assert len(topics[rec.RANGING]) == sum(m["ranged"] == "ranged" for m in metadata)  # others: skipped for newer
    assert sum(m["raw_left_out"] == BUDGET for m in metadata) == final["frames_decimated"] > 0
    assert sum(not m["raw_kept"] for m in metadata) == final["frames_decimated"] + final["frames_dropped"]
    assert len(images) == sum(m["raw_kept"] for m in metadata)
    assert {m.log_time for m in images} == {m.log_time for m, meta in zip(topics[rec.IMAGE_METADATA], metadata)
                                            if meta["raw_kept"]}
    assert final["raw_kept_ratio"] == pytest.approx(len(images) / len(metadata), abs=1e-3)
    # The kept share is what the budget affords at the rate frames came (a loaded machine's camera
    # delivers fewer than its 20 a second), less the previews and metadata: not all, not none.
    span_s = (metadata[-1]["wall_time"] - metadata[0]["wall_time"])
    afford = min(1.0, budget_mb_s * 1e6 / (RAW_FRAME_BYTES * len(metadata) / span_s))
    assert 0.4 * afford <= final["raw_kept_ratio"] <= afford + 0.1
    # On disk: within the budget over the capture time, plus the 2-second burst and the file's own records.
    assert path.stat().st_size <= budget_mb_s * 1e6 * (span_s + 2.0) * 1.1 + 200e3
    assert topics[rec.PREVIEW] and len(topics[rec.PREVIEW]) >= span_s * 2.0 * 0.5
    # Decimation is spread over the dive, not a block of kept frames then nothing.
    kept = [meta["raw_kept"] for meta in metadata]
    half = len(kept) // 2
    assert any(kept[half:]) and any(kept[:half])
    # The status says what the disk holds at this budget.
    free = shutil.disk_usage(tmp_path).free
    assert during["budget_mb_s"] == budget_mb_s
    assert during["hours_left"] == pytest.approx(free / (budget_mb_s * 1e6) / 3600, rel=0.05)


@pytest.mark.slow
def test_frames_recorded_with_a_budget_reprocess(tmp_path):
    """The reader pairs each kept image with its metadata and passes over the decimated ones."""
    path = tmp_path / "dive.mcap"
    cfg = recording_config(tmp_path, start_file=str(path), results=False, budget_mb_s=0.8)
    with running(cfg) as d:
        assert wait_for(lambda: d.recorder.status()["frames_decimated"] >= 5, 90.0)
        final = d.recorder.stop()
    with open(path, "rb") as fh:
        frames = list(rec.iter_recorded_frames(rec.open_reader(fh)))
    with open(path, "rb") as fh:
        metadata = [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[rec.IMAGE_METADATA])]
    assert len(frames) == sum(m["raw_kept"] for m in metadata)
    assert all(f.metadata["raw_kept"] for f in frames)
    # Reprocessing ranges every kept ranged frame and passes over the decimated ones.
    kept_ranged = sum(m["raw_kept"] and m["ranged"] == "ranged" for m in metadata)
    # The progress bar's total: an upper bound (frames skipped for a newer one have an image, no range).
    assert kept_ranged <= ranged_frame_count(str(path)) <= len(frames)
    out = tmp_path / "out"
    (made,) = reprocess([str(path)], str(out), progress=False)
    with open(made, "rb") as fh:
        depth = sum(1 for _ in make_reader(fh).iter_messages(topics=[rec.DEPTH]))
    assert depth == kept_ranged > 0
