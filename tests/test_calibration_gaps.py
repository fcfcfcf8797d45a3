"""Calibration behaviours the other calibration tests leave open (issue #14's mutation gaps).

Each expected value comes from outside uwcam.calibration.fit: a naive reference written here with
plain loops and numpy (the pixel sets of the black-patch fit and of the noise points, the
brightness bins, weighted least squares in closed form), the documented rules of
docs/calibration.md (the 5σ and 0.1 % backscatter tests, the ring of plate pixels around the
black patch, the noise region and its four brightness bins) or the data's construction.
"""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.calibration.fit import CalibrationInputs, calibrate_with_details
from uwcam.calibration.black_patch import backscatter_at_black_patch
from uwcam.calibration.noise_fit import NoisePoint, fit_noise, fit_noise_model, variance_floor
from uwcam.fileio import UserInputError

RHO_P = np.array([0.5, 0.4, 0.3])
RHO_B = np.array([0.05, 0.04, 0.02])


# ---------------------------------------------------------------------------------------------
# Naive pixel-set helpers (square neighbourhoods = Chebyshev distance; outside the image is empty)


def _shift_any(mask: np.ndarray, r: int) -> np.ndarray:
    """Pixels with some pixel of ``mask`` within Chebyshev distance r."""
    out = np.zeros_like(mask)
    for y, x in zip(*np.nonzero(mask)):
        out[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1] = True
    return out


def _inside(mask: np.ndarray, r: int) -> np.ndarray:
    """Pixels whose whole (2r+1)² neighbourhood lies in ``mask`` (and in the image)."""
    h, w = mask.shape
    out = np.zeros_like(mask)
    for y in range(h):
        for x in range(w):
            if y - r >= 0 and x - r >= 0 and y + r < h and x + r < w:
                out[y, x] = mask[y - r : y + r + 1, x - r : x + r + 1].all()
    return out


def _box(shape, x, y, w, h) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[y : y + h, x : x + w] = True
    return m


# ---------------------------------------------------------------------------------------------
# The black patch's backscatter: which pixels the plate's light is interpolated from


def _reference_backscatter(signal, black, plate, rho_b, rho_p):
    """docs/calibration.md, "Backscatter at the black patch", written out: the patch's pixels 2 or
    more inside its edge (the whole patch, and a ring from the next pixel on, when fewer than 4);
    a ring of plate pixels more than that edge and at most max(s, 4) pixels from the patch
    (s: the patch's smaller side in pixels, at least 4), themselves that edge inside the plate; a
    cubic surface from 60 ring pixels, a quadratic one from 24, a plane below; per pixel
    X = (plate − black)/(ρp − ρb), backscatter = black − ρb·X, averaged."""
    patch, edge = _inside(black, 2), 2
    if patch.sum() < 4:
        patch, edge = black, 0
    ys, xs = np.nonzero(black)
    s = max(min(ys.max() - ys.min(), xs.max() - xs.min()) + 1, 4)
    radius = max(s, 4)
    near = _shift_any(black, radius)
    too_near = _shift_any(black, edge) if edge else black
    ring = near & ~too_near & (_inside(plate, edge) if edge else plate) & ~black
    if ring.sum() < 6:
        return None
    degree = 3 if ring.sum() >= 60 else 2 if ring.sum() >= 24 else 1

    def design(m):
        yy, xx = np.nonzero(m)
        u, v = xx.astype(float), yy.astype(float)
        cols = [np.ones_like(u), u, v]
        if degree >= 2:
            cols += [u * u, u * v, v * v]
        if degree == 3:
            cols += [u**3, u * u * v, u * v * v, v**3]
        return np.stack(cols, 1)

    coef = np.linalg.lstsq(design(ring), signal[ring], rcond=None)[0]
    plate_at = design(patch) @ coef
    b = signal[patch]
    x = (plate_at - b) / (rho_p - rho_b)
    return (b - rho_b * x).mean(axis=0), int(ring.sum()), degree


@pytest.mark.parametrize(
    "box",
    [
        (20, 18, 9, 9),  # ring out to 9 pixels (the patch's side), not 8 or 10
        (20, 18, 10, 9),  # out to 9 (the smaller side)
        (18, 16, 12, 12),  # out to 12
        (20, 18, 6, 6),  # 4 patch pixels inside its edge: the interior is used, not the whole patch
        (20, 18, 7, 5),  # 3 inside its edge: the whole patch, ring from the next pixel on
        (21, 19, 3, 3),  # a patch 3 pixels across
        (21, 19, 1, 1),
    ],
)
def test_backscatter_uses_the_documented_ring_around_the_patch(box):
    """On a field that is no smooth surface (random per pixel), every other choice of ring or patch
    pixels gives another estimate."""
    rng = np.random.default_rng(sum(box))
    shape = (48, 52)
    signal = rng.uniform(50.0, 150.0, shape + (3,))
    black = _box(shape, *box)
    plate = _box(shape, 4, 3, 44, 42) & ~black
    got = backscatter_at_black_patch(signal, black, plate, RHO_B, RHO_P)
    want, _, _ = _reference_backscatter(signal, black, plate, RHO_B, RHO_P)
    np.testing.assert_allclose(got.level, want, rtol=1e-9, atol=1e-9)


