"""Lens shading (vignetting): measured from a flat field, stored in the profile, and taken into the
model of the water's light; where it is not measured, estimated with it or counted in σ.

The shading the tests put on frames is cos⁴ of each pixel's angle off the axis, computed here from
the pinhole geometry (cos θ = f / sqrt(f² + x² + y²)), not by the code under test."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from uwcam.calibration.profile import LensShading
from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics
from uwcam.optics.lens_shading import fit_shading, shading_map

WIDTH, HEIGHT = 320, 240


def natural_fall_off(intrinsics: Intrinsics, height: int, width: int, shift_x: float = 0.0) -> np.ndarray:
    """(H, W) cos⁴ of each pixel's angle off an axis through (cx + shift_x, cy)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    dx = (x - intrinsics.cx - shift_x) / intrinsics.fx
    dy = (y - intrinsics.cy) / intrinsics.fy
    return (1.0 / np.sqrt(1.0 + dx * dx + dy * dy)) ** 4


def test_a_flat_field_gives_the_lens_shading_within_half_a_per_cent():
    intr = Intrinsics(fx=260.0, fy=260.0, cx=159.5, cy=119.5)  # 63° across the view
    truth = natural_fall_off(intr, HEIGHT, WIDTH)
    rng = np.random.default_rng(4)
    levels = np.array([9000.0, 14000.0, 20000.0])
    frames = rng.normal(truth[None, ..., None] * levels + 100.0, 30.0, (4, HEIGHT, WIDTH, 3))
    coefficients, rms = fit_shading(frames, intr, dark_level=100.0, full_scale=65535.0)
    fitted = shading_map(coefficients, intr, HEIGHT, WIDTH)
    assert np.max(np.abs(fitted / truth - 1.0)) < 0.005
    assert rms < 0.01


def test_a_view_that_is_not_evenly_lit_or_holds_non_finite_values_is_refused():
    intr = Intrinsics(fx=260.0, fy=260.0, cx=159.5, cy=119.5)
    x = np.linspace(0.2, 1.0, WIDTH)[None, :, None]
    ramp = np.broadcast_to(x * 10000.0, (HEIGHT, WIDTH, 3)).copy()  # a lamp's spot, not a lens
    with pytest.raises(UserInputError, match="evenly lit"):
        fit_shading(ramp, intr)
    bad = np.full((HEIGHT, WIDTH, 3), 5000.0)
    bad[10:20, 10:20] = np.nan
    with pytest.raises(UserInputError, match="non-finite"):
        fit_shading(bad, intr)
    with pytest.raises(UserInputError, match="light in only"):
        fit_shading(np.zeros((HEIGHT, WIDTH, 3)), intr)


def test_a_profile_s_lens_shading_is_typed_bounded_and_needs_intrinsics():
    assert LensShading(coefficients=(-2.0, 0.0)).coefficients == (-2.0, 0.0)
    for bad in ((True, 1.0), ("-2", 1.0), (float("nan"), 1.0), (-50.0, 1.0)):
        with pytest.raises(ValidationError):
            LensShading(coefficients=bad)
    from uwcam.calibration.profile import profile_from_mapping
    profile = seabed_cell(distance=3.0, vignetting=None, frames=1, size=(160, 120))[0]
    data = profile.model_dump(mode="json")
    data["lens_shading"] = {"coefficients": [-2.0, 0.0]}
    assert profile_from_mapping(data).lens_shading.coefficients == (-2.0, 0.0)
    data["intrinsics"] = None
    with pytest.raises(UserInputError, match="intrinsics"):
        profile_from_mapping(data)


def seabed_cell(distance: float, vignetting: str | None, frames: int = 16, size: tuple[int, int] = (WIDTH, HEIGHT),
                water_name: str = "jerlov-II", lamp_x: float = 0.3):
    """uwcam's simulator's grey seabed and 16 open-water frames (:func:`tests.test_backscatter_unresolved.murky_cell`)
    seen through a lens with ``vignetting`` (None, "cos4", "decentred": cos⁴ about a point a fifth of
    the width right of the centre, or "one side": a port that passes half the light at the left edge,
    all at the right), the profile calibrated in the same water through a lens without it:
    (profile, frames, open water, truth)."""
    from tests.test_backscatter_unresolved import murky_cell

    profile, scene, open_water, truth = murky_cell(size, distance, water_name, lamp_x, frames)
    dark = profile.array("dark_level")
    shading = np.ones(size[::-1])
    if vignetting == "one side":
        shading = np.broadcast_to(np.linspace(0.5, 1.0, size[0])[None, :], size[::-1])
    elif vignetting is not None:
        shading = natural_fall_off(profile.camera_intrinsics(), size[1], size[0],
                                   shift_x=0.2 * size[0] if vignetting == "decentred" else 0.0)

    def lens(frame):
        return (frame.astype(np.float64) - dark) * shading[..., None] + dark

    return profile, [lens(f) for f in scene], np.stack([lens(f) for f in open_water]), truth


