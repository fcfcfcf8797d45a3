"""GET/PATCH /api/v1/config and POST /api/v1/config/restore: live processing settings."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from uwcam.api.common import get_daemon
from uwcam.config import (BackscatterConfig, Box, ExposureConfig, Flag, OrientationConfig, PatchConfig, ProcessingConfig, Real,
                          TemporalConfig, Whole)
from uwcam.runtime.daemon import Daemon

router = APIRouter(prefix="/api/v1/config", tags=["config"])


class ProcessingPatch(BaseModel):
    """Live-tunable processing settings; omitted keys keep their value."""

    # Bounds and finiteness are those of ProcessingConfig, which validates the merged result.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    pair: tuple[Annotated[str, Field(max_length=64)], Annotated[str, Field(max_length=64)]] | None = None
    fuse: Flag | None = None
    """true: fuse all channels (clears pair)."""
    smoothing: Literal["none", "mean", "median", "adaptive"] | None = None
    smoothing_stage: Literal["after", "before"] | None = None
    smoothing_target: Real | None = None
    """Adaptive smoothing's σ target, a fraction of the range (0.001–0.5)."""
    path_length_bounds: tuple[Real, Real] | None = None
    """[min, max] lamp → surface → camera path length, metres."""
    patch: PatchConfig | None = None
    lamp_off_interval: Annotated[Whole, Field(ge=0, le=100000)] | None = None
    backscatter: BackscatterConfig | None = None
    """Backscatter compensation in the loop ({"iterations": 2}); null switches it off."""
    exposure: ExposureConfig | None = None
    """Radiometric exposure control ({} for the defaults); null switches it off (the exposure stays where it is)."""
    vehicle_mask: Annotated[list[Box], Field(max_length=64)] | None = None
    """Regions [x, y, width, height] where the vehicle is in view: no range there."""
    orientation: OrientationConfig | None = None
    """Surface incidence angles in the loop ({"block": 16}); null switches them off."""
    temporal: TemporalConfig | None = None
    """Temporal fusion where the scene holds still ({"max_frames": 32}); null switches it off."""


@router.get("")
def get_config(d: Daemon = Depends(get_daemon)) -> dict:
    """The live-tunable processing settings."""
    return d.pipeline.processing.model_dump(mode="json")


@router.patch("")
def patch_config(change: ProcessingPatch, d: Daemon = Depends(get_daemon)) -> dict:
    """Change processing settings; validated before they apply, the previous ones kept on error."""
    current = d.pipeline.processing.model_dump()
    update = change.model_dump(exclude_unset=True)
    if update.pop("fuse", None):
        current["pair"] = None
    current.update(update)
    try:
        new = ProcessingConfig.model_validate(current)
    except ValidationError as exc:
        raise HTTPException(status_code=422, detail=exc.errors(include_url=False, include_context=False,
                                                                include_input=False)) from None
    names = d.pipeline.profile.channel_names
    if new.pair is not None and (len(set(new.pair)) != 2 or any(p not in names for p in new.pair)):
        raise HTTPException(status_code=422, detail=f"pair needs two different channels of {names}")
    try:
        d.pipeline.reconfigure(new)
    except ValueError as exc:  # e.g. a lamp-off interval without a lamp
        raise HTTPException(status_code=422, detail=str(exc)) from None
    d.save_state()
    return new.model_dump(mode="json")


@router.post("/restore")
def restore_config(d: Daemon = Depends(get_daemon)) -> dict:
    """Go back to the processing settings that were in force before the last change."""
    try:
        restored = d.pipeline.restore()
    except ValueError as exc:
        raise HTTPException(status_code=409, detail=str(exc)) from None
    d.save_state()
    return restored.model_dump(mode="json")