def test_a_ring_a_patch_width_wide_averages_the_sensors_fixed_pattern_down():
    """Each pixel's gain differs by 1 % (PRNU), the same in every frame, so averaging frames leaves
    it. Over 40 such sensors, the plate's light at the patch scatters half as much as with a ring
    half a patch width wide and a quadratic surface (the rule until this version, written out
    here), and the stated σ is that scatter."""
    shape = (60, 64)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    light = 2000.0 + 10.0 * xx - 6.0 * yy + 0.05 * xx * yy - 0.08 * (yy - 30.0) ** 2
    black = _box(shape, 26, 24, 12, 12)
    plate = _box(shape, 2, 2, 60, 56) & ~black
    clean = 40.0 + np.where(black[..., None], RHO_B, RHO_P) * light[..., None]
    inner = _inside(black, 2)
    truth = np.log(RHO_P * light[inner].mean())
    narrow_ring = _shift_any(black, 6) & ~_shift_any(black, 2) & _inside(plate, 2) & ~black

    def quadratic(m):
        yy_, xx_ = np.nonzero(m)
        u, v = xx_.astype(float), yy_.astype(float)
        return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], 1)

    errors, narrow, stated = [], [], []
    for seed in range(40):
        signal = clean * (1.0 + 0.01 * np.random.default_rng(seed).standard_normal(shape + (3,)))
        est = backscatter_at_black_patch(signal, black, plate, RHO_B, RHO_P, (0.01 * signal) ** 2)
        errors.append(est.plate_log - truth)
        stated.append(np.sqrt(est.plate_log_variance))
        coef = np.linalg.lstsq(quadratic(narrow_ring), signal[narrow_ring], rcond=None)[0]
        difference = (quadratic(inner) @ coef - signal[inner]).mean(axis=0)
        narrow.append(np.log(difference * RHO_P / (RHO_P - RHO_B)) - truth)
    spread, narrow_spread = np.sqrt(np.mean(np.square(errors))), np.sqrt(np.mean(np.square(narrow)))
    assert spread < 0.6 * narrow_spread, (spread, narrow_spread)
    assert 0.75 < spread / np.mean(stated) < 1.33, (spread, np.mean(stated))


def _one_pixel_patch_with_ring(n: int, seed: int):
    """A 1-pixel black patch with exactly ``n`` plate pixels within 4 pixels of it."""
    rng = np.random.default_rng(seed)
    shape = (30, 30)
    black = np.zeros(shape, bool)
    black[15, 15] = True
    near = [(y, x) for y in range(11, 20) for x in range(11, 20) if (y, x) != (15, 15)]
    chosen = rng.choice(len(near), n, replace=False)
    plate = np.zeros(shape, bool)
    for i in chosen:
        plate[near[i]] = True
    plate[0:3, :] = True  # plate pixels far from the patch: not in its ring
    signal = rng.uniform(50.0, 150.0, shape + (3,))
    return signal, black, plate


@pytest.mark.parametrize("n, degree", [(6, 1), (7, 1), (23, 1), (24, 2), (25, 2), (59, 2), (60, 3), (61, 3)])
def test_six_ring_pixels_give_a_plane_twenty_four_a_quadratic_and_sixty_a_cubic_surface(n, degree):
    signal, black, plate = _one_pixel_patch_with_ring(n, seed=n)
    want, count, got_degree = _reference_backscatter(signal, black, plate, RHO_B, RHO_P)
    assert (count, got_degree) == (n, degree)
    got = backscatter_at_black_patch(signal, black, plate, RHO_B, RHO_P)
    np.testing.assert_allclose(got.level, want, rtol=1e-9, atol=1e-9)


def test_fewer_than_six_ring_pixels_are_refused():
    signal, black, plate = _one_pixel_patch_with_ring(5, seed=5)
    with pytest.raises(UserInputError, match="not surrounded by enough plate pixels"):
        backscatter_at_black_patch(signal, black, plate, RHO_B, RHO_P)


def test_a_patch_with_no_plate_light_gets_a_log_variance_that_takes_it_out_of_the_fit():
    """Black brighter than the plate around it (no plate light left at the patch): the log of the
    plate's light there is meaningless, and its variance must be enormous, not a finite figure."""
    shape = (40, 40)
    black = _box(shape, 16, 16, 8, 8)
    plate = _box(shape, 2, 2, 36, 36) & ~black
    signal = np.where(black[..., None], 100.0, 90.0) * np.ones(3)
    est = backscatter_at_black_patch(signal, black, plate, RHO_B, RHO_P, np.full(shape + (3,), 4.0))
    assert np.all(est.plate_log_variance > 1e40)


# ---------------------------------------------------------------------------------------------
# The noise model


def test_variance_floor_of_an_exact_zero_in_float_data_is_not_zero():
    assert variance_floor(0.0, 0.0) > 0.0
    assert variance_floor(0.0, 0.0) == pytest.approx((1e-30 * 2.0**-23) ** 2 / 12, rel=1e-12)


def _point(e, t, s, frames=2, count=100):
    e = np.atleast_1d(float(e))
    return NoisePoint(e, e**2, np.atleast_1d(float(s)), np.atleast_1d(float(t)), frames, count)


