"""Without numba: the numpy path gives what the compiled kernels give, and uwcam works end to end.

The numpy path is chosen at import when numba is missing (no wheels for 32-bit ARM). Here it is
run in this process explicitly, on the same inputs as the compiled kernels, and in a child
process where `import numba` fails, through the command line.
"""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from tests.synthetic import RGB_ATTENUATION, make_profile, plate_frame, to_counts
from tests.test_estimator import random_frame, reference
from uwcam.optics import Intrinsics, Reason, kernels
from uwcam.ranging.estimator import RangeEstimator

needs_numba = pytest.mark.skipif(kernels.BACKEND != "numba", reason="numba is not installed here")


@pytest.fixture
def numpy_path(monkeypatch):
    """The estimator's kernels switched to the numpy path, as on a machine without numba."""
    monkeypatch.setattr(kernels, "fuse_lookup", kernels.fuse_lookup_numpy)
    monkeypatch.setattr(kernels, "fuse_arrays", kernels.fuse_arrays_numpy)


def estimator_and_frame(dtype, geometry, seed=11, shape=(45, 70)):
    rng = np.random.default_rng(seed)
    sat = {np.uint8: 250, np.uint16: 60000}.get(dtype, 3900.0)
    lamp = (0.0, 0.0, 0.0) if geometry == "equidistant" else (0.25, -0.1, 0.05)
    intr = Intrinsics.from_fov(shape[1], shape[0], 70) if geometry == "rays" else None
    floor = np.array([3.0, 5.0, 2.0, 8.0]) * (1 if dtype == np.uint8 else 40)
    profile = make_profile(
        [0.46, 0.11, 0.06, 0.11], [0.2, -0.1, 0.4, 0.0], names=["R", "G", "B", "N"],  # N shares G's attenuation
        read_noise=[2.0, 3.0, 2.5, 1.0], shot_gain=[0.5, 0.3, 0.2, 1.0], noise_floor=floor,
        dark_level=[1.0, 2.0, 0.0, 3.0], saturation_level=sat, lamp=lamp, intrinsics=intr,
        quantisation_step=0.0 if np.issubdtype(dtype, np.floating) else 1.0,
    )
    est = RangeEstimator(profile, backscatter_level=floor * 1.5, path_length_bounds=(0.5, 40.0))
    frame = random_frame(rng, shape, 4, dtype, sat)
    frame[:3, :, [0, 2]] = 0  # R and B dark: G and N, of one attenuation, are all there is (too few)
    return est, frame, profile


@needs_numba
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("geometry", ["equidistant", "axis", "rays"])
def test_numpy_path_equals_compiled_kernels(dtype, geometry):
    est, frame, _ = estimator_and_frame(dtype, geometry)
    background = np.full(frame.shape, 20.0) if dtype == np.float32 else None  # float frames: with a background
    compiled = est(frame, background=background)
    assert kernels.fuse_lookup is not kernels.fuse_lookup_numpy
    h, w = frame.shape[:2]
    out = [np.full((h, w), -1.0, np.float32), np.full((h, w), -1.0, np.float32), np.full((h, w), 99, np.uint8)]
    if background is None:
        table, offset = est._lookup_tables(frame.dtype)
        b = tuple(float(v) for v in est.log_constant - offset)
        kernels.fuse_lookup_numpy(frame, table, est._c, b, est._cv, est._geo, est.bounds, *out)
    else:
        y, weight, state = est.channel_terms(frame, background)
        pairs = kernels.pack_pairs(y, weight, state, 2, 3)
        kernels.fuse_arrays_numpy(pairs, est._c, (0.0,) * 4, est._cv, est._geo, est.bounds, *out)
    np.testing.assert_array_equal(out[2], compiled.reasons)
    if background is None:
        # Same float32 operations in the same order; only the compiler's choices may differ by an ulp.
        np.testing.assert_allclose(out[0], compiled.range, rtol=1e-6, equal_nan=True)
        np.testing.assert_allclose(out[1], compiled.variance, rtol=1e-6, equal_nan=True)
    else:
        # The compiled background kernel computes each channel's terms in float32, numpy in float64:
        # y = ln E − b differs by float32's rounding of ln E (~1e-6 at ln E ≈ 8), which the fit
        # divides by attenuation differences of ~0.1–0.5 1/m: ~1e-5 m, far inside any range's noise.
        np.testing.assert_allclose(out[0], compiled.range, rtol=1e-6, atol=3e-5, equal_nan=True)
        np.testing.assert_allclose(out[1], compiled.variance, rtol=1e-4, atol=1e-9, equal_nan=True)
    assert len(set(np.unique(compiled.reasons))) >= 4  # the comparison covers valid and invalid pixels


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float64])
@pytest.mark.parametrize("geometry", ["equidistant", "rays"])
def test_numpy_path_matches_the_reference(numpy_path, dtype, geometry):
    est, frame, profile = estimator_and_frame(dtype, geometry, seed=5)
    got = est(frame)
    want = reference(profile, frame, est.backscatter, tuple(est.bounds))
    np.testing.assert_array_equal(got.reasons, want[2])
    assert {Reason.VALID, Reason.SATURATED, Reason.TOO_FEW_CHANNELS} <= set(np.unique(got.reasons))
    np.testing.assert_allclose(got.range, want[0], rtol=2e-5, atol=2e-4, equal_nan=True)
    np.testing.assert_allclose(got.variance, want[1], rtol=2e-4, equal_nan=True)


