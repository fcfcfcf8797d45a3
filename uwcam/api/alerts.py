"""GET /api/v1/alerts: the alerts active now and the recent raised and cleared events."""

from fastapi import APIRouter, Depends

from uwcam.api.common import get_daemon
from uwcam.runtime.daemon import Daemon

router = APIRouter(prefix="/api/v1", tags=["alerts"])


@router.get("/alerts")
def alerts(d: Daemon = Depends(get_daemon)) -> dict:
    """Alerts active now and the recent events (raised, cleared; newest last), each with its rule, subject,
    severity (MAVLink's names), message, time and since (Unix s) and the figures that raised or cleared it;
    and the rules in force (docs/api.md, "Alerts")."""
    if d.alerts is None:
        return {"active": [], "history": [], "rules": None, "error": None}
    return d.alerts.snapshot()
