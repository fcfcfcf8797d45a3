"""Mitsuba 3 as an independent renderer of uwcam's world (issue #41 item 6).

uwcam's simulator and bench/independent_world.py both leave out multiple scattering and forward
scattering (the plate's light blurred into the black patch, the seabed's light scattered on its way
to the camera and from the lamp). This script has Mitsuba 3 (https://mitsuba.readthedocs.io, a
physically based renderer written by others) render the same rig with all of it, once; the tests
(tests/mitsuba_frames.py, tests/test_mitsuba_ranging.py) read the cached radiance and add a sensor.

The world: a pinhole camera 160×120, 60° horizontal field of view (f = 80/tan 30° = 138.56 px,
principal point at the image centre (79.5, 59.5), x right, y down, z forward) inside a homogeneous
water (Mitsuba ``homogeneous``, RGB σ_t = c and albedo b/c of the Jerlov-like waters of
bench/independent_world.py, Henyey–Greenstein phase g = 0.9); a ``spot`` lamp at (0.3, 0, 0) m
pointing along +z, intensity 1 W/sr in each channel, even out to 45° off its axis (``beam_width``) and
falling linearly to 0 at 60° (``cutoff_angle``), so that everything in view at ≥ 1 m is lit evenly,
in a housing: a sphere of no water, radius 0.1 m, round the lamp (a ``null`` boundary: it bounds the 1/d² of
multiply scattered paths that turn close to the point lamp; in a 64-spp trial it lowered the saved
7 m seabed's green noise from 9.4 to 7.3 %, a modest gain; its only other effect, 0.1 m less water on every lamp ray, is a constant colour of the lamp that the calibration
takes in); Lambertian (``diffuse``) surfaces square to the axis:

* ``plate-1m``, ``plate-2m``: the plate of calibration_rigs/grey-plate-large-patch.yaml (0.5 m,
  18 % grey, 20 cm black patch of 3 % at its centre), its printed layout drawn by
  bench/independent_world.plate_from_rig / plate_reflectance into a 2000×2000 texture (nearest
  texel; 0.25 mm texels), open water around it;
* ``seabed-3m``, ``seabed-5m``, ``seabed-7m``: a uniform 18 % grey plane (200 m square) filling the view;
* ``open``: no surface.

How each image is made (the renderer's delta tracking makes the unscattered surface light, which
must survive the water on two legs, a Bernoulli draw per sample: far too noisy at 160×120 on two CPU
cores for the red channel at 5–7 m, so the image is split into two parts with a known sum):

1. ``full``: Mitsuba ``volpathmis`` (the volumetric path tracer with spectral MIS, Miller et al.
   2019: plain ``volpath`` samples one colour channel's free flights per path and its weights for the
   other channels explode when red's c is 5–7× green's), ``max_depth`` 64, ``--spp`` samples per pixel,
   box pixel filter: every light path, unscattered, singly and multiply scattered;
2. ``unscattered`` S: the same scene without water, rendered by Mitsuba (``path``, direct light
   only; the lamp's beam, inverse square, incidence, the texture and each pixel's footprint), times
   the Beer–Lambert transmittance of its two legs, exp(−c (|x − lamp| − 0.1 m + |x|)), at the point x
   where the pixel centre's ray meets the surface (the definition of the unscattered light; checked
   against Mitsuba's own render of the same scene in water that only absorbs: equal within 0.2–0.5 %,
   the noise of 32 spp);
3. the scattered light M = full − S is smooth across the view except at the plate's edges; its
   Monte-Carlo noise is removed by a normalised Gaussian blur (σ ``--blur-far`` px for seabed and open
   water, ``--blur-plate`` px for the plates) *within* regions of one kind (pixels wholly on the grey,
   wholly on the black patch, wholly off the plate; the mixed edge pixels are left unblurred), and
   the saved radiance is S + blurred M.

Each scene is saved as tests/data/mitsuba/<water>_<scene>.npz: ``radiance`` (H, W, 3) float16 (the
mean, relative precision 5e-4 — float16 keeps the cache small), ``unscattered`` (float16), and
metadata (water, scene, distance_m, spp, blur, mitsuba version, seconds, c, b, g, intrinsics, lamp).
``--check`` renders the listed scenes a second time with another seed and prints the per-pixel relative
difference of the raw ``full`` render and of the saved radiance, and of ln(R/G), ln(G/B) (what ranging
reads). At 128 spp (the cache), one render's noise (difference of two seeds / √2, rms over the plate's
grey or the inner 80 % of the seabed), Jerlov II:

| scene | full render R, G, B | saved radiance R, G, B | ln(R/G) | ln(G/B) |
|---|---|---|---|---|
| plate 1 m | 7.5, 8.3, 8.7 % | 1.0, 1.2, 1.3 % | 0.24 % | 0.12 % |
| seabed 3 m | 13, 15, 16 % | 1.6, 2.0, 2.1 % | 0.56 % | 0.15 % |
| seabed 7 m | 27, 21, 23 % | 1.4, 2.9, 3.3 % | 3.0 % | 0.48 % |

The channels' noise comes from the same paths and mostly cancels in their ratios; the saved
radiance's noise is smooth over the blur (σ 8 px), not independent per pixel. In range: about 0.3 %
at 3 m through R/G and about 2 % at 7 m through G/B, below uwcam's own σ there. Render times on the
2-core test machine, shared: 15–65 s a scene, 8 minutes for the twelve.

    .venv/bin/pip install mitsuba        # scalar_rgb is the variant used (no GPU or LLVM needed)
    .venv/bin/python bench/mitsuba_world.py --out tests/data/mitsuba [--spp 128] [--only NAME ...]
                                            [--check jerlov-II-like_seabed-7m ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import independent_world as iw  # noqa: E402

RIG = os.path.join(ROOT, "calibration_rigs", "grey-plate-large-patch.yaml")
WIDTH, HEIGHT, FOV_X_DEG = 160, 120, 60.0
LAMP_M = (0.3, 0.0, 0.0)
BEAM_WIDTH_DEG, CUTOFF_DEG = 45.0, 60.0
SEABED_REFLECTANCE = 0.18
MAX_DEPTH = 64
HOUSING_M = 0.1
TEXELS = 2000
WATERS = ("jerlov-II-like", "jerlov-I-like")
# (name, kind, distance in m; None: no surface)
SCENES = (("plate-1m", "plate", 1.0), ("plate-2m", "plate", 2.0), ("seabed-3m", "seabed", 3.0),
          ("seabed-5m", "seabed", 5.0), ("seabed-7m", "seabed", 7.0), ("open", "open", None))


def intrinsics() -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of the Mitsuba camera: pixel centres at integers, principal point at the centre."""
    f = (WIDTH / 2.0) / np.tan(np.radians(FOV_X_DEG / 2.0))
    return f, f, (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0


def names() -> list[str]:
    """Every cached render's stem, <water>_<scene>."""
    return [f"{w}_{s[0]}" for w in WATERS for s in SCENES]


def pixel_rays() -> np.ndarray:
    fx, fy, cx, cy = intrinsics()
    x, y = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    v = np.stack([(x - cx) / fx, (y - cy) / fy, np.ones_like(x)], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def plate_texture(layout: iw.PlateLayout) -> np.ndarray:
    """The plate's printed reflectance, (TEXELS, TEXELS, 3) float32, row 0 at the plate's top (y < 0)."""
    w, h = layout.size_m
    s = (np.arange(TEXELS) + 0.5) / TEXELS
    xp, yp = np.meshgrid(s * w - w / 2, s * h - h / 2)
    return iw.plate_reflectance(layout, xp, yp).astype(np.float32)


def regions(kind: str, distance: float | None, layout: iw.PlateLayout | None) -> np.ndarray:
    """Each pixel's region for the blur, (H, W) int: 0 off any surface or uniform surface, 1 wholly on
    the plate's grey, 2 wholly on the black patch, −1 mixed (an edge: not blurred). 4×4 sub-pixels."""
    if kind != "plate":
        return np.zeros((HEIGHT, WIDTH), int)
    fx, fy, cx, cy = intrinsics()
    x, y = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    codes = []
    for oy in (np.arange(4) + 0.5) / 4 - 0.5:
        for ox in (np.arange(4) + 0.5) / 4 - 0.5:
            r = iw.plate_reflectance(layout, (x + ox - cx) / fx * distance, (y + oy - cy) / fy * distance)[..., 1]
            codes.append(np.where(np.isnan(r), 0, np.where(r > 0.1, 1, 2)))
    codes = np.stack(codes)
    return np.where(np.all(codes == codes[0], axis=0), codes[0], -1)


def gaussian_filter(a: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur of a 2-D array, zero outside (numpy only), kernel to ±4σ."""
    r = int(np.ceil(4 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    a = np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), 0, a)
    return np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), 1, a)


def blur_within(image: np.ndarray, region: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian blur of ``image`` (H, W, 3) within each region ≥ 0 (edge pixels −1 kept)."""
    if sigma <= 0:
        return image.copy()
    out = image.copy()
    for code in np.unique(region[region >= 0]):
        m = (region == code).astype(np.float64)
        norm = gaussian_filter(m, sigma)
        for k in range(3):
            num = gaussian_filter(image[..., k] * m, sigma)
            out[..., k] = np.where(m > 0, num / np.maximum(norm, 1e-12), out[..., k])
    return out


def scene_dict(mi, water: iw.Water | None, kind: str, distance: float | None, spp: int, texture: np.ndarray | None,
               integrator: dict) -> dict:
    def look(origin, target):
        return mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, -1, 0])  # y down in the image

    sensor = {"type": "perspective", "fov": FOV_X_DEG, "fov_axis": "x", "to_world": look([0, 0, 0], [0, 0, 1]),
              "sampler": {"type": "independent", "sample_count": spp},
              "film": {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT, "rfilter": {"type": "box"},
                       "pixel_format": "rgb"}}
    d = {"type": "scene", "integrator": integrator, "sensor": sensor,
         "lamp": {"type": "spot", "to_world": look(list(LAMP_M), [LAMP_M[0], LAMP_M[1], 1.0]),
                  "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
                  "beam_width": BEAM_WIDTH_DEG, "cutoff_angle": CUTOFF_DEG}}
    if water is not None:
        c, b = water.c, water.b
        d["water"] = {"type": "homogeneous", "sigma_t": {"type": "rgb", "value": c.tolist()},
                      "albedo": {"type": "rgb", "value": (b / c).tolist()}, "phase": {"type": "hg", "g": water.g}}
        sensor["medium"] = {"type": "ref", "id": "water"}
        # the lamp's housing: a sphere of no water around the point lamp (a null, index-matched boundary)
        d["housing"] = {"type": "sphere", "center": list(LAMP_M), "radius": HOUSING_M, "bsdf": {"type": "null"},
                        "exterior": {"type": "ref", "id": "water"}}
    if kind == "plate":
        # the rectangle spans [−1, 1]² in its frame; turned about x to face the camera (normal −z), which
        # puts the bitmap's first row at the plate's bottom: hence the flip
        half = 0.25
        bsdf = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture[::-1])),
                                                   "raw": True, "filter_type": "nearest"}}
        d["surface"] = {"type": "rectangle", "bsdf": bsdf,
                        "to_world": mi.ScalarTransform4f().translate([0, 0, distance]).rotate([1, 0, 0], 180).scale([half, half, 1])}
    elif kind == "seabed":
        d["surface"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [SEABED_REFLECTANCE] * 3}},
                        "to_world": mi.ScalarTransform4f().translate([0, 0, distance]).rotate([1, 0, 0], 180).scale([100, 100, 1])}
    return d


