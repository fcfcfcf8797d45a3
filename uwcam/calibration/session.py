"""A guided calibration at the tank: the state of one session, independent of the HTTP layer.

The engineer positions the marker plate while the session reports, from the newest frame,
whether the plate is found, its distance and tilt from the markers' pose, how the typed (or
rangefinder) distance compares, each channel's signal against the floor, saturation and
coverage. Captures take N frames at a distance and are refused, changing nothing, when the
plate is not found, saturated, too dark or not where the engineer says. A fit uses every
capture not held back; a held-back distance then validates the new profile, and only a
validated profile can be accepted (saved and activated by the caller).
"""

from __future__ import annotations

import threading
import uuid
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from uwcam.calibration.fit import MAX_SATURATED_FRACTION, CalibrationDetails, CalibrationInputs, calibrate_with_details
from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics, pixel_rays, plane_camera_range
from uwcam.calibration.plate import PlatePose, PlateSighting, sight_plate
from uwcam.calibration.profile import CalibrationProfile
from uwcam.calibration.rig import Rig, resolve_reflectance

# Distances closer than this count as the same distance (m).
SAME_DISTANCE_M = 0.01
# Poor-fit warnings: the distances' span (m) below which the slope is poorly pinned down; the
# σ of an attenuation difference, relative to it, above which it is called uncertain; the largest
# residual of ln(E_k/E_ref) (natural-log units, ≈ relative) a good fit leaves; and the change of
# the plate's colour within one capture beyond which its light drifted.
MIN_BASELINE_M = 0.5
MAX_RELATIVE_SIGMA = 0.1
MAX_RESIDUAL = 0.01
MAX_DRIFT = 0.01


class SessionError(Exception):
    """A request the session refuses; ``status`` is the HTTP status that says why (409 state, 422 input)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass
class Capture:
    distance_m: float
    frames: list[NDArray]
    held_back: bool
    pose: PlatePose
    rangefinder_m: float | None
    exposure_us: float | None
    drift: float = 0.0
    """Largest relative change of a channel's light on the target, relative to the reference
    channel's, between the frames of this capture (0: steady)."""

    def summary(self) -> dict:
        return {"distance_m": self.distance_m, "frames": len(self.frames), "held_back": self.held_back,
                "marker_distance_m": round(self.pose.distance_m, 4), "tilt_deg": round(self.pose.tilt_deg, 2),
                "rangefinder_m": self.rangefinder_m, "markers_found": len(self.pose.markers_found),
                "drift": round(self.drift, 5)}


def target_mask(shape: tuple[int, int], pose: PlatePose) -> NDArray[np.bool_]:
    """(H, W) the target box without the black patch: the pixels the fit measures the plate's light on."""
    mask = np.zeros(shape, bool)
    x, y, w, h = pose.target_box
    mask[y : y + h, x : x + w] = True
    if pose.black_box is not None:
        bx, by, bw, bh = pose.black_box
        mask[by : by + bh, bx : bx + bw] = False
    return mask


def saturated_fractions(frames: list[NDArray], mask: NDArray[np.bool_], level: float) -> NDArray[np.float64]:
    """Per channel, the largest fraction over ``frames`` of the masked pixels at or above ``level``
    (the calibration's own test, so that a capture accepted here is never refused by the fit)."""
    return np.max([(np.asarray(f)[mask] >= level).mean(axis=0) for f in frames], axis=0)


