"""GET /metrics: Prometheus text, from ``prometheus_client``.

Everything but the latency histogram is read from the daemon at scrape time by one custom
collector, so the frame loop never updates a metric. The latency histogram is observed per
published frame by a subscriber: one bucket increment under prometheus_client's lock, as cheap
as the stream's hand-off. The registry is the app's own (not the process-global one), with
prometheus_client's process collector (CPU, memory, open files) beside uwcam's metrics.

Names follow Prometheus's conventions (https://prometheus.io/docs/practices/naming/): base
units, plural and spelled as Prometheus spells them (``_seconds``, ``_meters``, ``_bytes``),
shares as ``_ratio`` between 0 and 1, counters ending in ``_total``, and times of events as
``_timestamp_seconds`` (an age is ``time() - …`` in PromQL, so it never goes stale between
scrapes). tests/test_metrics.py runs Prometheus's own ``promtool check metrics`` on the output.

What an operator alerts on: ``uwcam_device_up`` (and ``uwcam_device_state``) per device,
``uwcam_frames_dropped_total`` or ``uwcam_recorder_frames_dropped_total`` rising,
``uwcam_recording_disk_free_bytes`` falling, ``uwcam_rangefinder_reading_age_seconds`` growing,
``uwcam_patch_drift_per_meter`` beyond the water's usual change, ``uwcam_valid_pixels_ratio``
falling, ``uwcam_lamp_temperature_celsius`` climbing, ``uwcam_mavlink_sending`` at 0,
``time() - uwcam_calibration_created_timestamp_seconds`` beyond the calibration's useful life.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import datetime

import numpy as np
from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Histogram, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from uwcam.api.common import get_daemon
from uwcam.runtime.daemon import Daemon
from uwcam.optics.validity import Reason
from uwcam.runtime.published import Published

router = APIRouter(tags=["metrics"])
STATES = ("ok", "recovering", "lost", "stopped")
LATENCY_BUCKETS_S = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class DaemonCollector(Collector):
    """uwcam's state as Prometheus metrics, read when scraped."""

    def __init__(self, daemon: Daemon, app_state) -> None:
        self.daemon = daemon
        self.app_state = app_state

    def collect(self) -> Iterator[Metric]:
        s = self.daemon.status()
        frames = s["frames"]
        for name, doc in (("captured", "Frames delivered by the camera."),
                          ("processed", "Frames ranged and published by the frame loop."),
                          ("dropped", "Frames dropped: camera queue full, or skipped for a newer one.")):
            yield CounterMetricFamily(f"uwcam_frames_{name}", doc, value=frames[name])
        yield GaugeMetricFamily("uwcam_frames_per_second", "Processed frames per second, recent.", value=frames["fps"])
        yield GaugeMetricFamily("uwcam_uptime_seconds", "Seconds since the daemon started.", value=s["uptime_s"])

        health = {"camera": s["camera"]["health"]["state"] if s["camera"] else None,
                  "lamp": s["lamp"]["health"]["state"] if s["lamp"] else None,
                  "rangefinder": s["rangefinder"]["health"]["state"] if s["rangefinder"] else None}
        state = GaugeMetricFamily("uwcam_device_state", "1 for the device's present health state, 0 for the others.",
                                  labels=["device", "state"])
        up = GaugeMetricFamily("uwcam_device_up", "1 while the device is healthy (state ok).", labels=["device"])
        for device, current in health.items():
            if current is None:
                continue  # not configured
            for name in STATES:
                state.add_metric([device, name], float(current == name))
            up.add_metric([device], float(current == "ok"))
        yield state
        yield up

        lamp = s["lamp"]
        if lamp is not None:
            if lamp["on"] is not None:
                yield GaugeMetricFamily("uwcam_lamp_on", "1 while the lamp is on, as last reported.", value=float(lamp["on"]))
            if lamp["percent"] is not None:
                yield GaugeMetricFamily("uwcam_lamp_intensity_ratio", "Lamp intensity, 0 to 1 of full.",
                                        value=lamp["percent"] / 100.0)
            last = getattr(self.daemon.lamp, "last_status", None)
            if last is not None and last.temperature_c is not None:
                yield GaugeMetricFamily("uwcam_lamp_temperature_celsius", "Lamp temperature as last reported, °C.",
                                        value=last.temperature_c)

        rf = s["rangefinder"]
        if rf is not None and rf["age_s"] is not None:
            yield GaugeMetricFamily("uwcam_rangefinder_reading_age_seconds", "Age of the newest valid reading, s.",
                                    value=rf["age_s"])
            yield GaugeMetricFamily("uwcam_rangefinder_range_meters", "Newest valid range, m.", value=rf["range_m"])

        tracking = s["calibration"]["tracking"]
        if tracking is not None:
            drift = GaugeMetricFamily("uwcam_patch_drift_per_meter",
                                      "Tracked minus calibrated attenuation difference per channel, 1/m.", labels=["channel"])
            for channel, value in tracking["drift"].items():
                drift.add_metric([channel], value)
            yield drift
            std = GaugeMetricFamily("uwcam_calibration_attenuation_difference_std_per_meter",
                                    "The calibration's standard uncertainty of each attenuation difference, 1/m "
                                    "(0: not known); a drift beyond a few of these is a change of the water.",
                                    labels=["channel"])
            for channel, value in (tracking.get("drift_std") or {}).items():
                std.add_metric([channel], value)
            yield std
            yield CounterMetricFamily("uwcam_patch_frames_accepted", "Frames whose patch updated the tracking.",
                                      value=tracking["accepted"])
            yield CounterMetricFamily("uwcam_patch_frames_rejected", "Frames whose patch was rejected (saturated, "
                                      "dark, not found, outlier).", value=tracking["rejected"])

        published: Published | None = self.daemon.pipeline.latest if self.daemon.pipeline else None
        if published is not None:
            counts = np.bincount(published.result.reasons.ravel(), minlength=len(Reason))
            total = max(1, int(counts.sum()))
            yield GaugeMetricFamily("uwcam_valid_pixels_ratio", "Share of the newest range map's pixels with a range.",
                                    value=counts[Reason.VALID] / total)
            reasons = GaugeMetricFamily("uwcam_pixel_reason_ratio",
                                        "Share of the newest range map's pixels per validity reason.", labels=["reason"])
            for reason in Reason:
                reasons.add_metric([reason.name.lower()], counts[reason] / total)
            yield reasons
            yield from exposure_metrics(published)
            yield from range_metrics(published)

        yield from calibration_metrics(s["calibration"]["created"])
        yield from alert_metrics(s.get("alerts"))
        if s["recording"] is not None:
            yield from recorder_metrics(s["recording"])
        yield GaugeMetricFamily("uwcam_websocket_clients", "WebSocket stream clients connected now.",
                                value=getattr(self.app_state, "stream_clients", 0))
        if s["foxglove"] is not None:
            yield GaugeMetricFamily("uwcam_foxglove_clients", "Foxglove (or Lichtblick) clients connected now.",
                                    value=s["foxglove"]["clients"])
            yield CounterMetricFamily("uwcam_foxglove_frames_sent", "Frames sent to the Foxglove server.",
                                      value=s["foxglove"]["frames_sent"])

        mav = s.get("mavlink")
        if mav is not None:
            sent = CounterMetricFamily("uwcam_mavlink_messages_sent", "MAVLink messages sent, by message.",
                                       labels=["message"])
            for message, n in mav["sent"].items():
                sent.add_metric([message], n)
            yield sent
            yield CounterMetricFamily("uwcam_mavlink_send_errors", "MAVLink link failures (each followed by a reconnect).",
                                      value=mav["send_errors"])
            yield GaugeMetricFamily("uwcam_mavlink_sending", "1 while distances are being sent to the autopilot.",
                                    value=float(mav["sending"]))


