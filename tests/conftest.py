"""Shared test fixtures: no test and no test module may leave a thread of its own running."""

import os
import tempfile
import threading
import time

import pytest

# What uwcam keeps between runs (the simulated calibration) goes into a folder of this test run,
# never the user's ~/.cache: tests start from nothing, and the daemons they start see the same.
os.environ["UWCAM_CACHE_DIR"] = tempfile.mkdtemp(prefix="uwcam-test-cache-")
# Likewise what a daemon keeps of an open tank calibration session without a state folder
# ($XDG_STATE_HOME/uwcam): never the user's, and a test that needs its own gives a state_dir.
os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="uwcam-test-state-")

# Worker threads of the thread pools that a server's event loop keeps: anyio's for sync handlers,
# asyncio's default executor for asyncio.to_thread (parsing uploads, encoding the page's view).
# A module-scoped server starts them on demand and keeps them idle for a while after a request,
# so a single test cannot be blamed for them; they must be gone once the module's server has
# stopped, which the module-scoped check below verifies.
POOL_WORKERS = ("AnyIO worker thread", "asyncio_")


def _leaked(before: set[threading.Thread], ignore: tuple[str, ...], timeout_s: float) -> list[threading.Thread]:
    deadline = time.monotonic() + timeout_s
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()
                  and not t.name.startswith(("pydevd", *ignore))]
        if not leaked or time.monotonic() > deadline:
            return leaked
        leaked[0].join(timeout=0.1)


@pytest.fixture(autouse=True, scope="module")
def no_leaked_threads_in_module():
    """Fail a module that leaves any thread running once its module-scoped fixtures are torn down
    (practice 8 of STYLE.md); this fixture is set up before them and torn down after them."""
    before = set(threading.enumerate())
    yield
    leaked = _leaked(before, (), 15.0)
    assert not leaked, f"test module left threads running: {[t.name for t in leaked]}"


@pytest.fixture(autouse=True)
def own_state_home(tmp_path_factory, monkeypatch):
    """Each test keeps daemon state of its own ($XDG_STATE_HOME: an open calibration session), so
    a session one test leaves open is never resumed by another test's daemon."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state-home")))


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Fail any test that leaves a Python thread of its own running (practice 8 of STYLE.md)."""
    before = set(threading.enumerate())
    yield
    leaked = _leaked(before, POOL_WORKERS, 5.0)
    assert not leaked, f"test left threads running: {[t.name for t in leaked]}"


@pytest.fixture(scope="session")
def warm_kernels():
    """Compile (or load from numba's cache) the simulator's and the estimator's kernels once, before
    any test waits on a clock: on a fresh checkout compiling takes longer than a frame timeout."""
    import numpy as np

    from tests.synthetic import make_profile
    from uwcam.drivers.sim import SimulatedCamera, SimulatedRig
    from uwcam.ranging.estimator import RangeEstimator

    camera = SimulatedCamera(SimulatedRig(size=(16, 12), distance=2.0), fps=1000.0, serial_number="SIM-WARM-UP")
    camera.open()
    camera.start()
    try:
        camera.read(timeout_s=600.0)  # rendering and digitising compile here
    finally:
        camera.stop()
        camera.close()
    estimator = RangeEstimator(make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0]))
    estimator(np.full((2, 2, 3), 1000, np.uint16))
    estimator(np.full((2, 2, 3), 1000.0, np.float32))
