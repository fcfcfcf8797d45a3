"""Compensated ranges whose standard deviation exceeds twice the range lose their range (reason 3),
compiled and in numpy alike, against the rule written out here."""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.water import unresolved
from uwcam.water.unresolved import MAX_RELATIVE_SD, drop_unresolved
from uwcam.optics.validity import Reason
from uwcam.ranging.result import RangeResult


def sample(seed: int = 3, shape=(37, 53)) -> RangeResult:
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.2, 9.0, shape).astype(np.float32)
    sd = r * rng.uniform(0.0, 4.0, shape).astype(np.float32)  # relative sd 0–4: both sides of 2
    v = (sd * sd).astype(np.float32)
    reasons = np.zeros(shape, np.uint8)
    holes = rng.random(shape) < 0.1  # pixels already without a range keep their reason
    r[holes], v[holes], reasons[holes] = np.nan, np.nan, Reason.BELOW_NOISE_FLOOR
    return RangeResult(r, v, reasons)


@pytest.mark.parametrize("path", ["compiled", "numpy", "strided"])
def test_ranges_twice_as_uncertain_as_they_are_long_are_dropped(path, monkeypatch):
    if path == "compiled" and unresolved._drop_unresolved is None:
        pytest.skip("numba is not installed")  # the numpy case still runs
    if path == "numpy":
        monkeypatch.setattr(unresolved, "_drop_unresolved", None)
    given = sample()
    if path == "strided":  # not contiguous: the numpy rule runs whatever is installed
        wide = sample(shape=(37, 106))
        given = RangeResult(wide.range[:, ::2], wide.variance[:, ::2], wide.reasons[:, ::2])
    r0, v0, q0 = given.range.copy(), given.variance.copy(), given.reasons.copy()
    drop_unresolved(given)
    with np.errstate(invalid="ignore"):
        gone = np.sqrt(v0.astype(np.float64)) > MAX_RELATIVE_SD * r0.astype(np.float64)
    # Exactly at the limit the float32 arithmetic decides; none of these samples sit within 1e-6 of it.
    with np.errstate(invalid="ignore"):
        near = np.abs(np.sqrt(v0.astype(np.float64)) / r0 - MAX_RELATIVE_SD) < 1e-5
    assert not near.any()
    assert gone.sum() > 100 and (~gone & np.isfinite(r0)).sum() > 100
    assert np.all(np.isnan(given.range[gone])) and np.all(np.isnan(given.variance[gone]))
    assert np.all(given.reasons[gone] == Reason.BACKSCATTER_ONLY)
    kept = ~gone
    np.testing.assert_array_equal(given.range[kept], r0[kept])
    np.testing.assert_array_equal(given.variance[kept], v0[kept])
    np.testing.assert_array_equal(given.reasons[kept], q0[kept])


def murky_cell(size=(320, 240), distance=5.0, water_name="jerlov-III", lamp_x=0.3, frames=1):
    """A grey seabed at ``distance`` in murky water, the lamp ``lamp_x`` m aside, calibrated at 1 and 2 m
    in the simulator with the plate for scattering water (grey-plate-large-patch, docs/calibration.md),
    with 16 open-water frames: (profile, ``frames`` frames of the static seabed, open water, true
    camera range)."""
    from uwcam.calibration.rig import builtin_rig_path, load_rig
    from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset
    from uwcam.simulation.tank import calibrate_in_simulation

    water = water_preset(water_name, [675.0, 575.0, 475.0])
    lamp, camera = Lamp(position=(lamp_x, 0.0, 0.0)), CameraModel()
    profile = calibrate_in_simulation(water, lamp, size, camera, frames_per_distance=4,
                                      rig=load_rig(builtin_rig_path("grey-plate-large-patch")))
    scene = SimulatedWorld(scene="seabed", distance=distance, size=size, water=water, lamp=lamp, camera=camera,
                           material="grey", seed=5)
    view = SimulatedWorld(scene="open-water", distance=distance, size=size, water=water, lamp=lamp, camera=camera,
                          fixed_exposure=scene.exposure, seed=6)
    return (profile, [scene.frame(i) for i in range(frames)], np.stack([view.frame(i) for i in range(16)]),
            scene.camera_range)


