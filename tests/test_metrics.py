"""GET /metrics on a live server, parsed with prometheus_client's own text parser and checked
with Prometheus's own linter, ``promtool check metrics`` (Debian package prometheus)."""

import asyncio
import io
import re
import shutil
import subprocess
import time

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
            # The gauge is 0 whenever the newest frame is older than mavlink.max_age_s (0.5 s), which a
            # loaded machine reaches now and then; it must come back to 1 once frames are fresh again.
            assert wait_for(lambda: value(scrape(s)[1], "uwcam_mavlink_sending") == 1, 15.0)

    for family in ("uwcam_device_up", "uwcam_frames_dropped", "uwcam_frame_latency_seconds", "uwcam_valid_pixels_ratio"):
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
    assert value(f, "uwcam_lamp_intensity_ratio") == pytest.approx(status["lamp"]["percent"] / 100)
    assert value(f, "uwcam_lamp_temperature_celsius") == SimulatedLampDevice(None).temperature_c  # what the lamp says
    assert 0 <= value(f, "uwcam_rangefinder_reading_age_seconds") < 2.0
    assert value(f, "uwcam_rangefinder_range_meters") == pytest.approx(2.0, abs=0.01)
    assert {s.labels["channel"] for s in f["uwcam_patch_drift_per_meter"].samples} == {"R", "G", "B"}
    # Frames differ between the snapshot and the scrape; the valid share hardly moves.
    assert value(f, "uwcam_valid_pixels_ratio") == pytest.approx(np.mean(reasons == 0), abs=0.05)
    assert sum(s.value for s in f["uwcam_pixel_reason_ratio"].samples) == pytest.approx(1.0)
    assert value(f, "uwcam_mavlink_messages_sent", "uwcam_mavlink_messages_sent_total", message="DISTANCE_SENSOR") <= sent
    assert value(f, "uwcam_mavlink_messages_sent", "uwcam_mavlink_messages_sent_total", message="DISTANCE_SENSOR") >= 3
    assert value(f, "uwcam_mavlink_sending") in (0, 1)
    # prometheus_client's process collector, on the app's own registry.
    assert value(f, "process_cpu_seconds", "process_cpu_seconds_total") > 0
    assert value(f, "process_resident_memory_bytes") > 10e6


PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
NOT_PROMETHEUS_STYLE = re.compile(r"_(metres?|per_metre|fraction|percent|percentage|milliseconds|microseconds|"
                                  r"kilobytes|megabytes|celcius|fps)(_|$)")
"""Suffixes Prometheus's naming page (https://prometheus.io/docs/practices/naming/) replaces with
base units and ``_ratio``: promtool 2.42 flags only some of them (milli-/microseconds)."""


def promtool_check(text: str) -> subprocess.CompletedProcess:
    assert shutil.which("promtool") or __import__("os").path.exists(PROMTOOL), \
        "promtool is needed: .ci/run installs Debian's prometheus package"
    return subprocess.run([PROMTOOL, "check", "metrics"], input=text, capture_output=True, text=True, timeout=60)


def test_promtool_flags_what_it_should():
    """The linter is live: a counter without _total and a non-base unit fail it."""
    bad = "# HELP x_milliseconds t\n# TYPE x_milliseconds gauge\nx_milliseconds 1\n"
    checked = promtool_check(bad)
    assert checked.returncode != 0 and "base unit" in checked.stdout + checked.stderr


@pytest.mark.slow
def test_every_metric_passes_promtool_and_prometheus_naming(tmp_path):
    with Listener() as ear:
        config = small_config(token="t").model_copy(update={
            "mavlink": MavlinkConfig(connection=f"udpout:127.0.0.1:{ear.port}")})
        config.recording.folder = str(tmp_path)
        with Server(config) as s:
            assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["processed"] > 5, 30.0)
            assert s.http.post("/api/v1/recordings/start", headers={"Authorization": "Bearer t"}).status_code == 200
            assert wait_for(lambda: s.http.get("/api/v1/recordings/status").json()["frames_written"] > 2, 30.0)
            text, f = scrape(s)
            s.http.post("/api/v1/recordings/stop", headers={"Authorization": "Bearer t"})
    checked = promtool_check(text)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    names = {family.name for family in f.values()}
    assert not [n for n in names if NOT_PROMETHEUS_STYLE.search(n)]
    # What a monitor needs besides the frame loop: the recorder and its disk, exposure, calibration age.
    for family in ("uwcam_recorder_frames_written", "uwcam_recorder_frames_dropped", "uwcam_recording_size_bytes",
                   "uwcam_recording_disk_free_bytes", "uwcam_exposure_seconds", "uwcam_gain_decibels",
                   "uwcam_calibration_created_timestamp_seconds", "uwcam_recording_active"):
        assert family in f, family
    assert value(f, "uwcam_recorder_frames_written", "uwcam_recorder_frames_written_total") > 2
    assert value(f, "uwcam_recording_active") == 1 and value(f, "uwcam_recording_size_bytes") > 0
    assert value(f, "uwcam_recording_disk_free_bytes") == pytest.approx(shutil.disk_usage(tmp_path).free, rel=0.05)
    assert {s.labels["channel"] for s in f["uwcam_exposure_seconds"].samples} == {"R", "G", "B"}
    assert 0 < time.time() - value(f, "uwcam_calibration_created_timestamp_seconds") < 7 * 24 * 3600


def test_dropped_frames_metric_equals_the_status_count_when_frames_drop():
    """A backlogged loop (a subscriber that takes longer than a frame period) makes the loop drop
    frames; once the camera stops, the metric and the status agree, and neither is zero."""
    with Server(small_config()) as s:
        assert wait_for(lambda: s.daemon.pipeline.latest is not None, 60.0)

        def slow(published) -> None:  # runs in the loop's thread: 5 frame periods at 20 fps
            time.sleep(0.25)

        s.daemon.pipeline.subscribe(slow)
        try:
            assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["dropped"] >= 5, 60.0)
        finally:
            s.daemon.camera.stop()  # nothing more is captured, so nothing more can drop
            s.daemon.pipeline.unsubscribe(slow)
        counts = []  # the loop ranges what was queued, then the counts hold still

        def still() -> bool:  # unchanged for 2 s: the queue is drained and the loop idle
            frames = s.http.get("/api/v1/status").json()["frames"]
            counts.append((time.monotonic(), (frames["captured"], frames["processed"], frames["dropped"])))
            recent = [c for t, c in counts if t >= counts[-1][0] - 2.0]
            return counts[-1][0] - counts[0][0] > 2.0 and len(set(recent)) == 1 and len(recent) > 3

        assert wait_for(still, 30.0)
        status = s.http.get("/api/v1/status").json()["frames"]
        dropped = value(scrape(s)[1], "uwcam_frames_dropped", "uwcam_frames_dropped_total")
    assert dropped == status["dropped"] >= 5
    assert status["captured"] >= status["processed"] + status["dropped"] - 1
