"""Fusion kernels at their edges: every combination of channel states, exact boundaries, tiny
weights, 255 channels, the geometry vector's slots, and the choice of backend at import.

Expected values come from outside the kernels: the reason rules as docs/physics.md and
:func:`uwcam.optics.validity.pixel_reasons` state them, re-written here per pixel; ranges from the
closed form of the geometry (equidistant: r = d/2; lamp at S ⟂ the axis: d = r + √(r² + |S|²)).
Inputs are float32-representable, so that exact equalities (d equal to a bound or to |S|) are exact
in the kernels' float32 arithmetic too.
"""

from __future__ import annotations

import importlib.util
import itertools
import logging
import sys

import numpy as np
import pytest

import uwcam.optics
from tests.synthetic import make_profile
from uwcam.fileio import UserInputError
from uwcam.optics import ChannelState, Reason, kernels
from uwcam.ranging.estimator import RangeEstimator

USABLE, BELOW, SATURATED, BACKSCATTER = (ChannelState.USABLE, ChannelState.BELOW_NOISE_FLOOR,
                                         ChannelState.SATURATED, ChannelState.BACKSCATTER_ONLY)
NO_LAMP = np.array([kernels.EQUIDISTANT, 0, 0, 0, 0, 0, 0, 0, 0], np.float64)


def _fusers():
    fusers = [pytest.param(kernels.fuse_arrays_numpy, id="numpy")]
    if kernels.BACKEND == "numba":
        from uwcam.optics import kernels_numba

        fusers.append(pytest.param(kernels_numba.fuse_arrays, id="compiled"))
    return fusers


FUSERS = _fusers()


def fuse(fuser, y, w, states, c, geo=NO_LAMP, bounds=(0.5, 40.0)):
    """Range, variance and reason of pixels (H, W) from per-channel y, w, states (H, W, N)."""
    y, w, states = (np.asarray(a) for a in (y, w, states))
    pairs = kernels.pack_pairs(y, w, states, ChannelState.SATURATED, ChannelState.BACKSCATTER_ONLY)
    h, wd = pairs.shape[:2]
    out = (np.full((h, wd), -1.0, np.float32), np.full((h, wd), -1.0, np.float32), np.full((h, wd), 99, np.uint8))
    n = pairs.shape[-1]
    fuser(np.ascontiguousarray(pairs), tuple(float(v) for v in c), (0.0,) * n, np.zeros((n, n)), np.asarray(geo, np.float64),
          np.asarray(bounds, np.float64), *out)
    return out


def reference_reason(states, c, d, bounds):
    """The documented rule for one pixel, written out: two usable channels of distinct attenuation
    give a range (VALID or PATH_OUT_OF_BOUNDS). Otherwise (fewer, or usable ones of one
    attenuation) SATURATED if any channel is, then BACKSCATTER_ONLY (a backscatter-only channel,
    and usable + backscatter-only ≥ 2), then TOO_FEW_CHANNELS (a usable one), then BELOW_NOISE_FLOOR."""
    usable = [k for k, s in enumerate(states) if s == USABLE]
    if len({c[k] for k in usable}) >= 2:
        return Reason.VALID if bounds[0] <= d <= bounds[1] else Reason.PATH_OUT_OF_BOUNDS
    if any(s == SATURATED for s in states):
        return Reason.SATURATED
    backscatter = sum(s == BACKSCATTER for s in states)
    if backscatter > 0 and len(usable) + backscatter >= 2:
        return Reason.BACKSCATTER_ONLY
    return Reason.TOO_FEW_CHANNELS if usable else Reason.BELOW_NOISE_FLOOR


@pytest.mark.parametrize("fuser", FUSERS)
@pytest.mark.parametrize("weight", [0.25, 1.0, 6.0])  # weights ≤ 1 too: a usable channel counts whatever its weight
@pytest.mark.parametrize("d", [3.0, 48.0])  # in bounds, out of bounds
def test_every_combination_of_channel_states_gives_the_documented_reason(fuser, weight, d):
    c = (0.5, 0.25, 0.25, 0.0)  # channels 1 and 2 share one attenuation
    bounds = (0.5, 40.0)
    combos = list(itertools.product([USABLE, BELOW, SATURATED, BACKSCATTER], repeat=4))  # 256 pixels
    states = np.array(combos, np.uint8).reshape(16, 16, 4)
    y = np.broadcast_to(-np.array(c) * d, states.shape)  # ln E − b = −c·d: a surface at path length d
    w = np.where(states == USABLE, weight, 0.0)
    rng, var, reason = fuse(fuser, y, w, states, c, bounds=bounds)
    want = np.array([reference_reason(s, c, d, bounds) for s in combos]).reshape(16, 16)
    np.testing.assert_array_equal(reason, want)
    valid = want == Reason.VALID
    # Valid: two or more usable channels, not only channels 1 and 2 (5·9 + 4·3 + 1 combinations).
    assert valid.sum() == (0 if d > bounds[1] else 58)
    np.testing.assert_allclose(rng[valid], d / 2, rtol=1e-5)  # equidistant: r = d/2
    assert np.isnan(rng[~valid]).all() and np.isnan(var[~valid]).all()
    assert (var[valid] > 0).all()


