"""numba's cache filled for every setting by a child process of low priority, once per install.

``uwcam warmup`` compiles every kernel the frame loop can need (two minutes on 2 cores with an
empty cache). Run before the first start, it would stand between a new user and the page; not
run at all, every later change of a setting would compile in its request (seconds each). So
``uwcam run`` starts it beside the daemon, as a child at the lowest CPU priority, when this
install's cache is not known to be full: the kernels of a first start come first in its order
(:func:`uwcam.runtime.warm_up.warm_up_everything`: the daemon's own settings on 16-bit frames,
with and without a background), so that the daemon, compiling the simulator's meanwhile on its
own core, finds them in the cache; the rest follow. The
compilations are shared through numba's on-disk cache (files replaced whole, so a kernel
compiled by both is only compiled twice, never broken).

The cache is known to be full by a marker beside it (in uwcam's ``__pycache__``), named by a key
of numba's version, the CPU, the channel count and uwcam's sources (their sizes and times): a
new install, another machine or edited sources start it again.
"""

from __future__ import annotations

import hashlib
import logging
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

log = logging.getLogger(__name__)

_PACKAGE = Path(__file__).resolve().parents[1]


def cache_key(n_channels: int) -> str:
    """What numba's cached kernels depend on: its version, this CPU, the channel count (the
    kernels are compiled per channel count) and uwcam's sources."""
    import llvmlite.binding
    import numba

    digest = hashlib.sha256(f"{numba.__version__}|{llvmlite.binding.get_host_cpu_name()}|{n_channels}".encode())
    for path in sorted(_PACKAGE.rglob("*.py")):
        stat = path.stat()
        digest.update(f"{path.relative_to(_PACKAGE)}|{stat.st_size}|{stat.st_mtime_ns}".encode())
    return digest.hexdigest()[:16]


def marker(n_channels: int) -> Path:
    """The file whose presence says the cache holds every kernel for ``n_channels`` channels."""
    return _PACKAGE / "__pycache__" / f"warmed-up-{n_channels}-{cache_key(n_channels)}"


def is_warmed_up(n_channels: int) -> bool:
    return marker(n_channels).exists()


def mark_warmed_up(n_channels: int) -> None:
    """Say the cache is full (best effort: a read-only install only warms up again next time)."""
    path = marker(n_channels)
    try:
        path.parent.mkdir(exist_ok=True)
        path.touch()
        for stale in path.parent.glob(f"warmed-up-{n_channels}-*"):  # of sources since edited
            if stale != path:
                stale.unlink(missing_ok=True)
    except OSError as exc:
        log.info("could not mark numba's cache as complete (%s): the next start fills it again", exc)


class BackgroundWarmUp:
    """``uwcam warmup --profile FILE`` for the profile in use, in a child process at the lowest CPU
    priority, when the cache is not known to be full and numba is in use; stopped with the daemon
    (what it compiled so far stays in the cache)."""

    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._folder: tempfile.TemporaryDirectory | None = None
        self._watcher: threading.Thread | None = None
        self.state = "not started"
        """"not started", "not needed", "running", "done", "stopped" or "failed (…)"."""

    def start(self, profile, processing=None) -> None:
        """Start it for ``profile`` (a :class:`uwcam.calibration.profile.CalibrationProfile`) if
        needed, the kernels of ``processing`` (a :class:`uwcam.config.ProcessingConfig`, the
        daemon's) first."""
        from uwcam.calibration.profile import save_profile
        from uwcam.optics import kernels

        n = len(profile.channels)
        if kernels.BACKEND != "numba" or is_warmed_up(n):
            self.state = "not needed"
            return
        self._folder = tempfile.TemporaryDirectory(prefix="uwcam-warmup-")
        path = os.path.join(self._folder.name, "profile.yaml")
        save_profile(profile, path)
        command = [sys.executable, "-m", "uwcam", "warmup", "--profile", path]
        if processing is not None:
            settings = os.path.join(self._folder.name, "processing.json")
            with open(settings, "w", encoding="utf-8") as fh:
                fh.write(processing.model_dump_json())
            command += ["--processing", settings]
        self._log = open(os.path.join(self._folder.name, "warmup.log"), "w+b")
        # A process group of its own: Ctrl-C in the daemon's terminal is for the daemon, which
        # stops it. Not a session of its own: Linux shares the CPU fairly between sessions
        # (autogroups) whatever their nice values, and the daemon's start then compiled half as fast.
        # Started in its temporary folder: `python -m` looks in the working folder first, and a
        # checkout's (the daemon started from one) is not the installed package.
        self._process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL,
            stdout=self._log, stderr=subprocess.STDOUT, process_group=0, cwd=self._folder.name)
        try:
            os.setpriority(os.PRIO_PROCESS, self._process.pid, 19)
        except OSError:  # gone already, or not allowed: it still only fills the cache
            pass
        self.state = "running"
        log.info("compiling the kernels of every setting in the background (process %d, lowest priority; "
                 "once per install, about two minutes on 2 cores)", self._process.pid)
        # The process is handed over: stop() may clear self._process before the watcher first runs.
        self._watcher = threading.Thread(target=self._watch, args=(self._process,), name="background-warm-up", daemon=True)
        self._watcher.start()

    def _watch(self, process: subprocess.Popen) -> None:
        code = process.wait()
        if self.state == "stopped":
            return
        if code == 0:
            self.state = "done"
            log.info("the kernels of every setting are compiled: no change of settings compiles any more")
        else:
            self._log.seek(0)
            tail = self._log.read().decode(errors="replace").strip().splitlines()[-1:] or ["no output"]
            self.state = f"failed (exit {code}: {tail[0]})"
            log.warning("compiling the kernels in the background failed (exit %d: %s); a change of settings "
                        "compiles what it needs, in its request (run `uwcam warmup` to compile them all)",
                        code, tail[0])

    def stop(self) -> None:
        """Stop the child if it still runs; safe to call twice."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            self.state = "stopped"
            process.terminate()
            try:
                process.wait(10.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        if self._watcher is not None:
            self._watcher.join(10.0)
            self._watcher = None
        if self._folder is not None:
            self._log.close()
            self._folder.cleanup()
            self._folder = None
