"""Recording at frame rate: the hand-written foxglove.RawImage encoding, the recorder's queue
bounded in bytes, its compression setting, and its writer thread's lower priority."""

from __future__ import annotations

import os
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from pydantic import ValidationError

from tests.test_recording import decoded, recording_config, running
from tests.waiting import wait_for
from uwcam.recording import format as rec
from uwcam.config import RecordingConfig
from uwcam.drivers.base import Frame
from uwcam.recording.recorder import WRITER_NICENESS, Recorder, lower_this_threads_priority


def sdk_encoding(data: np.ndarray, log_time_ns: int, encoding: str | None) -> bytes:
    """The same message through the Foxglove SDK's own class: the reference."""
    m = rec._messages()
    data = np.ascontiguousarray(data)
    h, w = data.shape[:2]
    step = w * (data.shape[2] if data.ndim == 3 else 1) * data.dtype.itemsize
    stamp = m.Timestamp(log_time_ns // 1_000_000_000, log_time_ns % 1_000_000_000)
    return m.RawImage(timestamp=stamp, frame_id=rec.FRAME_ID, width=w, height=h, encoding=encoding or rec.image_encoding(data),
                      step=step, data=data.tobytes()).encode()


@pytest.mark.parametrize(("shape", "dtype", "encoding"), [
    ((3, 5, 3), np.uint16, None), ((4, 2, 3), np.uint8, None), ((7, 300, 4), np.uint16, None),
    ((6, 9), np.float32, "32FC1"), ((2, 3), np.uint8, "mono8"), ((5, 4, 3), np.float32, "32FC3"), ((0, 0), np.float32, "32FC1"),
])
@pytest.mark.parametrize("log_time_ns", [0, 5, 1_000_000_000, 1_795_558_835_666_189_700, (2**32 - 1) * 10**9 + 999_999_999])
def test_raw_image_bytes_equal_the_foxglove_sdks(shape, dtype, encoding, log_time_ns):
    rng = np.random.default_rng(sum(shape) + log_time_ns % 97)
    data = (rng.random(shape) * 200).astype(dtype)
    assert rec.raw_image(data, log_time_ns, encoding) == sdk_encoding(data, log_time_ns, encoding)


def test_raw_image_of_a_strided_or_big_endian_view_is_its_values():
    base = np.arange(4 * 6 * 3, dtype=np.uint16).reshape(4, 6, 3)
    view = base[:, ::2]  # not contiguous
    assert rec.raw_image(view, 7) == sdk_encoding(np.ascontiguousarray(view), 7, None)
    big = base.astype(">u2")
    assert rec.raw_image(big, 7) == sdk_encoding(base, 7, None)


def frame_of(nbytes_per_frame: int, k: int) -> Frame:
    return Frame(data=np.zeros((nbytes_per_frame // 6, 1, 3), np.uint16), sequence=k, host_monotonic_ns=k, wall_time=0.0)


def test_the_queue_is_bounded_in_bytes_dropping_the_oldest():
    recorder = Recorder(SimpleNamespace(), RecordingConfig(queue_frames=1000, queue_mb=1.0))
    for k in range(10):
        recorder._on_unranged(frame_of(300_000, k), "lamp off")  # 0.3 MB each: three fit in 1 MB
    # The oldest raw frames went; their summaries (metadata) stay, in order.
    assert [item[1].sequence for item in recorder._queue if item[0] != "summary"] == [7, 8, 9]
    summaries = [item[1]["metadata"] for item in recorder._queue if item[0] == "summary"]
    assert [m["sequence"] for m in summaries] == list(range(7))
    assert all(not m["raw_kept"] and m["raw_left_out"] == "the recorder fell behind" for m in summaries)
    assert recorder.frames_dropped == 7 and recorder.status()["queued_mb"] == pytest.approx(0.9)
    while recorder._dequeue() is not None:
        pass
    assert recorder.status()["queued_mb"] == 0.0


def test_the_frame_limit_counts_raw_frames_and_sheds_them_to_summaries():
    recorder = Recorder(SimpleNamespace(), RecordingConfig(queue_frames=2, queue_mb=100.0))
    for k in range(5):
        recorder._on_unranged(frame_of(6_000, k), "lamp off")
    kinds = [(item[0], item[1]["metadata"]["sequence"] if item[0] == "summary" else item[1].sequence)
             for item in recorder._queue]
    assert kinds == [("summary", 0), ("summary", 1), ("summary", 2), ("unranged", 3), ("unranged", 4)]
    assert recorder.frames_dropped == 3 and recorder.frames_lost == 0


def test_a_frame_larger_than_the_whole_queue_is_still_queued_alone():
    recorder = Recorder(SimpleNamespace(), RecordingConfig(queue_mb=0.5))
    recorder._on_unranged(frame_of(300_000, 1), "lamp off")
    recorder._on_unranged(frame_of(1_200_000, 2), "lamp off")
    # Frame 1 shed to its summary, which the big frame then needs the room of too: lost, and counted.
    assert [item[1].sequence for item in recorder._queue] == [2] and recorder.frames_dropped == 1
    assert recorder.frames_lost == 1


@pytest.mark.parametrize(("key", "value"), [("queue_mb", 0), ("queue_mb", float("nan")), ("queue_mb", -3),
                                            ("compression", "gzip"), ("compression", "")])
def test_bad_queue_or_compression_settings_are_refused(key, value):
    with pytest.raises(ValidationError, match=key):
        RecordingConfig(**{key: value})


def thread_niceness(native_id: int) -> int:
    with open(f"/proc/self/task/{native_id}/stat") as fh:
        return int(fh.read().rsplit(")", 1)[1].split()[16])  # field 19 of stat: nice


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="thread priorities are read from Linux's /proc")
def test_lowering_a_threads_priority_leaves_the_others_alone():
    seen = {}

    def body():
        seen["ok"] = lower_this_threads_priority(3)
        seen["id"] = threading.get_native_id()
        seen["nice"] = thread_niceness(seen["id"])

    before = thread_niceness(threading.get_native_id())
    t = threading.Thread(target=body)
    t.start()
    t.join()
    assert seen["ok"] and seen["nice"] == min(19, before + 3)
    assert thread_niceness(threading.get_native_id()) == before


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="thread priorities are read from Linux's /proc")
@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_each_compression_records_readable_files_from_a_lower_priority_writer(tmp_path, compression):
    loop_nice = thread_niceness(threading.get_native_id())
    path = str(tmp_path / f"{compression}.mcap")
    with running(recording_config(tmp_path, compression=compression)) as d:
        d.recorder.start(path)
        writer = d.recorder._thread
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 5, 60.0)
        niceness = thread_niceness(writer.native_id)
        d.recorder.stop()
    assert niceness == min(19, loop_nice + WRITER_NICENESS)
    images = decoded(path, rec.IMAGE)
    assert len(images) >= 5 and images[0][1].encoding == "16UC3"
    with open(path, "rb") as fh:
        from mcap.reader import make_reader
        compressions = {c.compression for c in make_reader(fh).get_summary().chunk_indexes}
    assert compressions == {"" if compression == "none" else compression}
