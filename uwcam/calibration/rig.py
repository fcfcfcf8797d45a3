"""Calibration rigs: declarative descriptions of plates, patches and their reflectance.

A rig file (``calibration_rigs/*.yaml``) describes a calibration plate: its size,
its reflectance per channel (a single grey value, one value per channel, or a sampled
spectrum interpolated at the channels' centre wavelengths), a black patch on it, and
optionally where plate and patch appear in the image in pixels. A plate may also carry
fiducial markers (OpenCV ArUco) around its target region: they locate the plate in the
image and give its distance and tilt (see :mod:`uwcam.calibration.plate`), and ``uwcam rig print``
draws the plate's artwork at true scale.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from uwcam.fileio import UserInputError, explain_validation_error, load_yaml_mapping

RIG_FORMAT = "uwcam-rig"
Reflectance = Annotated[float, Field(gt=0, le=1)]
Region = tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)], Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Spectrum(Strict):
    """Reflectance sampled at wavelengths (nm), linearly interpolated between samples."""

    wavelength_nm: Annotated[list[Annotated[float, Field(gt=0)]], Field(min_length=2)]
    reflectance: Annotated[list[Reflectance], Field(min_length=2)]

    @model_validator(mode="after")
    def _same_length(self) -> "Spectrum":
        if len(self.wavelength_nm) != len(self.reflectance):
            raise ValueError("wavelength_nm and reflectance must have the same number of samples")
        if any(b <= a for a, b in zip(self.wavelength_nm, self.wavelength_nm[1:])):
            raise ValueError("wavelength_nm must increase")
        return self


ReflectanceSpec = Reflectance | list[Reflectance] | Spectrum


def resolve_reflectance(spec: ReflectanceSpec, names: list[str], wavelengths: list[float | None], what: str) -> np.ndarray:
    """Per-channel reflectance (N,) from a scalar, a per-channel list or a spectrum."""
    n = len(names)
    if isinstance(spec, (int, float)):
        return np.full(n, float(spec))
    if isinstance(spec, list):
        if len(spec) != n:
            raise UserInputError(f"{what} lists {len(spec)} reflectances but the images have {n} channels ({','.join(names)})")
        return np.array(spec, dtype=np.float64)
    if any(w is None for w in wavelengths):
        raise UserInputError(
            f"{what} is a spectrum, so every channel needs a centre wavelength: give --channels NAME:NM,... (e.g. R:675,G:575,B:475)"
        )
    lo, hi = spec.wavelength_nm[0], spec.wavelength_nm[-1]
    outside = [w for w in wavelengths if not lo <= w <= hi]
    if outside:
        raise UserInputError(f"{what} covers {lo:g}–{hi:g} nm but channel wavelength(s) {outside} lie outside it")
    return np.interp(np.array(wavelengths, dtype=np.float64), spec.wavelength_nm, spec.reflectance)


class Patch(Strict):
    """A rectangular patch on the plate (plate coordinates: metres from its centre, x right, y down)."""

    centre_m: tuple[float, float]
    size_m: tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]]
    reflectance: ReflectanceSpec


class Area(Strict):
    """A rectangle on the plate (plate coordinates: metres from its centre, x right, y down)."""

    centre_m: tuple[float, float] = (0.0, 0.0)
    size_m: tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]]


class Marker(Strict):
    id: Annotated[int, Field(ge=0, le=999)]
    """Marker id in the board's dictionary."""
    centre_m: tuple[float, float]
    """Centre of the marker's outer black square, plate coordinates (m)."""


class MarkerBoard(Strict):
    """ArUco markers printed on the plate around its target region."""

    dictionary: Annotated[str, Field(pattern=r"^DICT_[A-Z0-9_]+$")] = "DICT_4X4_50"
    """OpenCV predefined dictionary name."""
    marker_size_m: Annotated[float, Field(gt=0)]
    """Side of each marker's outer black square, metres."""
    reflectance: ReflectanceSpec = 0.04
    """Reflectance of the printed black."""
    markers: Annotated[list[Marker], Field(min_length=1)]

    @model_validator(mode="after")
    def _unique(self) -> "MarkerBoard":
        ids = [m.id for m in self.markers]
        if len(set(ids)) != len(ids):
            raise ValueError(f"marker ids must be unique, got {ids}")
        return self


class Plate(Strict):
    size_m: tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]]
    """Width and height of the plate, metres."""
    reflectance: ReflectanceSpec
    """Reflectance of the plate's main surface."""
    black_patch: Patch | None = None
    """A dark patch whose image gives each channel's noise floor."""
    target: Area | None = None
    """The part of the plate used as calibration target, clear of markers (default: the whole plate)."""
    markers: MarkerBoard | None = None
    """Fiducial markers that locate the plate in the image."""

    @model_validator(mode="after")
    def _inside(self) -> "Plate":
        half = (self.size_m[0] / 2, self.size_m[1] / 2)
        areas = [("target", self.target), ("black_patch", self.black_patch)]
        areas += [(f"marker {m.id}", Area(centre_m=m.centre_m, size_m=(self.markers.marker_size_m,) * 2))
                  for m in (self.markers.markers if self.markers else [])]
        for what, a in areas:
            if a is None:
                continue
            for axis in (0, 1):
                if abs(a.centre_m[axis]) + a.size_m[axis] / 2 > half[axis] + 1e-9:
                    raise ValueError(f"{what} reaches beyond the plate's edge")
        return self

    def target_area(self) -> Area:
        return self.target or Area(size_m=self.size_m)


class PixelRegions(Strict):
    """Where plate and black patch appear in the image, x, y, width, height in pixels."""

    target: Region | None = None
    black: Region | None = None


class Rig(Strict):
    format: Literal["uwcam-rig"]
    version: Literal[1]
    name: str
    description: str = ""
    plate: Plate
    regions: PixelRegions = PixelRegions()


def load_rig(path: str | os.PathLike[str]) -> Rig:
    """Load and validate a rig file; UserInputError names the file and the key at fault."""
    data = load_yaml_mapping(path, "rig file")
    source = f"rig file {path}"
    if data.get("format") != RIG_FORMAT:
        raise UserInputError(f"{source}: key 'format' must be '{RIG_FORMAT}'")
    try:
        return Rig.model_validate(data)
    except ValidationError as exc:
        raise UserInputError(explain_validation_error(exc, source)) from None


def builtin_rig_path(name: str = "grey-plate") -> Path:
    """Path of a rig shipped with uwcam (calibration_rigs/NAME.yaml)."""
    path = Path(str(resources.files("uwcam.calibration_rigs").joinpath(f"{name}.yaml")))
    if not path.exists():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise UserInputError(f"no built-in rig '{name}'; known rigs: {', '.join(known)}")
    return path