@pytest.mark.parametrize("water_name, distance", [("jerlov-III", 5.0), ("jerlov-IB", 5.0), ("jerlov-II", 7.0)])
def test_ranges_are_found_with_the_backscatter_of_their_own_depth(water_name, distance):
    """Jerlov III at 5 m: the first pass, with the water's light left in, ranges some pixels short;
    the backscatter in front of that short range is subtracted, which leaves most of the red
    water light in, and two passes read those pixels 2 m for 5 m, far beyond their σ (160 pixels,
    143 of them beyond 3σ). Passes go on until the depths the backscatter is subtracted for are
    those found, and where they do not settle there is no range. Where two passes agree (Jerlov IB
    at 5 m, II at 7 m) the pixels keep their ranges. The truth is the simulator's."""
    from uwcam.ranging.images import range_images

    profile, frames, open_water, truth = murky_cell(distance=distance, water_name=water_name)
    result = range_images(profile, frames, compensate=True, iterations=2, open_water=open_water)
    valid = np.isfinite(result.range)
    z = (result.range[valid] - truth[valid]) / np.sqrt(result.variance[valid])
    beyond = int(np.sum(np.abs(z) > 3.0))
    assert beyond <= max(2, 0.02 * valid.sum()), f"{beyond} of {valid.sum()} valid pixels beyond 3σ"
    assert np.all(result.reasons[~valid] != Reason.VALID)
    if water_name == "jerlov-IB":
        assert valid.mean() > 0.95
    if water_name == "jerlov-II":  # 84 % of the whole image (94 % of its inner 80 %); 42 % at the model's former 5 % doubt
        assert valid.mean() > 0.8
        assert abs(np.median((result.range[valid] - truth[valid]) / truth[valid])) < 0.03


