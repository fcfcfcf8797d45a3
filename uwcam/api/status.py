"""GET /api/v1/status: the health of every device and of the frame loop."""

from fastapi import APIRouter, Depends, Request

from uwcam.api.calibration_session import open_session
from uwcam.api.common import get_daemon
from uwcam.runtime.daemon import Daemon

router = APIRouter(prefix="/api/v1", tags=["status"])


@router.get("/status")
def status(request: Request, d: Daemon = Depends(get_daemon)) -> dict:
    """Health of every device, frame counters, fps, latency, calibration and tracking, rangefinder, lamp,
    and the open tank calibration session, if any (its id, state and number of captures)."""
    return {**d.status(), "calibration_session": open_session(request)}
