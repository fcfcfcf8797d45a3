"""The MCAP recorder: every frame the camera delivered, raw at full bit depth, with the range
results, into one MCAP file per recording (layout in :mod:`uwcam.recording.format`).

An output of the frame loop: the loop's callbacks only append to a queue bounded in frames and
in bytes (the oldest item is dropped and counted when the disk cannot keep up); one writer
thread per recording encodes and writes, at a lower scheduling priority than the frame loop, so
a recorder short of CPU loses frames of its own first (its copies still take some CPU from the
loop: docs/recording.md). A write error (disk full, folder gone) or a vanished folder ends the
recording cleanly: the file is cut after its last complete record and closed with a footer,
so any MCAP reader reads it, and :meth:`Recorder.status` says why it stopped.

One class, over 500 lines on purpose: its queue, writer thread, budget and rotation share one
lock and one file; what it writes of each frame is in :mod:`uwcam.recording.records`, the disk's
arithmetic in :mod:`uwcam.recording.disk`.
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

from uwcam.recording import format as rec
from uwcam.api.view import Stretch
from uwcam.config import MountingConfig, RecordingConfig
from uwcam.drivers.base import Frame
from uwcam.fileio import UserInputError
from uwcam.runtime.pipeline import FramePipeline
from uwcam.runtime.published import Published
from uwcam.calibration.profile import CalibrationProfile
from uwcam.recording.disk import DiskBudget, NoRoom, disk_space_bytes, time_name, unique_path
from uwcam.recording.records import BUDGET, frame_metadata, ranging_record, summary_of, to_depth

log = logging.getLogger(__name__)

SUMMARY_BYTES = 1000
"""About what a frame's metadata and ranging records take (JSON)."""
SUMMARIES_PER_FRAME = 64
"""The queue holds at most this many items per raw frame it may hold (``queue_frames``)."""

WRITER_NICENESS = 10
"""How much less CPU priority the writer thread has than the frame loop (Linux nice levels)."""

START_MARGIN_BYTES = 1 << 20
"""Free disk a recording needs to start besides one chunk: the file's header and its calibration
attachment (a profile is 3-300 kB). With less, not one chunk of frames would reach the disk."""


def lower_this_threads_priority(niceness: int) -> bool:
    """Raise the nice level of the calling thread alone by ``niceness``; False where the system
    cannot (not Linux, where a thread id is no process id for setpriority, or refused)."""
    if not hasattr(os, "setpriority") or not os.path.isdir("/proc/self/task"):
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + niceness))
    except OSError:
        return False
    return True


def item_bytes(item: tuple) -> int:
    """Bytes a queued item holds: the raw frame and, for a ranged frame, its result arrays; for
    a decimated frame's summary, its preview's pixels if it carries one."""
    if item[0] == "summary":
        return SUMMARY_BYTES + (0 if item[1]["preview"] is None else item[1]["preview"].nbytes)
    if item[0] == "unranged":
        return item[1].data.nbytes
    published = item[1]
    r = published.result
    return published.frame.data.nbytes + r.range.nbytes + r.variance.nbytes + r.reasons.nbytes


