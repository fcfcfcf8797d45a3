"""Calibration profiles: a versioned YAML file holding everything ranging needs.

A profile stores, per channel, the attenuation difference c_k − c_ref (1/m), the log
constant b_k = ln(K_k ρ_k / K_ref ρ_ref) of the calibration target, their
uncertainties, the camera noise model and noise floor, plus the joint covariance of
all attenuation differences and log constants, the lamp position, optional intrinsics
and where the calibration came from.

Version history: 1 → 2 added the joint ``covariance`` and each channel's ``fixed_pattern``
noise term; the optional ``response`` (a gamma camera's response curve) came later within
version 2, so every earlier version-2 file still loads unchanged. A version-1 file still loads: its per-channel uncertainties become a diagonal
covariance (version 1 recorded no correlations) and its fixed pattern is 0 (not measured).
"""

from __future__ import annotations

import datetime as dt
import os
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from uwcam.fileio import UserInputError, atomic_write, explain_validation_error, load_yaml_mapping
from uwcam.optics.geometry import Intrinsics

PROFILE_FORMAT = "uwcam-calibration-profile"
PROFILE_VERSION = 2

# Every number strict: an integer is a number, but ``true`` or ``"1108"`` is refused, never read
# as 1 or 1108 (docs/api.md, "Errors").
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False, strict=True)]
Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
Count = Annotated[int, Field(strict=True)]
"""A whole number; booleans, floats and strings are refused."""

# Physical bounds of every number a profile holds: a finite but absurd value (fx = 1e308, a
# backscatter distance of 1e300) is refused with the key and the bound, on upload, on load and
# when `uwcam calibrate` writes one, rather than changing the live range.
MAX_ATTENUATION_PER_M = 100.0
"""1/m: beam attenuation of the murkiest harbour water is tens per metre (light falls e-fold in a
centimetre at 100); differences between channels are bounded by it too."""
MAX_LOG_CONSTANT = 50.0
"""ln of a ratio of channel gains × reflectances: e^50 ≈ 5·10²¹, far beyond any sensor's range."""
MAX_DN = 1e12
"""Raw values (DN, or a float camera's units): 32-bit sensors reach 4.3·10⁹."""
MAX_SATURATION = float(np.finfo(np.float32).max)
"""A float camera's frames clip only where float32 does (uwcam calibrate's default for them)."""
MAX_PIXELS = 100_000.0
"""Pixels: image coordinates and focal lengths of any camera stay below this."""
MAX_DISTANCE_M = 1000.0
"""Metres: no lamp lights a target further away in water."""
MAX_LAMP_OFFSET_M = 10.0
"""Metres: the lamp is mounted on the vehicle."""


def Bounded(low: float, high: float, low_open: bool = False) -> Any:  # noqa: N802 (a type factory)
    """A finite number in [low, high] (or (low, high] with ``low_open``); an integer is accepted,
    a boolean or a string is refused."""
    return Annotated[float, Field(gt=low, le=high, allow_inf_nan=False, strict=True) if low_open
                     else Field(ge=low, le=high, allow_inf_nan=False, strict=True)]


Attenuation = Bounded(-MAX_ATTENUATION_PER_M, MAX_ATTENUATION_PER_M)
LogConstant = Bounded(-MAX_LOG_CONSTANT, MAX_LOG_CONSTANT)
DigitalNumber = Bounded(0.0, MAX_DN)
Pixel = Bounded(-MAX_PIXELS, MAX_PIXELS)
Distance = Bounded(0.0, MAX_DISTANCE_M)
LampOffset = Bounded(-MAX_LAMP_OFFSET_M, MAX_LAMP_OFFSET_M)


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ChannelCalibration(Strict):
    """Calibration of one colour channel."""

    name: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_\-]+$")]
    """Channel name, e.g. R, G, B or a band name."""
    wavelength_nm: Bounded(100.0, 3000.0) | None = None
    """Centre wavelength in nanometres, if known."""
    attenuation_difference: Attenuation
    """c_k − c_ref in 1/m (0 for the reference channel)."""
    attenuation_difference_std: Bounded(0.0, MAX_ATTENUATION_PER_M) = 0.0
    """Standard uncertainty of attenuation_difference, 1/m."""
    log_constant: LogConstant
    """b_k = ln(K_k ρ_k / K_ref ρ_ref) for the calibration target (0 for the reference)."""
    log_constant_std: Bounded(0.0, MAX_LOG_CONSTANT) = 0.0
    """Standard uncertainty of log_constant."""
    attenuation: Bounded(0.0, MAX_ATTENUATION_PER_M) | None = None
    """Absolute beam attenuation c_k in 1/m, when a lamp spreading model was given."""
    target_reflectance: Bounded(0.0, 1.0, low_open=True) = 1.0
    """Reflectance of the calibration target in this channel (only ratios matter)."""
    dark_level: DigitalNumber = 0.0
    """Dark/black level in DN, subtracted from raw values before anything else."""
    read_noise: DigitalNumber = 0.0
    """Read noise, DN rms."""
    shot_gain: DigitalNumber = 0.0
    """Shot-noise variance per DN of signal (DN per photo-electron)."""
    fixed_pattern: Bounded(0.0, 1.0) = 0.0
    """Pixel response non-uniformity: relative rms of the fixed pattern (0.01 = 1 %), variance (fixed_pattern·E)²."""
    noise_floor: DigitalNumber = 0.0
    """Dark-corrected signal in DN at or below which the channel carries no surface signal (0: not measured)."""
    exposure_us: Bounded(0.0, 1e9, low_open=True) | None = None
    """Exposure time (µs) of this channel in the calibration frames; None: not recorded (then
    every channel is taken to have had the same exposure)."""
    gain_db: Bounded(-100.0, 100.0) | None = None
    """Analogue gain (dB) of this channel in the calibration frames; None: not recorded (0 dB)."""


