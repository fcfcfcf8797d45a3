"""Parallel kernels from several threads on a machine without libgomp or libtbb.

numba then falls back to its "workqueue" threading layer, which aborts the process when two
threads launch parallel kernels at once: the frame loop and the simulated camera do exactly
that. Each case runs in a fresh interpreter in which numba's OpenMP and TBB pools cannot be
imported, as on a minimal Debian or Raspberry Pi OS image.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

WITHOUT_THREADSAFE_POOLS = """
import sys
sys.modules["numba.np.ufunc.omppool"] = None  # libgomp missing
sys.modules["numba.np.ufunc.tbbpool"] = None  # libtbb missing
"""

TWO_THREADS = """
import threading
errors = []
def run():
    try:
        for _ in range(60):
            work()
    except BaseException as exc:
        errors.append(exc)
threads = [threading.Thread(target=run) for _ in range(2)]
[t.start() for t in threads]
[t.join() for t in threads]
assert not errors, errors
print("survived", flush=True)
"""


def run(code: str, env_layer: str | None = None) -> subprocess.CompletedProcess:
    import os

    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    if env_layer:
        env["NUMBA_THREADING_LAYER"] = env_layer
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300, env=env)


def test_the_hazard_is_real_a_bare_parallel_kernel_aborts_from_two_threads():
    code = WITHOUT_THREADSAFE_POOLS + """
import numpy as np
from numba import njit, prange, threading_layer
@njit(parallel=True, nogil=True)
def kernel(a):
    s = 0.0
    for i in prange(a.shape[0]):
        s += np.sqrt(a[i]).sum()
    return s
a = np.random.default_rng(0).random((1500, 1500))
kernel(a)
print(threading_layer(), flush=True)
def work():
    kernel(a)
""" + TWO_THREADS
    done = run(code)
    assert done.stdout.startswith("workqueue") and "survived" not in done.stdout
    assert done.returncode != 0 and "Concurrent access" in done.stderr


def test_uwcam_kernels_take_turns_there_and_give_the_same_ranges():
    code = WITHOUT_THREADSAFE_POOLS + """
import numpy as np
import uwcam.compute.parallel
from numba import threading_layer
from tests.synthetic import RGB_ATTENUATION, make_profile
from uwcam.ranging.estimator import RangeEstimator
from uwcam.simulation.camera import CameraModel

assert uwcam.compute.parallel.SERIALISED
est = RangeEstimator(make_profile(RGB_ATTENUATION, [0.0, 0.1, 0.2], read_noise=3.0, shot_gain=0.2))
frame = np.random.default_rng(1).integers(500, 3000, (720, 1280, 3)).astype(np.uint16)
expected = est(frame).range
camera = CameraModel(bits=12)
mean = (np.random.default_rng(2).random((480, 640, 3)) * 3000).astype(np.float32)
std = np.full(mean.shape, 20.0, np.float32)
camera.digitise(mean, std, seed=1, frame_index=0)
print(threading_layer(), flush=True)
def work():
    assert np.array_equal(est(frame).range, expected, equal_nan=True)
    camera.digitise(mean, std, seed=1, frame_index=0)  # the simulator's own parallel kernel, meanwhile
""" + TWO_THREADS
    done = run(code)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == ["workqueue", "survived"]


def test_where_openmp_is_there_the_kernels_run_concurrently_on_it():
    done = run("""
import numpy as np
import uwcam.compute.parallel
from numba import threading_layer
from tests.synthetic import RGB_ATTENUATION, make_profile
from uwcam.ranging.estimator import RangeEstimator
RangeEstimator(make_profile(RGB_ATTENUATION, [0.0, 0.1, 0.2]))(np.ones((4, 4, 3), np.uint16))
print(uwcam.compute.parallel.SERIALISED, uwcam.compute.parallel.threadsafe_layers(), threading_layer())
""")
    assert done.returncode == 0, done.stderr[-3000:]
    serialised, layers, layer = done.stdout.split(maxsplit=1)[0], done.stdout, done.stdout.split()[-1]
    assert serialised == "False" and "omp" in layers and layer == "omp"


def _openmp_wait_policy(preset: str | None) -> str:
    """The wait policy libgomp reports (OMP_DISPLAY_ENV) when a frame is ranged in a fresh daemon
    interpreter, with OMP_WAIT_POLICY preset by the user or not."""
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    env["OMP_DISPLAY_ENV"] = "true"
    if preset is not None:
        env["OMP_WAIT_POLICY"] = preset
    code = textwrap.dedent("""
        import numpy as np
        import uwcam.cli  # what `uwcam run` imports first
        from tests.synthetic import make_profile
        from uwcam.ranging.estimator import RangeEstimator
        RangeEstimator(make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5]))(np.full((16, 16, 3), 900, np.uint16))
    """)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line for line in out.stderr.splitlines() if "OMP_WAIT_POLICY" in line]
    if not lines:
        import pytest

        pytest.skip("numba does not run on OpenMP here (no libgomp): no wait policy to check")
    return lines[0].split("=")[1].strip().strip("'")


def test_openmp_workers_sleep_between_kernels_unless_the_user_says_otherwise():
    # Spinning workers take the cores the camera, the loop and the server need between kernels.
    assert _openmp_wait_policy(None) == "PASSIVE"
    assert _openmp_wait_policy("ACTIVE") == "ACTIVE"