def two_channel_pixel(d, weight=1.0):
    """One pixel, channels with c = (1, 0) and y = (−d, 0): path length exactly d in float32."""
    y = np.array([[[-d, 0.0]]])
    return y, np.full((1, 1, 2), weight), np.zeros((1, 1, 2), np.uint8), (1.0, 0.0)


@pytest.mark.parametrize("fuser", FUSERS)
@pytest.mark.parametrize("weight", [0.5, 1.0, 3.0])  # D = w²: below, at and above 1
def test_a_path_length_exactly_at_either_bound_is_in_bounds(fuser, weight):
    y, w, s, c = two_channel_pixel(2.0, weight)
    for bounds in ((2.0, 40.0), (0.5, 2.0), (2.0, 2.0)):
        rng, var, reason = fuse(fuser, y, w, s, c, bounds=bounds)
        assert reason[0, 0] == Reason.VALID, bounds
        assert rng[0, 0] == pytest.approx(1.0, rel=1e-6)
        # Var(d) = Σw / D = 2w / w², and ∂r/∂d = 1/2 without a lamp.
        assert var[0, 0] == pytest.approx(0.25 * 2 / weight, rel=1e-5)
    for bounds in ((2.5, 40.0), (0.5, 1.5)):
        assert fuse(fuser, y, w, s, c, bounds=bounds)[2][0, 0] == Reason.PATH_OUT_OF_BOUNDS


@pytest.mark.parametrize("fuser", FUSERS)
def test_a_path_length_equal_to_the_lamp_offset_has_no_range(fuser):
    """Lamp 2 m to the side (|S| = 2, S·u = 0 on the axis): light that travels d = |S| would come
    from a surface at range 0, where the camera cannot be; d = 3 is a surface at r = 5/6 m
    (5/6 + √((5/6)² + 4) = 5/6 + 13/6 = 3)."""
    geo = np.array([kernels.LAMP_ON_AXIS_RAY, 2.0, 0.0, 0.0, 2.0, 0, 0, 0, 0], np.float64)
    y, w, s, c = two_channel_pixel(2.0)
    rng, var, reason = fuse(fuser, y, w, s, c, geo=geo, bounds=(0.0, 40.0))
    assert reason[0, 0] == Reason.PATH_OUT_OF_BOUNDS and np.isnan(rng[0, 0]) and np.isnan(var[0, 0])
    y, w, s, c = two_channel_pixel(3.0)
    rng, _, reason = fuse(fuser, y, w, s, c, geo=geo, bounds=(0.0, 40.0))
    assert reason[0, 0] == Reason.VALID
    assert rng[0, 0] == pytest.approx(5 / 6, rel=1e-6)


@pytest.mark.parametrize("fuser", FUSERS)
def test_a_spread_that_underflows_to_zero_gives_no_range_even_without_bounds(fuser):
    """Weights of 1e−22 (w_k w_l = 1e−44, a float32 subnormal) and c_k − c_l = 1/4: D = w w (c_k − c_l)²
    underflows to exactly 0 while M does not, so d = −M/D is +∞. With bounds (0, ∞) only D > 0
    keeps such a pixel from being reported valid."""
    y = np.array([[[-100.0, 0.0]]])
    w = np.full((1, 1, 2), 1e-22)
    rng, var, reason = fuse(fuser, y, w, np.zeros((1, 1, 2), np.uint8), (0.25, 0.0), bounds=(0.0, np.inf))
    assert np.float32(1e-22) * np.float32(1e-22) * np.float32(0.0625) == 0.0  # the premise
    assert reason[0, 0] == Reason.TOO_FEW_CHANNELS
    assert np.isnan(rng[0, 0]) and np.isnan(var[0, 0])


@pytest.fixture
def numpy_path(monkeypatch):
    """The estimator's kernels on the numpy path (255 channels would take numba minutes to compile:
    the channel loops unroll)."""
    monkeypatch.setattr(kernels, "fuse_lookup", kernels.fuse_lookup_numpy)
    monkeypatch.setattr(kernels, "fuse_arrays", kernels.fuse_arrays_numpy)


def many_channel_profile(n):
    return make_profile(np.linspace(0.5, 0.0, n), np.zeros(n), read_noise=1.0, noise_floor=10.0,
                        saturation_level=60000.0, quantisation_step=0.0)


