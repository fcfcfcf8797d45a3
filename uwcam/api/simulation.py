"""/api/v1/simulation/plate: the simulated tank's rail (``uwcam run --simulate tank``). GET says
where the calibration plate is; PUT moves it along the optical axis, as a crew slides the plate
along a tank's rail. Only a simulated camera looking at the plate scene has a rail: any other
camera answers 404 with the reason. Handlers are sync (threadpool): rendering the moved plate
takes seconds and never runs on the event loop.
"""

from __future__ import annotations

import threading
import time
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.common import get_daemon
from uwcam.config import TANK_RAIL_M
from uwcam.daemon import Daemon

router = APIRouter(prefix="/api/v1/simulation", tags=["simulation"])
# How long a move waits for the first frame of the moved plate to be published (s).
FIRST_FRAME_TIMEOUT_S = 10.0


class PlateMove(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    distance_m: Annotated[float, Field(ge=TANK_RAIL_M[0], le=TANK_RAIL_M[1], allow_inf_nan=False)]
    """Camera-to-plate distance along the optical axis (m), within the rail."""


def _tank(d: Daemon):
    """The simulated rig of the tank; 404 saying why when there is none."""
    if d.rig is None or d.config.camera.driver != "sim":
        raise HTTPException(status_code=404, detail="the camera is not simulated, so there is no simulated plate to move; "
                                                    "move the real plate and type its distance")
    if d.rig.scene != "plate":
        raise HTTPException(status_code=404, detail=f"the simulated camera looks at the {d.rig.scene} scene, not the tank; "
                                                    "start the simulated tank with: uwcam run --simulate tank")
    return d.rig


def _where(rig) -> dict:
    return {"distance_m": rig.distance, "moving_to_m": rig.placing_to, "rig": rig.plate_rig or "grey-plate",
            "rail_m": list(TANK_RAIL_M)}


@router.get("/plate")
def plate(d: Daemon = Depends(get_daemon)) -> dict:
    """Where the simulated plate is (m along the optical axis), and where a move in progress takes it."""
    return _where(_tank(d))


@router.put("/plate")
def move_plate(body: PlateMove, d: Daemon = Depends(get_daemon)) -> dict:
    """Move the simulated plate to ``distance_m``, keeping the exposure. Answers once the first frame
    showing the plate there has been published (rendering the new view takes seconds)."""
    rig = _tank(d)
    rig.place(body.distance_m)
    moved = time.monotonic_ns()
    shown = threading.Event()

    def seen(published) -> None:  # in the loop's thread: only note it
        if published.frame.host_monotonic_ns > moved:
            shown.set()

    d.pipeline.subscribe(seen)
    try:
        if not shown.wait(FIRST_FRAME_TIMEOUT_S):
            raise HTTPException(status_code=503, detail=f"the plate moved but no frame came in {FIRST_FRAME_TIMEOUT_S:g} s; "
                                                        "see /api/v1/status")
    finally:
        d.pipeline.unsubscribe(seen)
    return _where(rig)


__all__ = ["router"]
