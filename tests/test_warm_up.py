"""A settings change never makes the frame loop compile a kernel.

numba compiles a kernel for each new combination of argument types where it first meets it; met
in the frame loop, that stalled the loop for 16 s after a switch to smoothing before the
transform (empty cache, 2 cores). The kernels a numba dispatcher knows are its ``signatures``:
none may be added while frames flow after the change was applied."""

import sys

import numpy as np
import pytest

from tests.served import Server
from tests.test_api import small_config
from tests.waiting import wait_for
from uwcam.compute.jit import HAVE_NUMBA

pytestmark = pytest.mark.skipif(not HAVE_NUMBA, reason="without numba nothing is compiled")


def known_kernels() -> dict[str, set]:
    """Every numba dispatcher in uwcam's modules, by name, with the signatures it holds."""
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("uwcam"):
            for attr, value in list(vars(module).items()):
                if hasattr(value, "signatures") and hasattr(value, "py_func"):
                    found[f"{name}.{attr}"] = set(value.signatures)
    return found


CHANGES = [
    {"smoothing": "mean", "smoothing_stage": "before"},
    {"smoothing": "median", "smoothing_stage": "before"},
    {"smoothing": "adaptive"},
    {"smoothing": "mean", "smoothing_stage": "after"},
    {"smoothing": "none", "temporal": {}},
    {"smoothing": "mean", "smoothing_stage": "before"},
    {"temporal": None, "smoothing": "none", "lamp_off_interval": 4},
    {"lamp_off_interval": 0, "backscatter": {"iterations": 2}, "smoothing": "mean", "smoothing_stage": "before"},
    {"backscatter": None, "smoothing": "none"},
]


def test_settings_changes_compile_nothing_in_the_frame_loop():
    with Server(small_config()) as s:
        assert wait_for(lambda: s.daemon.pipeline.processed > 2, 60.0)
        for change in CHANGES:
            # The change compiles (or loads from the cache) in the request's thread, however long it takes.
            assert s.http.patch("/api/v1/config", json=change, timeout=300.0).status_code == 200
            before = known_kernels()
            n = s.daemon.pipeline.processed
            assert wait_for(lambda: s.daemon.pipeline.processed > n + 4, 30.0), f"the loop stalled after {change}"
            after = known_kernels()
            met = {k: v - before.get(k, set()) for k, v in after.items() if v - before.get(k, set())}
            assert not met, f"after {change} the frame loop compiled {met}"
            latest = s.daemon.pipeline.latest
            assert np.isfinite(latest.result.range).mean() > 0.5
