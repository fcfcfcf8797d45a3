"""uwcam's command line on frames rendered by Mitsuba 3, an independent renderer (issue #41 item 6).

bench/mitsuba_world.py had Mitsuba render (volpathmis, multiple scattering, HG g = 0.9, a spot lamp
0.3 m aside) the grey-plate-large-patch plate at 1 and 2 m, a grey seabed at 3, 5 and 7 m and open
water, in two Jerlov-like waters; tests/mitsuba_frames.py adds a 16-bit sensor (PRNU 1 %, 4 e⁻/DN,
3 DN read noise, dark 256 DN, one exposure per water: the calibration's). Here, as a user would:

1. ``uwcam calibrate`` on 4 frames at each of 1 and 2 m with the rig, the intrinsics, the lamp's
   offset (0.3, 0, 0) m, radius 0 and the dark level;
2. ``uwcam range`` on the seabed at 3, 5, 7 m: ``--compensate-backscatter --smoothing mean
   --path-bounds 0,100``, one frame and 16 fused, with 16 ``--open-water`` frames and without;
3. ``uwcam range`` on open water alone (with 16 other open-water frames as ``--open-water`` and without).

Bounds (issue #41): in every cell at most 2 % of the valid pixels (inner 80 % of the image) beyond 3σ,
z = (range − truth)/√variance, the truth z_plane/cos(ray angle) from the intrinsics; open water alone
at most 1 % valid. Measured on the current code (median and rms relative error, valid share,
beyond-3σ share, z sd; ``pytest -s`` prints the table). Cache rendered at 128 spp; seabed frames at
the calibration's exposure; inner 80 % of the image; "—": no valid pixel:

| water | range | frames | open water | median error % | rms % | valid % | beyond 3σ % | z sd |
|---|---|---|---|---|---|---|---|---|
| jerlov-II-like | 3 m | 1 | 16 | +1.64 | 1.91 | 100.0 | 12.35 | 1.02 |
| jerlov-II-like | 3 m | 1 | no | +9.63 | 12.61 | 74.4 | 0.00 | 0.06 |
| jerlov-II-like | 3 m | 16 | 16 | +1.48 | 1.59 | 100.0 | 73.84 | 1.23 |
| jerlov-II-like | 3 m | 16 | no | +5.60 | 7.34 | 79.8 | 0.00 | 0.05 |
| jerlov-II-like | 5 m | 1 | 16 | +6.31 | 9.15 | 100.0 | 0.37 | 0.82 |
| jerlov-II-like | 5 m | 1 | no | — | — | 0.0 | 0.00 | — |
| jerlov-II-like | 5 m | 16 | 16 | +6.50 | 7.13 | 100.0 | 0.11 | 0.55 |
| jerlov-II-like | 5 m | 16 | no | — | — | 0.0 | 0.00 | — |
| jerlov-II-like | 7 m | 1 | 16 | +7.94 | 11.30 | 99.4 | 0.84 | 0.87 |
| jerlov-II-like | 7 m | 1 | no | — | — | 0.0 | 0.00 | — |
| jerlov-II-like | 7 m | 16 | 16 | +7.48 | 8.29 | 99.7 | 0.73 | 0.55 |
| jerlov-II-like | 7 m | 16 | no | — | — | 0.0 | 0.00 | — |
| jerlov-I-like | 3 m | 1 | 16 | +0.71 | 0.87 | 100.0 | 3.38 | 0.94 |
| jerlov-I-like | 3 m | 1 | no | +1.65 | 2.16 | 100.0 | 0.00 | 0.20 |
| jerlov-I-like | 3 m | 16 | 16 | +0.65 | 0.71 | 100.0 | 10.52 | 0.82 |
| jerlov-I-like | 3 m | 16 | no | +1.56 | 2.11 | 100.0 | 0.00 | 0.19 |
| jerlov-I-like | 5 m | 1 | 16 | +4.42 | 5.63 | 100.0 | 0.27 | 0.72 |
| jerlov-I-like | 5 m | 1 | no | +7.28 | 8.40 | 99.8 | 0.00 | 0.05 |
| jerlov-I-like | 5 m | 16 | 16 | +4.37 | 4.84 | 100.0 | 0.02 | 0.53 |
| jerlov-I-like | 5 m | 16 | no | +7.23 | 7.75 | 99.9 | 0.00 | 0.04 |
| jerlov-I-like | 7 m | 1 | 16 | +4.60 | 5.92 | 100.0 | 0.18 | 0.72 |
| jerlov-I-like | 7 m | 1 | no | — | — | 0.0 | 0.00 | — |
| jerlov-I-like | 7 m | 16 | 16 | +4.62 | 4.91 | 100.0 | 0.00 | 0.42 |
| jerlov-I-like | 7 m | 16 | no | — | — | 0.0 | 0.00 | — |

Open water alone: 0.00 % valid in both waters, with and without 16 ``--open-water`` frames.
The 3 m cells with open water break the 2 % bound (xfail, strict); every range reads long (+0.7 to
+8 %), the 5–7 m cells pass only because their variance is wide (z sd 0.4–0.9); without open-water
frames the 3 m variance is far too wide (z sd 0.05–0.2) and 5–7 m (Jerlov II; 7 m Jerlov I) have no
valid pixel at all (a cell with no valid pixel passes the bound vacuously).
"""

