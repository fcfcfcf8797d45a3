"""/api/v1/simulation/plate: the simulated tank's rail (``uwcam run --simulate tank``). GET says
where the calibration plate is; PUT moves it along the optical axis, as a crew slides the plate
along a tank's rail. Only a simulated camera looking at the plate scene has a rail: any other
camera answers 404 with the reason. Rendering the moved plate takes seconds: it runs in a thread
of its own, never on the event loop nor in a request.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.common import get_daemon
from uwcam.config import TANK_RAIL_M, Real
from uwcam.runtime.daemon import Daemon

router = APIRouter(prefix="/api/v1/simulation", tags=["simulation"])
log = logging.getLogger(__name__)
# One move starts at a time (checked and started together).
_MOVING = threading.Lock()
# How long a move waits for the first frame of the moved plate to be published (s).
FIRST_FRAME_TIMEOUT_S = 10.0


class PlateMove(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    distance_m: Annotated[Real, Field(ge=TANK_RAIL_M[0], le=TANK_RAIL_M[1])]
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


@router.get("")
def simulation(d: Daemon = Depends(get_daemon)) -> dict:
    """What is simulated: whether the camera is, its scene, and whether it is the tank (with a rail)."""
    simulated = d.rig is not None and d.config.camera.driver == "sim"
    scene = d.rig.scene if simulated else None
    return {"camera_simulated": simulated, "scene": scene, "tank": scene == "plate"}


@router.get("/plate")
def plate(d: Daemon = Depends(get_daemon)) -> dict:
    """Where the simulated plate is (m along the optical axis), and where a move in progress takes it."""
    return _where(_tank(d))


@router.put("/plate", status_code=202)
def move_plate(body: PlateMove, d: Daemon = Depends(get_daemon)) -> dict:
    """Start moving the simulated plate to ``distance_m``, keeping the exposure, and answer at once:
    rendering the new view takes seconds, meanwhile the camera goes on showing the plate where it was
    and GET says ``moving_to_m``. Once ``moving_to_m`` is null again, the newest published frame (the
    session's live feedback) shows the plate at ``distance_m``. 409 while an earlier move is under way."""
    rig = _tank(d)
    with _MOVING:
        if rig.placing_to is not None:
            raise HTTPException(status_code=409, detail=f"the plate is still moving to {rig.placing_to:g} m; "
                                                        "wait for it (GET shows moving_to_m null) and move it again")
        rig.placing_to = body.distance_m  # at once, so that a GET right after this answer sees the move
        threading.Thread(target=_move, args=(d, rig, body.distance_m), name="simulated-plate-move", daemon=True).start()
    return _where(rig)


def _move(d: Daemon, rig, distance_m: float) -> None:
    """Render the moved plate, swap it in, and call the move done once a frame taken after has been
    published: from then on the live feedback (the newest frame) shows the plate there."""
    try:
        rig.place(distance_m)
        moved = time.monotonic_ns()
        shown = threading.Event()

        def seen(published) -> None:  # in the loop's thread: only note it
            if published.frame.host_monotonic_ns > moved:
                shown.set()

        d.pipeline.subscribe(seen)
        try:
            if not shown.wait(FIRST_FRAME_TIMEOUT_S):
                log.warning("the simulated plate moved to %g m but no frame came in %g s", distance_m, FIRST_FRAME_TIMEOUT_S)
        finally:
            d.pipeline.unsubscribe(seen)
    except Exception:  # a failed render must not leave the rail stuck "moving"
        log.exception("moving the simulated plate to %g m failed", distance_m)
    finally:
        rig.placing_to = None


__all__ = ["router"]
