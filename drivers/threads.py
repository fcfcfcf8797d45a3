"""Background threads that stop at once when asked: no polling, no timeout to wait out.

* :class:`StoppableThread`: a daemon thread whose loop waits on its :attr:`~StoppableThread.stopping`
  event (or a condition it is woken through) instead of sleeping: the camera supervisor, the
  rangefinders, the lamp commander, the MAVLink output and the alert monitor.
* :class:`SelectThread`: a daemon thread running a ``select`` loop, stopped through a pipe: the
  loop waits on :attr:`~SelectThread.stop_fd` beside its own descriptors and returns once it is
  readable: the UDP bridge (:mod:`uwcam.drivers.udp_bridge`) and the simulated devices on a pty
  (:mod:`uwcam.drivers.sim_serial`).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable


class StoppableThread:
    """Runs ``target`` on a daemon thread named ``name`` from :meth:`start`; ``target`` returns
    once :attr:`stopping` is set. ``wake``: a condition the thread waits on, notified on stop."""

    def __init__(self, target: Callable[[], None], name: str, wake: threading.Condition | None = None) -> None:
        self.stopping = threading.Event()
        self._target, self._name, self._wake = target, name, wake
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._target, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> bool:
        """Set :attr:`stopping`, wake the thread and wait up to ``timeout_s`` for it to end.
        True when it has ended (or never started); False while it is still in a call that does
        not return at once (a driver's blocking read or open): what it uses is still in use."""
        self.stopping.set()
        if self._wake is not None:
            with self._wake:
                self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            if self._thread.is_alive():
                return False
            self._thread = None
        return True


class SelectThread:
    """Runs ``target`` on a daemon thread named ``name``; ``target`` returns when :attr:`stop_fd`
    is readable."""

    def __init__(self, target: Callable[[], None], name: str) -> None:
        self.stop_fd, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=target, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Wake the loop to return, wait up to ``timeout_s`` for it, and close the pipe."""
        os.write(self._stop_w, b"x")
        if self._thread.ident is not None:  # started
            self._thread.join(timeout=timeout_s)
        for fd in (self.stop_fd, self._stop_w):
            os.close(fd)
