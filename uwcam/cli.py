"""The ``uwcam`` command line: calibrate, range, simulate, run, config check."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from uwcam import __version__
from uwcam.drivers.base import ConfigurationError
from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics

DEFAULT_RGB = ["R", "G", "B"]


def parse_floats(text: str, what: str, count: int | None = None) -> list[float]:
    """'1,2,3' → [1.0, 2.0, 3.0]; UserInputError saying what was expected."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise UserInputError(f"{what} must be comma-separated numbers, got '{text}'") from None
    if count is not None and len(values) != count:
        raise UserInputError(f"{what} needs {count} comma-separated numbers, got {len(values)} in '{text}'")
    if not all(np.isfinite(values)):
        raise UserInputError(f"{what} must be finite numbers, got '{text}'")
    return values


def parse_box(text: str, what: str) -> tuple[int, int, int, int]:
    values = parse_floats(text, what, 4)
    if any(v != int(v) for v in values) or values[2] <= 0 or values[3] <= 0 or values[0] < 0 or values[1] < 0:
        raise UserInputError(f"{what} must be X,Y,WIDTH,HEIGHT in whole pixels with positive size, got '{text}'")
    x, y, w, h = (int(v) for v in values)
    return x, y, w, h


def parse_channels(text: str | None, n: int) -> tuple[list[str], list[float | None]]:
    """--channels R:675,G:575,B:475 or R,G,B → names and optional wavelengths (nm)."""
    if text is None:
        names = DEFAULT_RGB if n == 3 else [f"ch{k}" for k in range(n)]
        return names, [None] * n
    names, wavelengths = [], []
    for item in text.split(","):
        name, _, nm = item.partition(":")
        names.append(name.strip())
        if nm:
            wl = parse_floats(nm, f"wavelength of channel {name}", 1)[0]
            if wl <= 0:
                raise UserInputError(f"wavelength of channel {name} must be positive nanometres, got {nm}")
            wavelengths.append(wl)
        else:
            wavelengths.append(None)
    if len(names) != n:
        raise UserInputError(f"--channels names {len(names)} channels but the images have {n}")
    if len(set(names)) != n or not all(names):
        raise UserInputError(f"--channels needs {n} different, non-empty names, got '{text}'")
    return names, wavelengths


def default_saturation(dtype: np.dtype) -> float:
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return float(np.finfo(np.float32).max)


def check_calibration_frames(paths: list, frames: list[np.ndarray], distances: list[float]) -> None:
    """UserInputError, naming the image, unless the frames can be calibrated from: one camera's
    (same channels, same data type), each holding finite values, and not all alike when their
    distances differ (no attenuation can be seen then: the lamp did not light the target)."""
    first, n = paths[0], frames[0].shape[-1]
    for p, f in zip(paths, frames):
        if f.shape[-1] != n:
            raise UserInputError(f"image {p} has {f.shape[-1]} channels but {first} has {n}; use images from one camera")
        if f.dtype != frames[0].dtype:
            raise UserInputError(f"image {p} holds {f.dtype} values but {first} holds {frames[0].dtype}; use images "
                                 "from one camera, saved the same way")
        finite = float(np.isfinite(f).mean()) if np.issubdtype(f.dtype, np.floating) else 1.0
        if finite < 0.5:  # the fit averages regions: NaN in them leaves nothing to fit
            raise UserInputError(f"image {p} holds {100 * (1 - finite):.0f} % NaN or infinite values; use the camera's "
                                 "frames, with finite values at the target")
    if len(set(distances)) > 1 and all(f.shape == frames[0].shape and np.array_equal(f, frames[0], equal_nan=True)
                                       for f in frames[1:]):
        raise UserInputError("the images are all alike although their distances differ, so no attenuation can be "
                             "measured; image the lit target at each distance")