class Provenance(Strict):
    """Where a calibration came from."""

    created: str
    """ISO 8601 time the profile was made."""
    method: str
    """How attenuation differences were found."""
    distances_m: list[Distance] = []
    """Camera-to-target distances along the optical axis, metres (one per distance imaged)."""
    frames_per_distance: list[Annotated[Count, Field(ge=1, le=1_000_000)]] = []
    """Frames averaged at each distance (empty: one each)."""
    path_lengths_m: list[Bounded(0.0, 2 * MAX_DISTANCE_M)] = []
    """Mean lamp→target→camera path length over the target region at each distance, metres."""
    images: list[str] = []
    """The images used, in order."""
    target: str = "spectrally flat target"
    """What was imaged."""
    roi: list[Annotated[Count, Field(ge=0, le=int(MAX_PIXELS))]] | None = None
    """Target region x, y, width, height in pixels; None: the whole image."""
    residuals: dict[str, list[Bounded(-1e3, 1e3)]] = {}
    """Per channel, residual of ln(E_k/E_ref) at each distance after the fit."""
    rms_residual: Bounded(0.0, 1e3) = 0.0
    """Root mean square of all residuals (natural-log units)."""


class LensShading(Strict):
    """The lens's shading (vignetting), radially about the principal point: ln V = a·ln(1 + ρ²) + b·ρ⁴
    with ρ = tan of a pixel's ray's angle off the axis (:mod:`uwcam.optics.lens_shading`; cos⁴ is
    a = −2, b = 0). Needs the profile's intrinsics."""

    coefficients: tuple[Annotated[float, Field(ge=-20, le=20, allow_inf_nan=False, strict=True)],
                        Annotated[float, Field(ge=-20, le=20, allow_inf_nan=False, strict=True)]]
    """(a, b) of ln V."""
    rms: Bounded(0.0, 1.0) = 0.0
    """What the radial model left of the flat-field frames' light, rms in ln."""
    source: Literal["flat-field"] = "flat-field"
    """How it was measured: frames of an evenly lit view (``uwcam calibrate --flat-field``)."""


class BackscatterSamples(Strict):
    """Backscatter measured at the calibration plate's black patch, for compensation in ranging."""

    distances_m: Annotated[list[Bounded(0.0, MAX_DISTANCE_M, low_open=True)], Field(min_length=1)]
    """Depth (camera z) of the plate in each calibration image, metres."""
    patch_pixels: list[tuple[Pixel, Pixel]]
    """Pixel (x, y) at the centre of the black patch in each image."""
    levels: dict[str, list[DigitalNumber]]
    """Per channel, dark-corrected backscatter (DN) at the patch in each image."""
    noise_sigma: dict[str, DigitalNumber]
    """Per channel, pixel noise σ (DN) at the black patch: the floor once backscatter is subtracted is 3σ."""
    level_std: dict[str, list[Bounded(0.0, 1e9)]] = {}
    """Per channel, the standard deviation (DN) of each level from pixel noise; empty in profiles made
    before it was recorded (the levels are then taken as exact where the model is checked against them)."""
    exposure_scale: list[Bounded(0.0, 1e6, low_open=True)] = []
    """Relative exposure of each image (levels are divided by it); 1 when exposure was fixed."""


