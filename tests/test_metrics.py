"""GET /metrics on a live server, parsed with prometheus_client's own text parser."""

import asyncio
import io

import numpy as np
import pytest
import websockets
from prometheus_client.parser import text_string_to_metric_families

from tests.served import Server
from tests.test_api import small_config
from tests.test_mavlink import Listener
from tests.waiting import wait_for
from uwcam.config import MavlinkConfig
from uwcam.drivers.sim_serial import SimulatedLampDevice


def scrape(server) -> tuple[str, dict]:
    response = server.http.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain; version=")
    return response.text, {f.name: f for f in text_string_to_metric_families(response.text)}


def value(families: dict, family: str, sample: str | None = None, **labels) -> float:
    matches = [s.value for s in families[family].samples
               if s.name == (sample or family) and all(s.labels.get(k) == v for k, v in labels.items())]
    assert len(matches) == 1, (family, sample, labels, families[family].samples)
    return matches[0]


@pytest.mark.slow
def test_metrics_describe_the_running_daemon():
    with Listener() as ear:
        config = small_config().model_copy(update={"mavlink": MavlinkConfig(connection=f"udpout:127.0.0.1:{ear.port}")})
        with Server(config) as s:
            assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["processed"] > 5, 30.0)
            assert wait_for(lambda: len(ear.of("DISTANCE_SENSOR")) >= 3, 15.0)

            async def with_client():
                async with websockets.connect(f"ws://127.0.0.1:{s.port}/api/v1/stream?rate=5") as ws:
                    await ws.recv()  # hello
                    return await asyncio.to_thread(scrape, s)

            text, during = asyncio.run(with_client())
            assert value(during, "uwcam_websocket_clients") == 1
            assert wait_for(lambda: value(scrape(s)[1], "uwcam_websocket_clients") == 0, 5.0)

            status = s.http.get("/api/v1/status").json()
            reasons = np.load(io.BytesIO(s.http.get("/api/v1/snapshot/reasons?format=npy").content))
            text, f = scrape(s)
            after = s.http.get("/api/v1/status").json()
            sent = len(ear.of("DISTANCE_SENSOR"))

    for family in ("uwcam_device_up", "uwcam_frames_dropped", "uwcam_frame_latency_seconds", "uwcam_valid_pixel_fraction"):
        assert f"# HELP {family}" in text
    assert "# TYPE uwcam_frame_latency_seconds histogram" in text and "# TYPE uwcam_frames_captured_total counter" in text

    assert f["uwcam_frames_processed"].type == "counter"
    processed = value(f, "uwcam_frames_processed", "uwcam_frames_processed_total")
    assert status["frames"]["processed"] <= processed <= after["frames"]["processed"]
    assert value(f, "uwcam_frames_captured", "uwcam_frames_captured_total") >= processed

    # The histogram saw every published frame since the app started, and its buckets add up.
    hist = f["uwcam_frame_latency_seconds"]
    assert hist.type == "histogram"
    count = value(f, "uwcam_frame_latency_seconds", "uwcam_frame_latency_seconds_count")
    assert 0 < count <= processed and value(f, "uwcam_frame_latency_seconds", "uwcam_frame_latency_seconds_bucket", le="+Inf") == count
    buckets = [s.value for s in hist.samples if s.name.endswith("_bucket")]
    assert buckets == sorted(buckets)
    mean_s = value(f, "uwcam_frame_latency_seconds", "uwcam_frame_latency_seconds_sum") / count
    assert 0 < mean_s < 2.0

    for device in ("camera", "lamp", "rangefinder"):
        assert value(f, "uwcam_device_up", device=device) == 1
        assert value(f, "uwcam_device_state", device=device, state="ok") == 1
        assert value(f, "uwcam_device_state", device=device, state="lost") == 0
    assert value(f, "uwcam_lamp_on") == 1
    assert value(f, "uwcam_lamp_temperature_celsius") == SimulatedLampDevice(None).temperature_c  # what the lamp says
    assert 0 <= value(f, "uwcam_rangefinder_reading_age_seconds") < 2.0
    assert value(f, "uwcam_rangefinder_range_metres") == pytest.approx(2.0, abs=0.01)
    assert {s.labels["channel"] for s in f["uwcam_patch_drift_per_metre"].samples} == {"R", "G", "B"}
    # Frames differ between the snapshot and the scrape; the valid share hardly moves.
    assert value(f, "uwcam_valid_pixel_fraction") == pytest.approx(np.mean(reasons == 0), abs=0.05)
    assert sum(s.value for s in f["uwcam_pixel_reason_fraction"].samples) == pytest.approx(1.0)
    assert value(f, "uwcam_mavlink_messages_sent", "uwcam_mavlink_messages_sent_total", message="DISTANCE_SENSOR") <= sent
    assert value(f, "uwcam_mavlink_messages_sent", "uwcam_mavlink_messages_sent_total", message="DISTANCE_SENSOR") >= 3
    assert value(f, "uwcam_mavlink_sending") == 1
    # prometheus_client's process collector, on the app's own registry.
    assert value(f, "process_cpu_seconds", "process_cpu_seconds_total") > 0
    assert value(f, "process_resident_memory_bytes") > 10e6