def test_numpy_path_handles_frames_taller_than_one_block(numpy_path):
    log_constant = np.array([0.0, -0.3, -0.5])
    profile = make_profile(RGB_ATTENUATION, log_constant, read_noise=2.0, shot_gain=0.2)
    frame, truth = plate_frame(1.5, RGB_ATTENUATION, np.exp(log_constant), np.ones(3), shape=(101, 13), fov_deg=6.0)
    got = RangeEstimator(profile)(to_counts(frame, 60000))
    assert (got.reasons == Reason.VALID).all()
    np.testing.assert_allclose(got.range, truth, atol=0.02)  # quantisation noise only


BLOCKER = textwrap.dedent('''
    """Makes numba (and llvmlite) impossible to import, as on a platform without wheels."""
    import sys

    class _NoNumba:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("numba", "llvmlite"):
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, _NoNumba())
''')


@pytest.fixture
def without_numba(tmp_path):
    """Environment for a child process in which `import numba` fails."""
    blocker = tmp_path / "no_numba"
    blocker.mkdir()
    (blocker / "sitecustomize.py").write_text(BLOCKER)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(blocker), *filter(None, [env.get("PYTHONPATH")])])
    return env


def test_blocker_really_hides_numba(without_numba):
    """The daemon and its API (a real rig's `uwcam run`) import without numba, on the numpy path."""
    probe = ("import uwcam.api, uwcam.runtime.daemon, uwcam.optics.kernels as k, sys\n"
             "try:\n import numba\nexcept ImportError:\n print(k.BACKEND, 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], env=without_numba, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["numpy", "False"]


def test_range_command_without_numba(tmp_path, without_numba):
    """Calibrate and range with the command line in a process without numba; the maps equal
    those of this process's estimator (compiled where numba is installed)."""
    from uwcam.calibration.profile import load_profile

    consts = np.exp(-np.array([0.0, 0.3, 0.5])) * 1.5e5
    rng = np.random.default_rng(2)
    for name, d in (("near", 1.0), ("far", 2.0), ("scene", 1.6)):
        f, _ = plate_frame(d, RGB_ATTENUATION, consts, np.full(3, 0.2), shape=(60, 80), lamp=np.array([0.2, 0.0, 0.0]))
        f = f + np.sqrt(9.0 + 0.2 * f) * rng.standard_normal(f.shape)
        np.save(tmp_path / f"{name}.npy", np.clip(np.rint(f), 0, 65535).astype(np.uint16))
    run = [sys.executable, "-m", "uwcam"]
    profile = tmp_path / "p.yaml"
    subprocess.run([*run, "calibrate", str(tmp_path / "near.npy"), str(tmp_path / "far.npy"), "--distance", "1",
                    "--distance", "2", "-o", str(profile)], env=without_numba, check=True, capture_output=True)
    out = subprocess.run([*run, "range", str(profile), str(tmp_path / "scene.npy"), "-o", str(tmp_path / "r.npy"),
                          "--variance", str(tmp_path / "v.npy"), "--reasons", str(tmp_path / "q.npy")],
                         env=without_numba, check=True, capture_output=True, text=True)
    assert "100.0% of pixels valid" in out.stdout
    here = RangeEstimator(load_profile(profile))(np.load(tmp_path / "scene.npy"))
    np.testing.assert_array_equal(np.load(tmp_path / "q.npy"), here.reasons)
    np.testing.assert_allclose(np.load(tmp_path / "r.npy"), here.range, rtol=1e-6)
    np.testing.assert_allclose(np.load(tmp_path / "v.npy"), here.variance, rtol=1e-6)
