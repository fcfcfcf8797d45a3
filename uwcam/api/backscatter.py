"""GET /api/v1/backscatter, POST/DELETE /api/v1/backscatter/open-water: backscatter compensation.

Compensation itself is switched on and tuned with the processing settings
(``PATCH /api/v1/config`` with ``{"backscatter": {"iterations": 2}}``, ``null`` to switch off).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.common import get_daemon
from uwcam.config import Real, Whole
from uwcam.runtime.daemon import Daemon

router = APIRouter(prefix="/api/v1/backscatter", tags=["backscatter"])


class OpenWaterRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    frames: Annotated[Whole, Field(ge=1, le=64)] = 4
    """Lamp-lit frames averaged into the open-water frame."""
    timeout_s: Annotated[Real, Field(ge=0.1, le=600)] = 10.0
    """Frames that come later than this are not taken: the request lapses."""


@router.get("")
def status(d: Daemon = Depends(get_daemon)) -> dict:
    """Whether backscatter is compensated, the open-water frame in use (origin, age), the cost per frame."""
    return d.pipeline.backscatter_status()


@router.post("/open-water", status_code=202)
def take_open_water(request: OpenWaterRequest | None = None, d: Daemon = Depends(get_daemon)) -> dict:
    """Start averaging the next lamp-lit frames into the open-water frame (point the camera at
    open water first: nothing in range of the lamp). Answers at once; ``GET /api/v1/backscatter``
    says when it is in use (``open_water``) or that no frames came in time (``capture``). Kept
    beside the profiles, so it survives a restart."""
    request = request or OpenWaterRequest()
    d.pipeline.request_open_water(request.frames, request.timeout_s)
    return d.pipeline.backscatter_status()


@router.delete("/open-water")
def forget_open_water(d: Daemon = Depends(get_daemon)) -> dict:
    """Stop using the open-water frame; backscatter then comes from the calibration's black patch alone."""
    d.forget_open_water()
    return d.pipeline.backscatter_status()
