"""GET /metrics: Prometheus text."""

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse

from uwcam.api.common import get_daemon
from uwcam.daemon import Daemon

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(d: Daemon = Depends(get_daemon)) -> str:
    """Prometheus text format."""
    s = d.status()
    lines = [
        "# TYPE uwcam_frames_captured_total counter", f"uwcam_frames_captured_total {s['frames']['captured']}",
        "# TYPE uwcam_frames_processed_total counter", f"uwcam_frames_processed_total {s['frames']['processed']}",
        "# TYPE uwcam_frames_dropped_total counter", f"uwcam_frames_dropped_total {s['frames']['dropped']}",
        "# TYPE uwcam_fps gauge", f"uwcam_fps {s['frames']['fps']}",
    ]
    if s["latency_ms"]:
        lines += ["# TYPE uwcam_latency_ms gauge",
                  f'uwcam_latency_ms{{quantile="0.5"}} {s["latency_ms"]["p50"]}',
                  f'uwcam_latency_ms{{quantile="0.99"}} {s["latency_ms"]["p99"]}']
    camera = s["camera"]["health"]["state"] if s["camera"] else "none"
    lines += ["# TYPE uwcam_camera_ok gauge", f"uwcam_camera_ok {int(camera == 'ok')}"]
    return "\n".join(lines) + "\n"