def range_metrics(published: Published) -> Iterator[Metric]:
    """Centre and minimum range of the newest processed frame, as the Zenoh range summary gives them
    (docs/api.md, "Zenoh"); absent when the frame has too few valid pixels for them."""
    from uwcam.outputs.zenoh_publisher import range_summary

    summary = range_summary(published)
    if summary["centre_m"] is not None:
        yield GaugeMetricFamily("uwcam_range_centre_meters", "Median range of the central fifth of the newest "
                                "range map, m.", value=summary["centre_m"])
    if summary["minimum_m"] is not None:
        yield GaugeMetricFamily("uwcam_range_minimum_meters", "Smallest median range over small tiles of the "
                                "newest range map (the collision warning's figure), m.", value=summary["minimum_m"])


def alert_metrics(alerts: dict | None) -> Iterator[Metric]:
    """1 per alert uwcam itself holds raised (its own rules, uwcam.runtime.alerts)."""
    if alerts is None:
        return
    family = GaugeMetricFamily("uwcam_alert_active", "1 for each alert raised by uwcam's own rules and not cleared.",
                               labels=["alert", "severity"])
    for alert in alerts["active"]:
        family.add_metric([alert["key"], alert["severity"]], 1.0)
    yield family


def exposure_metrics(published: Published) -> Iterator[Metric]:
    """Exposure time and gain per channel of the newest processed frame, as the camera reported them."""
    exposure_us, gain_db = published.frame.exposures()
    names = published.frame.channel_names
    if exposure_us is not None:
        family = GaugeMetricFamily("uwcam_exposure_seconds", "Exposure time of the newest processed frame, per channel, s.",
                                   labels=["channel"])
        for name, t in zip(names, exposure_us):
            family.add_metric([name], t * 1e-6)
        yield family
    if gain_db is not None:
        family = GaugeMetricFamily("uwcam_gain_decibels", "Analogue gain of the newest processed frame, per channel, dB.",
                                   labels=["channel"])
        for name, g in zip(names, gain_db):
            family.add_metric([name], g)
        yield family