def cmd_calibrate(args: argparse.Namespace) -> int:
    from uwcam.calibration import CalibrationInputs, calibrate_with_details, project_plate_box
    from pydantic import ValidationError

    from uwcam.fileio import explain_validation_error
    from uwcam.imageio import read_frame
    from uwcam.profile import MAX_DISTANCE_M, MAX_LAMP_OFFSET_M, check_intrinsics_fit, save_profile
    from uwcam.rig import load_rig, resolve_reflectance

    out = Path(args.output)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise UserInputError(f"the profile {out} must be a .yaml file")
    if not out.parent.exists():
        raise UserInputError(f"output folder {out.parent} does not exist")
    distances = args.distance or []
    if len(distances) != len(args.images):
        raise UserInputError(
            f"got {len(args.images)} image(s) but {len(distances)} --distance value(s); give one --distance per image, in order"
        )
    for d in distances:
        if not (np.isfinite(d) and d > 0):
            raise UserInputError(f"--distance must be a positive number of metres, got {d}")
        if d > MAX_DISTANCE_M:
            raise UserInputError(f"--distance {d:g} m is farther than a lamp lights a target in water; give metres, "
                                 f"at most {MAX_DISTANCE_M:g}")
    frames = [read_frame(p) for p in args.images]
    check_calibration_frames(args.images, frames, distances)
    n = frames[0].shape[-1]
    names, wavelengths = parse_channels(args.channels, n)
    curve = None
    if args.response:
        from uwcam.response import load_response

        if not np.issubdtype(frames[0].dtype, np.integer):
            raise UserInputError("--response applies to a camera's integer codes; these images are float (already linear?)")
        curve = load_response(args.response, n, bits=8 * frames[0].dtype.itemsize)
        raw_dtype = frames[0].dtype
        frames = [curve.linearise(f) for f in frames]  # every later step works on linear light
    intrinsics = Intrinsics(*parse_floats(args.intrinsics, "--intrinsics", 4)) if args.intrinsics else None
    if intrinsics is not None and not (intrinsics.fx > 0 and intrinsics.fy > 0):
        raise UserInputError("--intrinsics focal lengths FX and FY must be positive")
    if intrinsics is not None:
        h, w = frames[0].shape[:2]
        try:
            check_intrinsics_fit({"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy}, w, h)
        except ValueError as exc:
            raise UserInputError(f"--intrinsics: {exc}") from None
    lamp = tuple(parse_floats(args.lamp_offset, "--lamp-offset", 3)) if args.lamp_offset else (0.0, 0.0, 0.0)
    if any(abs(v) > MAX_LAMP_OFFSET_M for v in lamp):
        raise UserInputError(f"--lamp-offset values are metres from the camera, at most {MAX_LAMP_OFFSET_M:g}, got {args.lamp_offset}")

    rig = load_rig(resolve_rig_path(args.rig)) if args.rig else None
    target_reflectance = np.ones(n)
    black_reflectance = None
    description = "spectrally flat target"
    if rig is not None:
        target_reflectance = resolve_reflectance(rig.plate.reflectance, names, wavelengths, f"plate reflectance of rig {args.rig}")
        description = f"rig {rig.name}"
        if rig.plate.black_patch is not None:
            black_reflectance = resolve_reflectance(rig.plate.black_patch.reflectance, names, wavelengths, f"black patch of rig {args.rig}")
    if args.target_reflectance:
        target_reflectance = np.array(parse_floats(args.target_reflectance, "--target-reflectance", n))
        if np.any(target_reflectance <= 0):
            raise UserInputError("--target-reflectance values must be positive")
        description = f"target of reflectance {args.target_reflectance}"

    target_box = parse_box(args.roi, "--roi") if args.roi else None
    target_boxes = black_boxes = None
    if target_box is None and rig is not None and rig.regions.target is not None:
        target_box = rig.regions.target
    if args.black_roi:
        black_boxes = [parse_box(args.black_roi, "--black-roi")] * len(frames)
    elif rig is not None and rig.regions.black is not None:
        black_boxes = [rig.regions.black] * len(frames)
    if rig is not None and intrinsics is not None:
        # No pixel regions given: find plate and patch by projecting the rig's geometry,
        # with the plate centred on the optical axis and square to it.
        if target_box is None:
            target_boxes = [project_plate_box((0.0, 0.0), rig.plate.size_m, d, intrinsics) for d in distances]
        if black_boxes is None and rig.plate.black_patch is not None:
            patch = rig.plate.black_patch
            black_boxes = [project_plate_box(patch.centre_m, patch.size_m, d, intrinsics) for d in distances]
    if black_boxes is not None and black_reflectance is None:
        black_reflectance = np.zeros(n)

    dark = None
    if args.dark_level:
        dark = np.array(parse_floats(args.dark_level, "--dark-level", n))
    elif args.dark:
        dark_frame = read_frame(args.dark)
        if curve is not None and np.issubdtype(dark_frame.dtype, np.integer):
            dark_frame = curve.linearise(dark_frame)
        if dark_frame.shape[-1] != n:
            raise UserInputError(f"dark frame {args.dark} has {dark_frame.shape[-1]} channels but the images have {n}")
        dark = dark_frame.reshape(-1, n).mean(axis=0)
    reference = 0
    if args.reference:
        if args.reference not in names:
            raise UserInputError(f"--reference must be one of the channels {','.join(names)}, got {args.reference}")
        reference = names.index(args.reference)
    saturation = args.saturation if args.saturation is not None else default_saturation(frames[0].dtype)
    step = 1.0 if np.issubdtype(frames[0].dtype, np.integer) else 0.0
    if curve is not None:  # linear DN: the top code's value; each code's width is the response's business
        saturation = float(curve.table[:, -1].min()) if args.saturation is None else \
            float(curve.table[:, min(int(args.saturation), curve.table.shape[1] - 1)].min())
        step = 0.0
        if raw_dtype != np.uint8 and args.response not in ("srgb", "rec709"):
            raise UserInputError("a recovered response curve applies to 8-bit frames")
    if args.lamp_radius is not None and not 0 <= args.lamp_radius <= MAX_LAMP_OFFSET_M:
        raise UserInputError(f"--lamp-radius must be zero (a point source) or a positive number of metres up to "
                             f"{MAX_LAMP_OFFSET_M:g}, got {args.lamp_radius}")

    inputs = CalibrationInputs(
        channel_names=names,
        wavelengths_nm=wavelengths,
        target_reflectance=target_reflectance,
        black_reflectance=black_reflectance,
        target_box=target_box,
        target_boxes=target_boxes,
        black_boxes=black_boxes,
        lamp_position_m=lamp,  # type: ignore[arg-type]
        intrinsics=intrinsics,
        lamp_radius_m=args.lamp_radius,
        dark_level=dark,
        saturation_level=saturation,
        quantisation_step=step,
        reference=reference,
        name=args.name or out.stem,
        target_description=description,
        image_names=[str(p) for p in args.images],
    )
    report = Path(args.report) if args.report else None
    if report is not None:
        if report.suffix.lower() not in (".html", ".htm"):
            raise UserInputError(f"--report {report} must be an .html file")
        if not report.parent.exists():
            raise UserInputError(f"output folder {report.parent} of --report does not exist")
    try:
        details = calibrate_with_details(frames, distances, inputs)
    except ValidationError as exc:  # the fit's result is outside what a profile may hold
        raise UserInputError(explain_validation_error(exc, "the images do not give a usable calibration")
                             + "; check that the lamp lights the target and that each --distance is right") from None
    except np.linalg.LinAlgError as exc:
        raise UserInputError(f"the images do not give a usable calibration ({exc}); check that the target region "
                             "holds finite, lit values in every image") from None
    profile = details.profile
    if curve is not None:
        from uwcam.profile import ResponseRecord

        profile = profile.model_copy(update={"response": ResponseRecord(**curve.to_record())})
    save_profile(profile, out)
    if report is not None:
        from uwcam.calibration_report import html_report
        from uwcam.fileio import atomic_write

        with atomic_write(report, "w") as fh:
            fh.write(html_report(details))
        print(f"wrote {report}")
    v = ", ".join(f"{c.name}−{profile.reference_channel} {c.attenuation_difference:+.4f}±{c.attenuation_difference_std:.4f}"
                  for c in profile.channels if c.name != profile.reference_channel)
    print(f"wrote {out}: attenuation differences (1/m) {v}; rms residual {profile.provenance.rms_residual:.2e}")
    return 0


def cmd_response(args: argparse.Namespace) -> int:
    from uwcam.imageio import read_frame
    from uwcam.response import recover, save_response

    out = Path(args.output)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise UserInputError(f"the response file {out} must be a .yaml file")
    if not out.parent.exists():
        raise UserInputError(f"output folder {out.parent} does not exist")
    exposures = parse_floats(args.exposure_ms, "--exposure-ms", len(args.images))
    if not all(np.isfinite(t) and t > 0 for t in exposures):
        raise UserInputError(f"--exposure-ms values must be positive milliseconds, got '{args.exposure_ms}'")
    frames = [read_frame(p) for p in args.images]
    curve = recover(frames, [t / 1000.0 for t in exposures], method=args.method)
    save_response(curve, out)
    mid = curve.table[:, 128] / curve.table[:, -1]
    print(f"wrote {out}: {curve.method}; code 128 is {', '.join(f'{v:.3f}' for v in mid)} of the top code's light "
          "(sRGB: 0.216, linear: 0.502)")
    return 0


def cmd_rig_print(args: argparse.Namespace) -> int:
    from uwcam.rig import load_rig
    from uwcam.rig_artwork import write_artwork

    out = Path(args.output)
    if out.suffix.lower() != ".pdf":
        raise UserInputError(f"the artwork {out} must be a .pdf file")
    if not out.parent.exists():
        raise UserInputError(f"output folder {out.parent} does not exist")
    rig = load_rig(resolve_rig_path(args.rig))
    write_artwork(rig, out)
    w, h = rig.plate.size_m
    print(f"wrote {out}: {rig.name}, {w * 100:g} × {h * 100:g} cm at true scale; print at 100 % and check the 10 cm bar")
    return 0


def cmd_range(args: argparse.Namespace) -> int:
    from uwcam.imageio import MAP_SUFFIXES, read_frame, write_map
    from uwcam.config import BackscatterConfig
    from uwcam.profile import load_profile
    from uwcam.range_images import range_images

    outputs = [(args.output, "-o")] + [(p, f) for p, f in ((args.variance, "--variance"), (args.reasons, "--reasons")) if p]
    for path, flag in outputs:
        p = Path(path)
        if p.suffix.lower() not in MAP_SUFFIXES:
            raise UserInputError(f"{flag} {p} must end in .npy, .tif or .tiff")
        if not p.parent.exists():
            raise UserInputError(f"output folder {p.parent} of {flag} does not exist")
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
    open_water = read_frame(args.open_water) if args.open_water else None
    result = range_images(profile, frames, pair=pair, surface_reflectance=surface,  # type: ignore[arg-type]
                          path_length_bounds=bounds, smoothing=args.smooth or "none",
                          compensate=args.compensate_backscatter, iterations=BackscatterConfig().iterations,
                          open_water=open_water)
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


def resolve_rig_path(text: str) -> Path:
    """A rig file path, or the name of a rig shipped with uwcam (e.g. grey-plate)."""
    from uwcam.rig import builtin_rig_path

    path = Path(text)
    if path.exists() or path.suffix in (".yaml", ".yml") or "/" in text:
        return path
    return builtin_rig_path(text)


def parse_per_channel(text: str | None, what: str, n: int) -> np.ndarray | None:
    """One number for every channel, or N comma-separated numbers."""
    if text is None:
        return None
    values = parse_floats(text, what)
    if len(values) not in (1, n):
        raise UserInputError(f"{what} takes one value or {n} comma-separated values (one per channel), got '{text}'")
    if any(v < 0 for v in values):
        raise UserInputError(f"{what} must not be negative, got '{text}'")
    return np.broadcast_to(np.array(values), (n,)).copy()


def cmd_simulate(args: argparse.Namespace) -> int:
    from uwcam.imageio import IMAGE_SUFFIXES, write_frame
    from uwcam.rig import load_rig
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
        from uwcam.imageio import write_map

        write_map(args.truth, world.camera_range.astype(np.float32))
    intr = world.intrinsics
    print(f"wrote {out}: {args.scene} at {args.range:g} m in {water.name}, {width}x{height}x{n} {frame.dtype}")
    print(f"intrinsics {intr.fx:.6g},{intr.fy:.6g},{intr.cx:.6g},{intr.cy:.6g}")
    print(f"dark level {world.camera.dark_level_dn:.6g} DN; saturation {world.camera.max_code} DN; exposure {world.exposure:.6g}")
    return 0


def require_websocket_support() -> None:
    """uvicorn serves WebSockets only with a WebSocket library beside it; without one it logs a
    warning and answers every WebSocket route with 404, so the page would have no live view."""
    import importlib

    for name in ("websockets", "wsproto"):  # what uvicorn tries, in its order
        try:
            importlib.import_module(name)
            return
        except ImportError:
            continue
    raise UserInputError("the Python package 'websockets' is missing (the page's live view and /api/v1/stream "
                         "need it): install it with '.venv/bin/pip install websockets', or run deploy/install.sh again")


def _orderly_server_class() -> type:
    import contextlib
    import signal
    import threading

    import uvicorn

    class OrderlyServer(uvicorn.Server):
        """uvicorn's server, stopped by Ctrl-C or SIGTERM in order (the lifespan stops the loop,
        switches the lamp off, releases the devices) and then done: uvicorn would raise the signal
        again afterwards, which only adds a traceback and a failed exit status to a clean stop."""

        @contextlib.contextmanager
        def capture_signals(self):  # type: ignore[override]
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            original = {sig: signal.signal(sig, self.handle_exit) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                yield
            finally:
                for sig, handler in original.items():
                    signal.signal(sig, handler)

    return OrderlyServer


def cmd_run(args: argparse.Namespace) -> int:
    import gc
    import logging
    import os

    require_websocket_support()

    from uwcam.memory import limit_malloc_arenas

    limit_malloc_arenas()  # before any thread allocates: see uwcam/memory.py

    import socket

    import uvicorn
    from pydantic import ValidationError

    from uwcam.api import create_app
    from uwcam.config import SIMULATED_SETUPS, DaemonConfig, load_config
    from uwcam.daemon import Daemon, check_devices
    from uwcam.fileio import explain_validation_error

    if args.config and args.simulate:
        raise UserInputError("give either --config FILE or --simulate NAME, not both")
    config = load_config(args.config) if args.config else SIMULATED_SETUPS[args.simulate or "vehicle"]()
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    if overrides:
        try:  # validated like the file: --port 80808 is a one-line error
            config = DaemonConfig.model_validate({**config.model_dump(), "api": {**config.api.model_dump(), **overrides}})
        except ValidationError as exc:
            raise UserInputError(explain_validation_error(exc, "command line").replace("key 'api.", "option '--")) from None
    check_devices(config)
    from uwcam.api import required_token

    required_token(config)  # before the socket is bound: no listening beyond loopback without a token
    if args.record:
        if os.path.exists(args.record):
            raise UserInputError(f"{args.record} exists; give a new file name (recordings are never overwritten)")
        if not args.record.endswith(".mcap"):
            raise UserInputError(f"--record {args.record}: the file name must end in .mcap")
        if not os.path.isdir(os.path.dirname(os.path.abspath(args.record))):
            raise UserInputError(f"--record {args.record}: its folder does not exist; create it first")
        config.recording.start_file = args.record
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    host, port = config.api.host, config.api.port
    try:  # bound before anything starts, so a port in use is one line, not a startup traceback
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.create_server((host, port), family=family, reuse_port=False)
    except OSError as exc:
        raise UserInputError(f"cannot listen on {host}:{port}: {exc.strerror or exc}; choose another --port or --host") from None
    daemon = Daemon(config)
    try:
        app = create_app(config, daemon)
        daemon.start()  # devices and calibration: a configuration that cannot work fails here, in one line
        where = args.config or ("embedded simulated tank" if args.simulate == "tank" else "embedded default (simulated rig)")
        shown = f"[{host}]" if ":" in host else host  # IPv6 literal
        root = f"http://{shown}:{sock.getsockname()[1]}"
        print(f"uwcam {__version__}: {where}; operator page {root}/, API {root}/docs", flush=True)
        # uvicorn handles SIGINT/SIGTERM: the lifespan then stops the loop, switches the lamp off
        # and releases the devices.
        # No per-message deflate: zlib on every multi-megabyte range map cost a third of the CPU
        # (measured with py-spy) and float maps barely compress.
        server = _orderly_server_class()(uvicorn.Config(app, log_level="warning", ws_per_message_deflate=False))
        # Everything made so far (modules, the calibration, FastAPI's routes and models: ~125,000
        # objects) lives as long as the process: out of the cyclic collector's sight, its full
        # collections no longer stop every thread for ~50 ms (a 60 fps loop then skips frames).
        gc.freeze()
        server.run(sockets=[sock])
    finally:
        daemon.stop()
        sock.close()
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    """The topside fleet view (uwcam.monitor): subscribe to every vehicle on Zenoh, serve the page."""
    import math
    import re
    import socket

    from uwcam.config import _KEY_SEGMENT, _ZENOH_ENDPOINT

    for option, endpoints in (("--connect", args.connect), ("--listen", args.listen)):
        for endpoint in endpoints:
            if not _ZENOH_ENDPOINT.match(endpoint):
                raise UserInputError(f"{option} {endpoint}: not a Zenoh endpoint; e.g. tcp/192.168.2.2:7447")
    if not (math.isfinite(args.stale_s) and 0 < args.stale_s <= 3600):
        raise UserInputError(f"--stale-s {args.stale_s}: give seconds between 0 and 3600, e.g. 5")
    if not 0 <= args.port <= 65535:
        raise UserInputError(f"--port {args.port}: give a port 0–65535")
    if not all(_KEY_SEGMENT.match(part) for part in args.root.split("/")) or re.search(r"[*$?#]", args.root):
        raise UserInputError(f"--root {args.root}: give the vehicles' key root without wildcards, e.g. uwcam")
    if not args.connect and not args.scouting:
        raise UserInputError("nothing to listen to: give --connect ENDPOINT... or leave scouting on")
    try:  # a port in use is one line, before Zenoh starts
        with socket.create_server((args.host, args.port), family=socket.AF_INET6 if ":" in args.host else socket.AF_INET):
            pass
    except OSError as exc:
        raise UserInputError(f"cannot listen on {args.host}:{args.port}: {exc.strerror or exc}; choose another --port") from None
    from uwcam.monitor import run_monitor
    from uwcam.outputs.zenoh_publisher import require_zenoh

    require_zenoh("uwcam monitor listens on Zenoh", "")
    print(f"uwcam monitor: fleet page http://{args.host}:{args.port}/ (vehicles under {args.root}/)", flush=True)
    run_monitor(args.connect, args.listen, args.scouting, args.host, args.port, args.stale_s, args.root)
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    """Run the embedded default until its first range, then stop: numba compiles every kernel the
    daemon's start needs into its on-disk cache, so the first ``uwcam run`` compiles nothing."""
    import logging
    import time

    from uwcam.config import default_config
    from uwcam.daemon import Daemon
    from uwcam.optics import kernels

    if not 1.0 <= args.timeout <= 86400.0:  # also refuses nan
        raise UserInputError(f"--timeout must be 1 to 86400 seconds, got {args.timeout}")
    if kernels.BACKEND != "numba":
        print("nothing to compile: numba is not installed here (the numpy path is used)")
        return 0
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    started = time.monotonic()
    daemon = Daemon(default_config())
    try:
        daemon.start()
        deadline = time.monotonic() + args.timeout
        while daemon.pipeline.processed < 1:
            if time.monotonic() > deadline:
                raise UserInputError(f"no range within {args.timeout:g} s; try again with a longer --timeout")
            time.sleep(0.05)
    finally:
        daemon.stop()
    print(f"compiled uwcam's kernels in {time.monotonic() - started:.0f} s (kept in numba's cache)")
    return 0


def cmd_reprocess(args: argparse.Namespace) -> int:
    from uwcam.reprocess import reprocess

    if args.workers is not None and not 1 <= args.workers <= 1024:
        raise UserInputError(f"--workers must be 1 to 1024, got {args.workers}")
    if not 0.01 <= args.part_mb <= 1e5:
        raise UserInputError(f"--part-mb must be 0.01 to 100000, got {args.part_mb}")
    outputs = reprocess(args.inputs, args.output, profile=args.profile, scheduler=args.scheduler,
                        workers=args.workers, progress=not args.quiet, part_mb=args.part_mb,
                        skip_corrupt=args.skip_corrupt, warn=lambda text: print(f"uwcam reprocess: warning: {text}",
                                                                               file=sys.stderr))
    for path in outputs:
        print(f"wrote {path}")
    return 0


def cmd_repair(args: argparse.Namespace) -> int:
    from uwcam import recording as rec

    for path in args.recordings:
        if not Path(path).is_file():
            raise UserInputError(f"recording {path} does not exist")
        if rec.is_complete(path):
            print(f"{path} is complete; left as it is")
            continue
        try:
            kept = rec.repair(path)
        except rec.RecordingError as exc:
            raise UserInputError(str(exc)) from None
        except OSError as exc:
            raise UserInputError(f"cannot repair {path}: {exc.strerror}") from None
        print(f"repaired {path}: {kept} bytes of complete records kept, the unfinished rest removed")
    return 0


def cmd_config_check(args: argparse.Namespace) -> int:
    from uwcam.api import required_token
    from uwcam.config import load_config
    from uwcam.daemon import check_devices

    config = load_config(args.file)
    check_devices(config)
    required_token(config)
    print(f"{args.file}: valid (camera {config.camera.driver}, API {config.api.host}:{config.api.port})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="uwcam", description="Underwater ranging camera: calibrate, range, simulate, run.")
    parser.add_argument("--version", action="version", version=f"uwcam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    cal = sub.add_parser("calibrate", help="make a calibration profile from a target imaged at known distances")
    cal.add_argument("images", nargs="+", metavar="IMAGE",
                     help="target images (.npy, .tif, .png), one per --distance; several at one distance are averaged")
    cal.add_argument("--distance", type=float, action="append", metavar="D",
                     help="camera-to-target distance along the optical axis in metres, one per image in order "
                          "(repeat a distance for several frames taken there)")
    cal.add_argument("--target-reflectance", metavar="R1,R2,...", help="target reflectance per channel (default: spectrally flat)")
    cal.add_argument("--rig", metavar="RIG.yaml", help="rig file describing the target (calibration_rigs/)")
    cal.add_argument("--roi", metavar="X,Y,W,H", help="target region in pixels (default: the whole image)")
    cal.add_argument("--black-roi", metavar="X,Y,W,H", help="black patch region in pixels, for the noise floor")
    cal.add_argument("--channels", metavar="NAME[:NM],...", help="channel names, optionally with centre wavelengths (R:675,G:575,B:475)")
    cal.add_argument("--reference", metavar="NAME", help="reference channel (default: the first)")
    cal.add_argument("--lamp-offset", metavar="X,Y,Z", help="lamp position in metres, camera frame (x right, y down, z forward)")
    cal.add_argument("--lamp-radius", type=float, metavar="R",
                     help="effective lamp radius sqrt(A0/Ω) in metres (0: point source); enables absolute attenuation")
    cal.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="pinhole intrinsics in pixels")
    cal.add_argument("--dark", metavar="IMAGE", help="dark frame (lamp off, lens capped) to subtract")
    cal.add_argument("--dark-level", metavar="D1,D2,...", help="dark level per channel in DN to subtract")
    cal.add_argument("--saturation", type=float, metavar="DN", help="raw level at which pixels clip (default: the dtype's maximum)")
    cal.add_argument("--name", help="name stored in the profile (default: the file's stem)")
    cal.add_argument("-o", "--output", required=True, metavar="PROFILE.yaml", help="profile to write")
    cal.add_argument("--report", metavar="REPORT.html",
                     help="also write a self-contained HTML report: fits, residuals, noise model, plate overlay, range σ")
    cal.add_argument("--response", metavar="srgb|rec709|FILE",
                     help="the camera's response curve (a gamma-encoded 8-bit camera): frames are linearised "
                          "through it and the profile keeps it; FILE from 'uwcam response'")
    cal.set_defaults(func=cmd_calibrate)

    resp = sub.add_parser("response", help="recover an 8-bit camera's response curve from an exposure bracket")
    resp.add_argument("images", nargs="+", metavar="BRACKET",
                      help="8-bit frames of one still, lit scene at different exposures (fixed gain and white balance)")
    resp.add_argument("--exposure-ms", required=True, metavar="T1,T2,...", help="exposure of each frame in ms, in order")
    resp.add_argument("--method", choices=("debevec", "robertson"), default="debevec",
                      help="OpenCV's calibration method (default debevec)")
    resp.add_argument("-o", "--output", required=True, metavar="RESPONSE.yaml",
                      help="response file, for 'uwcam calibrate --response'")
    resp.set_defaults(func=cmd_response)

    rig = sub.add_parser("rig", help="calibration rig tools")
    rig_sub = rig.add_subparsers(dest="rig_command", required=True, metavar="ACTION")
    rig_print = rig_sub.add_parser("print", help="draw a rig's plate (markers, target, black patch) at true scale as PDF")
    rig_print.add_argument("rig", metavar="RIG", help="rig file or built-in rig name (e.g. charuco-plate)")
    rig_print.add_argument("-o", "--output", required=True, metavar="BOARD.pdf")
    rig_print.set_defaults(func=cmd_rig_print)

    rng = sub.add_parser("range", help="turn an image into a range map with a calibration profile")
    rng.add_argument("profile", metavar="PROFILE.yaml")
    rng.add_argument("image", metavar="IMAGE", nargs="+",
                     help="image to range; several of one static scene are fused first (their mean, noise from their count)")
    rng.add_argument("-o", "--output", required=True, metavar="RANGE.(npy|tif)", help="float32 camera range in metres, NaN invalid")
    rng.add_argument("--variance", metavar="VAR.(npy|tif)", help="variance of the range in m²")
    rng.add_argument("--reasons", metavar="REASONS.(npy|tif)", help="uint8 reason code per pixel (0 valid)")
    rng.add_argument("--surface-reflectance", metavar="R1,R2,...", help="surface reflectance per channel, if it differs in hue from the target")
    rng.add_argument("--pair", metavar="NAME,NAME", help="use one channel pair instead of fusing all channels")
    rng.add_argument("--path-bounds", metavar="MIN,MAX", help="accepted lamp→surface→camera path length in metres")
    rng.add_argument("--smooth", choices=("mean", "median"), help="3×3 smoothing of the range map over valid pixels")
    rng.add_argument("--compensate-backscatter", action="store_true",
                     help="insist on subtracting modelled backscatter (done anyway whenever the profile was calibrated "
                     "with a black patch; with this flag a profile without one is refused)")
    rng.add_argument("--open-water", metavar="IMAGE", help="lamp-lit frame of open water, same exposure: the backscatter "
                     "pattern, and the light each pixel must be clearly above to have a range")
    rng.set_defaults(func=cmd_range)

    sim = sub.add_parser("simulate", help="render a physically modelled underwater frame (and its ground truth)")
    sim.add_argument("--list", action="store_true", help="list scenes and water presets")
    sim.add_argument("--scene", metavar="NAME", help="seabed, brick, pipe, ball, ring, tilted-plane, plate or open-water")
    sim.add_argument("--range", type=float, metavar="METRES", help="camera-to-seabed (or plate) distance along the optical axis")
    sim.add_argument("--water", default="jerlov-II", metavar="PRESET", help="water preset (default jerlov-II; see --list)")
    sim.add_argument("--attenuation", metavar="C[,C,...]", help="override beam attenuation c, 1/m")
    sim.add_argument("--forward-blur", type=float, metavar="B", help="forward-scatter blur B (OTF exp(−B·d·f))")
    sim.add_argument("--scatter-attenuation", metavar="G[,G,...]", help="attenuation of forward-scattered light G, 1/m")
    sim.add_argument("--backscatter", metavar="BETA[,BETA,...]", help="backscatter β, 1/(m·sr)")
    sim.add_argument("--gated", action="store_true", help="range gating: only water just in front of the surface scatters back")
    sim.add_argument("--gate-width", type=float, default=0.05, metavar="M", help="depth of the range gate (default 0.05 m)")
    sim.add_argument("--slabs", type=int, default=32, help="water-column slabs for backscatter (default 32)")
    sim.add_argument("--bits", type=int, default=16, choices=(8, 12, 16), help="sensor bit depth (default 16)")
    sim.add_argument("--response", default="linear", choices=("linear", "srgb", "rec709"),
                     help="tone curve of the camera's 8-bit output (default linear); needs --bits 8")
    sim.add_argument("--jpeg-quality", type=int, metavar="Q",
                     help="JPEG-compress the frame at quality Q (1–100), as an MJPEG camera does; needs --bits 8")
    sim.add_argument("--size", default="640x480", metavar="WxH", help="image size (default 640x480)")
    sim.add_argument("--fov", type=float, default=60.0, metavar="DEG", help="horizontal field of view (default 60)")
    sim.add_argument("--channels", metavar="NAME:NM,...", help="channel names and centre wavelengths (default R:675,G:575,B:475)")
    sim.add_argument("--lamp-offset", metavar="X,Y,Z", help="lamp position in metres, camera frame (default at the camera)")
    sim.add_argument("--lamp-off", action="store_true", help="lamp off: dark current, noise and any ambient light only")
    sim.add_argument("--ambient", metavar="I[,I,...]", help="daylight from above, relative to the lamp")
    sim.add_argument("--peak", type=float, metavar="DN",
                     help="auto-exposure target for the brightest pixel (default 226 at 8 bits, 4077 at 12, 65250 at 16)")
    sim.add_argument("--exposure", type=float, help="fix the exposure (electrons per unit radiance) instead of auto-exposure")
    sim.add_argument("--rig", metavar="RIG", help="rig file or built-in rig name for --scene plate (default grey-plate)")
    sim.add_argument("--material", metavar="NAME", help="give every surface one material (sand, brick, pipe, ball, ring, grey)")
    sim.add_argument("--noise-free", action="store_true", help="write the expected value (float32 DN) without noise")
    sim.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    sim.add_argument("-o", "--output", metavar="FRAME.(tif|npy|png)")
    sim.add_argument("--truth", metavar="TRUTH.npy", help="write camera range per pixel (m, NaN where no surface)")
    sim.set_defaults(func=cmd_simulate)

    run = sub.add_parser("run", help="run the camera daemon (default: simulated rig, API on 127.0.0.1:8080)")
    run.add_argument("--config", metavar="FILE", help="rig configuration (YAML); default: the embedded simulated rig")
    run.add_argument("--simulate", choices=("vehicle", "tank"),
                     help="run an embedded simulation: vehicle (the default: a survey over a varied seabed) or tank "
                          "(a calibration plate on a rail, moved with PUT /api/v1/simulation/plate)")
    run.add_argument("--host", help="API address (default 127.0.0.1)")
    run.add_argument("--port", type=int, help="API port (default 8080)")
    run.add_argument("--record", metavar="FILE.mcap", help="record the dive into this MCAP file from start to stop")
    run.set_defaults(func=cmd_run)

    mon = sub.add_parser("monitor", help="topside fleet view: every vehicle publishing on Zenoh, on one page")
    mon.add_argument("--connect", nargs="+", default=[], metavar="ENDPOINT",
                     help="Zenoh endpoints of the vehicles (or of a router), e.g. tcp/192.168.2.2:7447")
    mon.add_argument("--listen", nargs="+", default=[], metavar="ENDPOINT",
                     help="Zenoh endpoints to listen on, for vehicles that connect to the monitor")
    mon.add_argument("--no-scouting", dest="scouting", action="store_false",
                     help="do not look for vehicles on the LAN by multicast (only --connect and --listen)")
    mon.add_argument("--host", default="127.0.0.1", help="address of the fleet page (default 127.0.0.1)")
    mon.add_argument("--port", type=int, default=8090, help="port of the fleet page (default 8090)")
    mon.add_argument("--stale-s", type=float, default=5.0, metavar="S",
                     help="a vehicle unheard for S seconds is shown stale (default 5)")
    mon.add_argument("--root", default="uwcam", help="key root the vehicles publish under (default uwcam)")
    mon.set_defaults(func=cmd_monitor)

    warm = sub.add_parser("warmup", help="compile the ranging and simulation kernels now (deploy/install.sh runs it), "
                                         "so the first start compiles nothing")
    warm.add_argument("--timeout", type=float, default=600.0, metavar="S", help="give up after S seconds (default 600)")
    warm.set_defaults(func=cmd_warmup)

    rep = sub.add_parser("reprocess", help="range recorded dives (MCAP) again, here or on a Dask cluster")
    rep.add_argument("inputs", nargs="+", metavar="IN.mcap", help="recordings made by uwcam run")
    rep.add_argument("-o", "--output", required=True, metavar="OUT",
                     help="output .mcap for one input, else a folder (one file per input, same names)")
    rep.add_argument("--profile", metavar="P.yaml", help="calibration profile to use (default: the one recorded in each file)")
    rep.add_argument("--scheduler", nargs="?", const="local", metavar="ADDRESS",
                     help="run on a Dask cluster: a scheduler address (tcp://host:8786; workers must see the same "
                          "paths), or without ADDRESS a local cluster on this machine (default: in this process)")
    rep.add_argument("--workers", type=int, metavar="N", help="worker processes of the local cluster (default: CPU count)")
    rep.add_argument("--part-mb", type=float, default=64.0, metavar="MB",
                     help="megabytes of recording per unit of work, cut at MCAP chunks (default 64)")
    rep.add_argument("--quiet", action="store_true", help="no progress bar")
    rep.add_argument("--skip-corrupt", action="store_true",
                     help="reprocess a recording with damaged chunks (failing their CRC check), leaving them out; "
                          "without it such a recording is refused")
    rep.set_defaults(func=cmd_reprocess)

    fix = sub.add_parser("repair", help="make unfinished recordings (writer killed, disk full) readable, in place")
    fix.add_argument("recordings", nargs="+", metavar="FILE.mcap")
    fix.set_defaults(func=cmd_repair)

    cfg = sub.add_parser("config", help="configuration tools")
    cfg_sub = cfg.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    check = cfg_sub.add_parser("check", help="validate a configuration file without starting anything")
    check.add_argument("file", metavar="FILE")
    check.set_defaults(func=cmd_config_check)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (UserInputError, ConfigurationError) as exc:
        print(f"uwcam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