from __future__ import annotations

import os
from functools import lru_cache

import numpy as np
import pytest

from tests import mitsuba_frames as mf
from uwcam.cli import main

pytestmark = pytest.mark.slow

RIG = "grey-plate-large-patch"
WATERS = mf.mw.WATERS
RANGES = (3.0, 5.0, 7.0)
FRAMES = (1, 16)
CAL_FRAMES = 4
OPEN_FRAMES = 16
SENSOR = mf.Sensor()
CELLS = [(w, d, n, ow) for w in WATERS for d in RANGES for n in FRAMES for ow in (True, False)]

# Cells that break the 2 % bound on the current code (issue #41 findings; the figures measured from
# the cache rendered at 128 spp: median error, rms, valid, beyond 3σ, z sd over the inner 80 %).
XFAIL: dict[tuple, str] = {
    ("jerlov-II-like", 3.0, 1, True): "Mitsuba Jerlov II 3 m, 1 frame, 16 open-water frames: median +1.64 %, rms 1.91 %, "
                                      "valid 100 %, 12.35 % beyond 3σ (bound 2 %), z sd 1.02: a bias the variance does not cover",
    ("jerlov-II-like", 3.0, 16, True): "Mitsuba Jerlov II 3 m, 16 frames, 16 open-water frames: median +1.48 %, rms 1.59 %, "
                                       "valid 100 %, 73.84 % beyond 3σ (bound 2 %), z sd 1.23",
    ("jerlov-I-like", 3.0, 1, True): "Mitsuba Jerlov I 3 m, 1 frame, 16 open-water frames: median +0.71 %, rms 0.87 %, "
                                     "valid 100 %, 3.38 % beyond 3σ (bound 2 %), z sd 0.94",
    ("jerlov-I-like", 3.0, 16, True): "Mitsuba Jerlov I 3 m, 16 frames, 16 open-water frames: median +0.65 %, rms 0.71 %, "
                                      "valid 100 %, 10.52 % beyond 3σ (bound 2 %), z sd 0.82",
}


def cell_id(cell) -> str:
    w, d, n, ow = cell
    return f"{w}-{d:g}m-{n}f-{'ow' if ow else 'noow'}"


def save(frames, folder, stem) -> list[str]:
    paths = []
    for k, f in enumerate(frames):
        p = os.path.join(folder, f"{stem}_{k:02d}.npy")
        np.save(p, f)
        paths.append(p)
    return paths


def run_cli(args: list[str]) -> None:
    assert main(args) == 0, args


