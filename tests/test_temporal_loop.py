"""Temporal fusion in the daemon, on the simulated tank: a camera holding station on the grey plate,
then the plate moved along the rail.

Expected values come from outside the fuser: the simulator's own camera range of every pixel
(its ground truth), the spread of each pixel's range over frames measured with fusion off (the
frame-to-frame noise, which a running average of weight 1/M divides by √(2M − 1)), and the raw
image, which says which frame first shows the moved plate.
"""

from __future__ import annotations

import io
import json
import os
import socket
import threading
import time

import numpy as np
import pytest

from tests.served import Server
from tests.waiting import wait_for
from uwcam.config import ApiConfig, CameraConfig, DaemonConfig, DeviceConfig, MavlinkConfig, ProcessingConfig, TemporalConfig

TOKEN = "temporal-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
M = 8  # max_frames: beyond it a running average of weight 1/M, whose noise is that of 2M − 1 frames
SIM = {"scene": "plate", "distance": 3.0, "size": [320, 240], "water": "jerlov-IA", "lamp_offset": [0.3, 0.0, 0.0],
       "seed": 0}


class Collector:
    """Every published frame, kept (the callback only appends: it runs on the loop's thread)."""

    def __init__(self) -> None:
        self.frames: list = []
        self.lock = threading.Lock()

    def __call__(self, published) -> None:
        with self.lock:
            self.frames.append(published)

    def take(self, n: int, every: int = 1, timeout_s: float = 240.0) -> list:
        """The next n frames published from now, every ``every``-th of them."""
        with self.lock:
            start = len(self.frames)
        assert wait_for(lambda: len(self.frames) >= start + n * every, timeout_s, 0.05), "frames stopped coming"
        with self.lock:
            return self.frames[start: start + n * every: every]


def config(state_dir) -> DaemonConfig:
    return DaemonConfig(camera=CameraConfig(driver="sim", options={"fps": 10.0, "serial_number": "SIM-TEMPORAL"}),
                        lamp=DeviceConfig(driver="sim"), simulation=SIM, api=ApiConfig(token=TOKEN),
                        state_dir=str(state_dir))


