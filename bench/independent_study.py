"""uwcam's command line against a world it did not simulate (issue #41).

The frames come from bench/independent_world.py, a forward model written from the physics (point lamp
with a Gaussian beam, Lambertian surfaces, single scattering with a Henyey–Greenstein phase function,
cos⁴ vignetting, PRNU, shot and read noise), not from uwcam.simulation. For one water and vignetting
on or off it:

1. renders the grey-plate-large-patch plate at 1 m and 2 m (CAL_FRAMES noisy frames each, one exposure:
   the 1 m plate's bright end at 70 % of full scale) and runs ``uwcam calibrate`` on the PNGs with the
   rig, the intrinsics, the lamp's offset and radius (0: a point lamp) and the dark level;
2. renders a uniform grey seabed (ρ = 0.18, the plate's grey) square to the camera at 3, 5 and 7 m and
   open water, and ranges them with ``uwcam range`` as bench/water_study.py's goal protocol does:
   backscatter compensated, 3×3 mean smoothing, path bounds 0–100 m; one frame and the mean of 16
   frames; with an open-water frame (the scene and the open water at the scene's exposure, its bright
   end at 70 % of full scale) and without one (the scene at the calibration's exposure: ``uwcam range``
   cannot be told a frame's exposure, so a frame ranged on the profile's black-patch measurements alone
   must be taken at the calibration's);
3. ranges open-water frames alone (no surface in view: valid % should be ≤ 1).

Statistics over the inner 80 % of the image (as water_study): median and rms relative error, the
valid share, the share of valid pixels more than 3σ from the truth (σ = √variance map) and the sd of
the z-scores.

    .venv/bin/python bench/independent_study.py [--water jerlov-II-like] [--vignetting] [--size 160x120]
                                                [--cal-frames 4] [--frames 16] [--open-frames 1] [--beam-sigma 30] [--keep DIR] [--uwcam CMD]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import independent_world as iw  # noqa: E402

UWCAM = [os.path.join(ROOT, ".venv", "bin", "uwcam")]  # --uwcam replaces it (e.g. another checkout's)
RIG = os.path.join(ROOT, "calibration_rigs", "grey-plate-large-patch.yaml")
CAL_DISTANCES = (1.0, 2.0)
RANGES = (3.0, 5.0, 7.0)
CHANNELS = "R:650,G:520,B:470"
BOUNDS = "0,100"  # the daemon's default path-length bounds, as in water_study


def uwcam(*args: str) -> str:
    """Run the uwcam command line; its stdout (raises with its stderr on failure)."""
    proc = subprocess.run([*UWCAM, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"uwcam {args[0]} failed ({proc.returncode}): {proc.stderr.strip() or proc.stdout.strip()}")
    return proc.stdout.strip()


def save(frames: list[np.ndarray], folder: str, stem: str) -> list[str]:
    paths = []
    for k, f in enumerate(frames):
        p = os.path.join(folder, f"{stem}_{k:02d}.png")
        iw.write_png(p, f)
        paths.append(p)
    return paths


def statistics(range_m: np.ndarray, variance: np.ndarray, truth: np.ndarray, region: np.ndarray) -> dict:
    """Median and rms relative error, valid share, share beyond 3σ and z sd over ``region``."""
    valid = np.isfinite(range_m) & region
    out = {"valid": float(valid.sum() / region.sum()), "count": int(valid.sum())}
    if not valid.any():
        return out | {"median": np.nan, "rms": np.nan, "beyond": np.nan, "z_sd": np.nan}
    r, t = range_m[valid].astype(np.float64), truth[valid]
    e = (r - t) / t
    z = (r - t) / np.sqrt(variance[valid].astype(np.float64))
    return out | {"median": float(np.median(e)), "rms": float(np.sqrt(np.mean(e**2))),
                  "beyond": float(np.mean(np.abs(z) > 3.0)), "z_sd": float(np.std(z))}


def range_files(profile: str, images: list[str], folder: str, tag: str, open_water: list[str] | None) -> tuple[np.ndarray, np.ndarray]:
    out, var = os.path.join(folder, f"range_{tag}.npy"), os.path.join(folder, f"var_{tag}.npy")
    args = ["range", profile, *images, "-o", out, "--variance", var, "--smoothing", "mean",
            "--compensate-backscatter", "--path-bounds", BOUNDS]
    if open_water:
        args += ["--open-water", *open_water]  # several: a uwcam whose --open-water takes several frames
    uwcam(*args)
    return np.load(out), np.load(var)


def run(water_name: str, vignetting: bool, size: tuple[int, int], cal_frames: int, frames: int, folder: str,
        lamp_offset: float = 0.3, open_frames: int = 1, beam_sigma_deg: float | None = 30.0) -> tuple[list[dict], dict]:
    water = iw.WATERS[water_name]
    camera = iw.Camera(width=size[0], height=size[1], vignetting=vignetting)
    lamp = iw.Lamp(position_m=(lamp_offset, 0.0, 0.0), sigma_beam_deg=beam_sigma_deg)
    layout = iw.plate_from_rig(RIG)
    timings = {}
    started = time.monotonic()
    # 1. calibration frames and uwcam calibrate
    images, distances, exposure = [], [], None
    for d in CAL_DISTANCES:
        plate = iw.render(camera, iw.Scene("plate", d, layout), lamp, water, exposure=exposure)
        exposure = plate.exposure
        images += save(plate.frames(camera, cal_frames, seed=int(10 * d)), folder, f"plate_{d:g}m")
        distances += [d] * cal_frames
    cal_exposure = exposure
    profile = os.path.join(folder, "profile.yaml")
    fx, fy, cx, cy = camera.intrinsics
    args = ["calibrate", *images]
    for d in distances:
        args += ["--distance", f"{d:g}"]
    args += ["--rig", RIG, "--intrinsics", f"{fx:.6f},{fy:.6f},{cx:g},{cy:g}", "--lamp-offset", f"{lamp_offset:g},0,0",
             "--lamp-radius", "0", "--dark-level", ",".join([f"{camera.dark_level_dn:g}"] * 3), "--channels", CHANNELS,
             "-o", profile]
    calibration = uwcam(*args)
    timings["calibrate"] = time.monotonic() - started
    h, w = size[1], size[0]
    inner = np.zeros((h, w), bool)
    inner[h // 10 : h - h // 10, w // 10 : w - w // 10] = True
    rows = []
    for d in RANGES:
        # with open water: the scene at its own exposure, the open water at the same
        scene = iw.render(camera, iw.Scene("seabed", d), lamp, water)
        ow = iw.render(camera, iw.Scene("open-water", d), lamp, water, exposure=scene.exposure)
        seabed_paths = save(scene.frames(camera, frames, seed=100 + int(d)), folder, f"seabed_{d:g}m_scene")
        ow_paths = save(ow.frames(camera, open_frames, seed=200 + int(d)), folder, f"open_{d:g}m_scene")
        # without: the scene at the calibration's exposure
        scene_cal = iw.render(camera, iw.Scene("seabed", d), lamp, water, exposure=cal_exposure)
        cal_paths = save(scene_cal.frames(camera, frames, seed=300 + int(d)), folder, f"seabed_{d:g}m_cal")
        for n in (1, frames):
            for with_ow in (True, False):
                paths = (seabed_paths if with_ow else cal_paths)[:n]
                r, v = range_files(profile, paths, folder, f"{d:g}_{n}_{int(with_ow)}", ow_paths if with_ow else None)
                stats = statistics(r, v, scene.truth_m, inner)
                rows.append({"water": water_name, "vignetting": "cos⁴" if vignetting else "off", "range": d, "frames": n,
                             "open water": "yes" if with_ow else "no",
                             "exposure": f"scene ×{scene.exposure / cal_exposure:.1f}" if with_ow else "calibration",
                             **stats})
    timings["seabed"] = time.monotonic() - started - timings["calibrate"]
    # 3. open water alone
    alone = {}
    ow_cal = iw.render(camera, iw.Scene("open-water", 5.0), lamp, water, exposure=cal_exposure)
    p = save(ow_cal.frames(camera, 1, seed=400), folder, "open_alone_cal")
    r, _ = range_files(profile, p, folder, "alone_cal", None)
    alone["calibration exposure, no --open-water"] = float(np.isfinite(r).mean())
    ow_scene = iw.render(camera, iw.Scene("open-water", 7.0), lamp, water, exposure=scene.exposure)
    p = save(ow_scene.frames(camera, 1 + open_frames, seed=500), folder, "open_alone_scene")
    r, _ = range_files(profile, p[:1], folder, "alone_scene", p[1:])
    alone[f"7 m scene exposure, {open_frames} other open-water frame(s) as --open-water"] = float(np.isfinite(r).mean())
    timings["total"] = time.monotonic() - started
    return rows, {"calibration": calibration, "alone": alone, "timings": timings, "exposure": cal_exposure,
                  "water": water}


def pct(x: float, signed: bool = True) -> str:
    if not np.isfinite(x):
        return "—"
    return f"{100 * x:+.2f}" if signed else f"{100 * x:.1f}"


def table(rows: list[dict]) -> str:
    lines = ["| water | vignetting | range | frames | open water | exposure | median error % | rms % | valid % | beyond 3σ % | z sd |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['water']} | {r['vignetting']} | {r['range']:g} m | {r['frames']} | {r['open water']} | {r['exposure']} | "
                     f"{pct(r['median'])} | {pct(r['rms'], False)} | {100 * r['valid']:.1f} | {pct(r['beyond'], False)} | "
                     + ("—" if not np.isfinite(r["z_sd"]) else f"{r['z_sd']:.2f}") + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--water", default="jerlov-II-like", choices=sorted(iw.WATERS))
    parser.add_argument("--vignetting", action="store_true", help="cos⁴ lens vignetting on")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--cal-frames", type=int, default=4, help="calibration frames per distance")
    parser.add_argument("--frames", type=int, default=16, help="frames of each static scene fused")
    parser.add_argument("--open-frames", type=int, default=1, help="open-water frames given to --open-water (more than "
                        "one needs a uwcam whose --open-water takes several, as water_study's 16)")
    parser.add_argument("--beam-sigma", type=float, default=30.0, help="the lamp's Gaussian beam σ, degrees (0: an even lamp)")
    parser.add_argument("--lamp-offset", type=float, default=0.3, help="lamp offset to the right, m")
    parser.add_argument("--uwcam", metavar="CMD", help="the uwcam command to run, split at spaces (default: "
                        ".venv/bin/uwcam; e.g. 'env PYTHONPATH=/tmp/head .venv/bin/python -m uwcam' for another copy)")
    parser.add_argument("--keep", metavar="DIR", help="write the frames, profile and maps here (default: a temporary folder)")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.uwcam:
        UWCAM[:] = args.uwcam.split()
    if args.keep:
        os.makedirs(args.keep, exist_ok=True)
        folder_ctx = None
        folder = args.keep
    else:
        folder_ctx = tempfile.TemporaryDirectory(prefix="uwcam-independent-")
        folder = folder_ctx.name
    try:
        rows, info = run(args.water, args.vignetting, size, args.cal_frames, args.frames, folder, args.lamp_offset, args.open_frames,
                         args.beam_sigma or None)
    finally:
        if folder_ctx is not None:
            folder_ctx.cleanup()
    water = info["water"]
    c = water.c
    print(f"# uwcam against the independent world: {args.water}, vignetting {'cos⁴' if args.vignetting else 'off'}\n")
    beam = f"σ_beam {args.beam_sigma:g}°" if args.beam_sigma else "even beam"
    print(f"{size[0]}×{size[1]}, lamp ({args.lamp_offset:g}, 0, 0) m, {beam}, g = {water.g}; water c = "
          f"{c[0]:.3f}/{c[1]:.3f}/{c[2]:.3f} 1/m (b = {water.b[0]:.3f}/{water.b[1]:.3f}/{water.b[2]:.3f}), true "
          f"c_G − c_R = {c[1] - c[0]:+.4f}, c_B − c_R = {c[2] - c[0]:+.4f} 1/m")
    print(f"open-water frames per --open-water: {args.open_frames}")
    print(f"uwcam calibrate ({args.cal_frames} frames at each of 1 and 2 m): {info['calibration']}\n")
    print(table(rows))
    print("\nOpen water alone (valid share of the whole image; should be ≤ 1 %): "
          + "; ".join(f"{k}: {100 * v:.2f} %" for k, v in info["alone"].items()))
    t = info["timings"]
    print(f"\nTime: calibration {t['calibrate']:.0f} s, seabed {t['seabed']:.0f} s, total {t['total']:.0f} s")


if __name__ == "__main__":
    main()
