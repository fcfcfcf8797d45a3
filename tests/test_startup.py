"""Start-up: the frame loop readies the kernels for its camera's pixel type once, on the first
frame, before ranging it (from numba's cache, which ``uwcam warmup`` fills at install and a
low-priority child fills at start), so the frames after it compile nothing (compiling among them
stalled the loop for seconds and dropped a burst of frames)."""

import time

import numpy as np
import pytest
import yaml

from tests.synthetic import make_profile
from uwcam.config import load_config
from uwcam.runtime.daemon import Daemon
from uwcam.optics import kernels
from uwcam.calibration.profile import save_profile


@pytest.mark.skipif(kernels.BACKEND != "numba", reason="nothing is compiled without numba")
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_first_frames_compile_nothing(tmp_path, dtype):
    import numba

    from uwcam.optics import kernels_numba

    rng = np.random.default_rng(3)
    (tmp_path / "frames").mkdir()
    top = np.iinfo(dtype).max
    for i in range(3):
        np.save(tmp_path / "frames" / f"{i}.npy", rng.integers(top // 10, top // 2, (24, 32, 3)).astype(dtype))
    save_profile(make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5], read_noise=2.0), tmp_path / "p.yaml")
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump({
        "version": 1, "calibration": str(tmp_path / "p.yaml"),
        "camera": {"driver": "replay", "options": {"source": str(tmp_path / "frames"), "fps": 50.0}}}))
    daemon = Daemon(load_config(tmp_path / "rig.yaml"))
    try:
        daemon.start()
        deadline = time.monotonic() + 30
        while daemon.pipeline.processed < 1 and time.monotonic() < deadline:
            time.sleep(0.005)
        # The first frame readied the kernels of its kind (whatever earlier tests in this process
        # compiled: the dispatchers are shared, so only what comes after it is measured).
        assert daemon.pipeline._frame_kind is not None and daemon.pipeline._frame_kind[0] == np.dtype(dtype)
        lookup = {sig[0] for sig in kernels_numba.fuse_lookup.signatures}
        assert any(getattr(t, "dtype", None) == numba.from_dtype(np.dtype(dtype)) for t in lookup), lookup
        compiled = {k: list(k.signatures) for k in (kernels_numba.fuse_lookup, kernels_numba.fuse_arrays)}
        first = daemon.pipeline.processed
        while daemon.pipeline.processed < first + 5 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert daemon.pipeline.processed >= first + 5
        assert {k: list(k.signatures) for k in compiled} == compiled  # nothing new compiled in the loop
    finally:
        daemon.stop()


def test_run_refuses_to_start_without_a_websocket_library(tmp_path):
    """Without a WebSocket library uvicorn would serve the page with no live view (every WebSocket
    route 404): uwcam run says in one line which package is missing, and starts nothing."""
    import subprocess
    import sys

    # The packages are hidden from the import system, as on a machine where they were never installed.
    script = (
        "import importlib.abc, sys\n"
        "class Hide(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('websockets', 'wsproto'):\n"
        "            raise ModuleNotFoundError(name)\n"
        "sys.meta_path.insert(0, Hide())\n"
        "from uwcam.cli import main\n"
        "sys.exit(main(['run', '--port', '0']))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "UWCAM_CACHE_DIR": str(tmp_path)})
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "'websockets' is missing" in lines[0], out.stderr
    assert "operator page" not in out.stdout  # nothing was served