class CalibrationCovariance(Strict):
    """Joint covariance of the calibration's attenuation differences and log constants.

    ``parameters`` names each row: ``V:<channel>`` for c_k − c_ref (1/m) and ``b:<channel>``
    for the log constant, for every channel but the reference (whose are 0 by definition).
    """

    parameters: Annotated[list[str], Field(min_length=2)]
    """Row and column names, e.g. [V:G, V:B, b:G, b:B]."""
    matrix: list[list[Bounded(-1e4, 1e4)]]
    """Symmetric positive semi-definite matrix, units (1/m)², 1/m and 1 as the names say."""

    @model_validator(mode="after")
    def _square(self) -> "CalibrationCovariance":
        n = len(self.parameters)
        if len(self.matrix) != n or any(len(row) != n for row in self.matrix):
            raise ValueError(f"covariance matrix must be {n}×{n}, one row and column per parameter")
        m = np.array(self.matrix, dtype=np.float64)
        scale = max(float(np.max(np.abs(np.diag(m)))), 1e-300)
        if not np.allclose(m, m.T, rtol=1e-6, atol=1e-12 * scale):
            raise ValueError("covariance matrix must be symmetric")
        if np.min(np.linalg.eigvalsh(0.5 * (m + m.T))) < -1e-9 * scale:
            raise ValueError("covariance matrix must be positive semi-definite (no negative variances)")
        return self


class ResponseRecord(Strict):
    """The camera's response curve: how its codes map back to linear light (see uwcam.imaging.response)."""

    kind: Literal["srgb", "rec709", "table"]
    """A standard curve, or a table recovered from an exposure bracket (``uwcam response``)."""
    bits: Literal[8, 10, 12, 16] = 8
    """Bit depth of the codes the curve applies to."""
    method: str = ""
    """How the curve was found."""
    table: list[list[NonNegative]] | None = None
    """For ``table``: per channel, the linear value (DN) of every code, non-decreasing."""

    @model_validator(mode="after")
    def _table(self) -> "ResponseRecord":
        if (self.kind == "table") != (self.table is not None):
            raise ValueError("a response of kind 'table' needs a table, and only it")
        if self.table is not None and any(len(row) != 2**self.bits for row in self.table):
            raise ValueError(f"every row of the response table needs {2**self.bits} values ({self.bits}-bit codes)")
        return self


