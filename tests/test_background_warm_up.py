"""``uwcam run`` fills numba's cache for every setting in a low-priority child, once per install.

The child is the real ``uwcam warmup --profile`` started by :class:`BackgroundWarmUp`; the marker
that says the cache is full is the one the daemon reads at its next start."""

import os
import time

import pytest

from tests.waiting import wait_for
from uwcam.compute.jit import HAVE_NUMBA
from uwcam.runtime import background_warm_up as bw
from uwcam.runtime.background_warm_up import BackgroundWarmUp

pytestmark = pytest.mark.skipif(not HAVE_NUMBA, reason="without numba nothing is compiled")


@pytest.fixture
def profile():
    from uwcam.calibration.profile import load_profile
    from uwcam.config import default_config
    from uwcam.runtime.daemon import Daemon
    from uwcam.runtime.simulated_rig import shipped_calibration_path

    rig = Daemon(default_config())._options("sim", {})["rig"]  # the embedded default's, as uwcam run makes it
    return load_profile(shipped_calibration_path(rig))


@pytest.fixture
def no_marker(profile):
    """The real marker of this install removed for the test, and put back as it was after."""
    path = bw.marker(len(profile.channels))
    existed = path.exists()
    if existed:
        path.unlink()
    yield path
    if existed:
        path.touch()


def test_the_key_follows_channels_and_sources(tmp_path, monkeypatch):
    monkeypatch.setattr(bw, "_PACKAGE", tmp_path)
    source = tmp_path / "kernels.py"
    source.write_text("x = 1\n")
    three, four = bw.cache_key(3), bw.cache_key(4)
    assert three != four
    os.utime(source, ns=(time.time_ns(), source.stat().st_mtime_ns + 10**9))  # an edited source
    assert bw.cache_key(3) != three
    bw.mark_warmed_up(3)
    assert bw.is_warmed_up(3) and not bw.is_warmed_up(4)


def test_nothing_starts_where_the_cache_is_known_full(tmp_path, monkeypatch, profile):
    monkeypatch.setattr(bw, "_PACKAGE", tmp_path)
    bw.mark_warmed_up(len(profile.channels))
    warm = BackgroundWarmUp()
    warm.start(profile)
    assert warm.state == "not needed" and warm._process is None
    warm.stop()


@pytest.mark.slow
def test_the_child_compiles_at_low_priority_and_marks_the_cache_full(profile, no_marker, tmp_path, monkeypatch):
    # Started from a folder with a package of uwcam's name in it, as from a checkout: the child
    # must run the installed uwcam (`python -m` looks in the working folder first).
    (tmp_path / "uwcam").mkdir()
    (tmp_path / "uwcam" / "__init__.py").write_text("raise ImportError('not the installed uwcam')\n")
    monkeypatch.chdir(tmp_path)
    from uwcam.config import ProcessingConfig

    warm = BackgroundWarmUp()
    try:
        warm.start(profile, ProcessingConfig(smoothing="mean"))  # its kernels first
        assert warm.state == "running"
        assert os.getpriority(os.PRIO_PROCESS, warm._process.pid) == 19
        assert os.getpgid(warm._process.pid) != os.getpgid(0)  # Ctrl-C in the terminal does not reach it
        assert os.getsid(warm._process.pid) == os.getsid(0)  # its nice value counts against the daemon's
        assert wait_for(lambda: warm.state != "running", 900.0), "the background warm-up did not end"
        assert warm.state == "done", warm.state
        assert no_marker.exists()  # written by the child, read by the next start
    finally:
        warm.stop()


def test_stopping_the_daemon_stops_the_child(profile, no_marker):
    warm = BackgroundWarmUp()
    warm.start(profile)
    process = warm._process
    warm.stop()
    assert process.poll() is not None
    assert warm.state == "stopped"
    assert not no_marker.exists()  # cut short: the next start goes on with it
    warm.stop()  # twice is harmless


def test_a_configured_profile_is_read_once_and_the_child_warms_up_the_one_the_daemon_ranges_with(
        tmp_path, monkeypatch):
    """The calibration file is read before the devices open (for the child) and not again: a file
    replaced in between could otherwise give the child and the daemon different profiles."""
    from uwcam.calibration.profile import load_profile, save_profile
    from uwcam.config import default_config
    from uwcam.runtime import daemon as daemon_module
    from uwcam.runtime.daemon import Daemon
    from uwcam.runtime.simulated_rig import shipped_calibration_path

    config = default_config()
    config.api.port = 0
    config.calibration = str(tmp_path / "rig.yaml")
    save_profile(load_profile(shipped_calibration_path(Daemon(default_config())._options("sim", {})["rig"])),
                 config.calibration)
    reads, children = [], []
    monkeypatch.setattr(daemon_module, "load_profile", lambda path: reads.append(path) or load_profile(path))

    def start(self, profile, processing):  # the child itself is the other tests' subject
        children.append(profile)
        self.state = "running"

    monkeypatch.setattr(BackgroundWarmUp, "start", start)
    config.state_dir = str(tmp_path / "state")
    daemon = Daemon(config)
    daemon.warm_up_in_background = True
    daemon.start()
    try:
        assert reads == [config.calibration]
        assert len(children) == 1 and children[0] is daemon.profiles[daemon.profile_name]
    finally:
        daemon.stop()


def test_a_stop_before_the_watcher_first_runs_is_harmless(profile, no_marker, monkeypatch):
    """The daemon stops it when its own start fails, possibly before the watcher thread has run at
    all: the watcher still waits on the child it was started for (it read self._process, which
    stop() clears: an AttributeError in a thread, a traceback in the log)."""
    held = []

    class HeldThread:  # the watcher thread, started only once stop() has returned
        def __init__(self, target, args=(), **kwargs):
            self.run = lambda: target(*args)
            held.append(self)

        def start(self):
            pass

        def join(self, timeout=None):
            pass

    monkeypatch.setattr(bw.threading, "Thread", HeldThread)
    warm = BackgroundWarmUp()
    warm.start(profile)
    warm.stop()
    assert len(held) == 1
    held[0].run()  # the watcher's first step, after the stop
    assert warm.state == "stopped"
