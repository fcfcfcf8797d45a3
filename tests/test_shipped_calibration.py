"""The simulated-water calibrations of the setups ``uwcam run --simulate NAME`` starts (the embedded
default vehicle and the tank) ship with uwcam, so that a new user's first start ranges at once.
Each must be what calibrating in that water gives today."""

from __future__ import annotations

import math
import os

import pytest

from uwcam.config import SIMULATED_SETUPS
from uwcam.runtime.simulated_rig import calibrate_simulated_water, shipped_calibration_path, simulated_calibration
from uwcam.drivers.sim import SimulatedRig
from uwcam.calibration.profile import load_profile
from uwcam.simulation import tank



def regenerate(setup: str) -> str:
    return (f"regenerate it: .venv/bin/python -c 'from uwcam.config import SIMULATED_SETUPS; "
            f"from uwcam.runtime.simulated_rig import ship_simulated_calibration; "
            f"ship_simulated_calibration(SIMULATED_SETUPS[\"{setup}\"]())'")


def setup_rig(setup: str) -> SimulatedRig:
    return SimulatedRig(**SIMULATED_SETUPS[setup]().simulation)


def differences(a, b, where: str = "") -> list[str]:
    """Where two profile dumps differ beyond floating-point noise (1e-9 relative)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{where}: keys {sorted(a)} != {sorted(b)}"]
        return [d for k in a if k != "created" for d in differences(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{where}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{where}[{i}]")]
    if isinstance(a, float) or isinstance(b, float):
        if a is None or b is None or not math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12):
            return [f"{where}: shipped {a!r}, fresh {b!r}"]
        return []
    return [] if a == b else [f"{where}: shipped {a!r}, fresh {b!r}"]


@pytest.mark.slow
@pytest.mark.parametrize("setup", sorted(SIMULATED_SETUPS))
def test_the_shipped_calibration_is_what_calibrating_gives_today(setup):
    rig = setup_rig(setup)
    path = shipped_calibration_path(rig)
    assert os.path.exists(path), f"no shipped calibration for the simulated {setup} at {path}: {regenerate(setup)}"
    shipped = load_profile(path).model_dump(mode="json")
    fresh = calibrate_simulated_water(rig).model_dump(mode="json")
    assert differences(shipped, fresh) == [], f"the simulator or calibration changed: {regenerate(setup)}"


@pytest.mark.parametrize("setup", sorted(SIMULATED_SETUPS))
def test_each_simulated_setup_starts_from_the_shipped_calibration_without_calibrating(setup, monkeypatch, tmp_path, caplog):
    monkeypatch.setenv("UWCAM_CACHE_DIR", str(tmp_path / "empty"))
    monkeypatch.setattr(tank, "calibrate_in_simulation", lambda *a, **k: pytest.fail("calibrated at start"))
    caplog.set_level("INFO", logger="uwcam.runtime.simulated_rig")
    rig = setup_rig(setup)
    profile = simulated_calibration(rig)
    assert profile.intrinsics["fx"] == pytest.approx(rig.world.intrinsics.fx)
    assert "ships with uwcam" in caplog.text and "calibrating" not in caplog.text
    assert not os.path.exists(tmp_path / "empty")  # nothing written to the cache
