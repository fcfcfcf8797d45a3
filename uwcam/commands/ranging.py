"""``uwcam range`` and ``uwcam simulate``: ranging frames from files, and making them."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from uwcam.fileio import UserInputError
from uwcam.commands.arguments import (
    checked_output,
    parse_channels,
    parse_exposure,
    parse_floats,
    parse_per_channel,
    resolve_rig_path,
)

if TYPE_CHECKING:
    from uwcam.ranging.images import Exposure


def cmd_range(args: argparse.Namespace) -> int:
    from uwcam.imaging.imageio import MAP_SUFFIXES, read_frame, write_map
    from uwcam.config import BackscatterConfig
    from uwcam.calibration.profile import load_profile
    from uwcam.ranging.estimator import DEFAULT_SMOOTHING_TARGET
    from uwcam.ranging.images import open_water_mean, range_images

    outputs = [(args.output, "-o")] + [(p, f) for p, f in ((args.variance, "--variance"), (args.reasons, "--reasons")) if p]
    for path, flag in outputs:
        checked_output(path, MAP_SUFFIXES, flag + " {path} must end in .npy, .tif or .tiff", flag)
    profile = load_profile(args.profile)
    frames = [read_frame(path) for path in args.image]
    pair = None
    if args.pair:
        pair = tuple(s.strip() for s in args.pair.split(","))
        if len(pair) != 2:
            raise UserInputError(f"--pair needs two channel names separated by a comma, got '{args.pair}'")
    surface = None
    if args.surface_reflectance:
        surface = parse_floats(args.surface_reflectance, "--surface-reflectance", len(profile.channels))
    bounds = (0.0, np.inf)
    if args.path_bounds:
        bounds = tuple(parse_floats(args.path_bounds, "--path-bounds", 2))
        if not 0 <= bounds[0] < bounds[1]:
            raise UserInputError(f"--path-bounds must be MIN,MAX metres with 0 ≤ MIN < MAX, got '{args.path_bounds}'")
    if args.open_water and profile.backscatter is None:
        raise UserInputError("--open-water needs a profile with backscatter measurements; calibrate with a rig that "
                             "has a black patch (e.g. --rig grey-plate)")
    exposure, open_water_exposure = exposures_of(args, profile.channel_names)
    open_water, open_water_frames = None, 1
    if args.open_water:
        water_frames = [read_frame(path) for path in args.open_water]
        open_water_frames = len(water_frames)  # as the daemon's capture: their mean, and how many
        open_water = water_frames[0] if open_water_frames == 1 else open_water_mean(profile, water_frames)
    target = DEFAULT_SMOOTHING_TARGET
    if args.smoothing_target is not None:
        if (args.smooth or "none") != "adaptive":
            raise UserInputError("--smoothing-target is the target of adaptive smoothing: give --smoothing adaptive too")
        target = parse_floats(args.smoothing_target, "--smoothing-target", 1)[0]
        if not 0.001 <= target <= 0.5:
            raise UserInputError(f"--smoothing-target must be a fraction of the range from 0.001 to 0.5 (0.02 is 2 %), "
                                 f"got '{args.smoothing_target}'")
    result = range_images(profile, frames, pair=pair, surface_reflectance=surface,  # type: ignore[arg-type]
                          path_length_bounds=bounds, smoothing=args.smooth or "none", smoothing_target=target,
                          compensate=args.compensate_backscatter, iterations=BackscatterConfig().iterations,
                          open_water=open_water, open_water_frames=open_water_frames, exposure=exposure,
                          open_water_exposure=open_water_exposure)
    write_map(args.output, result.range)
    if args.variance:
        write_map(args.variance, result.variance)
    if args.reasons:
        write_map(args.reasons, result.reasons)
    valid = np.isfinite(result.range)
    summary = f"{valid.mean():.1%} of pixels valid"
    if valid.any():
        summary += f", range {np.nanmin(result.range):.3f}–{np.nanmax(result.range):.3f} m"
    print(f"wrote {args.output}: {summary}")
    return 0


def exposures_of(args: argparse.Namespace, names: list[str]) -> tuple[Exposure, Exposure]:
    """(the frames' :class:`~uwcam.ranging.images.Exposure`, the open-water frames') from
    --exposure-us, --gain-db, --open-water-exposure-us and --open-water-gain-db."""
    from uwcam.ranging.images import Exposure

    if not args.open_water and (args.open_water_exposure_us is not None or args.open_water_gain_db is not None):
        raise UserInputError("--open-water-exposure-us and --open-water-gain-db are the exposure of --open-water "
                             "frames: give those frames too")
    frames = Exposure(parse_exposure(args.exposure_us, "--exposure-us", names),
                      parse_exposure(args.gain_db, "--gain-db", names, gain=True))
    water = Exposure(parse_exposure(args.open_water_exposure_us, "--open-water-exposure-us", names),
                     parse_exposure(args.open_water_gain_db, "--open-water-gain-db", names, gain=True))
    return frames, water


def cmd_simulate(args: argparse.Namespace) -> int:
    from uwcam.imaging.imageio import IMAGE_SUFFIXES, write_frame
    from uwcam.calibration.rig import load_rig
    from uwcam.simulation import SCENES, WATER_PRESETS, Ambient, CameraModel, Channels, Lamp, SimulatedWorld, water_preset

    if args.list:
        print("scenes:")
        for name, text in SCENES.items():
            print(f"  {name:14s} {text}")
        print("water presets:")
        for name, text in WATER_PRESETS.items():
            print(f"  {name:14s} {text}")
        return 0
    if args.scene is None or args.range is None or args.output is None:
        raise UserInputError("simulate needs --scene NAME, --range METRES and -o FRAME (or --list to see scenes and water)")
    out = Path(args.output)
    if out.suffix.lower() not in IMAGE_SUFFIXES:
        raise UserInputError(f"the frame {out} must end in {', '.join(IMAGE_SUFFIXES)}")
    for path in (out, Path(args.truth) if args.truth else None):
        if path is not None and not path.parent.exists():
            raise UserInputError(f"output folder {path.parent} does not exist")
    if args.truth and Path(args.truth).suffix.lower() != ".npy":
        raise UserInputError(f"--truth {args.truth} must be a .npy file")
    if not (np.isfinite(args.range) and args.range > 0):
        raise UserInputError(f"--range must be a positive number of metres, got {args.range}")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise UserInputError(f"--size must be WIDTHxHEIGHT in pixels, e.g. 640x480, got '{args.size}'") from None
    names, wavelengths = parse_channels(args.channels or "R:675,G:575,B:475", len((args.channels or "R,G,B").split(",")))
    if any(w is None for w in wavelengths):
        raise UserInputError("simulated channels need centre wavelengths: --channels NAME:NM,... (e.g. R:675,G:575,B:475)")
    n = len(names)
    channels = Channels(tuple(names), tuple(float(w) for w in wavelengths))  # type: ignore[arg-type]
    water = water_preset(args.water, list(channels.wavelengths_nm)).with_overrides(
        forward_blur=args.forward_blur,
        scatter_attenuation=parse_per_channel(args.scatter_attenuation, "--scatter-attenuation", n),
        backscatter=parse_per_channel(args.backscatter, "--backscatter", n),
        attenuation=parse_per_channel(args.attenuation, "--attenuation", n),
    )
    lamp = Lamp(position=tuple(parse_floats(args.lamp_offset, "--lamp-offset", 3)) if args.lamp_offset else (0.0, 0.0, 0.0),
                on=not args.lamp_off)
    ambient = None
    if args.ambient:
        ambient = Ambient(tuple(parse_per_channel(args.ambient, "--ambient", n)))  # type: ignore[arg-type]
    rig = load_rig(resolve_rig_path(args.rig)) if args.rig else None
    if args.slabs < 1:
        raise UserInputError(f"--slabs must be at least 1, got {args.slabs}")
    world = SimulatedWorld(
        scene=args.scene, distance=args.range, size=(width, height), fov_deg=args.fov, channels=channels, water=water,
        lamp=lamp, camera=CameraModel(bits=args.bits, peak_code=args.peak, response=args.response,
                                                  jpeg_quality=args.jpeg_quality), ambient=ambient, slabs=args.slabs,
        gate_width=args.gate_width if args.gated else None, rig=rig, seed=args.seed, material=args.material,
        fixed_exposure=args.exposure,
    )
    if args.exposure is not None and not args.exposure > 0:
        raise UserInputError(f"--exposure must be positive, got {args.exposure}")
    if args.exposure is None and args.lamp_off:
        raise UserInputError("a lamp-off frame needs the lamp-on frame's --exposure (printed when you simulate it)")
    frame = world.noise_free_frame() if args.noise_free else world.frame(0, lamp_on=not args.lamp_off)
    if args.noise_free and out.suffix.lower() == ".png":
        raise UserInputError("a --noise-free frame is float32: write it as .npy or .tif")
    write_frame(out, frame)
    if args.truth:
        from uwcam.imaging.imageio import write_map

        write_map(args.truth, world.camera_range.astype(np.float32))
    intr = world.intrinsics
    print(f"wrote {out}: {args.scene} at {args.range:g} m in {water.name}, {width}x{height}x{n} {frame.dtype}")
    print(f"intrinsics {intr.fx:.6g},{intr.fy:.6g},{intr.cx:.6g},{intr.cy:.6g}")
    print(f"dark level {world.camera.dark_level_dn:.6g} DN; saturation {world.camera.max_code} DN; exposure {world.exposure:.6g}")
    return 0