def test_fixed_pattern_is_what_the_spatial_spread_holds_beyond_the_temporal_noise_at_dim_and_negative_means():
    """Temporal noise read² + gain·E (+ step²/12), with no shot noise for a mean at or below 0 (a dark level
    over-subtracted) and the shot noise of E itself below 1 DN: the fixed pattern is what the spatial spread
    of m-frame averages holds beyond temporal/m. Spatial spreads built with fpn = 0.02 exactly."""
    read2, gain, fpn, m, q = 4.0, 2.0, 0.02, 2, 1.0 / 12
    means = [-0.5, 0.5, 50.0, 400.0]
    temporal = [read2 + gain * max(e, 0.0) + q for e in means]
    # Read and gain come from the temporal points alone; the −0.5 DN point is off their line.
    first = fit_noise([_point(e, t, 1.0, m) for e, t in zip(means, temporal)], 1.0)
    r2, g = float(first.read_noise[0] ** 2), float(first.shot_gain[0])
    spatial = [(r2 + g * max(e, 0.0) + q) / m + (fpn * e) ** 2 for e in means]
    fit = fit_noise([_point(e, t, s, m) for e, t, s in zip(means, temporal, spatial)], 1.0)
    assert fit.fixed_pattern[0] == pytest.approx(fpn, rel=1e-9)


def test_fixed_pattern_weights_small_spatial_variances_by_their_relative_error():
    """Float data (step 0): weights 1/s² even for variances far below 1 DN², by weighted least squares
    of (s − t/m) on mean(E²) written out in closed form."""
    pts = [_point(1.0, 0.02, 0.05, 2), _point(2.0, 0.02, 0.3, 2), _point(3.0, 0.02, 0.2, 2)]
    fit = fit_noise(pts, 0.0)
    t_model = fit.read_noise[0] ** 2 + fit.shot_gain[0] * np.array([1.0, 2.0, 3.0])
    s = np.array([0.05, 0.3, 0.2])
    e2 = np.array([1.0, 4.0, 9.0])
    w = 1.0 / s**2
    r = s - t_model / 2
    want = np.sum(w * e2 * r) / np.sum(w * e2**2)
    assert want > 0
    assert fit.fixed_pattern[0] ** 2 == pytest.approx(want, rel=1e-9)


def test_noise_fit_keeps_the_best_nonnegative_solution_not_a_later_worse_one():
    """Variances falling with the signal: the free fit's gain is negative, so the best non-negative fit
    is read noise alone (its weighted mean, weights 1/σ⁴), although shot noise alone fits not much worse."""
    means = np.array([[10.0], [10.2], [10.4]])
    var = np.array([[3.0], [2.8], [2.68]])
    read, gain = fit_noise_model(means, var, 0.0)
    w = 1.0 / var[:, 0] ** 2
    assert gain[0] == 0.0
    assert read[0] ** 2 == pytest.approx(np.sum(w * var[:, 0]) / np.sum(w), rel=1e-12)
    # (shot noise alone: cost within twice read noise's, for this data)
    g = np.sum(w * means[:, 0] * var[:, 0]) / np.sum(w * means[:, 0] ** 2)
    cost_gain = np.sum(w * (g * means[:, 0] - var[:, 0]) ** 2)
    cost_read = np.sum(w * (read[0] ** 2 - var[:, 0]) ** 2)
    assert cost_read < cost_gain < 2 * cost_read


def test_a_single_noise_level_is_read_noise():
    """One point: read and shot noise cannot be told apart (docs/calibration.md), and all of it is read noise."""
    read, gain = fit_noise_model(np.array([[1.0]]), np.array([[2.0]]), 0.0)
    assert (read[0] ** 2, gain[0]) == (pytest.approx(2.0, rel=1e-12), 0.0)