@pytest.mark.slow
def test_holding_station_fusion_divides_the_noise_and_a_move_is_never_smeared(tmp_path):
    with Server(config(tmp_path)) as s:
        pipeline = s.daemon.pipeline
        assert wait_for(lambda: pipeline.latest is not None, 180.0)
        assert s.http.get("/api/v1/status").json()["temporal"] == {"enabled": False}
        # Writes need the token; every number is checked.
        assert s.http.patch("/api/v1/config", json={"temporal": {}}).status_code == 401
        for bad in ({"max_frames": 1}, {"max_frames": 1025}, {"max_frames": 8.5}, {"max_frames": True},
                    {"change_sigmas": 1.0}, {"change_sigmas": 101}, {"change_sigmas": "4"}, {"frames": 8}):
            r = s.http.patch("/api/v1/config", json={"temporal": bad}, headers=AUTH)
            assert r.status_code == 422, (bad, r.text)
        collect = Collector()
        pipeline.subscribe(collect)
        truth = s.daemon.rig.world.camera_range.astype(np.float64)

        off = collect.take(12)
        ranges = np.stack([p.result.range for p in off])
        plate = np.isfinite(truth) & np.all(np.isfinite(ranges), axis=0)
        assert plate.sum() > 1000, plate.sum()
        t2 = np.var(ranges[:, plate], axis=0, ddof=1)  # each pixel's frame-to-frame variance (m²)
        static2 = (np.mean(ranges[:, plate], axis=0) - truth[plate]) ** 2  # fixed pattern, calibration
        sigma2_off = np.median(np.stack([p.result.variance[plate] for p in off]), axis=0)
        assert all(p.frames is None for p in off)
        frames_off = np.load(io.BytesIO(s.http.get("/api/v1/snapshot/frames").content))
        assert frames_off.dtype == np.uint16 and set(np.unique(frames_off)) <= {0, 1}

        on = s.http.patch("/api/v1/config", json={"temporal": {"max_frames": M}}, headers=AUTH)
        assert on.status_code == 200 and on.json()["temporal"] == {"max_frames": M, "change_sigmas": 4.0, "motion_pixels": 0.5}
        with open(os.path.join(tmp_path, "uwcam-state.json")) as fh:
            saved = json.load(fh)
        assert ProcessingConfig.model_validate(saved["processing"]).temporal.max_frames == M  # kept for a restart
        assert wait_for(lambda: (s.http.get("/api/v1/status").json()["temporal"].get("median_frames") or 0) == M, 60.0, 0.2)
        status = s.http.get("/api/v1/status").json()["temporal"]
        assert status["enabled"] and status["max_frames"] == M and status["ms_per_frame"] > 0, status
        # Fused frames 3M apart: their running averages share (1 − 1/M)^(3M) ≈ 4 % of their weight.
        fused = collect.take(6, every=3 * M)
        assert all(np.mean(p.frames[plate] == M) > 0.95 for p in fused), [np.bincount(p.frames[plate]) for p in fused]
        ranges_on = np.stack([p.result.range[plate] for p in fused])
        assert np.isfinite(ranges_on).mean() > 0.99
        served = np.load(io.BytesIO(s.http.get("/api/v1/snapshot/frames").content))
        assert served.shape == truth.shape and s.http.get("/api/v1/snapshot/frames?format=png").status_code == 422
        assert s.http.get("/api/v1/snapshot/frames?format=tiff").headers["content-type"] == "image/tiff"

        # The frame-to-frame spread: √(2M − 1) = 3.9 times smaller (pooled over the plate's pixels).
        spread_off = np.sqrt(np.mean(t2))
        spread_on = np.sqrt(np.nanmean(np.nanvar(ranges_on, axis=0, ddof=1)))
        assert spread_off / spread_on == pytest.approx(np.sqrt(2 * M - 1), rel=0.25), (spread_off, spread_on)
        # The reported σ² loses the frame-to-frame part, all but 1/(2M − 1) of it; the fixed
        # pattern and the calibration stay: σ_off² − σ_on² ≈ t²·(1 − 1/(2M − 1)).
        sigma2_on = np.median(np.stack([p.result.variance[plate] for p in fused]), axis=0)
        drop = np.median(sigma2_off - sigma2_on)
        assert drop == pytest.approx(np.median(t2) * (1 - 1 / (2 * M - 1)), rel=0.25), (drop, np.median(t2))
        # Honest: the errors against the simulator's truth are what σ says, and smaller than one frame's.
        error = ranges_on - truth[plate]
        z = error / np.sqrt(np.stack([p.result.variance[plate] for p in fused]))
        assert 0.8 < np.nanstd(z) < 1.25, np.nanstd(z)
        rms_on = np.sqrt(np.nanmean(error**2))
        assert rms_on == pytest.approx(np.sqrt(np.mean(static2) + np.mean(t2) / (2 * M - 1)), rel=0.25)

        # The plate moves 0.5 m closer: the first frames that show it range it at once, never a blend.
        before = np.mean(fused[-1].frame.data[plate].astype(np.float64))
        with collect.lock:
            start = len(collect.frames)
        assert s.http.put("/api/v1/simulation/plate", json={"distance_m": 2.5}, headers=AUTH).status_code == 202
        assert wait_for(lambda: s.http.get("/api/v1/simulation/plate").json()["moving_to_m"] is None, 180.0, 0.1)
        moved_truth = s.daemon.rig.world.camera_range.astype(np.float64)
        collect.take(4)
        with collect.lock:
            after = collect.frames[start:]
        # The first frame whose image is the moved plate's (brighter: 0.5 m nearer).
        first = next(k for k, p in enumerate(after) if np.mean(p.frame.data[plate].astype(np.float64)) > 1.2 * before)
        shown = after[first: first + 3]
        assert len(shown) == 3
        on_plate = np.isfinite(moved_truth)
        for k, p in enumerate(shown):
            seen = on_plate & np.isfinite(p.result.range)
            assert seen.sum() > 1000
            error = np.median(p.result.range[seen] / moved_truth[seen] - 1.0)
            assert abs(error) < 0.02, (k, error)
            assert np.mean(p.frames[seen] <= k + 1) > 0.95, (k, np.bincount(p.frames[seen]))

        # Off again: every range is its own frame's.
        assert s.http.patch("/api/v1/config", json={"temporal": None}, headers=AUTH).status_code == 200
        assert wait_for(lambda: s.http.get("/api/v1/status").json()["temporal"] == {"enabled": False}, 10.0)
        assert wait_for(lambda: pipeline.latest.frames is None, 10.0)
        pipeline.unsubscribe(collect)


