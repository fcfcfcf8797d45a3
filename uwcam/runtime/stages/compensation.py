"""The water's own light in the frame loop: the open-water frame (captured on request, kept,
forgotten) and the backscatter compensation built from it and the profile's black-patch
measurements, subtracted before ranging wherever the water's light is known.

A part of :class:`uwcam.runtime.pipeline.FramePipeline` (a mixin: it shares the loop's lock and settings),
kept apart because it is a concern of its own: what the water adds to every frame.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
from numpy.typing import NDArray

from uwcam.config import ProcessingConfig
from uwcam.drivers.base import Frame
from uwcam.calibration.profile import CalibrationProfile
from uwcam.ranging.estimator import RangeEstimator

log = logging.getLogger(__name__)


UNRELATED_CALIBRATION = ("the camera says its exposure but the profile records none, so the calibration's backscatter "
                         "cannot be scaled to it: take an open-water frame (POST /api/v1/backscatter/open-water) or use a "
                         "profile calibrated with its exposure (uwcam calibrate --exposure-us)")
UNRELATED_OPEN_WATER = ("the camera says its exposure but the open-water frame does not, so its backscatter cannot be "
                        "scaled to it: take the open-water frame again (POST /api/v1/backscatter/open-water)")


class UnrelatedExposure(Exception):
    """A frame whose exposure the backscatter model's light cannot be related to: not ranged."""


def _same_inputs(a: tuple, b: tuple) -> bool:
    """Compensator inputs alike: the same profile and open-water objects (immutable once in use),
    equal shape, passes, pair and bounds."""
    return a[0] is b[0] and a[1] is b[1] and a[2:] == b[2:]


