"""A daemon thread running a ``select`` loop, stopped through a pipe: the loop waits on
:attr:`SelectThread.stop_fd` beside its own descriptors and returns once it is readable, so a
stop wakes it at once, however long the loop would otherwise wait (no polling, no timeout).

Shared by the serial peers that serve descriptors: the UDP bridge
(:mod:`uwcam.drivers.udp_bridge`) and the simulated devices on a pty
(:mod:`uwcam.drivers.sim_serial`).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable


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
