"""GET /api/v1/status: the health of every device and of the frame loop."""

from fastapi import APIRouter, Depends

from uwcam.api.common import get_daemon
from uwcam.daemon import Daemon

router = APIRouter(prefix="/api/v1", tags=["status"])


@router.get("/status")
def status(d: Daemon = Depends(get_daemon)) -> dict:
    """Health of every device, frame counters, fps, latency, calibration and tracking, rangefinder, lamp."""
    return d.status()