class CalibrationProfile(Strict):
    """Everything the intensity–range transform needs for one camera, lamp and water."""

    format: Literal["uwcam-calibration-profile"] = PROFILE_FORMAT
    version: Literal[2] = PROFILE_VERSION
    name: Annotated[str, Field(min_length=1)]
    """Human-readable name of this calibration."""
    reference_channel: str
    """Name of the channel whose attenuation and constant the others are relative to."""
    channels: Annotated[list[ChannelCalibration], Field(min_length=2)]
    """Per-channel calibration in the order the camera delivers channels."""
    saturation_level: Bounded(0.0, MAX_SATURATION, low_open=True)
    """Raw value (DN) at or above which a pixel is clipped."""
    quantisation_step: DigitalNumber = 1.0
    """Size of one code in DN (0 for float data, which a camera delivering integers refuses);
    below the saturation level."""
    lamp_position_m: tuple[LampOffset, LampOffset, LampOffset] = (0.0, 0.0, 0.0)
    """Lamp position in the camera frame (x right, y down, z forward), metres."""
    lamp_radius_m: Bounded(0.0, MAX_LAMP_OFFSET_M) | None = None
    """Effective lamp radius sqrt(A0/Ω) in metres used for absolute attenuation, if any."""
    intrinsics: dict[str, Pixel] | None = None
    """Pinhole intrinsics fx, fy, cx, cy in pixels (fx, fy > 0); checked against the camera's
    image size when the profile is put in use (:func:`check_intrinsics_fit`)."""
    backscatter: BackscatterSamples | None = None
    """Backscatter measured during calibration (when the target had a black patch)."""
    covariance: CalibrationCovariance | None = None
    """Joint covariance of attenuation differences and log constants; None: uncorrelated, from the stds."""
    lens_shading: LensShading | None = None
    """The lens's shading (vignetting), where measured; None: not measured (the backscatter model then
    estimates it from the open-water frames, or counts what it could be in σ)."""
    response: ResponseRecord | None = None
    """The camera's response curve; None: a linear camera. With one, every integer frame is
    linearised through it before anything else, and the noise model, dark level and saturation
    are in linear DN."""
    provenance: Provenance

    @model_validator(mode="after")
    def _consistent(self) -> "CalibrationProfile":
        names = [c.name for c in self.channels]
        if len(set(names)) != len(names):
            raise ValueError(f"channel names must be unique, got {names}")
        if self.reference_channel not in names:
            raise ValueError(f"reference_channel '{self.reference_channel}' is not one of the channels {names}")
        ref = self.channels[names.index(self.reference_channel)]
        if ref.attenuation_difference != 0 or ref.log_constant != 0:
            raise ValueError("the reference channel must have attenuation_difference 0 and log_constant 0")
        if len({c.attenuation_difference for c in self.channels}) < 2:
            raise ValueError("all channels have the same attenuation_difference, so no range can be computed")
        if self.backscatter is not None:
            bs = self.backscatter
            n = len(bs.distances_m)
            if set(bs.levels) != set(names) or set(bs.noise_sigma) != set(names):
                raise ValueError(f"backscatter levels and noise_sigma need one entry per channel {names}")
            if len(bs.patch_pixels) != n or any(len(v) != n for v in bs.levels.values()):
                raise ValueError(f"backscatter needs {n} patch_pixels and {n} levels per channel, one per distance")
            if bs.level_std and (set(bs.level_std) != set(names) or any(len(v) != n for v in bs.level_std.values())):
                raise ValueError(f"backscatter level_std, where given, needs {n} values per channel {names}, one per distance")
        if self.covariance is not None:
            others = [n for n in names if n != self.reference_channel]
            want = [f"V:{n}" for n in others] + [f"b:{n}" for n in others]
            if self.covariance.parameters != want:
                raise ValueError(f"covariance parameters must be {want} (attenuation differences, then log constants)")
        if self.response is not None and self.response.table is not None and len(self.response.table) != len(names):
            raise ValueError(f"the response table needs one row per channel {names}")
        if self.intrinsics is not None:
            if set(self.intrinsics) != {"fx", "fy", "cx", "cy"}:
                raise ValueError(f"intrinsics need exactly fx, fy, cx, cy, got {sorted(self.intrinsics)}")
            if not (self.intrinsics["fx"] > 0 and self.intrinsics["fy"] > 0):
                raise ValueError("intrinsics fx and fy must be positive")
        if self.lens_shading is not None and self.intrinsics is None:
            raise ValueError("lens_shading needs the camera's intrinsics (fx, fy, cx, cy): its model is in the angle "
                             "of each pixel's ray off the axis")
        for c in self.channels:
            for key in ("dark_level", "noise_floor", "read_noise"):
                if getattr(c, key) >= self.saturation_level:
                    raise ValueError(f"channel {c.name}: {key} {getattr(c, key):g} DN must be below the saturation "
                                     f"level {self.saturation_level:g} DN")
        if self.quantisation_step >= self.saturation_level:
            raise ValueError(f"quantisation_step {self.quantisation_step:g} DN must be below the saturation level "
                             f"{self.saturation_level:g} DN")
        return self

    # Convenience views as arrays, in channel order.
    @property
    def channel_names(self) -> list[str]:
        return [c.name for c in self.channels]

    @property
    def reference_index(self) -> int:
        return self.channel_names.index(self.reference_channel)

    def array(self, field: str) -> np.ndarray:
        """One per-channel field as a float64 array of shape (N,)."""
        return np.array([getattr(c, field) for c in self.channels], dtype=np.float64)

    def calibration_exposure(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(exposure µs, gain dB) per channel in the calibration frames, (N,) each, or None
        where not recorded for every channel."""
        exposure = None if any(c.exposure_us is None for c in self.channels) else self.array("exposure_us")
        gain = None if any(c.gain_db is None for c in self.channels) else self.array("gain_db")
        return exposure, gain

    def camera_intrinsics(self) -> Intrinsics | None:
        return None if self.intrinsics is None else Intrinsics(**self.intrinsics)

    def response_curve(self):
        """The camera's :class:`uwcam.imaging.response.ResponseCurve`, or None for a linear camera."""
        if self.response is None:
            return None
        from uwcam.imaging.response import ResponseCurve

        return ResponseCurve.from_record(self.response, len(self.channels))

    def covariance_blocks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Cvv, Cvb, Cbb), each (N, N) in channel order with zero reference row and column:
        covariances of attenuation differences, of attenuation differences with log constants,
        and of log constants. Without a stored covariance, diagonal from the stds."""
        n = len(self.channels)
        cvv, cvb, cbb = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
        if self.covariance is None:
            cvv[np.diag_indices(n)] = self.array("attenuation_difference_std") ** 2
            cbb[np.diag_indices(n)] = self.array("log_constant_std") ** 2
            return cvv, cvb, cbb
        others = [k for k in range(n) if k != self.reference_index]
        m = np.array(self.covariance.matrix, dtype=np.float64)
        q = len(others)
        idx = np.ix_(others, others)
        cvv[idx], cvb[idx], cbb[idx] = m[:q, :q], m[:q, q:], m[q:, q:]
        return cvv, cvb, cbb


def _v1_to_v2(data: dict[str, Any]) -> dict[str, Any]:
    """Version 1 had per-channel stds only: the covariance is theirs, uncorrelated."""
    out = dict(data)
    out["version"] = 2
    channels = data.get("channels")
    ref = data.get("reference_channel")
    if isinstance(channels, list) and all(isinstance(c, dict) for c in channels):
        others = [c for c in channels if c.get("name") != ref]
        try:
            variances = [float(c.get("attenuation_difference_std", 0.0)) ** 2 for c in others] + \
                        [float(c.get("log_constant_std", 0.0)) ** 2 for c in others]
        except (TypeError, ValueError):
            return out  # validation will name the bad value
        if others and all(np.isfinite(variances)):
            names = [str(c.get("name")) for c in others]
            out["covariance"] = {"parameters": [f"V:{n}" for n in names] + [f"b:{n}" for n in names],
                                 "matrix": np.diag(variances).tolist()}
    return out


# version → function taking the mapping of that version and returning version + 1.
_MIGRATIONS: dict[int, Any] = {1: _v1_to_v2}


def _migrate(data: dict[str, Any], source: str) -> dict[str, Any]:
    version = data.get("version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise UserInputError(f"{source}: key 'version' must be an integer profile version (this uwcam writes {PROFILE_VERSION})")
    if version > PROFILE_VERSION:
        raise UserInputError(
            f"{source}: profile version {version} is newer than this uwcam understands ({PROFILE_VERSION}); upgrade uwcam"
        )
    while version < PROFILE_VERSION:
        if version not in _MIGRATIONS:
            raise UserInputError(f"{source}: profile version {version} is too old to migrate; recalibrate")
        data = _MIGRATIONS[version](data)
        version = data["version"]
    return data


def profile_from_mapping(data: dict[str, Any], source: str = "calibration profile") -> CalibrationProfile:
    """Validate a mapping (e.g. an uploaded profile) into a profile; UserInputError on any problem."""
    if data.get("format") != PROFILE_FORMAT:
        raise UserInputError(f"{source}: key 'format' must be '{PROFILE_FORMAT}'; is this a uwcam calibration profile?")
    data = _migrate(dict(data), source)
    try:
        return CalibrationProfile.model_validate(data)
    except ValidationError as exc:
        raise UserInputError(explain_validation_error(exc, source)) from None


def load_profile(path: str | os.PathLike[str]) -> CalibrationProfile:
    """Load and validate a profile; UserInputError names the file and the key at fault."""
    return profile_from_mapping(load_yaml_mapping(path, "calibration profile"), f"calibration profile {path}")


def profile_to_yaml(profile: CalibrationProfile) -> str:
    data = profile.model_dump(mode="json")
    for channel in data["channels"]:  # not recorded: left out, as files made before they existed
        for key in ("exposure_us", "gain_db"):
            if channel.get(key) is None:
                channel.pop(key, None)
    if data.get("lens_shading") is None:  # not measured: left out, as files made before it existed
        data.pop("lens_shading", None)
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


def save_profile(profile: CalibrationProfile, path: str | os.PathLike[str]) -> None:
    """Write atomically: the file is either the old one or the complete new one."""
    with atomic_write(path, "w") as fh:
        fh.write(profile_to_yaml(profile))


def now_iso() -> str:
    return dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat()


def check_intrinsics_fit(k: dict[str, float] | None, width: int, height: int) -> None:
    """ValueError unless intrinsics ``k`` (fx, fy, cx, cy in pixels; None: none) suit images of ``width`` × ``height`` pixels: the
    principal point within an image size of the image, focal lengths between a hundredth and a
    hundred image sizes (a fisheye's is about a third, a narrow telephoto's a few)."""
    if k is None:
        return
    size = max(width, height)
    if not (-width <= k["cx"] <= 2 * width and -height <= k["cy"] <= 2 * height):
        raise ValueError(f"intrinsics cx {k['cx']:g}, cy {k['cy']:g} px lie far outside the camera's "
                         f"{width}×{height} image; calibrate with this camera")
    if not all(size / 100 <= k[f] <= 100 * size for f in ("fx", "fy")):
        raise ValueError(f"intrinsics fx {k['fx']:g}, fy {k['fy']:g} px do not suit the camera's {width}×{height} image "
                         f"(between {size / 100:g} and {100 * size:g} px); calibrate with this camera")
