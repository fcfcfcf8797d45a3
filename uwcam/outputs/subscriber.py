"""The shape every threaded output shares: the frame loop's callback only hands a published frame
over, under a lock, and wakes the output's own thread, which does the work (encoding, sending)
off the loop. Subclasses define ``_on_published`` (the hand-over) and ``_run`` (the thread)."""

from __future__ import annotations

import threading

from uwcam.runtime.pipeline import FramePipeline


class ThreadedOutput:
    """A subscriber of ``pipeline`` with a thread of its own named ``thread_name``."""

    def __init__(self, pipeline: FramePipeline, thread_name: str) -> None:
        self.pipeline = pipeline
        self._lock = threading.Lock()  # guards what the loop hands over and the output's counters
        self._ready = threading.Condition(self._lock)
        self._stop = False
        self._thread: threading.Thread | None = None
        self._thread_name = thread_name

    def _on_published(self, published) -> None:  # pragma: no cover - every output defines it
        raise NotImplementedError

    def _run(self) -> None:  # pragma: no cover - every output defines it
        raise NotImplementedError

    def _start_thread(self) -> None:
        """Start the thread, then take frames from the loop."""
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        self.pipeline.subscribe(self._on_published)

    def _stop_thread(self, timeout_s: float = 10.0) -> None:
        """Take no more frames, wake the thread to stop, and wait for it."""
        self.pipeline.unsubscribe(self._on_published)
        with self._lock:
            self._stop = True
            self._ready.notify()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            self._thread = None