@lru_cache(maxsize=None)
def calibrated(water: str, folder: str) -> tuple[str, float]:
    exposure = mf.calibration_exposure(water, SENSOR)
    images, distances = [], []
    for d in (1.0, 2.0):
        images += save(mf.frames(f"{water}_plate-{d:g}m", SENSOR, exposure, CAL_FRAMES, seed=int(10 * d)), folder, f"{water}_plate{d:g}")
        distances += [d] * CAL_FRAMES
    fx, fy, cx, cy = mf.intrinsics()
    profile = os.path.join(folder, f"{water}.yaml")
    args = ["calibrate", *images]
    for d in distances:
        args += ["--distance", f"{d:g}"]
    dark = f"{SENSOR.dark_level_dn:g}"
    args += ["--rig", RIG, "--intrinsics", f"{fx:.6f},{fy:.6f},{cx:g},{cy:g}", "--lamp-offset", "0.3,0,0",
             "--lamp-radius", "0", "--dark-level", f"{dark},{dark},{dark}", "--channels", "R:650,G:520,B:470", "-o", profile]
    run_cli(args)
    return profile, exposure


def inner() -> np.ndarray:
    h, w = mf.mw.HEIGHT, mf.mw.WIDTH
    m = np.zeros((h, w), bool)
    m[h // 10 : h - h // 10, w // 10 : w - w // 10] = True
    return m


def statistics(range_m, variance, truth, region) -> dict:
    valid = np.isfinite(range_m) & region
    out = {"valid": float(valid.sum() / region.sum()), "count": int(valid.sum())}
    if not valid.any():
        return out | {"median": np.nan, "rms": np.nan, "beyond": 0.0, "z_sd": np.nan}
    r, t = range_m[valid].astype(np.float64), truth[valid]
    e = (r - t) / t
    z = (r - t) / np.sqrt(variance[valid].astype(np.float64))
    return out | {"median": float(np.median(e)), "rms": float(np.sqrt(np.mean(e**2))),
                  "beyond": float(np.mean(np.abs(z) > 3.0)), "z_sd": float(np.std(z))}


def range_maps(profile, images, folder, tag, open_water):
    out, var = os.path.join(folder, f"range_{tag}.npy"), os.path.join(folder, f"var_{tag}.npy")
    args = ["range", profile, *images, "-o", out, "--variance", var, "--smoothing", "mean",
            "--compensate-backscatter", "--path-bounds", "0,100"]
    if open_water:
        args += ["--open-water", *open_water]
    run_cli(args)
    return np.load(out), np.load(var)


@lru_cache(maxsize=None)
def results(folder: str) -> dict:
    """Every cell's statistics and the open-water-alone valid shares, per water."""
    rows, alone = {}, {}
    for water in WATERS:
        profile, exposure = calibrated(water, folder)
        ow = save(mf.frames(f"{water}_open", SENSOR, exposure, OPEN_FRAMES, seed=200), folder, f"{water}_open")
        for d in RANGES:
            scene = save(mf.frames(f"{water}_seabed-{d:g}m", SENSOR, exposure, max(FRAMES), seed=100 + int(d)), folder,
                         f"{water}_seabed{d:g}")
            for n in FRAMES:
                for with_ow in (True, False):
                    r, v = range_maps(profile, scene[:n], folder, f"{water}_{d:g}_{n}_{int(with_ow)}", ow if with_ow else None)
                    rows[(water, d, n, with_ow)] = statistics(r, v, mf.true_range(d), inner())
        lone = save(mf.frames(f"{water}_open", SENSOR, exposure, 1, seed=400), folder, f"{water}_open_alone")
        r, _ = range_maps(profile, lone, folder, f"{water}_alone", None)
        alone[(water, False)] = float(np.isfinite(r).mean())
        r, _ = range_maps(profile, lone, folder, f"{water}_alone_ow", ow)
        alone[(water, True)] = float(np.isfinite(r).mean())
    return {"rows": rows, "alone": alone}


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    folder = str(tmp_path_factory.mktemp("mitsuba"))
    res = results(folder)
    print("\n" + table(res))
    return res


def pct(x: float, signed: bool = True) -> str:
    if not np.isfinite(x):
        return "—"
    return f"{100 * x:+.2f}" if signed else f"{100 * x:.2f}"


def table(res: dict) -> str:
    lines = ["| water | range | frames | open water | median error % | rms % | valid % | beyond 3σ % | z sd |",
             "|---|---|---|---|---|---|---|---|---|"]
    for (w, d, n, ow), r in res["rows"].items():
        lines.append(f"| {w} | {d:g} m | {n} | {'16' if ow else 'no'} | {pct(r['median'])} | {pct(r['rms'], False)} | "
                     f"{100 * r['valid']:.1f} | {pct(r['beyond'], False)} | "
                     + ("—" if not np.isfinite(r["z_sd"]) else f"{r['z_sd']:.2f}") + " |")
    for (w, ow), v in res["alone"].items():
        lines.append(f"open water alone, {w}, {'16 --open-water frames' if ow else 'no --open-water'}: valid {100 * v:.2f} %")
    return "\n".join(lines)


def test_cache_holds_every_scene_of_the_script():
    """tests/data/mitsuba holds one render per scene of bench/mitsuba_world.py, with its metadata."""
    cached = sorted(f[:-4] for f in os.listdir(mf.DATA) if f.endswith(".npz"))
    assert cached == sorted(mf.mw.names())
    for name in cached:
        r = mf.load(name)
        assert r["radiance"].shape == (mf.mw.HEIGHT, mf.mw.WIDTH, 3)
        assert np.all(np.isfinite(r["radiance"])) and np.all(r["radiance"] >= 0)
        assert str(r["water"]) in WATERS and int(r["spp"]) > 0 and float(r["seconds"]) > 0
        assert str(r["mitsuba_version"]).startswith("3.")
        assert np.allclose(r["intrinsics"], mf.intrinsics())


def test_sensor_exposure_puts_the_1m_plate_at_60_percent():
    for water in WATERS:
        e = mf.calibration_exposure(water, SENSOR)
        mean = mf.mean_dn(f"{water}_plate-1m", mf.Sensor(prnu=0.0), e)
        assert mean.max() == pytest.approx(SENSOR.dark_level_dn + 0.6 * (65535 - SENSOR.dark_level_dn), rel=1e-9)
        f = mf.frames(f"{water}_seabed-3m", SENSOR, e, 2, seed=1)
        assert f[0].dtype == np.uint16 and f[0].shape == (mf.mw.HEIGHT, mf.mw.WIDTH, 3)
        assert not np.array_equal(f[0], f[1])


def test_vignetting_is_cos4_of_the_ray_angle_from_the_field_of_view():
    v = mf.vignetting(mf.Sensor(vignetting=True))
    fx, fy, cx, cy = mf.intrinsics()
    assert fx == pytest.approx(80 / np.tan(np.radians(30)))
    corner = np.cos(np.arctan(np.hypot(0 - cx, 0 - cy) / fx)) ** 4
    assert v[0, 0] == pytest.approx(corner) and v.max() < 1 and v.max() > 0.999
    assert np.all(mf.vignetting(SENSOR) == 1)


def _cell_params():
    out = []
    for cell in CELLS:
        marks = [pytest.mark.xfail(strict=True, reason=XFAIL[cell])] if cell in XFAIL else []
        out.append(pytest.param(cell, id=cell_id(cell), marks=marks))
    return out


@pytest.mark.parametrize("cell", _cell_params())
def test_at_most_2_percent_of_valid_pixels_beyond_3_sigma(measured, cell):
    r = measured["rows"][cell]
    assert r["beyond"] <= 0.02, f"{cell_id(cell)}: {r}"


@pytest.mark.parametrize("water", WATERS)
def test_open_water_alone_is_at_most_1_percent_valid(measured, water):
    for with_ow in (True, False):
        assert measured["alone"][(water, with_ow)] <= 0.01, (water, with_ow, measured["alone"])
