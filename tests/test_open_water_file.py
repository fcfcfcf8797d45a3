"""The open-water frame's file follows what the operator last did: a removal during a slow write
(megabytes and an fsync on an SD card) is not undone by that write finishing, and of two captures
the later one is what the next start restores, whichever write finishes first."""

from __future__ import annotations

import threading
import time
import types

import numpy as np

from tests.test_api import small_config
from uwcam.runtime.daemon import Daemon


def daemon_with_state(tmp_path):
    cfg = small_config()
    cfg.state_dir = str(tmp_path)
    d = Daemon(cfg)  # not started: only its open-water file handling is exercised
    d.pipeline = types.SimpleNamespace(set_open_water=lambda frame, info=None: None)
    return d


def slow_savez(monkeypatch, delays):
    """np.savez taking delays[i] seconds on its i-th call; `writing` is set when one begins."""
    real, calls, writing = np.savez, [], threading.Event()

    def savez(*args, **kwargs):
        calls.append(1)
        writing.set()
        time.sleep(delays[min(len(calls) - 1, len(delays) - 1)])
        return real(*args, **kwargs)

    monkeypatch.setattr(np, "savez", savez)
    return writing


def writers_done(timeout_s=10.0):
    for t in [t for t in threading.enumerate() if t.name == "open-water-writer"]:
        t.join(timeout_s)
        assert not t.is_alive()


def test_a_removal_during_the_write_stays_removed(tmp_path, monkeypatch):
    d = daemon_with_state(tmp_path)
    writing = slow_savez(monkeypatch, [0.5])
    d._keep_open_water(np.ones((8, 8, 3), np.float32), {"source": "capture"})
    assert writing.wait(5.0)
    d.forget_open_water()  # DELETE /api/v1/backscatter/open-water while the file is being written
    writers_done()
    assert not (tmp_path / Daemon.OPEN_WATER_FILE).exists(), "the deleted open-water frame would come back at the next start"


def test_the_later_capture_is_kept_whichever_write_ends_first(tmp_path, monkeypatch):
    d = daemon_with_state(tmp_path)
    writing = slow_savez(monkeypatch, [0.5, 0.0])
    d._keep_open_water(np.full((8, 8, 3), 1.0, np.float32), {"source": "first"})
    assert writing.wait(5.0)
    d._keep_open_water(np.full((8, 8, 3), 2.0, np.float32), {"source": "second"})
    writers_done()
    with np.load(tmp_path / Daemon.OPEN_WATER_FILE) as saved:
        assert float(saved["frame"][0, 0, 0]) == 2.0


def test_a_capture_after_a_removal_is_kept(tmp_path, monkeypatch):
    d = daemon_with_state(tmp_path)
    d.forget_open_water()
    d._keep_open_water(np.full((8, 8, 3), 3.0, np.float32), {"source": "capture"})
    writers_done()
    with np.load(tmp_path / Daemon.OPEN_WATER_FILE) as saved:
        assert float(saved["frame"][0, 0, 0]) == 3.0