def render_scene(mi, water: iw.Water, kind: str, distance: float | None, spp: int, seed: int, texture, region,
                 blur: float, vacuum_spp: int = 256) -> dict:
    """Render one scene: the full image, the unscattered part and the saved radiance (S + blurred M)."""
    started = time.monotonic()
    full = np.array(mi.render(mi.load_dict(scene_dict(mi, water, kind, distance, spp, texture,
                                                     {"type": "volpathmis", "max_depth": MAX_DEPTH})), seed=seed), dtype=np.float64)
    seconds_full = time.monotonic() - started
    unscattered = np.zeros_like(full)
    if kind != "open":
        vac = np.array(mi.render(mi.load_dict(scene_dict(mi, None, kind, distance, vacuum_spp, texture,
                                                        {"type": "path", "max_depth": 2})), seed=seed), dtype=np.float64)
        rays = pixel_rays()
        points = rays * (distance / rays[..., 2])[..., None]
        legs = np.linalg.norm(points - np.asarray(LAMP_M), axis=-1) - HOUSING_M + np.linalg.norm(points, axis=-1)
        unscattered = vac * np.exp(-water.c * legs[..., None])
    scattered = blur_within(full - unscattered, region, blur)
    return {"full": full, "unscattered": unscattered, "radiance": unscattered + scattered,
            "seconds": time.monotonic() - started, "seconds_full": seconds_full}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join(ROOT, "tests", "data", "mitsuba"))
    parser.add_argument("--spp", type=int, default=128, help="samples per pixel of the full render")
    parser.add_argument("--blur-far", type=float, default=8.0, help="σ px of the scattered light's blur: seabed, open water")
    parser.add_argument("--blur-plate", type=float, default=3.0, help="σ px of the scattered light's blur: plates")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--only", nargs="*", help="render only these <water>_<scene> names")
    parser.add_argument("--check", nargs="*", default=[], help="render these again with another seed and print the "
                        "per-pixel relative difference (raw full render and saved radiance)")
    args = parser.parse_args()
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    os.makedirs(args.out, exist_ok=True)
    layout = iw.plate_from_rig(RIG)
    texture = plate_texture(layout)
    wanted = set(args.only) if args.only else set(names())
    fx, fy, cx, cy = intrinsics()
    print(f"Mitsuba {mi.__version__} scalar_rgb, volpathmis max_depth {MAX_DEPTH}, {args.spp} spp, "
          f"{WIDTH}×{HEIGHT}, f = {fx:.4f} px", flush=True)
    for water_name in WATERS:
        water = iw.WATERS[water_name]
        for scene, kind, distance in SCENES:
            name = f"{water_name}_{scene}"
            if name not in wanted and name not in args.check:
                continue
            region = regions(kind, distance, layout)
            blur = args.blur_plate if kind == "plate" else args.blur_far
            r = render_scene(mi, water, kind, distance, args.spp, args.seed, texture, region, blur)
            if name in wanted:
                np.savez_compressed(
                    os.path.join(args.out, f"{name}.npz"), radiance=r["radiance"].astype(np.float16),
                    unscattered=r["unscattered"].astype(np.float16), water=water_name, scene=scene, kind=kind,
                    distance_m=np.nan if distance is None else distance, spp=args.spp, blur_px=blur, max_depth=MAX_DEPTH,
                    mitsuba_version=mi.__version__, variant="scalar_rgb", integrator="volpathmis",
                    seconds=r["seconds"], c_per_m=water.c, b_per_m=water.b, g=water.g,
                    intrinsics=np.array(intrinsics()), lamp_m=np.array(LAMP_M), seabed_reflectance=SEABED_REFLECTANCE,
                    beam_width_deg=BEAM_WIDTH_DEG, cutoff_deg=CUTOFF_DEG)
            share = np.mean(r["full"] - r["unscattered"], axis=(0, 1)) / np.mean(r["full"], axis=(0, 1))
            print(f"{name}: {r['seconds']:.1f} s (full render {r['seconds_full']:.1f} s); mean radiance R,G,B "
                  f"{', '.join(f'{v:.3e}' for v in r['radiance'].mean(axis=(0, 1)))}; scattered share "
                  f"{', '.join(f'{v:.2f}' for v in share)}", flush=True)
            if name in args.check:
                again = render_scene(mi, water, kind, distance, args.spp, args.seed + 1000, texture, region, blur)
                use = (region == 1) if kind == "plate" else np.ones(region.shape, bool)
                use[: HEIGHT // 10] = use[-HEIGHT // 10:] = False
                use[:, : WIDTH // 10] = use[:, -WIDTH // 10:] = False
                for part in ("full", "radiance"):
                    a, b = r[part][use], again[part][use]
                    rel = (a - b) / np.maximum(0.5 * (a + b), 1e-30) / np.sqrt(2.0)  # one render's relative noise
                    print(f"  seed check {part} ({'plate grey' if kind == 'plate' else 'inner 80 %'}): per-pixel relative "
                          "noise of one render (difference of two seeds / mean / √2), R,G,B: rms "
                          + ", ".join(f"{np.sqrt(np.mean(rel[:, k] ** 2)):.4f}" for k in range(3))
                          + "; 99th percentile of |·| " + ", ".join(f"{np.percentile(np.abs(rel[:, k]), 99):.4f}" for k in range(3)),
                          flush=True)
                a, b = r["radiance"][use], again["radiance"][use]
                for (i, j) in ((0, 1), (1, 2)):
                    d = (np.log(a[:, i] / a[:, j]) - np.log(b[:, i] / b[:, j])) / np.sqrt(2.0)
                    print(f"  seed check radiance: ln({'RGB'[i]}/{'RGB'[j]}) noise of one render, rms {np.sqrt(np.mean(d ** 2)):.4f}",
                          flush=True)


if __name__ == "__main__":
    main()