class Autopilot:
    """A MAVLink peer on loopback that, once the daemon has sent it something, reports the vehicle's
    motion to it 20 times a second: ATTITUDE with ``turn`` rad/s of yaw rate and LOCAL_POSITION_NED
    with ``speed`` m/s northwards."""

    def __init__(self) -> None:
        from pymavlink.dialects.v20 import common as mavlink2

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.turn = self.speed = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="autopilot")

    def _run(self) -> None:
        peer = None
        started = time.monotonic()
        while not self._stop.is_set():
            try:
                _, peer = self.sock.recvfrom(65536)
            except socket.timeout:
                pass
            if peer is None:
                continue
            ms = int((time.monotonic() - started) * 1000)
            self.sock.sendto(self.mav.attitude_encode(ms, 0.0, 0.0, 0.0, 0.0, 0.0, self.turn).pack(self.mav), peer)
            self.sock.sendto(self.mav.local_position_ned_encode(ms, 0.0, 0.0, 3.0, self.speed, 0.0, 0.0).pack(self.mav), peer)

    def __enter__(self) -> "Autopilot":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


@pytest.mark.slow
def test_the_vehicle_turning_or_moving_over_mavlink_restarts_every_pixel(tmp_path):
    # The simulated view does not move: only the autopilot's word says the vehicle did.
    with Autopilot() as autopilot:
        cfg = config(tmp_path).model_copy(update={
            "mavlink": MavlinkConfig(connection=f"udpout:127.0.0.1:{autopilot.port}", rate_hz=20),
            "processing": ProcessingConfig(temporal=TemporalConfig(max_frames=M))})
        with Server(cfg) as s:
            pipeline = s.daemon.pipeline
            collect = Collector()
            pipeline.subscribe(collect)

            def temporal():
                return s.http.get("/api/v1/status").json()["temporal"]

            assert wait_for(lambda: temporal().get("median_frames") == M, 120.0, 0.2), temporal()
            # Reported still (the autopilot answers once the daemon's first message has reached it).
            assert wait_for(lambda: temporal()["vehicle_shift_px"] == 0.0, 30.0, 0.1), temporal()
            autopilot.turn = 0.2  # rad/s: at 10 frames/s about 0.02 rad, several pixels, a frame
            assert wait_for(lambda: "the vehicle moved" in temporal()["restarted"], 20.0, 0.1), temporal()
            turning = collect.take(5)
            assert all(np.max(p.frames) == 1 for p in turning), [np.bincount(p.frames.ravel()) for p in turning]
            assert temporal()["vehicle_shift_px"] > 0.5
            autopilot.turn = 0.0
            assert wait_for(lambda: temporal().get("median_frames") == M, 60.0, 0.2), temporal()
            # Moving at 0.5 m/s, the plate 3 m away: a frame's motion moves the image by pixels too.
            autopilot.speed = 0.5
            assert wait_for(lambda: temporal()["vehicle_shift_px"] > 0.5, 20.0, 0.1), temporal()
            moving = collect.take(5)
            assert all(np.max(p.frames) == 1 for p in moving), [np.bincount(p.frames.ravel()) for p in moving]
            pipeline.unsubscribe(collect)


@pytest.mark.slow
def test_a_recording_says_which_frames_were_fused_and_reprocessing_says_it_ranges_them_singly(tmp_path):
    from tests.test_recording import decoded, recording_config, running
    from uwcam.recording import format as rec
    from uwcam.recording.reprocess import reprocess

    cfg = recording_config(tmp_path, results=False)
    cfg.processing = ProcessingConfig(temporal=TemporalConfig(max_frames=M))
    path = str(tmp_path / "fused.mcap")
    with running(cfg) as d:
        d.recorder.start(path)
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 10, 60.0)
        d.recorder.stop()
    records = [r for _, r in decoded(path, rec.RANGING)]
    assert records and all(r["processing"]["temporal"] == {"max_frames": M, "change_sigmas": 4.0, "motion_pixels": 0.5}
                           for r in records)
    warnings: list[str] = []
    reprocess([path], str(tmp_path / "again.mcap"), progress=False, warn=warnings.append)
    assert [w for w in warnings if f"{len(records)} frames were fused over time" in w and "as single frames" in w], warnings
