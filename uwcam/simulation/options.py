"""The ``simulation:`` section of a daemon configuration: the shared simulated rig's options,
checked strictly (every number finite and in range, unknown keys refused)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from uwcam.simulation.scene import MATERIALS, SCENES
from uwcam.simulation.water import WATER_PRESETS

SCENE_NAMES = ("survey", *SCENES)
SURVEY_KEYS = ("speed", "altitude", "altitude_period")
NAMED = {"scene": SCENE_NAMES, "water": WATER_PRESETS, "material": MATERIALS}
"""The options that name one of a known set, and that set."""

Finite = Annotated[float, Field(allow_inf_nan=False)]


class SimulationOptions(BaseModel):
    """Options of :class:`uwcam.drivers.sim.SimulatedRig`; distances in metres."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    scene: str = "seabed"
    """``survey`` (a vehicle surveying a varied seabed) or a static scene (see ``uwcam simulate --list``)."""
    distance: Annotated[float, Field(gt=0, le=50)] = 2.0
    """Static scenes: the seabed's (or plate's) distance along the optical axis."""
    size: tuple[Annotated[int, Field(ge=16, le=7680)], Annotated[int, Field(ge=16, le=4320)]] = (640, 480)
    """Image width and height in pixels."""
    water: str = "jerlov-II"
    lamp_offset: tuple[Annotated[float, Field(ge=-3, le=3)], Annotated[float, Field(ge=-3, le=3)],
                       Annotated[float, Field(ge=-3, le=3)]] = (0.3, 0.0, 0.0)
    """Lamp position in the camera frame (x right, y down in the image, z forward)."""
    bits: Annotated[int, Field(ge=8, le=16)] = 16
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    material: str | None = None
    """Give every surface this material (e.g. grey, the calibration plate's hue)."""
    ambient: tuple[Annotated[float, Field(ge=0, le=1)], ...] | None = None
    """Daylight per channel (R, G, B), relative to the lamp."""
    lamp_on: bool = True
    lamp_intensity: Annotated[float, Field(ge=0, le=1)] = 1.0
    speed: Annotated[float, Field(ge=0, le=5)] = 0.4
    """Survey: speed over ground, m/s."""
    altitude: tuple[Annotated[float, Field(ge=0.5, le=10)], Annotated[float, Field(ge=0.5, le=10)]] = (1.5, 4.0)
    """Survey: lowest and highest altitude above the smooth seabed, m."""
    altitude_period: Annotated[float, Field(ge=10, le=3600)] = 120.0
    """Survey: seconds from the lowest altitude to the highest and back."""
    drift: tuple[Annotated[float, Field(ge=-1, le=1)], Annotated[float, Field(ge=-1, le=1)],
                  Annotated[float, Field(ge=-1, le=1)]] | None = None
    """Static scenes: change of the water's attenuation per channel (R, G, B), 1/m, over half a
    drift_period and back (a tide, a plume, a temperature front); None: still water."""
    drift_period: Annotated[float, Field(ge=1, le=86400)] = 300.0
    """Seconds of one drift cycle."""
    plate_rig: str | None = None
    """Scene ``plate``: a built-in calibration rig to draw (e.g. charuco-plate); None: the grey plate."""

    @field_validator("plate_rig")
    @classmethod
    def _known_rig(cls, v: str | None) -> str | None:
        if v is not None:
            from uwcam.calibration.rig import builtin_rig_path

            try:
                builtin_rig_path(v)
            except Exception as exc:  # the rig module says which rigs exist
                raise ValueError(str(exc)) from None
        return v

    @field_validator(*NAMED)
    @classmethod
    def _known_name(cls, v: str | None, info: ValidationInfo) -> str | None:
        known = NAMED[info.field_name]
        if v is not None and v not in known:
            raise ValueError(f"unknown {info.field_name} '{v}'; known: {', '.join(known)}")
        return v

    @field_validator("bits")
    @classmethod
    def _bit_depth(cls, v: int) -> int:
        if v not in (8, 12, 16):
            raise ValueError("bit depth must be 8, 12 or 16")
        return v

    @field_validator("ambient")
    @classmethod
    def _three_channels(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and len(v) != 3:
            raise ValueError("give one daylight level per channel: [R, G, B]")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "SimulationOptions":
        if self.altitude[0] > self.altitude[1]:
            raise ValueError("altitude must be [lowest, highest] with lowest ≤ highest")
        if self.scene != "survey":
            given = [k for k in SURVEY_KEYS if k in self.model_fields_set]
            if given:
                raise ValueError(f"'{given[0]}' applies only to scene: survey (this scene is static)")
        elif "drift" in self.model_fields_set or "drift_period" in self.model_fields_set:
            raise ValueError("'drift' applies only to static scenes; the survey's water stays as it is")
        elif "distance" in self.model_fields_set:
            raise ValueError("'distance' applies only to static scenes; the survey's range follows its 'altitude'")
        return self


def check_simulation_options(options: dict[str, Any]) -> dict[str, Any]:
    """Validate a ``simulation:`` mapping; return it with the keys given (values normalised).

    Raises ValueError with one line naming the key: ``simulation.speed: ...``."""
    try:
        model = SimulationOptions.model_validate(options)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"])
        message = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            message = "unknown key; remove it or check its spelling"
        elif "input" in err and not isinstance(err["input"], (dict, list)) and key:
            message = f"{message} (got {err['input']!r})"
        raise ValueError(f"{key}: {message}" if key else message) from None
    return {k: getattr(model, k) for k in options}