def calibration_metrics(created: str | None) -> Iterator[Metric]:
    """When the calibration in use was made (its provenance), as a Unix time."""
    if not created:
        return
    try:
        when = datetime.fromisoformat(created).timestamp()
    except ValueError:
        return  # a profile with an unreadable date: no metric rather than a wrong one
    yield GaugeMetricFamily("uwcam_calibration_created_timestamp_seconds",
                            "When the calibration in use was made, Unix time; its age is time() minus this.", value=when)


def recorder_metrics(recording: dict) -> Iterator[Metric]:
    """The recorder's counts (of the recording in progress or the last one) and the disk it writes to."""
    yield GaugeMetricFamily("uwcam_recording_active", "1 while a recording is being written.",
                            value=float(recording["state"] == "recording"))
    yield CounterMetricFamily("uwcam_recorder_frames_written", "Frames written to the recording (since it started).",
                              value=recording["frames_written"])
    yield CounterMetricFamily("uwcam_recorder_frames_dropped", "Raw frames the recorder dropped because the disk "
                              "fell behind, their metadata kept (since the recording started).",
                              value=recording["frames_dropped"])
    yield GaugeMetricFamily("uwcam_recording_size_bytes", "Bytes in the recording's files so far.", value=recording["bytes"])
    yield CounterMetricFamily("uwcam_recorder_frames_decimated", "Raw frames left out to keep within "
                              "recording.budget_mb_s (their metadata kept; since the recording started).",
                              value=recording["frames_decimated"])
    yield CounterMetricFamily("uwcam_recorder_frames_lost", "Frames of which not even the metadata could be kept "
                              "(since the recording started).", value=recording["frames_lost"])
    yield GaugeMetricFamily("uwcam_recorder_queue_bytes", "Bytes of frames waiting for the disk.",
                            value=recording["queued_mb"] * 1e6)
    free = recording["disk_free_bytes"]
    if free is not None:
        yield GaugeMetricFamily("uwcam_recording_disk_free_bytes", "Free bytes on the disk recordings go to.", value=free)
    if recording.get("disk_total_bytes"):
        yield GaugeMetricFamily("uwcam_recording_disk_size_bytes", "Size of the disk recordings go to, bytes.",
                                value=recording["disk_total_bytes"])


class Metrics:
    """The app's registry: uwcam's collector, the process collector and the latency histogram.

    ``observe`` is the frame loop subscriber; ``close`` unsubscribes it.
    """

    def __init__(self, daemon: Daemon, app_state) -> None:
        self.daemon = daemon
        self.registry = CollectorRegistry(auto_describe=True)
        # Registered (so read at a scrape) before the daemon's counters: a frame published during
        # the scrape then never makes the histogram count more frames than frames processed.
        self.latency = Histogram("uwcam_frame_latency_seconds", "Capture to publication of each processed frame, s.",
                                 buckets=LATENCY_BUCKETS_S, registry=self.registry)
        self.registry.register(DaemonCollector(daemon, app_state))
        ProcessCollector(registry=self.registry)
        daemon.pipeline.subscribe(self.observe)

    def observe(self, published: Published) -> None:  # in the frame loop's thread: one increment
        self.latency.observe(published.latency_s)

    def close(self) -> None:
        if self.daemon.pipeline is not None:
            self.daemon.pipeline.unsubscribe(self.observe)

    def text(self) -> bytes:
        return generate_latest(self.registry)


@router.get("/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
def metrics(request: Request, d: Daemon = Depends(get_daemon)) -> Response:
    """Prometheus text format (HELP and TYPE lines, counters, gauges, the latency histogram, process metrics)."""
    return Response(request.app.state.metrics.text(), media_type=CONTENT_TYPE_LATEST)