def errors(result, truth):
    """Relative errors and z-scores of the valid pixels of the inner 80 % of the view, and the share valid there."""
    h, w = truth.shape
    inner = np.zeros((h, w), bool)
    inner[h // 10: h - h // 10, w // 10: w - w // 10] = True
    valid = np.isfinite(result.range) & inner
    e = (result.range[valid] - truth[valid]) / truth[valid]
    z = (result.range[valid] - truth[valid]) / np.sqrt(result.variance[valid])
    return e, z, valid.sum() / inner.sum()


def test_an_ordinary_lens_s_vignetting_no_longer_ranges_a_seabed_a_quarter_short():
    """Jerlov II, lamp 0.3 m aside, seabed at 5 m, 16 frames fused, 16 open-water frames, cos⁴
    vignetting on the scene and the open water. Before the shading was fitted with the water's
    column, the fit read the lens's fall-off as a column of c = 0.01 1/m in every channel: −26 %,
    76 % of the valid pixels beyond 3σ. Now within 2 % (the same frames without vignetting: +0.8 %),
    none beyond 3σ, and the shading fitted is the lens's."""
    from uwcam.ranging.images import range_images
    from uwcam.water.backscatter import BackscatterModel

    profile, frames, open_water, truth = seabed_cell(5.0, "cos4")
    result = range_images(profile, frames, path_length_bounds=(0.0, 100.0), smoothing="mean", compensate=True,
                          iterations=2, open_water=open_water)
    e, z, valid = errors(result, truth)
    assert valid >= 0.85
    assert abs(np.median(e)) <= 0.02
    assert np.mean(np.abs(z) > 3.0) <= 0.02
    fit = BackscatterModel.from_profile(profile, open_water).column_fit
    # cos⁴ = (1 + ρ²)⁻²: a = −2, b = 0.
    assert np.all(np.abs(fit.shading[:, 0] + 2.0) < 0.2)
    truth_map = natural_fall_off(profile.camera_intrinsics(), HEIGHT, WIDTH)
    for coefficients in fit.shading:
        assert np.max(np.abs(shading_map(coefficients, profile.camera_intrinsics(), HEIGHT, WIDTH) / truth_map - 1)) < 0.02


def test_a_decentred_lens_s_shading_ranges_within_its_sigma():
    """cos⁴ about a point a fifth of the width right of the image's centre (a lens off the port's
    axis): the radial model centred on the image holds it only in part, and the column fitted with
    it takes c's of 0.8–1.0 1/m, which put the same share of the water's light in front of a seabed
    at 5 m as the true column (all but 0.03 %). Within 2 %, none beyond 3σ."""
    from uwcam.ranging.images import range_images

    profile, frames, open_water, truth = seabed_cell(5.0, "decentred")
    result = range_images(profile, frames, path_length_bounds=(0.0, 100.0), smoothing="mean", compensate=True,
                          iterations=2, open_water=open_water)
    e, z, valid = errors(result, truth)
    assert valid >= 0.85 and abs(np.median(e)) <= 0.02
    assert np.mean(np.abs(z) > 3.0) <= 0.02


def test_a_shading_no_column_makes_grows_the_doubt_instead_of_ranging_wrong():
    """A port that passes half the light at the left edge and all at the right: no column of the
    model, radial shading or not, makes that shape with a c the calibration's allows (the fit wants
    0.01–0.03 1/m where the calibration says 0.1–0.5), so the model keeps the calibration's c and
    doubts the share beyond the surface as far as the two columns part. Pixels whose light that
    doubt swamps lose their range, each with its reason; of those kept, no more than 2 % lie beyond 3σ."""
    from uwcam.optics.validity import Reason
    from uwcam.ranging.images import range_images
    from uwcam.water.backscatter import BackscatterModel, column_fit_agrees

    profile, frames, open_water, truth = seabed_cell(5.0, "one side")
    model = BackscatterModel.from_profile(profile, open_water)
    assert not column_fit_agrees(model.column_fit, profile.array("attenuation")).all()
    assert model.tail_uncertainty is not None and model.tail_uncertainty.max() > 0.4
    result = range_images(profile, frames, path_length_bounds=(0.0, 100.0), smoothing="mean", compensate=True,
                          iterations=2, open_water=open_water)
    e, z, valid = errors(result, truth)
    assert z.size == 0 or np.mean(np.abs(z) > 3.0) <= 0.02
    lost = ~np.isfinite(result.range)
    assert np.all(result.reasons[lost] != Reason.VALID)


def test_a_measured_shading_shapes_the_water_s_light_without_open_water():
    """Without an open-water frame the model spreads the black patch's level across the view with the
    lamp's geometry. With the lens's shading in the profile, it takes the shading with it."""
    from uwcam.water.backscatter import BackscatterModel

    profile = seabed_cell(3.0, None, frames=1)[0]
    intr = profile.camera_intrinsics()
    plain = BackscatterModel.from_profile(profile, shape=(HEIGHT, WIDTH))
    shaded_profile = profile.model_copy(update={"lens_shading": LensShading(coefficients=(-2.0, 0.0))})
    shaded = BackscatterModel.from_profile(shaded_profile, shape=(HEIGHT, WIDTH))
    x, y = (int(round(v)) for v in profile.backscatter.patch_pixels[-1])
    lens = shading_map((-2.0, 0.0), intr, HEIGHT, WIDTH)
    ratio = shaded.pattern / plain.pattern
    np.testing.assert_allclose(ratio, (lens / lens[y, x])[..., None] * np.ones(3), rtol=1e-6)


def test_uwcam_calibrate_measures_the_lens_shading_from_flat_field_frames(tmp_path, capsys):
    """`uwcam calibrate --flat-field` keeps the shading of an evenly lit view in the profile; it needs
    the intrinsics, and a view that is not evenly lit is refused with one line."""
    from tests.synthetic import RGB_ATTENUATION, plate_frame
    from uwcam.calibration.profile import load_profile
    from uwcam.cli import main

    rng = np.random.default_rng(3)
    images = []
    for d in (1.0, 2.0):
        f, _ = plate_frame(d, RGB_ATTENUATION, np.array([0.8, 1.0, 0.9]) * 2e5, np.full(3, 0.18), (60, 80))
        images.append(str(tmp_path / f"{d}.npy"))
        np.save(images[-1], np.clip(np.rint(f + np.sqrt(9.0 + 0.2 * f) * rng.standard_normal(f.shape)), 0, 65535).astype(np.uint16))
    h, w = np.load(images[0]).shape[:2]
    intr = Intrinsics(fx=0.8 * w, fy=0.8 * w, cx=(w - 1) / 2, cy=(h - 1) / 2)
    flat = natural_fall_off(intr, h, w)[..., None] * np.array([20000.0, 30000.0, 25000.0])
    flat_path = tmp_path / "flat.npy"
    np.save(flat_path, np.clip(np.rint(flat + rng.normal(0, 20, flat.shape)), 0, 65535).astype(np.uint16))
    base = ["calibrate", *images, "--distance", "1", "--distance", "2", "--dark-level", "0,0,0"]
    out = tmp_path / "p.yaml"
    k = f"{intr.fx},{intr.fy},{intr.cx},{intr.cy}"
    assert main([*base, "--intrinsics", k, "--flat-field", str(flat_path), "-o", str(out)]) == 0
    shading = load_profile(out).lens_shading
    assert shading is not None
    fitted = shading_map(shading.coefficients, intr, h, w)
    assert np.max(np.abs(fitted / natural_fall_off(intr, h, w) - 1)) < 0.01
    capsys.readouterr()
    assert main([*base, "--flat-field", str(flat_path), "-o", str(tmp_path / "q.yaml")]) == 2
    assert "--flat-field needs --intrinsics" in capsys.readouterr().err
    uneven = np.broadcast_to(np.linspace(0.1, 1.0, w)[None, :, None] * 30000.0, (h, w, 3))
    np.save(flat_path, uneven.astype(np.uint16))
    assert main([*base, "--intrinsics", k, "--flat-field", str(flat_path), "-o", str(tmp_path / "r.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "evenly lit" in err
    assert not (tmp_path / "q.yaml").exists() and not (tmp_path / "r.yaml").exists()