def test_a_seabed_at_7_m_in_jerlov_ii_keeps_its_ranges_when_frames_are_fused():
    """The issue's cell: Jerlov II, lamp 0.3 m aside, calibrated at 1 and 2 m, 16 frames of a grey
    seabed at 7 m fused, compensated with 16 open-water frames, 3×3 mean: at least 85 % of the
    image's inner 80 % keeps a range (97 % here; 62 % at the open-water model's former 5 % doubt),
    none beyond 3σ of the simulator's truth, rms within 5 % (3.6 %). Its median, +2.1 %, is the
    calibration's (its green–blue attenuation difference, known to some 5 % from plates at 1–2 m,
    carries to 7 m, where red is lost and green and blue range): not asserted."""
    from uwcam.ranging.images import range_images

    profile, frames, open_water, truth = murky_cell(distance=7.0, water_name="jerlov-II", frames=16)
    result = range_images(profile, frames, smoothing="mean", compensate=True, iterations=2, open_water=open_water)
    h, w = truth.shape
    inner = np.zeros(truth.shape, bool)
    inner[h // 10: h - h // 10, w // 10: w - w // 10] = True
    valid = np.isfinite(result.range) & inner
    assert valid.sum() >= 0.85 * inner.sum()
    error = result.range[valid] / truth[valid] - 1
    z = (result.range[valid] - truth[valid]) / np.sqrt(result.variance[valid])
    assert np.mean(np.abs(z) > 3) <= 0.02
    assert np.sqrt(np.mean(error**2)) <= 0.05


@pytest.mark.parametrize("frames, distance, lamp_x", [(1, 5.0, 0.3), (1, 3.0, 0.0), (16, 5.0, 0.3), (16, 3.0, 0.0)])
def test_a_depth_that_only_the_near_side_reaches_is_no_range(frames, distance, lamp_x):
    """Jerlov III, where the seabed's red light hardly clears the water's: passes that start from
    the near side (the water's light left in) can settle on a depth 40–60 % short whose own
    backscatter, subtracted, leaves the rest of the water's red light to read as the seabed's, a
    depth as self-consistent as the true one (the bench's water study kept 11 to 47 such pixels per
    cell, every one beyond 3σ). The same passes started from the far side (the open water's light
    subtracted first) do not reach it: a block whose two starts settle apart has no range
    (reason 3). The truth is the simulator's; 3×3 means as the water study ranges. 16 frames fused
    at 5 m kept 9 pixels 62 % short that both starts reach, alone in blocks where nothing else had
    a range: a block needs a tenth of its pixels ranged for any to keep a range (MIN_SUPPORT). 16
    frames at 3 m, lamp on the axis, with the open-water model's 2 % doubt: 44 pixels 25 % short, 6
    beyond 3σ, that the far start reached too, through a pass that took a range from green and blue
    alone (which attenuate alike here: anything) for a depth; a pass's ranges too uncertain for
    their length are no depth now.

    None of those pixels was left beyond 3σ while the open-water model was doubted by 2 % of its
    level, but the cell at 3 m with the lamp on the axis then kept 3 % of its pixels. With the
    model's doubt as measured (0.4 % of the level, and 40 % of the share beyond the surface) it
    keeps 62 %, their z-scores' sd 0.8; what the threshold lets through of red light barely 3σ
    above the water's (half of a percent of those pixels here, 15–35 % short) is held to the
    issue's bound: at most 2 % of the valid pixels beyond 3σ, with the 3×3 mean the study ranges with."""
    from uwcam.ranging.images import range_images

    profile, stack, open_water, truth = murky_cell(distance=distance, lamp_x=lamp_x, frames=frames)
    result = range_images(profile, stack, smoothing="mean", compensate=True, iterations=2, open_water=open_water)
    valid = np.isfinite(result.range)
    z = (result.range[valid] - truth[valid]) / np.sqrt(result.variance[valid])
    if z.size:  # at 5 m no pixel keeps a range
        assert np.mean(np.abs(z) > 3.0) <= 0.02, (valid.mean(), np.mean(np.abs(z) > 3.0))
        assert np.std(z) < 1.3, np.std(z)
    assert np.all(result.reasons[~valid] != Reason.VALID)


def test_a_block_keeps_its_ranges_only_where_a_tenth_of_its_pixels_have_one(monkeypatch):
    """Blocks of 8×8: 6 ranged pixels of 64 lose their ranges (reason 3), 7 keep theirs; pixels
    without a range keep their own reasons; saturated pixels could have none and do not count
    (4 ranged beside 30 saturated: 4 of 34 keep theirs)."""
    from uwcam.water.unresolved import drop_unsupported

    rng = np.full((16, 24), np.nan, np.float32)
    reasons = np.full((16, 24), Reason.BELOW_NOISE_FLOOR, np.uint8)
    counts = {(0, 0): 6, (0, 1): 7, (0, 2): 64, (1, 0): 0, (1, 1): 1, (1, 2): 4}
    for (by, bx), n in counts.items():
        block = np.zeros(64, bool)
        block[np.random.default_rng(by * 3 + bx).choice(64, n, replace=False)] = True
        rng[by * 8:(by + 1) * 8, bx * 8:(bx + 1) * 8][block.reshape(8, 8)] = 3.0
    reasons[np.isfinite(rng)] = Reason.VALID
    highlight = reasons[8:16, 16:24].copy()  # block (1, 2): 30 of its 60 unranged pixels saturated
    flat = highlight.reshape(-1)
    flat[np.flatnonzero(flat != Reason.VALID)[:30]] = Reason.SATURATED
    reasons[8:16, 16:24] = flat.reshape(8, 8)
    result = RangeResult(rng.copy(), np.where(np.isfinite(rng), np.float32(0.01), np.nan).astype(np.float32),
                         reasons.copy(), np.where(np.isfinite(rng), np.float32(0.001), np.nan).astype(np.float32))
    drop_unsupported(result, (2, 3))  # blocks of 8×8 over 24×16
    for (by, bx), n in counts.items():
        sl = (slice(by * 8, (by + 1) * 8), slice(bx * 8, (bx + 1) * 8))
        kept = np.isfinite(result.range[sl]).sum()
        keeps = n >= 7 or (by, bx) == (1, 2)
        assert kept == (n if keeps else 0), ((by, bx), n, kept)
        was = np.isfinite(rng[sl])
        if not keeps:
            assert np.all(result.reasons[sl][was] == Reason.BACKSCATTER_ONLY)
            assert np.all(np.isnan(result.variance[sl][was]) & np.isnan(result.common_variance[sl][was]))
        assert np.all(result.reasons[sl][~was] == reasons[sl][~was])
