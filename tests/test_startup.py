"""Start-up: the daemon readies its kernels before the camera starts, so the frame loop's first
frames compile nothing (compiling there stalled the loop for seconds and dropped a burst of frames)."""

import time

import numpy as np
import pytest
import yaml

from tests.synthetic import make_profile
from uwcam.config import load_config
from uwcam.daemon import Daemon
from uwcam.optics import kernels
from uwcam.profile import save_profile


@pytest.mark.skipif(kernels.BACKEND != "numba", reason="nothing is compiled without numba")
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_first_frames_compile_nothing(tmp_path, dtype):
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
        compiled = {k: list(k.signatures) for k in (kernels_numba.fuse_lookup, kernels_numba.fuse_arrays)}
        deadline = time.monotonic() + 30
        while daemon.pipeline.processed < 5 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert daemon.pipeline.processed >= 5
        assert {k: list(k.signatures) for k in compiled} == compiled  # nothing new compiled in the loop
    finally:
        daemon.stop()