class Recorder:
    """Records the pipeline's frames on request; idle (no thread, not subscribed) otherwise."""

    def __init__(self, pipeline: FramePipeline, config: RecordingConfig,
                 status: Callable[[], dict] | None = None, rangefinder: object | None = None,
                 mounting: MountingConfig | None = None) -> None:
        self.pipeline = pipeline
        self.config = config
        self.mounting = mounting
        self._status_fn = status
        self.rangefinder = rangefinder
        self._lock = threading.Lock()  # guards the queue and the counters read by status()
        self._control = threading.Lock()  # one start or stop at a time (API requests run in parallel)
        self._ready = threading.Condition(self._lock)
        self._queue: collections.deque = collections.deque()
        self._queued_bytes = 0
        self._queued_raw = 0
        self._thread: threading.Thread | None = None
        self._stop_reason: str | None = None
        self._state = "idle"
        self._files: list[str] = []
        self._file: rec.McapFile | None = None
        self._started_wall: float | None = None
        self._file_started = 0.0
        self.frames_written = 0
        self.frames_dropped = 0
        self.frames_decimated = 0
        self.frames_lost = 0
        """Frames of which not even the summary could be kept (a queue of nothing but summaries)."""
        self.bytes_closed = 0
        self.payload_closed = 0
        self._budget: DiskBudget | None = None
        self._disk_ratio = 1.0
        """Bytes on disk per byte of message data, as measured by the writer (read by the loop's thread)."""
        self._next_preview_ns = 0
        self._next_drop_log = 0.0
        self.last_stop_reason: str | None = None

    # ---------------------------------------------------------------- loop-thread callbacks
    def _enqueue(self, item: tuple) -> None:
        size = item_bytes(item)
        limit = self.config.queue_mb * 1e6
        raw = item[0] != "summary"
        with self._lock:
            dropped = 0
            while self._queue and ((raw and self._queued_raw >= self.config.queue_frames)
                                   or self._queued_bytes + size > limit
                                   or len(self._queue) >= SUMMARIES_PER_FRAME * self.config.queue_frames):
                # The disk cannot keep up: the oldest raw frame goes, its summary stays (counted);
                # only a queue of nothing but summaries loses whole frames.
                if self._shed_oldest_raw():
                    self.frames_dropped += 1
                else:
                    self._dequeue()
                    self.frames_lost += 1
                dropped += 1
            if raw:
                self._queued_raw += 1
            self._queue.append(item)
            self._queued_bytes += size
            self._ready.notify()
            total = self.frames_dropped
        now = time.monotonic()
        if dropped and now >= self._next_drop_log:  # said, not only counted; at most every 10 s
            self._next_drop_log = now + 10.0
            log.warning("recorder behind: %d frames dropped so far (the disk or the recorder's CPU share cannot "
                        "keep up; lower recording.budget_mb_s or the frame rate)", total)

    def _dequeue(self) -> tuple | None:
        """The oldest queued item, or None; the caller holds the lock."""
        if not self._queue:
            return None
        item = self._queue.popleft()
        self._queued_bytes -= item_bytes(item)
        if item[0] != "summary":
            self._queued_raw -= 1
        return item

    def _shed_oldest_raw(self) -> bool:
        """Replace the oldest queued raw frame by its summary; False if none is queued. The caller holds the lock."""
        for k, item in enumerate(self._queue):
            if item[0] != "summary":
                summary = ("summary", summary_of(item, "the recorder fell behind"))
                self._queue[k] = summary
                self._queued_bytes += item_bytes(summary) - item_bytes(item)
                self._queued_raw -= 1
                return True
        return False

    def _clear_queue(self) -> None:
        """Forget every queued item; the caller holds the lock."""
        self._queue.clear()
        self._queued_bytes = 0
        self._queued_raw = 0

    def _on_published(self, published: Published) -> None:
        # Profile and settings are read here, in the loop's thread, so they match the frame.
        profile, processing = self.pipeline.profile, self.pipeline.processing
        frame, t = published.frame, int(published.frame.wall_time * 1e9)
        preview = self._preview_due(t)
        item = ("ranged", published, profile, processing, preview)
        # Decimated: its summary only, so that its pixels never wait in the queue.
        self._enqueue(item if self._admit(frame, t) else ("summary", summary_of(item, BUDGET)))

    def _on_unranged(self, frame: Frame, why: str) -> None:
        t = int(frame.wall_time * 1e9)
        preview = self._preview_due(t)
        item = ("unranged", frame, why, preview)
        self._enqueue(item if self._admit(frame, t) else ("summary", summary_of(item, BUDGET)))

    def _preview_due(self, t: int) -> bool:
        rate = self.config.preview_rate_hz
        if rate <= 0 or t < self._next_preview_ns:
            return False
        self._next_preview_ns = t + int(1e9 / rate)
        return True

    def _admit(self, frame: Frame, t: int) -> bool:
        """Whether the disk budget has room for this raw frame (and its results); spends it if so.
        Runs in the loop's thread: arithmetic only."""
        budget = self._budget
        if budget is None:
            return True
        h, w = frame.data.shape[:2]
        results = h * w * (4 + 4 + 1) if self.config.results else 0  # depth, variance float32; reasons uint8
        cost = (frame.data.nbytes + results) * self._disk_ratio
        with self._lock:
            budget.accrue(t)
            if not budget.affords(cost):
                return False
            budget.spend(cost)
            return True

    # -------------------------------------------------------------------------- control
    def start(self, path: str | None = None) -> dict:
        """Start recording into ``path`` (must not exist) or a time-named file in the folder."""
        with self._control:
            return self._start(path)

    def _start(self, path: str | None) -> dict:
        with self._lock:
            if self._thread is not None:
                raise UserInputError(f"already recording into {self._files[-1]}; stop it first")
        if path is None:
            os.makedirs(self.config.folder, exist_ok=True)
            repair_folder(self.config.folder)
            path = unique_path(os.path.join(self.config.folder, time_name()))
        elif os.path.exists(path):
            raise UserInputError(f"{path} exists; give a new file name (recordings are never overwritten)")
        elif not path.endswith(".mcap"):
            raise UserInputError(f"recording file {path} must end in .mcap")
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise UserInputError(f"folder {folder} does not exist; create it or record elsewhere")
        free, _ = disk_space_bytes(folder)
        need = int(self.config.chunk_kb * 1024) + START_MARGIN_BYTES
        if free is not None and free < need:  # a full disk: refused, rather than an empty file and a stop
            raise NoRoom(f"no room to record in {folder}: {free / 1e6:.1f} MB free, a recording needs at least "
                         f"{need / 1e6:.1f} MB to start; free space on that disk or record elsewhere")
        self._base = path
        self._part = 1
        try:
            self._open(path)
        except FileExistsError:
            raise UserInputError(f"{path} exists; give a new file name (recordings are never overwritten)") from None
        except OSError as exc:
            self._discard(path)  # no empty or half-begun file is left behind
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise NoRoom(f"no room to record in {folder}: {exc.strerror}; free space on that disk or record "
                             "elsewhere") from None
            raise UserInputError(f"cannot create {path}: {exc.strerror}") from None
        with self._lock:
            self._files = [path]
            self._clear_queue()
            self.frames_written = self.frames_dropped = self.frames_decimated = self.frames_lost = self.bytes_closed = 0
            self.payload_closed = 0
            budget = self.config.budget_mb_s
            self._budget = DiskBudget(budget * 1e6) if budget else None
            self._disk_ratio = 1.0
            self._next_preview_ns = 0
            self._stop_reason = None
            self._state = "recording"
            self._started_wall = time.time()
            self._thread = threading.Thread(target=self._run, name="mcap-recorder", daemon=True)
        self._last_reading_ns: int | None = None
        self._next_status = 0.0
        self._stretch = Stretch()  # the operator page's display stretch, smoothed over the previews
        self.pipeline.subscribe(self._on_published)
        self.pipeline.subscribe_unranged(self._on_unranged)
        self._thread.start()
        log.info("recording into %s", path)
        return self.status()

    def _discard(self, path: str) -> None:
        """Close and remove ``path``, a file :meth:`_open` created but could not begin."""
        if self._file is not None and self._file.path == path:
            self._file.abandon()
            self._file = None
        try:
            os.unlink(path)
        except OSError:
            pass  # never created, or already gone

    def stop(self, reason: str = "stopped on request") -> dict:
        """Stop: write what is queued, finish the file. Returns the final status."""
        with self._control:
            return self._stop_recording(reason)

    def _stop_recording(self, reason: str) -> dict:
        # No new frames from here on: the writer drains what is queued (at most queue_frames).
        self.pipeline.unsubscribe(self._on_published)
        self.pipeline.unsubscribe_unranged(self._on_unranged)
        with self._lock:
            thread = self._thread
            if thread is None:
                return self._status_locked()
            if self._stop_reason is None:
                self._stop_reason = reason
            self._ready.notify()
        thread.join(timeout=60.0)
        return self.status()

    def close(self) -> None:
        self.stop("the daemon stopped")

    def status(self) -> dict:
        with self._lock:
            return self._status_locked()

    def _status_locked(self) -> dict:
        recording = self._thread is not None and self._state == "recording"
        size = self.bytes_closed
        current = self._file  # replaced by the writer thread at rotation: read it once
        if current is not None:
            try:
                size += current.size()
            except (OSError, ValueError):  # closed in the meantime
                pass
        return {
            "state": "recording" if recording else "idle",
            "file": self._files[-1] if self._files else None,
            "files": list(self._files),
            "started": self._started_wall,
            "duration_s": round(time.time() - self._started_wall, 1) if recording and self._started_wall else None,
            "frames_written": self.frames_written,
            "frames_dropped": self.frames_dropped,
            "frames_decimated": self.frames_decimated,
            "frames_lost": self.frames_lost,
            "raw_kept_ratio": None if not self.frames_written else
            round(max(0.0, 1.0 - (self.frames_decimated + self.frames_dropped) / self.frames_written), 4),
            "budget_mb_s": self.config.budget_mb_s,
            **self._disk_outlook(size, recording),
            "queued": self._queued_raw,
            "queued_summaries": len(self._queue) - self._queued_raw,
            "queued_mb": round(self._queued_bytes / 1e6, 1),
            "bytes": size,
            "last_stop_reason": self.last_stop_reason,
        }

    def _disk_outlook(self, size: int, recording: bool) -> dict:
        """Free disk where recordings go, and the hours of recording it holds at the budget (or,
        without one, at the rate measured while recording)."""
        free, total = disk_space_bytes(self._files[-1] if self._files else self.config.folder)
        rate = self.config.budget_mb_s * 1e6 if self.config.budget_mb_s else None
        if rate is None and recording and self._started_wall:
            elapsed = time.time() - self._started_wall
            rate = size / elapsed if elapsed > 5 and size > 0 else None
        hours = None if free is None or not rate else round(free / rate / 3600, 2)
        return {"disk_free_bytes": free, "disk_total_bytes": total, "hours_left": hours}

    # ---------------------------------------------------------------------- writer thread
    def _open(self, path: str) -> None:
        self._file = rec.McapFile(path, chunk_size=int(self.config.chunk_kb * 1024), compression=self.config.compression)
        self._file_started = time.monotonic()
        self._attached = set()
        self._last_profile = None
        self._last_ambient = None
        self._last_open_water = None
        self._rotate_due = False
        # Every file carries the calibration in use and the camera's mounting from its start
        # (self-contained parts).
        profile = self.pipeline.profile
        self._file.attach_profile(profile, time.time_ns())
        self._attached.add(profile.name)
        self._write_transform(time.time_ns())

    def _write_transform(self, t: int) -> None:
        m = self.mounting
        if m is not None:
            self._file.write(rec.TRANSFORM, "foxglove.FrameTransform",
                             rec.frame_transform(m.parent_frame, m.translation_m, m.rotation_deg, t), t)

    def _run(self) -> None:
        reason = "stopped"
        lower_this_threads_priority(WRITER_NICENESS)
        try:
            while True:
                with self._lock:
                    if not self._queue and self._stop_reason is None:
                        # Woken by a frame, a stop, or the timeout: the folder, the rangefinder
                        # and the status are checked even when no frame comes.
                        self._ready.wait(timeout=0.25)
                    item = self._dequeue()
                    stopping = item is None and self._stop_reason is not None
                if item is not None:
                    self._write_item(item)
                self._housekeeping()
                if stopping:
                    reason = self._stop_reason
                    break
            self._finish()
        except OSError as exc:
            reason = self._failed(exc)
        except Exception as exc:  # never leave a half-open file behind a silent thread
            log.exception("recorder failed")
            reason = self._failed(exc)
        finally:
            self.pipeline.unsubscribe(self._on_published)
            self.pipeline.unsubscribe_unranged(self._on_unranged)
            with self._lock:
                self._state = "idle"
                self.last_stop_reason = reason
                self._thread = None
                self._clear_queue()
            log.info("recording stopped: %s", reason)

    def _finish(self) -> None:
        if self._file is not None:
            self._file.finish()  # on an error, _failed() cuts the file at its last complete record
            self.bytes_closed += os.path.getsize(self._file.path) if os.path.exists(self._file.path) else 0
            self.payload_closed += self._file.payload_bytes
            self._file = None

    def _failed(self, exc: Exception) -> str:
        path = self._file.path if self._file is not None else (self._files[-1] if self._files else "?")
        if self._file is not None:
            self._file.abandon()
            self._file = None
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            reason = f"disk full: {path} ends at the last frame that fit"
        elif isinstance(exc, OSError):
            reason = f"write failed ({exc.strerror or exc}): {path} ends at the last complete frame"
        else:
            reason = f"recorder error ({type(exc).__name__}: {exc}); {path} ends at the last complete frame"
        if os.path.exists(path):
            try:
                rec.repair(path)
            except OSError as err:
                reason += f"; could not close the file ({err.strerror}); run uwcam again to repair it"
            except rec.RecordingError:  # not even its header reached the disk: nothing to keep
                self._discard(path)
                reason += "; nothing of it reached the disk, so the empty file was removed"
        log.error("recording stopped: %s", reason)
        return reason

    def _housekeeping(self) -> None:
        if self._file is None:
            return
        if not os.path.exists(self._file.path):
            raise FileNotFoundError(errno.ENOENT, "the recording file or its folder was removed", self._file.path)
        now = time.monotonic()
        reading = self.rangefinder.latest() if self.rangefinder is not None else None
        if reading is not None and reading.monotonic_ns != self._last_reading_ns:
            self._last_reading_ns = reading.monotonic_ns
            self._file.write_json(rec.RANGEFINDER, {"range_m": reading.range_m, "confidence": reading.confidence,
                                                    "wall_time": reading.wall_time}, int(reading.wall_time * 1e9))
        if self._status_fn is not None and now >= self._next_status:
            self._next_status = now + self.config.status_interval_s
            t = time.time_ns()
            self._file.write_json(rec.STATUS, self._status_fn(), t)
            self._write_transform(t)  # again now and then: a reader that seeks still finds one near
        c = self.config
        if (c.max_size_mb and self._file.size() >= c.max_size_mb * 1e6) or \
                (c.max_duration_s and now - self._file_started >= c.max_duration_s):
            self._rotate_due = True  # the next frame opens the next file: no file without frames

    def _rotate(self) -> None:
        self._finish()
        self._part += 1
        stem, ext = os.path.splitext(self._base)
        if os.path.basename(self._base).startswith("uwcam-") and os.path.dirname(self._base) == self.config.folder:
            path = unique_path(os.path.join(self.config.folder, time_name()))
        else:
            path = unique_path(f"{stem}-{self._part:03d}{ext}")
        self._open(path)
        with self._lock:
            self._files.append(path)
        log.info("recording continues in %s", path)

    def _measure_disk_ratio(self) -> None:
        """Bytes on disk per byte of message data so far (1 until a few chunks are out), for the budget."""
        f = self._file
        payload = self.payload_closed + f.payload_bytes
        disk = self.bytes_closed + f.size()
        if payload > 8 * self.config.chunk_kb * 1024 and disk > 0:
            self._disk_ratio = max(0.05, disk / payload)

    def _spend(self, payload_bytes: int) -> None:
        if self._budget is not None:
            with self._lock:
                self._budget.spend(payload_bytes * self._disk_ratio)

    def _frame_messages(self, frame: Frame, t: int, ranged: str, number: int | None, preview: bool) -> None:
        """The raw frame, its metadata and, when due, a preview."""
        self._file.write(rec.IMAGE, "foxglove.RawImage", rec.raw_image(frame.data, t), t)
        self._file.write_json(rec.IMAGE_METADATA, frame_metadata(frame, ranged, number), t)
        if preview:
            self._write_preview(frame.data, t)

    def _write_preview(self, data: np.ndarray, t: int) -> None:
        bgr = self._stretch(data)
        jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.config.preview_quality])[1].tobytes()
        self._file.write(rec.PREVIEW, "foxglove.CompressedImage", rec.compressed_image(jpeg, t, "jpeg"), t)
        self._spend(len(jpeg))

    def _write_summary(self, summary: dict) -> None:
        """A frame without its raw image (decimated, or shed by a recorder behind): its metadata,
        ranging record and, when due, its preview."""
        t = summary["t"]
        self._file.write_json(rec.IMAGE_METADATA, summary["metadata"], t)
        if summary["ranging"] is not None:
            self._file.write_json(rec.RANGING, summary["ranging"], t)
        self._spend(SUMMARY_BYTES)
        if summary["preview"] is not None:
            self._write_preview(summary["preview"], t)
        if summary["metadata"]["raw_left_out"] == BUDGET:
            with self._lock:
                self.frames_decimated += 1

    def _write_item(self, item: tuple) -> None:
        if self._rotate_due:
            self._rotate()
        if item[0] == "summary":
            self._write_summary(item[1])
        elif item[0] == "unranged":
            _, frame, why, preview = item
            self._frame_messages(frame, int(frame.wall_time * 1e9), why, None, preview)
        else:
            _, published, profile, processing, preview = item
            self._write_published(published, profile, processing, preview)
        self._measure_disk_ratio()
        with self._lock:
            self.frames_written += 1

    def _write_published(self, p: Published, profile: CalibrationProfile, processing, preview: bool) -> None:
        f = self._file
        frame, t = p.frame, int(p.frame.wall_time * 1e9)
        h, w = frame.data.shape[:2]
        if profile is not self._last_profile:
            self._last_profile = profile
            self._uz = rec.depth_factor(profile, h, w)
            f.write(rec.CALIBRATION, "foxglove.CameraCalibration", rec.camera_calibration(profile, w, h, t), t)
            if profile.name not in self._attached:
                f.attach_profile(profile, t)
                self._attached.add(profile.name)
        self._frame_messages(frame, t, "ranged", p.number, preview)
        if p.ambient is not None and p.ambient is not self._last_ambient:
            self._last_ambient = p.ambient
            c = p.ambient.shape[-1]
            f.write(rec.AMBIENT, "foxglove.RawImage", rec.raw_image(p.ambient.astype(np.float32), t, f"32FC{c}"), t)
        if p.open_water is not None and p.open_water is not self._last_open_water:
            self._last_open_water = p.open_water
            c = p.open_water.shape[-1]
            f.write(rec.OPEN_WATER, "foxglove.RawImage", rec.raw_image(p.open_water.astype(np.float32), t, f"32FC{c}"), t)
        f.write_json(rec.RANGING, ranging_record(p, profile, processing), t)
        self._spend(SUMMARY_BYTES)
        if not self.config.results:
            return
        depth, variance = to_depth(p.result.range, p.result.variance, self._uz)
        f.write(rec.DEPTH, "foxglove.RawImage", rec.raw_image(depth, t, "32FC1"), t)
        f.write(rec.VARIANCE, "foxglove.RawImage", rec.raw_image(variance, t, "32FC1"), t)
        f.write(rec.REASONS, "foxglove.RawImage", rec.raw_image(p.result.reasons, t, "mono8"), t)


def repair_folder(folder: str) -> list[str]:
    """Give recordings left unfinished by a crash or power loss their footer; returns their paths."""
    repaired = []
    for name in sorted(os.listdir(folder)):
        path = os.path.join(folder, name)
        if name.endswith(".mcap") and os.path.isfile(path) and not rec.is_complete(path):
            try:
                kept = rec.repair(path)
                repaired.append(path)
                log.warning("repaired unfinished recording %s (%d bytes kept)", path, kept)
            except (OSError, rec.RecordingError) as exc:
                log.warning("could not repair %s: %s", path, exc)
    return repaired


