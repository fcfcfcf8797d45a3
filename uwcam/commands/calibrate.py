"""``uwcam calibrate``, ``uwcam response`` and ``uwcam rig print``: calibration from files."""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics
from uwcam.commands.arguments import (
    checked_output,
    parse_box,
    parse_channels,
    parse_exposure,
    parse_floats,
    resolve_rig_path,
)


def default_saturation(dtype: np.dtype) -> float:
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return float(np.finfo(np.float32).max)


def check_calibration_frames(paths: list, frames: list[np.ndarray], distances: list[float]) -> None:
    """UserInputError, naming the image, unless the frames can be calibrated from: one camera's
    (same channels, same data type), each holding finite values only, and not all alike when their
    distances differ (no attenuation can be seen then: the lamp did not light the target)."""
    first, n = paths[0], frames[0].shape[-1]
    for p, f in zip(paths, frames):
        if f.shape[-1] != n:
            raise UserInputError(f"image {p} has {f.shape[-1]} channels but {first} has {n}; use images from one camera")
        if f.dtype != frames[0].dtype:
            raise UserInputError(f"image {p} holds {f.dtype} values but {first} holds {frames[0].dtype}; use images "
                                 "from one camera, saved the same way")
        # Before the fit: a single NaN in a region it averages reaches LAPACK, which prints its own
        # line ("On entry to DLASCL ...") and fails with a message about SVD naming no image.
        bad = ~np.isfinite(f).all(axis=-1) if np.issubdtype(f.dtype, np.floating) else None
        if bad is not None and bad.any():
            rows, cols = np.flatnonzero(bad.any(axis=1)), np.flatnonzero(bad.any(axis=0))
            raise UserInputError(f"image {p} holds NaN or infinite values in {int(bad.sum())} pixels "
                                 f"({100 * bad.mean():.2g} %, rows {rows[0]}–{rows[-1]}, columns {cols[0]}–{cols[-1]}); "
                                 "use the camera's frames, with finite values in every pixel")
    if len(set(distances)) > 1 and all(f.shape == frames[0].shape and np.array_equal(f, frames[0], equal_nan=True)
                                       for f in frames[1:]):
        raise UserInputError("the images are all alike although their distances differ, so no attenuation can be "
                             "measured; image the lit target at each distance")


def with_exposure(profile, exposure_us: np.ndarray, gain_db: np.ndarray | None):
    """``profile`` recording, per channel, the exposure (µs) and gain (dB; None: not recorded) of
    its calibration frames, as the daemon's calibration session records them."""
    channels = [c.model_copy(update={"exposure_us": float(exposure_us[k]),
                                     "gain_db": None if gain_db is None else float(gain_db[k])})
                for k, c in enumerate(profile.channels)]
    return profile.model_copy(update={"channels": channels})


def with_lens_shading(profile, paths: list[str], curve=None):
    """``profile`` with the lens's shading measured from the flat-field frames at ``paths`` (an evenly
    lit view: a diffuser over the port, a white target filling the view), linearised through
    ``curve`` where the camera has one (:func:`uwcam.optics.lens_shading.fit_shading`)."""
    from uwcam.calibration.profile import LensShading
    from uwcam.imaging.imageio import read_frame
    from uwcam.optics.lens_shading import fit_shading, shading_map

    intrinsics = profile.camera_intrinsics()
    if intrinsics is None:
        raise UserInputError("--flat-field needs --intrinsics: the lens's shading is modelled in the angle of each "
                             "pixel's ray off the axis")
    frames = []
    n = len(profile.channels)
    for path in paths:
        frame = read_frame(path)
        if frame.ndim != 3 or frame.shape[-1] != n:
            raise UserInputError(f"flat-field image {path} must have {n} channels like the calibration images")
        if curve is not None and np.issubdtype(frame.dtype, np.integer):
            frame = curve.linearise(frame)
        if frames and frame.shape != frames[0].shape:
            raise UserInputError(f"flat-field image {path} is {frame.shape[1]}×{frame.shape[0]}, the first "
                                 f"{frames[0].shape[1]}×{frames[0].shape[0]}; take them with one camera and its settings")
        frames.append(np.asarray(frame, np.float64))
    check_intrinsics_fit_or_refuse(profile, frames[0].shape[1], frames[0].shape[0])
    try:
        coefficients, rms = fit_shading(np.stack(frames), intrinsics, profile.array("dark_level"),
                                        profile.saturation_level)
    except UserInputError as exc:
        raise UserInputError(f"--flat-field: {exc}") from None
    shading = LensShading(coefficients=(float(coefficients[0]), float(coefficients[1])), rms=min(rms, 1.0))
    h, w = frames[0].shape[:2]
    corner = float(shading_map(coefficients, intrinsics, h, w)[[0, 0, -1, -1], [0, -1, 0, -1]].min())
    print(f"lens shading from {len(frames)} flat-field frame(s): the corners pass {corner:.0%} of the centre's light "
          f"(radial model, {rms:.2%} rms left)")
    return profile.model_copy(update={"lens_shading": shading})