def test_255_channels_are_counted_exactly_and_256_are_refused(numpy_path):
    """The channel counts are packed in 8 bits per state, so 255 channels is the most the kernels
    count exactly: a profile with 255 is accepted, with every count at its largest; 256 is refused."""
    n = 255
    c = np.linspace(0.5, 0.0, n)
    est = RangeEstimator(many_channel_profile(n), backscatter_level=np.full(n, 50.0))
    d = 6.0
    surface = 1e4 * np.exp(-c * d)  # every channel well above the floor and the water's light
    frame = np.empty((1, 6, n))
    frame[0, 0] = surface                       # all usable
    frame[0, 1] = 30.0                          # all above the floor but not the water's light
    frame[0, 2] = 65000.0                       # all saturated
    frame[0, 3] = 5.0                           # all below the floor
    frame[0, 4] = 30.0                          # one usable, the rest backscatter-only
    frame[0, 4, 0] = surface[0]
    frame[0, 5] = 65000.0                       # one usable, the rest saturated
    frame[0, 5, 7] = surface[7]
    got = est(frame)
    assert list(got.reasons[0]) == [Reason.VALID, Reason.BACKSCATTER_ONLY, Reason.SATURATED,
                                    Reason.BELOW_NOISE_FLOOR, Reason.BACKSCATTER_ONLY, Reason.SATURATED]
    # Log constants of 0 with a surface 1e4 bright: y = ln 1e4 − c·d, a common shift, which the fit
    # ignores; d = 6 m without a lamp is a range of 3 m.
    assert got.range[0, 0] == pytest.approx(d / 2, rel=1e-4)
    with pytest.raises(UserInputError, match="at most 255"):
        RangeEstimator(many_channel_profile(n + 1))


def test_lamp_geometry_returns_the_documented_slots():
    """geo = [mode, Sx, Sy, Sz, |S|, 1/fx, 1/fy, cx, cy]; ray terms only with per-pixel rays, Sz
    only for the lamp on the axis, |S| always (lamp at (0.3, −0.4, 1.2): |S| = 1.3)."""
    slots = [0.3, -0.4, 1.2, 1.3, 1 / 800, 1 / 600, 320.0, 240.0]
    got = {mode: kernels.lamp_geometry(np.array([mode, *slots])) for mode in
           (kernels.EQUIDISTANT, kernels.LAMP_ON_AXIS_RAY, kernels.LAMP_PIXEL_RAYS)}
    assert got[kernels.LAMP_PIXEL_RAYS] == pytest.approx((0.3, -0.4, 1.2, 1 / 800, 1 / 600, 320.0, 240.0, 1.3))
    assert got[kernels.LAMP_ON_AXIS_RAY] == pytest.approx((0, 0, 1.2, 0, 0, 0, 0, 1.3))
    assert got[kernels.EQUIDISTANT] == pytest.approx((0, 0, 0, 0, 0, 0, 0, 1.3))


class _FailingImport:
    """Makes `import uwcam.optics.kernels_numba` raise a given ImportError."""

    def __init__(self, exc):
        self.exc = exc

    def find_spec(self, name, path=None, target=None):
        if name == "uwcam.optics.kernels_numba":
            raise self.exc
        return None


def _import_kernels_afresh(monkeypatch, exc):
    """A fresh copy of uwcam.optics.kernels (under another name; the real one is untouched) whose
    import of the compiled kernels raises ``exc``."""
    monkeypatch.delitem(sys.modules, "uwcam.optics.kernels_numba", raising=False)
    monkeypatch.delattr(uwcam.optics, "kernels_numba", raising=False)
    monkeypatch.setattr(sys, "meta_path", [_FailingImport(exc), *sys.meta_path])
    spec = importlib.util.spec_from_file_location("uwcam_kernels_probe", kernels.__file__)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("missing", ["numba", "llvmlite"])
def test_without_numba_the_numpy_path_is_chosen_quietly(monkeypatch, caplog, missing):
    caplog.set_level(logging.WARNING)
    probe = _import_kernels_afresh(monkeypatch, ModuleNotFoundError(f"No module named {missing!r}", name=missing))
    assert probe.BACKEND == "numpy"
    assert probe.fuse_lookup is probe.fuse_lookup_numpy and probe.fuse_background is None
    assert not caplog.records  # a platform without numba is normal, not a fault


def test_a_broken_numba_falls_back_to_numpy_with_a_warning(monkeypatch, caplog):
    caplog.set_level(logging.WARNING)
    exc = ImportError("numpy.core.multiarray failed to import", name="numba.core.typeconv._typeconv")
    probe = _import_kernels_afresh(monkeypatch, exc)
    assert probe.BACKEND == "numpy" and probe.fuse_arrays is probe.fuse_arrays_numpy
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "numba cannot be imported" in caplog.records[0].getMessage()