class CompensationStage:
    """Open-water capture and backscatter compensation for :class:`~uwcam.runtime.pipeline.FramePipeline`."""

    def set_open_water(self, frame: NDArray | None, info: dict | None = None) -> None:
        """Use this open-water frame (H, W, N; raw DN less ambient light) for backscatter from the
        next frame on; None forgets it (the profile's black-patch measurements are used alone).
        The compensator for it is built here, in the caller's thread (0.3-0.6 s at 720p), while
        the loop goes on with the one it has."""
        water = None if frame is None else np.asarray(frame, np.float32)
        processing, profile, shape = self.processing, self.profile, self._frame_shape
        compensator = None
        if self._iterations(processing, profile) is not None and shape is not None:
            try:
                compensator = self._make_compensator(processing, profile, shape, water, self._frames_of(info or {}))
            except Exception:  # the frame is kept all the same; the loop tries again, and says why
                log.exception("could not build backscatter compensation for the open-water frame")
        with self._lock:
            self.open_water = water
            self.open_water_info = dict(info or {})
            # Settings or profile changed meanwhile: the loop builds one for what it has now.
            current = self.processing is processing and self.profile is profile
            self._compensator = compensator if current else None

    @staticmethod
    def _frames_of(info: dict) -> int:
        """How many frames an open-water frame with this ``info`` is the mean of (1 where it does
        not say, or says something that is not a count: a state file from elsewhere)."""
        from uwcam.water.backscatter import frames_averaged_count

        return frames_averaged_count(info.get("frames", 1)) or 1

    def request_open_water(self, frames: int = 4, timeout_s: float = 10.0) -> threading.Event:
        """Average the next ``frames`` lamp-lit frames into the open-water frame; the event is set
        when it is in use. Frames later than ``timeout_s`` from now are not taken (the request
        lapses, and :meth:`backscatter_status` says so). The view must show only water meanwhile.
        Frames are taken by their capture time: one captured before the request (still on its way
        through a loop that fell behind) may show what the camera saw before, and is not taken."""
        done = threading.Event()
        now_ns = time.monotonic_ns()
        with self._lock:
            self._open_water_request = {"frames": int(frames), "sum": None, "count": 0, "done": done,
                                        "requested_ns": now_ns, "deadline_ns": now_ns + int(timeout_s * 1e9),
                                        "timeout_s": timeout_s}
            self._open_water_capture = "capturing"
        return done

    def _pending_open_water(self) -> dict | None:
        """The open-water request still pending, dropping one past its deadline."""
        with self._lock:
            request = self._open_water_request
            if request is not None and time.monotonic_ns() > request["deadline_ns"]:
                self._lapse(request)
                return None
            return request

    def _lapse(self, request: dict) -> None:
        """Drop ``request`` if it is still the pending one, saying why; the caller holds the lock."""
        if self._open_water_request is not request:  # taken, or replaced by a newer request meanwhile
            return
        self._open_water_request = None
        self._open_water_capture = (f"lapsed: {request['count']} of {request['frames']} lamp-lit frames came "
                                    f"within {request['timeout_s']:g} s (is the camera streaming and the lamp on?)")

    def _take_open_water(self, frame: Frame, ambient: NDArray | None, source: str) -> None:
        """Accumulate ``frame`` for a pending open-water request."""
        request = self._pending_open_water()
        if request is None or frame.host_monotonic_ns < request["requested_ns"]:
            return
        if frame.host_monotonic_ns > request["deadline_ns"]:  # captured too late, however soon it is processed
            with self._lock:
                self._lapse(request)
            return
        light = frame.data.astype(np.float32) if ambient is None else frame.data.astype(np.float32) - ambient
        gathered = frame.light_gathered()
        if gathered is not None:
            if request.get("exposure") is None:
                request["exposure"] = gathered
            elif not np.array_equal(gathered, request["exposure"]):  # the exposure moved: to the first frame's
                dark = self.profile.array("dark_level").astype(np.float32)
                light = dark + (light - dark) * (request["exposure"] / gathered).astype(np.float32)
        request["sum"] = light if request["sum"] is None else request["sum"] + light
        request["count"] += 1
        total, count = request["sum"], request["count"]
        if count < request["frames"]:
            return
        info = {"source": source, "frames": count, "wall_time": frame.wall_time, "monotonic": time.monotonic(),
                "shape": list(frame.data.shape)}
        if request.get("exposure") is not None:
            info["exposure"] = [float(v) for v in request["exposure"]]  # per channel, exposure × gain (µs)
        with self._lock:
            self._open_water_request = None  # no more frames taken; still "capturing" until in use
        # Put in use by a thread of its own: building its compensator would stall the loop.
        self._open_water_thread = threading.Thread(target=self._use_open_water, args=(total / count, info, request),
                                                   name="open-water", daemon=True)
        self._open_water_thread.start()

    def _use_open_water(self, mean: NDArray, info: dict, request: dict) -> None:
        try:
            self.set_open_water(mean, info)
        except Exception as exc:  # e.g. the profile changed to one the frame does not fit
            log.exception("the open-water frame could not be put in use")
            with self._lock:
                self._open_water_capture = f"failed: {exc}"
            return
        with self._lock:
            self._open_water_capture = "done"
        request["done"].set()
        if self.on_open_water is not None:
            self.on_open_water(mean, info)

    @staticmethod
    def _iterations(processing: ProcessingConfig, profile: CalibrationProfile) -> int | None:
        """Passes of backscatter compensation: as configured, else wherever the profile knows the
        water's light (:func:`uwcam.water.frame_compensator.compensation_iterations`); None: none."""
        from uwcam.water.frame_compensator import compensation_iterations

        return compensation_iterations(None if processing.backscatter is None else processing.backscatter.iterations, profile)

    def _make_compensator(self, processing: ProcessingConfig, profile: CalibrationProfile, frame_shape: tuple[int, ...],
                          open_water: NDArray | None, open_water_frames: int | None = None):
        """A backscatter compensator for frames of ``frame_shape`` (H, W, N), with the open-water
        frame if it is of that shape (the mean of ``open_water_frames``; None: as the one in use
        says): the one in use when it was built from the same inputs (a
        new one costs 0.3-0.6 s at 720p, which a change of smoothing or of the page's pins must
        not pay), else a new one."""
        from uwcam.water.frame_compensator import BackscatterCompensator

        water = open_water if open_water is not None and open_water.shape == tuple(frame_shape) else None
        inputs = (profile, water, tuple(frame_shape[:2]), self._iterations(processing, profile), processing.pair,
                  tuple(processing.path_length_bounds),
                  1 if water is None else open_water_frames or self._frames_of(self.open_water_info))
        current = self._compensator
        built_from = getattr(current, "built_from", None)
        if built_from is not None and _same_inputs(built_from, inputs):
            return current
        kind = self._frame_kind  # its kernels readied for the frames the camera gives, once known
        ready = {} if kind is None else {"frame_dtypes": (kind[0].type,), "strided": not kind[2]}
        compensator = BackscatterCompensator(profile, inputs[2], inputs[3], water, open_water_frames=inputs[6],
                                             pair=processing.pair,
                                             path_length_bounds=processing.path_length_bounds, **ready)
        compensator.built_from = inputs
        return compensator

    def _compensation(self, frame: Frame, processing: ProcessingConfig, profile: CalibrationProfile,
                      estimator: RangeEstimator, ambient: NDArray | None) -> tuple:
        """(the transform of range_frame that subtracts backscatter or None, the open-water light
        each pixel is judged against or None, the frame's light over the model's per channel or None)."""
        from uwcam.water.frame_compensator import compensation
        from uwcam.water.light_scale import light_scale

        exposure = self.open_water_info.get("exposure")
        if self._iterations(processing, profile) is None:
            return None, None, None
        comp = self._compensator
        if comp is None or comp.shape != frame.data.shape[:2]:
            comp = self._make_compensator(processing, profile, frame.data.shape, self.open_water)
            # Kept only while the profile and settings it was built for are the ones in use: a
            # profile put in use while this was built (seconds on a loaded machine) has its own,
            # which this must not replace (it did: the new profile then ranged with the old one's
            # water light for good).
            with self._lock:
                current = self._compensator
                if self.profile is profile and self.processing is processing and (
                        current is None or current.shape != comp.shape):
                    self._compensator = comp
        # The modelled backscatter is in the counts of the light it came from: scaled to this frame's exposure.
        gathered = frame.light_gathered()
        scale = light_scale(profile, estimator, gathered, comp.open_water, exposure)
        if scale is None and gathered is not None:
            # A frame that says its exposure, a model whose light does not: subtracted as it is, the
            # water's light of another exposure ranged 19–80 % short with every pixel valid.
            self._exposure_refusal = (UNRELATED_OPEN_WATER if comp.open_water else UNRELATED_CALIBRATION)
            raise UnrelatedExposure(self._exposure_refusal)
        self._exposure_refusal = None
        return compensation(comp, estimator, ambient, scale, self._compensation_ms), comp.water, scale

    def _light_before_footprint(self, frame: Frame, corrector, transform, ambient: NDArray | None,
                                scale: NDArray | None) -> NDArray | None:
        """The light (DN) in the rangefinder's footprint that is not the surface's ((h, w, N), the
        footprint clipped to the frame; or the whole frame's ambient light): the ambient
        light and, where backscatter is subtracted before ranging, the water's own light in front
        of a surface at the reading's range. The corrector's log constants must describe the
        surface's light alone, as the ranges they enter are made from it: fitted to light with the
        water's in it, they absorbed the backscatter that compensation then subtracts again
        (Jerlov IB, seabed at 2 m: +3.4 % in the middle of the view)."""
        comp = self._compensator
        reading = corrector.rangefinder.latest()
        if transform is None or comp is None or reading is None or not np.isfinite(reading.range_m):
            return ambient
        x, y, w, h = footprint = tuple(corrector.config.footprint)
        # The reading's range over the footprint's blocks, open water (no surface) elsewhere; the
        # footprint's pixels only, which are all the corrector reads.
        water = comp.footprint_level(reading.range_m, footprint, 1.0 if scale is None else np.asarray(scale, np.float32))
        return water if ambient is None else water + ambient[y : y + h, x : x + w]

    def backscatter_status(self) -> dict:
        """Whether backscatter is compensated, with what, and its cost per frame."""
        iterations = self._iterations(self.processing, self.profile)
        info = dict(self.open_water_info)
        if "monotonic" in info:
            info["age_s"] = round(time.monotonic() - info.pop("monotonic"), 1)
        ms = list(self._compensation_ms)
        # Compensated wherever the profile knows the water's light, asked for or not (a range with
        # that light left in reads short): "configured" says whether the settings asked for it.
        return {"enabled": iterations is not None, "iterations": iterations,
                "refused": self._exposure_refusal,
                "configured": self.processing.backscatter is not None,
                "open_water": info or None,
                "model": None if iterations is None else ("open-water frame and black-patch measurements" if self.open_water is not None
                                                       else "black-patch measurements of the calibration"),
                "ms_per_frame": round(float(np.median(ms)), 2) if ms else None,
                "capture": "capturing" if self._pending_open_water() is not None else self._open_water_capture}
