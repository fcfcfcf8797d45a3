"""GET/PUT /api/v1/lamp: the lamp's state and intensity."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.common import get_daemon
from uwcam.config import Flag, Real
from uwcam.runtime.daemon import Daemon
from uwcam.drivers.base import DeviceLost, DriverError

router = APIRouter(prefix="/api/v1/lamp", tags=["lamp"])


class LampCommand(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    on: Flag | None = None
    intensity: Annotated[Real, Field(ge=0, le=100)] | None = None
    """Percent."""


@router.get("")
def get_lamp(d: Daemon = Depends(get_daemon)) -> dict:
    """The lamp: on or off, intensity (percent), temperature and faults where it reports them, health."""
    lamp = d.lamp  # read once: the daemon's stop clears it
    if lamp is None:
        raise HTTPException(status_code=404, detail="no lamp configured")
    try:
        s = lamp.status()
    except DriverError as exc:  # silent, unplugged or refusing: say so; /api/v1/status has its health
        raise HTTPException(status_code=503, detail=f"the lamp does not answer: {exc}") from None
    return {"on": s.on, "intensity": s.percent, "temperature_c": s.temperature_c, "fault": s.fault,
            "health": lamp.health.as_dict()}


@router.put("")
def put_lamp(command: LampCommand, d: Daemon = Depends(get_daemon)) -> dict:
    """Switch the lamp on or off and set its intensity (`{"on": true, "intensity": 80}`, percent)."""
    lamp = d.lamp  # read once: the daemon's stop clears it
    if lamp is None:
        raise HTTPException(status_code=404, detail="no lamp configured")
    try:
        if command.intensity is not None:
            lamp.set_intensity(command.intensity)
        if command.on is True:
            lamp.on()
        elif command.on is False:
            lamp.off()
    except DeviceLost as exc:  # silent or unplugged: 503, as GET says (docs/api.md, "Errors")
        raise HTTPException(status_code=503, detail=f"the lamp does not answer: {exc}") from None
    except Exception as exc:  # it answered, and refused
        raise HTTPException(status_code=502, detail=f"lamp did not accept the command: {exc}") from None
    d.save_state()
    return get_lamp(d)  # reads the lamp's status back, so status() shows it too