def test_a_broken_uwcam_module_is_not_hidden_behind_the_numpy_path(monkeypatch):
    """An import inside uwcam that fails (here: a module the compiled kernels import) is a broken
    install of uwcam itself, not a missing numba: it is raised, not answered with the numpy path."""
    exc = ModuleNotFoundError("No module named 'uwcam.compute.parallel'", name="uwcam.compute.parallel")
    with pytest.raises(ModuleNotFoundError, match="uwcam.compute.parallel"):
        _import_kernels_afresh(monkeypatch, exc)


def _python(f):
    """The Python source of a numba kernel (``py_func``; the function itself when JIT is off)."""
    return getattr(f, "py_func", f)


@pytest.mark.skipif(kernels.BACKEND != "numba", reason="numba is not installed: no compiled kernels")
def test_the_compiled_row_function_counts_255_channels_exactly():
    """The compiled kernels' row function (run as Python: compiled, 255 unrolled channels would take
    minutes) at 255 channels, every count at its largest: all usable, all backscatter-only, all
    saturated, all below the floor, one usable among backscatter-only or saturated ones."""
    from uwcam.optics import kernels_numba

    n, d = 255, 6.0
    c = tuple(float(v) for v in np.linspace(0.5, 0.0, n))
    kinds = [(USABLE,) * n, (BACKSCATTER,) * n, (SATURATED,) * n, (BELOW,) * n,
             (USABLE,) + (BACKSCATTER,) * (n - 1), (SATURATED,) * (n - 1) + (USABLE,)]
    states = np.array(kinds, np.uint8).T[:, None, :].transpose(1, 2, 0)  # (1, W, N)
    y = np.broadcast_to(-np.array(c) * d, states.shape)
    pairs = kernels.pack_pairs(y, np.where(states == USABLE, 1.0, 0.0), states, ChannelState.SATURATED,
                               ChannelState.BACKSCATTER_ONLY)[0]  # (W, N) uint64
    row = np.ascontiguousarray(pairs.T).view(np.float32)  # (N, 2W): [y, w] per pixel, as the kernels lay it out
    w = len(kinds)
    out = (np.full(w, -1.0, np.float32), np.full(w, -1.0, np.float32), np.full(w, 99, np.uint8))
    with np.errstate(divide="ignore", invalid="ignore"):  # as Python, 1/0 warns; compiled, it is silent (inf)
        _python(kernels_numba._fuse_row)(row, np.zeros(w, np.float32), c, (0.0,) * n, np.zeros((n, n)), 0.5, 40.0, 0.0, *out)
    assert list(out[2]) == [Reason.VALID, Reason.BACKSCATTER_ONLY, Reason.SATURATED, Reason.BELOW_NOISE_FLOOR,
                            Reason.BACKSCATTER_ONLY, Reason.SATURATED]
    assert out[0][0] == pytest.approx(d / 2, rel=1e-4)


@pytest.mark.skipif(kernels.BACKEND != "numba", reason="numba is not installed: no compiled kernels")
def test_the_compiled_logarithm_is_within_float32s_rounding():
    """ln x of the background kernel (a float32 series, branch-free) against the library's log in
    float64: within a few units of float32's last place of max(1, |ln x|), also where the series is
    at its worst, mantissas at √2 and √½."""
    from uwcam.optics import kernels_numba

    k = np.arange(-30, 31, dtype=np.float64)
    root2 = np.float32(np.sqrt(2.0))
    x = np.concatenate([root2 * 2.0**k, np.nextafter(root2, np.float32(2.0)) * 2.0**k, np.float32(np.sqrt(0.5)) * 2.0**k,
                        np.geomspace(1e-6, 1e9, 3001)]).astype(np.float32)
    out = np.empty_like(x)
    kernels_numba._ln_row(x.copy(), out, np.empty(x.shape, np.int32))
    exact = np.log(x.astype(np.float64))
    assert np.all(np.abs(out - exact) <= 4 * 2.0**-23 * np.maximum(1.0, np.abs(exact)))


@pytest.mark.parametrize("fuser", FUSERS)
def test_255_usable_channels_of_one_attenuation_are_too_few_not_backscatter(fuser):
    """The usable count fills its 8 bits exactly (255): a count that spilled into the
    backscatter-only field would turn 'too few' into 'backscatter only' (at 128 usable channels and
    more, if a usable channel counted 2). Every channel shares one attenuation: no range, reason 4."""
    n = 255
    c = (0.25,) * n
    states = np.full((1, 1, n), USABLE, np.uint8)
    y = np.full(states.shape, -1.5)
    w = np.ones(states.shape)
    reason = fuse(_python(fuser) if fuser is not kernels.fuse_arrays_numpy else fuser, y, w, states, c)[2]
    assert reason[0, 0] == Reason.TOO_FEW_CHANNELS
