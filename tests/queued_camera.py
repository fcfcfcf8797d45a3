"""A camera for frame-loop tests: it hands out the frames a test puts in its queue, oldest first,
as :meth:`uwcam.drivers.supervisor.SupervisedCamera.get` does, so a test decides exactly which
frames the loop sees and when (a backlog after a stall, a scripted drift)."""

from __future__ import annotations

import collections
import threading
import time

from uwcam.drivers.base import Frame


class QueuedCamera:
    """Put frames in ``queue`` (under ``lock``); :meth:`get` returns the oldest, or None after ``timeout_s``."""

    def __init__(self) -> None:
        self.queue: collections.deque[Frame] = collections.deque()
        self.lock = threading.Lock()

    def get(self, timeout_s: float) -> Frame | None:
        deadline = time.monotonic() + timeout_s
        while True:
            with self.lock:
                if self.queue:
                    return self.queue.popleft()
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.002)

    def put(self, *frames: Frame) -> None:
        with self.lock:
            self.queue.extend(frames)
