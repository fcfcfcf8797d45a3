"""The embedded default's simulated calibration is computed once per rig and code, then loaded."""

from __future__ import annotations

import os

import pytest

from uwcam.runtime import simulated_rig
from uwcam.runtime.simulated_rig import simulated_calibration, simulated_calibration_key
from uwcam.drivers.sim import SimulatedRig
from uwcam.simulation import tank


@pytest.fixture
def counted(monkeypatch, tmp_path):
    """Calibrations actually run, with the cache in a folder of this test."""
    monkeypatch.setenv("UWCAM_CACHE_DIR", str(tmp_path / "cache"))
    calls = []
    original = tank.calibrate_in_simulation

    def counting(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(tank, "calibrate_in_simulation", counting)
    return calls


def rig(**kw) -> SimulatedRig:
    return SimulatedRig(**{"scene": "seabed", "size": (64, 48), "water": "jerlov-IB", **kw})


def test_the_second_start_loads_what_the_first_calibrated(counted, tmp_path):
    first = simulated_calibration(rig())
    second = simulated_calibration(rig())
    assert len(counted) == 1
    assert second.model_dump() == first.model_dump()  # the same profile, to the last digit
    assert os.listdir(tmp_path / "cache") == [f"simulated-calibration-{simulated_calibration_key(rig())}.yaml"]


@pytest.mark.parametrize("change", [{"water": "jerlov-II"}, {"lamp_offset": (0.3, 0.1, 0.0)}, {"size": (80, 48)}, {"bits": 8}])
def test_another_rig_calibrates_afresh(counted, change):
    simulated_calibration(rig())
    simulated_calibration(rig(**change))
    assert len(counted) == 2
    assert simulated_calibration_key(rig(**change)) != simulated_calibration_key(rig())


def test_the_key_follows_uwcams_own_code(monkeypatch, tmp_path):
    before = simulated_calibration_key(rig())
    fake = tmp_path / "uwcam"
    fake.mkdir()
    (fake / "__init__.py").write_text("# another uwcam\\n")
    import uwcam

    monkeypatch.setattr(uwcam, "__file__", str(fake / "__init__.py"))
    assert simulated_calibration_key(rig()) != before


def test_a_damaged_cache_file_is_calibrated_over(counted, tmp_path):
    simulated_calibration(rig())
    path = tmp_path / "cache" / f"simulated-calibration-{simulated_calibration_key(rig())}.yaml"
    path.write_text("channels: [unfinished")
    profile = simulated_calibration(rig())
    assert len(counted) == 2 and profile.channels
    assert simulated_calibration(rig()).model_dump() == profile.model_dump() and len(counted) == 2


def test_an_unwritable_cache_still_gives_a_calibration(counted, monkeypatch, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("UWCAM_CACHE_DIR", str(blocker / "cache"))
    assert simulated_calibration(rig()).channels and simulated_calibration(rig()).channels
    assert len(counted) == 2  # calibrated at every start, as without a cache


def test_the_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("UWCAM_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert simulated_rig.cache_dir() == str(tmp_path / "uwcam")
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert simulated_rig.cache_dir() == os.path.expanduser("~/.cache/uwcam")


def test_only_the_newest_calibrations_are_kept(counted, monkeypatch, tmp_path):
    monkeypatch.setattr(simulated_rig, "SIMULATED_CALIBRATIONS_KEPT", 2)
    for water in ("jerlov-IA", "jerlov-IB", "jerlov-II"):
        simulated_calibration(rig(water=water))
    kept = sorted(os.listdir(tmp_path / "cache"))
    assert len(kept) == 2 and f"simulated-calibration-{simulated_calibration_key(rig(water='jerlov-II'))}.yaml" in kept