def check_intrinsics_fit_or_refuse(profile, width: int, height: int) -> None:
    """UserInputError unless the profile's intrinsics suit flat-field frames of ``width`` × ``height``."""
    from uwcam.calibration.profile import check_intrinsics_fit

    try:
        check_intrinsics_fit(profile.intrinsics, width, height)
    except ValueError as exc:
        raise UserInputError(f"--flat-field: {exc}") from None


def cmd_calibrate(args: argparse.Namespace) -> int:
    from uwcam.calibration.fit import CalibrationInputs, calibrate_with_details, project_plate_box
    from pydantic import ValidationError

    from uwcam.fileio import explain_validation_error
    from uwcam.imaging.imageio import read_frame
    from uwcam.calibration.profile import MAX_DISTANCE_M, MAX_LAMP_OFFSET_M, check_intrinsics_fit, save_profile
    from uwcam.calibration.rig import load_rig, resolve_reflectance

    out = checked_output(args.output, (".yaml", ".yml"), "the profile {path} must be a .yaml file")
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
    exposure_us = parse_exposure(args.exposure_us, "--exposure-us", names)
    gain_db = parse_exposure(args.gain_db, "--gain-db", names, gain=True)
    if gain_db is not None and exposure_us is None:
        raise UserInputError("--gain-db needs --exposure-us: a profile records the light its frames gathered, "
                             "exposure × gain")
    curve = None
    if args.response:
        from uwcam.imaging.response import load_response

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
    report = checked_output(args.report, (".html", ".htm"), "--report {path} must be an .html file", "--report") if args.report else None
    if report is not None:
        from uwcam.extras import require_extra

        require_extra("reports")  # before the fit, not after the user has waited for it
    try:
        details = calibrate_with_details(frames, distances, inputs)
    except ValidationError as exc:  # the fit's result is outside what a profile may hold
        raise UserInputError(explain_validation_error(exc, "the images do not give a usable calibration")
                             + "; check that the lamp lights the target and that each --distance is right") from None
    except np.linalg.LinAlgError as exc:
        raise UserInputError(f"the images do not give a usable calibration ({exc}); check that the target region "
                             "holds finite, lit values in every image") from None
    if exposure_us is not None:
        details = replace(details, profile=with_exposure(details.profile, exposure_us, gain_db))
    profile = details.profile
    if curve is not None:
        from uwcam.calibration.profile import ResponseRecord

        profile = profile.model_copy(update={"response": ResponseRecord(**curve.to_record())})
    if args.flat_field:
        profile = with_lens_shading(profile, args.flat_field, curve)
    save_profile(profile, out)
    from uwcam.calibration.rig_advice import calibration_rig_advice

    advice = calibration_rig_advice(details, rig)
    if report is not None:
        from uwcam.calibration.report import html_report
        from uwcam.fileio import atomic_write

        with atomic_write(report, "w") as fh:
            fh.write(html_report(details, advice=advice))
        print(f"wrote {report}")
    v = ", ".join(f"{c.name}−{profile.reference_channel} {c.attenuation_difference:+.4f}±{c.attenuation_difference_std:.4f}"
                  for c in profile.channels if c.name != profile.reference_channel)
    print(f"wrote {out}: attenuation differences (1/m) {v}; rms residual {profile.provenance.rms_residual:.2e}")
    if advice is not None:
        print(f"note: {advice}")
    return 0


def cmd_response(args: argparse.Namespace) -> int:
    from uwcam.imaging.imageio import read_frame
    from uwcam.imaging.response import recover, save_response

    out = checked_output(args.output, (".yaml", ".yml"), "the response file {path} must be a .yaml file")
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
    from uwcam.calibration.rig import load_rig
    from uwcam.calibration.artwork import write_artwork

    out = checked_output(args.output, (".pdf",), "the artwork {path} must be a .pdf file")
    rig = load_rig(resolve_rig_path(args.rig))
    write_artwork(rig, out)
    w, h = rig.plate.size_m
    print(f"wrote {out}: {rig.name}, {w * 100:g} × {h * 100:g} cm at true scale; print at 100 % and check the 10 cm bar")
    return 0