def test_points_at_one_signal_level_put_the_noise_in_the_read_term():
    """With every point at the same mean, read and shot noise cannot be told apart (docs/calibration.md):
    of the fits that are as good (to rounding), the one with read noise alone is kept, and the shot gain is 0."""
    read, gain = fit_noise_model(np.array([[1.0], [1.0], [1.0]]), np.array([[2.0], [3.0], [2.5]]), 0.0)
    w = 1.0 / np.array([2.0, 3.0, 2.5]) ** 2
    assert gain[0] == 0.0
    assert read[0] ** 2 == pytest.approx(np.sum(w * np.array([2.0, 3.0, 2.5])) / np.sum(w), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# Documented defaults of the Python API


def test_calibration_inputs_defaults_are_the_documented_ones():
    """docs/calibration.md: lamp at the camera, 16-bit saturation, integer data (step 1 DN)."""
    c = CalibrationInputs(["R", "G", "B"], [None] * 3, np.ones(3))
    assert c.lamp_position_m == (0.0, 0.0, 0.0)
    assert c.saturation_level == 65535.0
    assert c.quantisation_step == 1.0


# ---------------------------------------------------------------------------------------------
# calibrate_with_details on crafted frames (no intrinsics: every pixel's ray is the axis)


def _inputs(**kw):
    base = dict(channel_names=["R", "G", "B"], wavelengths_nm=[None] * 3, target_reflectance=RHO_P,
                saturation_level=1e12, quantisation_step=0.0)
    base.update(kw)
    return CalibrationInputs(**base)


SHAPE = (40, 56)
SCALE = np.array([1.0, 0.8, 0.6])


def _textured(distance: float, seed: int) -> np.ndarray:
    """A plate brighter to the right (so brightness bins are bands of columns) with a random texture
    (so that every different set of pixels has other statistics)."""
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    rng = np.random.default_rng(seed)
    base = (100.0 + 3.0 * xx + 0.05 * yy) / distance**2
    return base[..., None] * SCALE + rng.uniform(-1.0, 1.0, SHAPE + (3,))


def _box_blur_reflect101(a: np.ndarray) -> np.ndarray:
    p = np.pad(a, 2, mode="reflect")  # numpy's "reflect" leaves the edge pixel out, as OpenCV's default
    h, w = a.shape
    return sum(p[dy : dy + h, dx : dx + w] for dy in range(5) for dx in range(5)) / 25.0


def _triples(m: np.ndarray) -> np.ndarray:
    """Pixels of m whose left and right neighbours are in m too (the centres of noise_point's second differences)."""
    c = np.zeros_like(m)
    c[:, 1:-1] = m[:, 1:-1] & m[:, :-2] & m[:, 2:]
    return c


def _expected_noise_points(frame, distance, target, black):
    """docs/calibration.md, "Noise model": the noise region keeps 2 pixels clear of the target region's
    edges and 7 (2 + the 5-pixel box) from the black patch; on a smaller plate 1 pixel clear of both;
    then the whole target without the patch; the first with two second differences. Four brightness
    bins (quartiles of the 5×5 box average of the summed channels over the region) of 64 or more
    pixels each give a point, else the whole region one; the black patch, 2 pixels inside its edge,
    one when it holds two second differences. Per point: (label, pixel count, mean signal)."""
    usable = target & ~black if black is not None else target
    away = black if black is not None else np.zeros_like(target)
    candidates = [_inside(usable, 2) & ~_shift_any(away, 7), _inside(usable, 1) & ~_shift_any(away, 1), usable & ~away]
    region = next((r for r in candidates if _triples(r).sum() >= 2), None)
    assert region is not None
    brightness = _box_blur_reflect101(frame.sum(axis=-1))
    edges = np.quantile(brightness[region], [0.0, 0.25, 0.5, 0.75, 1.0])
    out = []
    for j in range(4):
        part = region & (brightness >= edges[j]) & (brightness <= edges[j + 1])
        if part.sum() >= 64:
            c = _triples(part)
            out.append((f"plate {distance:g} m, level {j + 1}", int(c.sum()), frame[c].mean(axis=0)))
    if not out:
        c = _triples(region)
        out.append((f"plate {distance:g} m", int(c.sum()), frame[c].mean(axis=0)))
    if black is not None:
        c = _triples(_inside(black, 2))
        if c.sum() >= 2:
            out.append((f"black patch {distance:g} m", int(c.sum()), frame[c].mean(axis=0)))
    return out


NOISE_GEOMETRIES = {
    # target box, black box
    "plate with a black patch": ((4, 4, 48, 32), (24, 14, 8, 8)),
    "black patch 8x5: two second differences inside its edge": ((4, 4, 48, 32), (24, 14, 8, 5)),
    "black patch 7x5: one, no noise point": ((4, 4, 48, 32), (24, 14, 7, 5)),
    "quartiles of exactly 64 pixels": ((10, 10, 20, 20), None),
    "quartiles of 63 pixels: one point": ((10, 10, 32, 13), None),
    "small plate: 1 pixel from its edges and the patch": ((10, 10, 12, 7), (15, 12, 2, 2)),
    "7x5 plate: one second difference 2 pixels in, nine 1 pixel in": ((10, 10, 7, 5), None),
    "plate 2 pixels high: all of it": ((10, 10, 6, 2), None),
    "plate 4x1: two second differences": ((10, 10, 4, 1), None),
}


@pytest.mark.parametrize("name", list(NOISE_GEOMETRIES))
def test_noise_points_are_measured_on_the_documented_regions(name):
    target_box, black_box = NOISE_GEOMETRIES[name]
    distances = [1.0, 1.5]
    frames = [_textured(d, seed=i) for i, d in enumerate(distances)]
    kw = {}
    black = None
    if black_box is not None:
        kw = dict(black_boxes=[black_box] * 2, black_reflectance=RHO_B)
        black = _box(SHAPE, *black_box)
        for f in frames:
            f[black] *= 0.1
    details = calibrate_with_details(frames, distances, _inputs(target_box=target_box, **kw))
    got = details.noise_points
    want = [p for f, d in zip(frames, distances)
            for p in _expected_noise_points(f, d, _box(SHAPE, *target_box), black)]
    assert [label for label, _ in got] == [label for label, _, _ in want]
    for (_, point), (label, count, mean) in zip(got, want):
        assert point.count == count, label
        np.testing.assert_allclose(point.mean, mean, rtol=1e-12, err_msg=label)


def test_frames_at_one_distance_are_measured_in_the_regions_given_for_the_first_of_them():
    """Per-image regions (a marker plate found in every frame): the frames averaged at one distance use
    the target and black patch regions of the first of them."""
    distances = [1.0, 1.0, 2.0]
    frames = [_textured(d, seed=i) for i, d in enumerate(distances)]
    targets = [(4, 4, 48, 32), (6, 5, 44, 30), (8, 6, 40, 28)]
    blacks = [(24, 14, 8, 8), (26, 16, 8, 8), (22, 12, 8, 8)]
    # The plate holds still at one distance: both frames there show the patch in one place, though the
    # second's pose put its region 2 px off (the patch is located in the averaged image near the first's).
    for f, b in zip(frames, (blacks[0], blacks[0], blacks[2])):
        f[_box(SHAPE, *b)] *= 0.1
    details = calibrate_with_details(frames, distances, _inputs(target_boxes=targets, black_boxes=blacks,
                                                                 black_reflectance=RHO_B))
    first, second = details.groups
    np.testing.assert_array_equal(first.black, _box(SHAPE, *blacks[0]))
    np.testing.assert_array_equal(first.target, _box(SHAPE, *targets[0]) & ~_box(SHAPE, *blacks[0]))
    np.testing.assert_array_equal(second.target, _box(SHAPE, *targets[2]) & ~_box(SHAPE, *blacks[2]))
    x, y, w, h = blacks[0]
    x2, y2, w2, h2 = blacks[2]
    assert details.profile.backscatter.patch_pixels == [(x + w / 2 - 0.5, y + h / 2 - 0.5), (x2 + w2 / 2 - 0.5, y2 + h2 / 2 - 0.5)]


# ---------------------------------------------------------------------------------------------
# When backscatter counts as measured: more than 5σ from 0 and more than 0.1 % of the plate's light


BLACK_BOX = (24, 14, 10, 10)


def _lamp_field(distance: float) -> np.ndarray:
    """Lamp light on the plate (H, W, N): a quadratic bowl, so that the ring's surface fit is exact."""
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    x = 1000.0 * (1.0 - ((xx - 28.0) ** 2 + (yy - 20.0) ** 2) / 4000.0) / distance**2
    return x[..., None] * SCALE * np.exp(-np.array([0.4, 0.1, 0.05]) * 2.0 * distance)


def _frame_pairs(backscatter, delta: float):
    """Two float frames per distance (1 m and 2 m): plate ρ·X + backscatter, ± delta in a checkerboard, so
    that their average is exactly the noise-free frame and every pixel's frame-to-frame variance is
    2·delta² (read noise only)."""
    black = _box(SHAPE, *BLACK_BOX)
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    checker = np.where((xx + yy) % 2 == 0, 1.0, -1.0)[..., None]
    out, distances = [], []
    for i, d in enumerate([1.0, 2.0]):
        base = np.where(black[..., None], RHO_B, RHO_P) * _lamp_field(d) + backscatter[i]
        out += [base + delta * checker, base - delta * checker]
        distances += [d, d]
    return out, distances


def _measured(backscatter, delta) -> tuple[bool, object]:
    frames, distances = _frame_pairs(backscatter, delta)
    details = calibrate_with_details(frames, distances, _inputs(black_boxes=[BLACK_BOX] * 4, black_reflectance=RHO_B))
    return "backscatter measured" in details.profile.provenance.method, details


def _plate_light_at_patch(distance: float) -> np.ndarray:
    patch = _inside(_box(SHAPE, *BLACK_BOX), 2)
    return RHO_P * _lamp_field(distance)[patch].mean(axis=0)


@pytest.mark.parametrize("ratio, measured", [(4.5, False), (5.5, True)])
def test_backscatter_counts_as_measured_above_five_sigma(ratio, measured):
    bs = np.array([[2.0, 2.0, 2.0]] * 2)  # well above 0.1 % of the plate's light
    assert np.all(bs[1] > 0.01 * _plate_light_at_patch(2.0))
    _, probe = _measured(bs, 1.0)
    sigma1 = np.array([np.sqrt(g.backscatter.variance) for g in probe.groups])
    levels = np.array([g.backscatter.level for g in probe.groups])
    np.testing.assert_allclose(levels, bs, rtol=1e-6)
    # Read noise alone, the same in every pixel: σ of the level scales with delta.
    delta = float(np.max(np.abs(levels) / sigma1)) / ratio
    got, details = _measured(bs, delta)
    sig = np.array([np.sqrt(g.backscatter.variance) for g in details.groups])
    assert np.max(np.abs(levels) / sig) == pytest.approx(ratio, rel=1e-6)
    assert got is measured


@pytest.mark.parametrize("fraction, measured", [(0.0009, False), (0.0011, True)])
def test_backscatter_counts_as_measured_above_a_thousandth_of_the_plates_light(fraction, measured):
    bs = np.array([fraction * _plate_light_at_patch(d) for d in (1.0, 2.0)])
    got, details = _measured(bs, 1e-4)
    for g, want in zip(details.groups, bs):
        np.testing.assert_allclose(g.backscatter.level, want, rtol=1e-6)
        assert np.all(np.abs(g.backscatter.level) > 50 * np.sqrt(g.backscatter.variance))  # far beyond 5σ
    assert got is measured


class EqualToAnything:
    """A bound equal to whatever it is compared with: a value exactly at its bound, which no real
    data's rounding gives on demand. Python asks it when a float cannot compare with it."""

    def __lt__(self, other):
        return False

    def __gt__(self, other):
        return False

    def __le__(self, other):
        return True

    def __ge__(self, other):
        return True

    def __eq__(self, other):
        return True

    __hash__ = None


def test_a_chi2_exactly_at_its_bound_does_not_scale_the_covariance(monkeypatch):
    """Scaled by χ² only when χ² *exceeds* its 5 % bound (docs/calibration.md)."""
    from uwcam.calibration import line_fit as calibration

    d = np.array([1.0, 2.0, 3.0, 4.0])
    c = np.array([0.0, -0.3, -0.4])  # V of G and B against R
    ln_e = np.array([[8.0, 8.0 + 0.2, 8.0 + 0.5]]) + np.outer(d, c) + np.array([[0, 0.01, -0.02], [0, -0.02, 0.01],
                                                                            [0, 0.015, 0.0], [0, -0.005, 0.01]])
    variance = np.full_like(ln_e, 1e-5)  # far less than the scatter: χ² ≫ 1

    def fit(bound):
        monkeypatch.setattr(calibration, "chi2_upper", lambda dof, z=1.645: bound)
        return calibration.fit_attenuation_differences(ln_e, d, 0, variance).covariance

    unscaled, scaled = fit(np.inf), fit(0.0)
    assert not np.allclose(unscaled, scaled)  # the scaling is live: χ² > 1 here
    np.testing.assert_array_equal(fit(EqualToAnything()), unscaled)


@pytest.mark.parametrize("rule", ["five sigma", "a thousandth"])
def test_backscatter_exactly_at_a_threshold_does_not_count_as_measured(rule, monkeypatch):
    """The rules are strict: more than 5σ and more than 0.1 % of the plate's light. The patch's
    measurement is replaced by exactly representable values at one threshold, far beyond the other."""
    from dataclasses import replace

    from uwcam.calibration import fit as calibration

    real = calibration.backscatter_at_black_patch

    def at_threshold(*args, **kwargs):
        e = real(*args, **kwargs)
        n = e.level.shape[0]
        if rule == "five sigma":  # 1000 = 5·√40000 exactly; ≫ 0.1 % of any plate light here
            return replace(e, level=np.full(n, 1000.0), variance=np.full(n, 40000.0))
        # 0.001 = 0.001·e⁰ exactly (the plate's ln light set to 0); 5σ = 5e-6
        return replace(e, level=np.full(n, 0.001), variance=np.full(n, 1e-12), plate_log=np.zeros(n))

    monkeypatch.setattr(calibration, "backscatter_at_black_patch", at_threshold)
    got, _ = _measured(np.zeros((2, 3)), 1.0)
    assert got is False


# ---------------------------------------------------------------------------------------------
# Signals below 1 DN and below 0


def test_an_over_subtracted_dark_level_stores_no_negative_backscatter_and_no_floor_below_the_noise():
    """Dark level 0.5 DN above the frames' (noise-free float frames, no backscatter): every level is −0.5 DN;
    the profile stores 0 for each, and the floor is 3σ of the black patch's (float-rounding) noise."""
    frames, distances = _frame_pairs(np.zeros((2, 3)), 0.0)
    details = calibrate_with_details(frames, distances, _inputs(black_boxes=[BLACK_BOX] * 4, black_reflectance=RHO_B,
                                                                dark_level=np.full(3, 0.5)))
    for g in details.groups:
        np.testing.assert_allclose(g.backscatter.level, -0.5, rtol=1e-6)
    for name in ["R", "G", "B"]:
        assert details.profile.backscatter.levels[name] == [0.0, 0.0]
    floor = details.profile.array("noise_floor")
    assert np.all(floor >= 0) and np.all(floor < 1e-3)


def test_dim_float_frames_under_one_dn_calibrate_with_an_honest_log_variance():
    """Float frames of 0.2–0.6 DN with pixel noise 0.05 DN: the calibration runs, and each distance's
    stated variance of its mean ln E matches the scatter of that mean over independent noise draws."""
    shape = (24, 32)
    rng = np.random.default_rng(11)
    truth = [np.full(shape + (3,), 0.6) * [1.0, 0.7, 0.4], np.full(shape + (3,), 0.5) * [0.5, 0.6, 0.4]]
    logs, stated = [], []
    for _ in range(60):
        frames = [t + 0.05 * rng.standard_normal(t.shape) for t in truth]
        details = calibrate_with_details(frames, [1.0, 2.0], _inputs(target_reflectance=np.full(3, 0.3)))
        logs.append([g.log_signal for g in details.groups])
        stated.append([g.log_variance for g in details.groups])
    ratio = np.var(np.array(logs), axis=0, ddof=1) / np.mean(np.array(stated), axis=0)
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio


def test_fixed_pattern_of_a_black_patch_under_one_dn_enters_its_backscatter_variance_by_its_own_signal():
    """A black patch read at 0 ± 2 DN (pixels below 0 and under 1 DN) with a 1 % fixed pattern: each pixel's
    variance is read² + gain·E⁺ + (fpn·E⁺)² with E⁺ = max(E, 0), as the patch's backscatter variance shows."""
    rng = np.random.default_rng(4)
    distances = [1.0, 2.0]
    shape = (48, 64)
    black_box = (28, 20, 10, 10)
    black = _box(shape, *black_box)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    out = []
    for d in distances:
        f = (2000.0 * (1.0 - ((xx - 32) ** 2 + (yy - 24) ** 2) / 6000.0) / d**2)[..., None] * RHO_P / RHO_P[0]
        f[black] *= 1e-4
        f *= 1.0 + 0.01 * np.random.default_rng(9).standard_normal(shape)[..., None]
        out.append(f + 2.0 * rng.standard_normal(f.shape))
    details = calibrate_with_details(out, distances, _inputs(black_boxes=[black_box] * 2,
                                                             black_reflectance=RHO_P * 1e-4))
    noise = details.noise
    assert np.all(noise.fixed_pattern > 0)
    for g in details.groups:
        assert np.mean(g.mean_frame[black] < 0) > 0.2 and np.mean((g.mean_frame[black] > 0) & (g.mean_frame[black] < 1)) > 0.1
        e = np.maximum(g.mean_frame, 0)
        pixel_var = noise.read_noise**2 + noise.shot_gain * e + (noise.fixed_pattern * e) ** 2
        expected = backscatter_at_black_patch(g.mean_frame, g.black, g.target, RHO_P * 1e-4, RHO_P, pixel_var)
        np.testing.assert_allclose(g.backscatter.variance, expected.variance, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# Absolute attenuation (--lamp-radius): the pixels every distance measured


LAMP_R = 0.15


def _uniform_lamp_frames(attenuation, lamp):
    """No intrinsics (every pixel on the axis): uniform frames E = K·(r/(d_s + r))²·cos θ·exp(−c·(d + d_s))."""
    out = []
    for d in (1.0, 2.0):
        ds = float(np.linalg.norm(np.array([0.0, 0.0, d]) - lamp))
        cos = (d - lamp[2]) / ds
        e = 5000.0 * RHO_P * (LAMP_R / (ds + LAMP_R)) ** 2 * cos * np.exp(-np.asarray(attenuation) * (d + ds))
        out.append(np.ones(SHAPE + (3,)) * e)
    return out


def test_absolute_attenuation_without_per_pixel_rays_is_that_of_the_frames():
    lamp = np.array([0.1, -0.05, 0.02])
    c = np.array([0.4, 0.1, 0.05])
    profile = calibrate_with_details(_uniform_lamp_frames(c, lamp), [1.0, 2.0],
                                     _inputs(lamp_position_m=tuple(lamp), lamp_radius_m=LAMP_R)).profile
    np.testing.assert_allclose(profile.array("attenuation"), c, rtol=1e-9)


def test_a_negative_absolute_attenuation_is_stored_as_zero():
    """Frames that fade slower than spreading allows (c < 0 in every channel: impossible water, a
    lamp or distance error): the profile keeps c = 0, not a negative attenuation."""
    lamp = np.zeros(3)
    c = np.array([-0.05, -0.1, -0.2])
    profile = calibrate_with_details(_uniform_lamp_frames(c, lamp), [1.0, 2.0],
                                     _inputs(lamp_radius_m=LAMP_R)).profile
    assert list(profile.array("attenuation")) == [0.0, 0.0, 0.0]


def _reference_absolute(frames, distances, boxes, intr, lamp):
    """The spreading- and incidence-corrected ln E of every pixel whose 5×5 box lies in its target box,
    averaged (with the path length d_c + d_s) over the pixels both distances measured when they are 16
    or more, else over each distance's own; c from the two points' slope."""
    from uwcam.optics.geometry import pixel_rays

    rays = pixel_rays(intr, *SHAPE)
    masks = [_inside(_box(SHAPE, *b), 2) for b in boxes]
    common = masks[0] & masks[1]
    ys, ts = [], []
    for f, d, m in zip(frames, distances, masks):
        use = common if common.sum() >= 16 else m
        y_list, t_list = [], []
        for py, px in zip(*np.nonzero(use)):
            e = f[py - 2 : py + 3, px - 2 : px + 3].mean(axis=(0, 1))
            u = rays[py, px]
            dc = d / u[2]
            ds = np.linalg.norm(dc * u - lamp)
            cos = (dc * u[2] - lamp[2]) / ds
            y_list.append(np.log(e) + 2 * np.log(ds + LAMP_R) - np.log(cos))
            t_list.append(dc + ds)
        ys.append(np.mean(y_list, axis=0))
        ts.append(np.mean(t_list))
    return -(ys[1] - ys[0]) / (ts[1] - ts[0]), int(common.sum())


@pytest.mark.parametrize("boxes, common", [([(10, 10, 20, 20), (22, 22, 16, 16)], 16),
                                           ([(10, 10, 19, 21), (22, 22, 16, 16)], 15)])
def test_absolute_attenuation_uses_the_pixels_in_common_from_sixteen_of_them(boxes, common):
    """A beam pattern that depends on the pixel's direction (unknown to the calibration) cancels only over
    the same pixels at every distance: with 16 or more in common those are used, with fewer each
    distance's own (docs/calibration.md)."""
    from tests.synthetic import plate_frame
    from uwcam.optics import Intrinsics

    intr = Intrinsics.from_fov(SHAPE[1], SHAPE[0], 50.0)
    lamp = np.array([0.2, -0.15, 0.05])
    c = np.array([0.46, 0.11, 0.06])
    distances = [1.0, 1.5]
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    beam = np.exp(-(((xx - 20.0) / 15.0) ** 2) - ((yy - 15.0) / 12.0) ** 2)[..., None]
    frames = [plate_frame(d, c, np.full(3, 4e5), RHO_P, SHAPE, lamp, LAMP_R)[0] * beam for d in distances]
    profile = calibrate_with_details(frames, distances, _inputs(target_boxes=boxes, intrinsics=intr, lamp_position_m=tuple(lamp),
                                                                lamp_radius_m=LAMP_R)).profile
    want, n = _reference_absolute(frames, distances, boxes, intr, lamp)
    assert n == common and np.all(want > 0)
    np.testing.assert_allclose(profile.array("attenuation"), want, rtol=1e-9)


def test_a_lamp_level_with_the_plate_gives_a_finite_profile():
    """Grazing light (the lamp as far forward as the nearer plate: cos θ = 0 there) is clipped, not a log
    of 0: the calibration still finishes with finite values and no warning."""
    lamp = np.array([0.3, 0.0, 1.0])
    frames = []
    for d in (1.0, 2.0):
        e = 5000.0 * RHO_P * np.exp(-np.array([0.4, 0.1, 0.05]) * 2 * d) + 10.0
        frames.append(np.ones(SHAPE + (3,)) * e)
    profile = calibrate_with_details(frames, [1.0, 2.0], _inputs(lamp_position_m=tuple(lamp), lamp_radius_m=LAMP_R)).profile
    assert np.all(np.isfinite(profile.array("attenuation")))


def test_covariance_between_distances_enters_the_generalised_least_squares():
    """Four distances, three channels (reference 0), each channel's entries correlated between
    distances (the same pixels' fixed pattern): V, b and their covariance are the generalised
    least squares written out here, channel-major, with the full covariance of the ratios
    y_ik = ln E_k − ln E_ref (their reference share included); leaving the cross-distance
    covariance out gives another answer."""
    from uwcam.calibration.line_fit import fit_attenuation_differences

    rng = np.random.default_rng(21)
    d = np.array([1.0, 1.6, 2.3, 3.1])
    n, chans, ref = len(d), 3, 0
    v_true, b_true = np.array([0.0, 0.35, 0.4]), np.array([0.0, -0.2, 0.1])
    ln_e = np.log(5000.0) - 0.1 * d[:, None] + (b_true - np.outer(d, v_true)) + rng.normal(0, 1e-3, (n, chans))
    lv = rng.uniform(1e-4, 3e-4, (n, chans))
    lc = np.zeros((n, n, chans))
    for k in range(chans):  # a fixed pattern shared by every distance: 60 % correlated
        s = np.sqrt(lv[:, k])
        lc[:, :, k] = 0.6 * np.outer(s, s)
    fit = fit_attenuation_differences(ln_e, d, ref, lv, lc)

    others = [1, 2]
    rows = [(k, i) for k in others for i in range(n)]  # channel-major, unlike the code's order
    y = np.array([ln_e[i, k] - ln_e[i, ref] for k, i in rows])
    x = np.zeros((len(rows), 4))
    cov_y = np.zeros((len(rows), len(rows)))
    for r, (k, i) in enumerate(rows):
        j = others.index(k)
        x[r, j], x[r, 2 + j] = -d[i], 1.0
        for c, (k2, i2) in enumerate(rows):
            ref_part = lv[i, ref] if i == i2 else lc[i, i2, ref]
            own = (lv[i, k] if i == i2 else lc[i, i2, k]) if k == k2 else 0.0
            cov_y[r, c] = own + ref_part
    w = np.linalg.inv(cov_y)
    cov = np.linalg.inv(x.T @ w @ x)
    theta = cov @ x.T @ w @ y
    np.testing.assert_allclose(fit.attenuation_difference[others], theta[:2], rtol=1e-9)
    np.testing.assert_allclose(fit.log_constant[others], theta[2:], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fit.covariance, cov, rtol=1e-8)  # χ² well within its bound: unscaled
    independent = fit_attenuation_differences(ln_e, d, ref, lv)
    assert not np.allclose(independent.covariance, fit.covariance, rtol=1e-3)


def test_several_frames_per_distance_without_a_black_patch_calibrate():
    """Two frames per distance give the light beside the plate its noise points (docs/calibration.md,
    "Noise model"); without a black patch only the plate is left out of that light: the fit runs,
    with points of the light beside the plate at both distances."""
    distances = [1.0, 1.0, 1.5, 1.5]
    frames = [_textured(d, seed=i) for i, d in enumerate(distances)]
    target_box = (30, 4, 22, 32)  # the right, brighter part: the dimmer left is light beside the plate
    details = calibrate_with_details(frames, distances, _inputs(target_box=target_box))
    beside = [label for label, _ in details.noise_points if not label.startswith(("plate", "black patch"))]
    assert {label.split(" m,")[0] for label in beside} == {"beside the plate 1", "beside the plate 1.5"}, beside
    assert np.all(np.isfinite(details.profile.array("attenuation_difference")))


def test_one_frame_per_distance_takes_no_points_from_the_light_beside_the_plate():
    """The light beside the plate counts only its temporal noise, so it needs two frames or more
    of a distance (uwcam.calibration.noise_fit.dim_noise_points); from one frame each, the points
    are the plate's alone, and so is the read noise they give."""
    distances = [1.0, 1.5]
    frames = [_textured(d, seed=i) for i, d in enumerate(distances)]
    details = calibrate_with_details(frames, distances, _inputs(target_box=(30, 4, 22, 32)))
    assert [label.split(",")[0] for label, _ in details.noise_points] == ["plate 1 m"] * 4 + ["plate 1.5 m"] * 4


def test_the_black_patch_is_never_taken_for_light_beside_the_plate():
    """The black patch is dim, as the water beside the plate is, but it lies on the plate: its noise
    is measured as the black patch's, and the light beside the plate leaves it out with the plate
    (docs/calibration.md, "Noise model"). A plate filling the view but a 4-pixel rim, with a large
    black patch, two frames per distance: no point of light beside the plate."""
    distances = [1.0, 1.0, 1.5, 1.5]
    frames = [_textured(d, seed=i) for i, d in enumerate(distances)]
    patch = (20, 12, 24, 16)
    for f in frames:
        f[_box(SHAPE, *patch)] *= 0.1
    details = calibrate_with_details(frames, distances, _inputs(target_box=(4, 4, 48, 32), black_boxes=[patch] * 4,
                                                                black_reflectance=RHO_B))
    assert [label for label, _ in details.noise_points] == ["plate 1 m", "black patch 1 m", "plate 1.5 m", "black patch 1.5 m"]