@dataclass
class CalibrationSession:
    rig_name: str
    rig: Rig
    intrinsics: Intrinsics
    base: CalibrationProfile
    """The active profile when the session started: channels, dark level, floor, saturation, lamp."""
    frames_per_capture: int = 4
    distance_tolerance_m: float = 0.05
    exposure: dict = field(default_factory=dict)
    id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])
    state: str = "positioning"
    captures: list[Capture] = field(default_factory=list)
    details: CalibrationDetails | None = None
    validation: list[dict] = field(default_factory=list)
    ignore_ids: tuple[int, ...] = ()
    """Marker ids of the rig's dictionary that belong to something else in view (the vehicle's patch marker)."""
    ignore_regions: tuple[tuple[int, int, int, int], ...] = ()
    """Image boxes (x, y, w, h in pixels) where no marker is the plate's (the vehicle mask)."""
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _plots: dict[str, bytes] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.rig.plate.markers is None:
            raise SessionError(422, f"rig {self.rig_name} has no markers, and the session finds the plate by them; "
                                    "use a rig with markers such as charuco-plate")
        names = self.base.channel_names
        wavelengths = [c.wavelength_nm for c in self.base.channels]
        try:
            self.plate_reflectance = resolve_reflectance(self.rig.plate.reflectance, names, wavelengths, f"plate of rig {self.rig_name}")
            bp = self.rig.plate.black_patch
            self.black_reflectance = None if bp is None else resolve_reflectance(bp.reflectance, names, wavelengths,
                                                                                  f"black patch of rig {self.rig_name}")
        except UserInputError as exc:
            raise SessionError(422, str(exc)) from None

    # -- the checks a capture must pass, shared by the live feedback and the capture itself ---------
    def _tolerance(self, distance: float) -> float:
        return max(self.distance_tolerance_m, 0.02 * distance)

    def _sight(self, frame: NDArray) -> PlateSighting:
        return sight_plate(frame, self.rig, self.intrinsics, ignore_ids=self.ignore_ids, ignore_regions=self.ignore_regions)

    def assess(self, frames: list[NDArray], sighting: PlateSighting, distance_m: float | None, held_back: bool,
               rangefinder_m: float | None, exposures: list[float | None],
               channel_exposures: list[tuple[float, ...] | None] | None = None) -> tuple[dict, list[SessionError]]:
        """What ``frames`` (H, W, N each) show and every reason a capture of them at ``distance_m`` would be
        refused, in the order the capture reports them. The live feedback calls this with the newest
        frame, a capture with its N frames: one set of checks, so the page and the API agree."""
        refusals: list[SessionError] = []
        out: dict = {"plate_found": sighting.pose is not None, "markers_found": sighting.markers,
                     "markers_count": len(sighting.markers), "markers_ignored": sighting.ignored,
                     "typed_distance_m": distance_m, "rangefinder_m": rangefinder_m,
                     "tolerance_m": None if distance_m is None else round(self._tolerance(distance_m), 4),
                     "image_size": [int(frames[0].shape[1]), int(frames[0].shape[0])],
                     "saturation_limit": MAX_SATURATED_FRACTION}
        if self.state not in ("positioning", "fitted"):
            refusals.append(SessionError(409, f"the session is {self.state}; start a new one"))
        if distance_m is None:
            refusals.append(SessionError(422, "type the plate's distance, measured along the optical axis"))
        elif not (np.isfinite(distance_m) and 0.05 <= distance_m <= 100.0):
            refusals.append(SessionError(422, f"distance_m must be between 0.05 and 100 m, got {distance_m}"))
        known = [e for e in exposures if e is not None]
        if known and (max(known) - min(known) > 1e-6 * max(known) or
                      (self.exposure.get("exposure_us") is not None and abs(known[0] - self.exposure["exposure_us"]) > 1e-6 * known[0])):
            refusals.append(SessionError(409, "the camera's exposure changed during the session; fix the exposure and start again"))
        per_channel = [tuple(e) for e in (channel_exposures or []) if e is not None]
        first = self.exposure.get("channel_exposure_us")
        if per_channel and (len(set(per_channel)) > 1 or (first is not None and tuple(first) != per_channel[0])):
            refusals.append(SessionError(409, "the camera's exposure changed during the session (is the exposure controller "
                                              "on? switch it off while calibrating); fix the exposure and start again"))
        pose = sighting.pose
        if pose is None:
            refusals.append(SessionError(422, f"plate not found: {sighting.why_not}; bring the whole plate into the image, "
                                              "lit, and capture again"))
            return out, refusals
        stack = [np.asarray(f) for f in frames]
        mean = stack[0].astype(np.float64) if len(stack) == 1 else np.mean([f.astype(np.float64) for f in stack], axis=0)
        mask = target_mask(mean.shape[:2], pose)
        signal = mean[mask].mean(axis=0) - self.base.array("dark_level")
        floor = self.base.array("noise_floor")
        full = self.base.saturation_level - self.base.array("dark_level")
        saturated = saturated_fractions(stack, mask, self.base.saturation_level)
        out.update({
            "marker_distance_m": round(pose.distance_m, 4), "tilt_deg": round(pose.tilt_deg, 2),
            "reprojection_px": round(pose.reprojection_px, 3), "coverage": round(pose.coverage, 4),
            "saturated_fraction": round(float(saturated.max()), 5), "target_in_view": pose.target_in_view,
            "target_box": list(pose.target_box), "black_box": None if pose.black_box is None else list(pose.black_box),
            "plate_outline_px": np.round(pose.plate_polygon, 1).tolist(),
            "target_outline_px": np.round(pose.target_polygon, 1).tolist(),
            "channels": {n: {"signal_dn": round(float(sg), 2), "floor_dn": round(float(f), 2), "above_floor": bool(sg > f),
                             "full_scale_dn": round(float(fs), 2), "saturated_fraction": round(float(sf), 5)}
                         for n, sg, f, fs, sf in zip(self.base.channel_names, signal, floor, full, saturated)},
        })
        if not pose.target_in_view:
            refusals.append(SessionError(422, "the plate's target region runs off the image; move the plate (or the camera) "
                                              "so that the whole plate is in view"))
        if saturated.max() > MAX_SATURATED_FRACTION:
            k = int(np.argmax(saturated))
            refusals.append(SessionError(422, f"{saturated[k]:.0%} of the plate's target region is saturated in channel "
                                              f"{self.base.channel_names[k]}; lower the lamp or the exposure, or move "
                                              "the plate farther, and capture again"))
        if not np.all(signal > floor):
            k = int(np.argmin(signal - floor))
            refusals.append(SessionError(422, f"channel {self.base.channel_names[k]} is below its noise floor on the plate "
                                              f"({signal[k]:.1f} ≤ {floor[k]:.1f} DN); bring the plate closer or raise the lamp"))
        for label, value in (("typed", distance_m), ("rangefinder", rangefinder_m)):
            if value is not None:
                out[f"{label}_agrees"] = bool(abs(value - pose.distance_m) <= self._tolerance(value))
                out[f"{label}_difference_m"] = round(value - pose.distance_m, 4)
        if distance_m is not None:
            tol = self._tolerance(distance_m)
            if abs(pose.distance_m - distance_m) > tol:
                refusals.append(SessionError(422, f"the markers put the plate at {pose.distance_m:.3f} m but {distance_m:.3f} m "
                                                  f"was given (tolerance {tol:.3f} m); measure the distance again"))
            if rangefinder_m is not None and abs(rangefinder_m - distance_m) > tol:
                refusals.append(SessionError(422, f"the rangefinder reads {rangefinder_m:.3f} m but {distance_m:.3f} m was given "
                                                  f"(tolerance {tol:.3f} m); measure the distance again"))
            others = [c for c in self.captures if c.held_back != held_back]
            if any(abs(c.distance_m - distance_m) < SAME_DISTANCE_M for c in others):
                refusals.append(SessionError(422, f"{distance_m:g} m is already used "
                                                  f"{'for the fit' if held_back else 'as the held-back distance'}; "
                                                  "a held-back distance must differ from the fitted ones"))
        return out, refusals

    # -- live feedback -------------------------------------------------------------------------
    def feedback(self, frame: NDArray, typed_distance_m: float | None, rangefinder_m: float | None,
                 exposure_us: float | None = None, held_back: bool = False,
                 channel_exposure_us: tuple[float, ...] | None = None) -> dict:
        """What the engineer needs while positioning the plate, from one frame (H, W, N): what the
        camera sees, and whether a capture now would be accepted (``capture_ok``) or why not."""
        out, refusals = self.assess([frame], self._sight(frame), typed_distance_m, held_back, rangefinder_m,
                                    [exposure_us], [channel_exposure_us])
        out["exposure_us"] = exposure_us
        out["capture_ok"] = not refusals
        out["refusals"] = [str(r) for r in refusals]
        advice = [str(r) for r in refusals]
        if out.get("tilt_deg", 0) > 10:
            advice.append(f"the plate is tilted {out['tilt_deg']:.0f}°: turn it square to the camera")
        out["advice"] = advice
        return out

    # -- captures ------------------------------------------------------------------------------
    def capture(self, frames: list[NDArray], distance_m: float, held_back: bool, rangefinder_m: float | None,
                exposures: list[float | None], channel_exposures: list[tuple[float, ...] | None] | None = None) -> Capture:
        """Check N frames taken at ``distance_m`` and keep them; SessionError (nothing kept) when they are unusable."""
        stack = np.asarray(frames)
        mean = stack.astype(np.float64).mean(axis=0)
        _, refusals = self.assess(list(stack), self._sight(mean), distance_m, held_back, rangefinder_m, exposures,
                                  channel_exposures)
        if refusals:
            raise refusals[0]
        pose = self._sight(mean).pose
        assert pose is not None  # assess refused otherwise
        known = [e for e in exposures if e is not None]
        per_channel = [tuple(e) for e in (channel_exposures or []) if e is not None]
        cap = Capture(float(distance_m), [np.asarray(f) for f in frames], bool(held_back), pose, rangefinder_m,
                      known[0] if known else None, self._drift(stack, pose))
        self.captures.append(cap)
        if self.exposure.get("exposure_us") is None and known:
            self.exposure["exposure_us"] = known[0]
        if self.exposure.get("channel_exposure_us") is None and per_channel:
            self.exposure["channel_exposure_us"] = list(per_channel[0])
        # New data: any earlier fit no longer describes the captures.
        self.state, self.details, self.validation, self._plots = "positioning", None, [], {}
        return cap

    def _drift(self, stack: NDArray, pose: PlatePose) -> float:
        """How much the plate's colour (each channel's light over the reference's) changed across the frames."""
        if len(stack) < 2:
            return 0.0
        mask = target_mask(stack.shape[1:3], pose)
        light = np.array([f[mask].astype(np.float64).mean(axis=0) for f in stack]) - self.base.array("dark_level")
        ratio = light / light[:, [self.base.reference_index]]
        return float(np.max((ratio.max(axis=0) - ratio.min(axis=0)) / np.abs(ratio.mean(axis=0))))

    # -- fit and validation ----------------------------------------------------------------------
    def fit(self) -> dict:
        used = [c for c in self.captures if not c.held_back]
        distances = sorted({round(c.distance_m, 2) for c in used})
        if len(distances) < 2:
            raise SessionError(409, f"the fit needs captures at two or more distances, got {distances or 'none'}")
        frames, at, target_boxes, black_boxes = [], [], [], []
        for c in used:
            for f in c.frames:
                frames.append(f)
                at.append(c.distance_m)
                target_boxes.append(c.pose.target_box)
                black_boxes.append(c.pose.black_box)
        has_black = self.black_reflectance is not None and all(b is not None for b in black_boxes)
        base = self.base
        inputs = CalibrationInputs(
            channel_names=base.channel_names, wavelengths_nm=[c.wavelength_nm for c in base.channels],
            target_reflectance=self.plate_reflectance, black_reflectance=self.black_reflectance if has_black else None,
            target_boxes=target_boxes, black_boxes=black_boxes if has_black else None,
            lamp_position_m=tuple(base.lamp_position_m), intrinsics=self.intrinsics, dark_level=base.array("dark_level"),
            saturation_level=base.saturation_level, quantisation_step=base.quantisation_step,
            reference=base.reference_index, name=f"tank-{self.id}", target_description=f"rig {self.rig_name} in the tank",
            image_names=[f"capture {i + 1} at {d:g} m" for i, d in enumerate(at)],
        )
        try:
            details = calibrate_with_details(frames, at, inputs)
        except UserInputError as exc:
            raise SessionError(422, f"the fit failed: {exc}") from None
        exposure = self.exposure.get("channel_exposure_us")
        if exposure is not None and len(exposure) == len(details.profile.channels):
            # The profile records the exposure it was made at, so frames at other exposures range exactly.
            channels = [c.model_copy(update={"exposure_us": float(t)}) for c, t in zip(details.profile.channels, exposure)]
            details = replace(details, profile=details.profile.model_copy(update={"channels": channels}))
        self.details, self._plots = details, {}
        self.validation = [self._validate(c, details.profile) for c in self.captures if c.held_back]
        self.state = "fitted"
        return self.fit_summary()

    def _validate(self, capture: Capture, profile: CalibrationProfile) -> dict:
        """Range one frame of a held-back capture with the new profile and compare with the distance given."""
        from uwcam.ranging.estimator import RangeEstimator

        frame = capture.frames[0]
        result = RangeEstimator(profile)(frame)
        x, y, w, h = capture.pose.target_box
        rng = result.range[y : y + h, x : x + w].astype(np.float64)
        var = result.variance[y : y + h, x : x + w].astype(np.float64)
        cal = result.common_variance
        rays = pixel_rays(self.intrinsics, *frame.shape[:2])[y : y + h, x : x + w]
        truth = plane_camera_range(capture.distance_m, rays)
        ok = np.isfinite(rng)
        if ok.mean() < 0.5:
            return {"distance_m": capture.distance_m, "passed": False, "valid_fraction": float(ok.mean()),
                    "reason": "fewer than half the plate's pixels have a range with the new profile"}
        err = float(np.median(rng[ok] - truth[ok]))
        cal_var = 0.0 if cal is None else float(np.mean(cal[y : y + h, x : x + w][ok]))
        pixel_var = float(np.mean(var[ok])) - cal_var
        sigma = float(np.sqrt(cal_var + pixel_var / ok.sum() * np.pi / 2))  # σ of a median of n noisy pixels
        allowed = max(3.0 * sigma, self._tolerance(capture.distance_m))
        return {"distance_m": capture.distance_m, "median_range_error_m": round(err, 5),
                "relative_error": round(err / capture.distance_m, 6), "rms_pixel_error_m": round(float(np.sqrt(np.mean((rng[ok] - truth[ok]) ** 2))), 5),
                "predicted_sigma_m": round(sigma, 5), "allowed_m": round(allowed, 5), "valid_fraction": round(float(ok.mean()), 4),
                "passed": bool(abs(err) <= allowed)}

    def fit_summary(self) -> dict:
        if self.details is None:
            return {}
        p = self.details.profile
        return {
            "method": p.provenance.method,
            "distances_m": p.provenance.distances_m,
            "frames_per_distance": p.provenance.frames_per_distance,
            "channels": {c.name: {"attenuation_difference": c.attenuation_difference,
                                  "attenuation_difference_std": c.attenuation_difference_std,
                                  "log_constant": c.log_constant, "log_constant_std": c.log_constant_std,
                                  "read_noise": c.read_noise, "shot_gain": c.shot_gain, "fixed_pattern": c.fixed_pattern,
                                  "noise_floor": c.noise_floor} for c in p.channels},
            "residuals": p.provenance.residuals,
            "rms_residual": p.provenance.rms_residual,
            "validation": self.validation,
            "warnings": self.fit_warnings(),
            "plots": [f"plots/{name}.png" for name in _plot_names()],
        }

    def fit_warnings(self) -> list[str]:
        """Why the fit may be poor, in the engineer's words (empty: nothing known against it)."""
        if self.details is None:
            return []
        p, out = self.details.profile, []
        distances = sorted(p.provenance.distances_m)
        if len(distances) < 3:
            out.append(f"only {len(distances)} distances: the line passes exactly through them, so nothing shows a "
                       "distance measured wrong; capture a third distance")
        if distances[-1] - distances[0] < MIN_BASELINE_M:
            out.append(f"the distances span only {distances[-1] - distances[0]:.2f} m: the attenuation differences are "
                       f"poorly pinned down; spread the distances at least {MIN_BASELINE_M:g} m apart (e.g. 1, 1.5, 2 m)")
        for c in p.channels:
            if c.name != p.reference_channel and c.attenuation_difference_std > MAX_RELATIVE_SIGMA * abs(c.attenuation_difference):
                out.append(f"channel {c.name}'s attenuation difference is uncertain ({c.attenuation_difference:+.4f} ± "
                           f"{c.attenuation_difference_std:.4f} 1/m); spread the distances farther apart or take more frames")
        worst = max((abs(r) for rs in p.provenance.residuals.values() for r in rs), default=0.0)
        if len(distances) >= 3 and worst > MAX_RESIDUAL:
            out.append(f"the colour of the plate's light is off the fitted line by up to {worst:.1%} at one distance: a "
                       "distance measured wrong, or the plate's light changed between captures (lamp, exposure, stirred "
                       "water); check the distances and capture again")
        for c in self.captures:
            if c.drift > MAX_DRIFT:
                out.append(f"the plate's light changed colour by {c.drift:.1%} during the capture at {c.distance_m:g} m "
                           "(lamp warming up, water stirred, something moving): capture it again")
        from uwcam.calibration.rig_advice import calibration_rig_advice

        advice = calibration_rig_advice(self.details, self.rig)
        if advice is not None:
            out.append(advice)
        for v in self.validation:
            if not v["passed"]:
                why = v.get("reason") or (f"the new profile ranges the plate {v['median_range_error_m']:+.3f} m off, "
                                          f"more than the {v['allowed_m']:.3f} m allowed")
                out.append(f"held-back distance {v['distance_m']:g} m failed: {why}")
        return out

    def report(self) -> str:
        """The fit as one self-contained HTML page (tables and plots)."""
        from uwcam.calibration.report import html_report

        if self.details is None:
            raise SessionError(409, "no fit yet: POST …/fit first")
        from uwcam.calibration.rig_advice import calibration_rig_advice

        return html_report(self.details, f"uwcam tank calibration {self.id} (rig {self.rig_name})",
                           advice=calibration_rig_advice(self.details, self.rig))

    def plot(self, name: str) -> bytes:
        from uwcam.calibration.report import figure

        if self.details is None:
            raise SessionError(409, "no fit yet: POST …/fit first")
        if name not in _plot_names():
            raise SessionError(404, f"no plot '{name}'; plots: {', '.join(_plot_names())}")
        if name not in self._plots:
            self._plots[name] = figure(self.details, name)
        return self._plots[name]

    def acceptable(self) -> CalibrationProfile:
        """The fitted profile, if a held-back distance validated it."""
        if self.state != "fitted" or self.details is None:
            raise SessionError(409, f"nothing to accept: the session is {self.state}; capture and fit first")
        if not self.validation:
            raise SessionError(409, "capture a held-back distance (held_back: true) and fit again to validate the profile "
                                    "before accepting it")
        failed = [v for v in self.validation if not v["passed"]]
        if failed:
            v = failed[0]
            raise SessionError(409, f"validation failed at {v['distance_m']:g} m ({v.get('reason') or 'range error ' + str(v['median_range_error_m']) + ' m'}); "
                                    "check the distances and capture again")
        return self.details.profile

    def summary(self) -> dict:
        return {"id": self.id, "state": self.state, "rig": self.rig_name, "frames_per_capture": self.frames_per_capture,
                "distance_tolerance_m": self.distance_tolerance_m, "exposure": self.exposure,
                "intrinsics": [self.intrinsics.fx, self.intrinsics.fy, self.intrinsics.cx, self.intrinsics.cy],
                "captures": [c.summary() for c in self.captures], "fit": self.fit_summary()}


def _plot_names() -> list[str]:
    from uwcam.calibration.report import PLOTS

    return list(PLOTS)
