"""The daemon over HTTP and WebSocket: a real uvicorn server on an ephemeral port, real clients."""

import asyncio
import io
import json
import struct

import cv2
import numpy as np
import pytest
import websockets

from tests.served import Server
from tests.waiting import wait_for
from uwcam.api import HEADER, create_app
from uwcam.cli import main
from uwcam.config import ApiConfig, CameraConfig, DaemonConfig, DeviceConfig
from uwcam.drivers.sim import SimulatedCamera
from uwcam.fileio import UserInputError
from uwcam.optics.validity import Reason

SERIAL = "SIM-API"


def small_config(token=None) -> DaemonConfig:
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 20.0, "serial_number": SERIAL}, watchdog_s=0.5),
        lamp=DeviceConfig(driver="sim"),
        rangefinder=DeviceConfig(driver="sim-ping1d", options={"rate_hz": 20}),
        simulation={"scene": "seabed-patch", "distance": 2.0, "size": [160, 120], "water": "jerlov-IB",
                    "lamp_offset": [0.3, 0.0, 0.0], "material": "grey"},
        api=ApiConfig(token=token),
    )


@pytest.fixture(scope="module")
def server():
    with Server(small_config()) as s:
        assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["processed"] > 2, 30.0)
        yield s


def test_status_reports_devices_and_moving_figures(server):
    first = server.http.get("/api/v1/status").json()
    assert wait_for(lambda: server.http.get("/api/v1/status").json()["frames"]["processed"] > first["frames"]["processed"] + 3)
    s = server.http.get("/api/v1/status").json()
    assert s["camera"]["health"]["state"] == "ok" and s["camera"]["device"]["serial_number"] == SERIAL
    assert s["frames"]["captured"] >= s["frames"]["processed"] > 0
    # fps counts frames in the last 2 s: right after start it still includes the first frame's wait.
    assert wait_for(lambda: server.http.get("/api/v1/status").json()["frames"]["fps"] > 5, 20.0)
    assert s["latency_ms"]["p99"] >= s["latency_ms"]["p50"] > 0
    assert s["calibration"]["name"] == "simulated tank calibration"
    assert s["calibration"]["tracking"]["state"] == "tracking" and abs(s["calibration"]["tracking"]["drift"]["G"]) < 0.01
    assert s["rangefinder"]["range_m"] == pytest.approx(2.0, abs=0.01) and s["rangefinder"]["confidence"] == pytest.approx(0.97)


def wait_for_lit_frames(server) -> None:
    """Wait until frames published after now are lamp-lit ranges: a test before this one (in a
    random order) may just have switched the lamp back on or taken a dark frame."""
    n = server.daemon.pipeline.processed

    def lit():
        latest = server.daemon.pipeline.latest
        return (server.daemon.pipeline.processed > n + 2 and latest.frame.lamp_on
                and np.isfinite(latest.result.range[latest.result.reasons != Reason.VEHICLE]).mean() > 0.95)

    assert wait_for(lit, 20.0), "no lamp-lit frame with a range"


def same_frame(server, *paths):
    """Responses for ``paths`` that all come from one published frame (same X-Frame-Number)."""
    for _ in range(100):
        responses = [server.http.get(p) for p in paths]
        if len({r.headers["x-frame-number"] for r in responses}) == 1:
            return responses
    raise AssertionError("could not fetch two snapshots of one frame")


def pixel_rays_of(profile: dict, h: int, w: int) -> np.ndarray:
    """Unit rays from the profile's pinhole intrinsics, written out: ((j − cx)/fx, (i − cy)/fy, 1)."""
    k = profile["intrinsics"]
    x = (np.arange(w) - k["cx"]) / k["fx"]
    y = (np.arange(h) - k["cy"]) / k["fy"]
    rays = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((h, w))), axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def outside_vehicle(server, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) True outside the vehicle mask (the simulated rig masks the patch's bracket)."""
    keep = np.ones(shape, bool)
    for x, y, w, h in server.daemon.pipeline.processing.vehicle_mask:
        keep[y : y + h, x : x + w] = False
    return keep


def assert_close_to_truth(r: np.ndarray, var: np.ndarray, truth: np.ndarray, keep: np.ndarray) -> None:
    """Errors against the simulator's own geometry, judged by the uncertainty published with them.

    The simulated camera has ~9 cm of noise per pixel at 2 m here, so per-pixel errors are
    that large; but they must be what the variance map says (|error|/σ has median 0.67 for
    unbiased Gaussian errors), and the model error common to all pixels (backscatter and
    forward scatter the transform ignores, calibration) stays under 10 cm."""
    err = r - truth
    assert np.isfinite(r[keep]).mean() > 0.95 and not np.isfinite(r[~keep]).any()
    assert abs(np.nanmedian(err)) < 0.1, np.nanmedian(err)
    assert np.nanmedian(np.abs(err) / np.sqrt(var)) < 1.2


def assert_millimetres(mm: np.ndarray, metres: np.ndarray) -> None:
    """uint16 millimetres equal to the metres to within the rounding (½ mm), 0 exactly where invalid."""
    ok = np.isfinite(metres)
    assert mm.dtype == np.uint16 and mm.shape == metres.shape
    np.testing.assert_array_equal(mm == 0, ~ok)
    assert np.max(np.abs(mm[ok] - metres[ok].astype(np.float64) * 1000.0)) <= 0.5 + 1e-3


def test_snapshots_match_the_simulated_truth(server):
    truth = server.daemon.rig.world.camera_range
    wait_for_lit_frames(server)
    npy, png16, var_npy, var_tiff = same_frame(server, "/api/v1/snapshot/range?format=npy", "/api/v1/snapshot/range?format=png16",
                                               "/api/v1/snapshot/variance?format=npy", "/api/v1/snapshot/variance?format=tiff")
    r = np.load(io.BytesIO(npy.content))
    var = np.load(io.BytesIO(var_npy.content))
    assert r.shape == truth.shape == var.shape
    assert_close_to_truth(r, var, truth, outside_vehicle(server, r.shape))
    # The same frame in millimetres: equal to the metres to the rounding (½ mm), 0 where invalid.
    mm = cv2.imdecode(np.frombuffer(png16.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert_millimetres(mm, r)
    assert var_tiff.headers["content-type"] == "image/tiff" and int(var_tiff.headers["x-frame-number"]) > 0
    import tifffile

    np.testing.assert_array_equal(tifffile.imread(io.BytesIO(var_tiff.content)), var)
    image = server.http.get("/api/v1/snapshot/image?format=png")
    assert cv2.imdecode(np.frombuffer(image.content, np.uint8), cv2.IMREAD_UNCHANGED).shape == (120, 160, 3)
    bad = server.http.get("/api/v1/snapshot/variance?format=png16")
    assert bad.status_code == 422 and "png16 is for the range map" in bad.json()["detail"]
    assert server.http.get("/api/v1/snapshot/depth").status_code == 422


def test_websocket_stream_decodes_to_the_range_map(server):
    """Frames from the stream equal the snapshot of the same frame to the millimetre."""
    async def client():
        async with websockets.connect(f"ws://127.0.0.1:{server.port}/api/v1/stream?encoding=mm&rate=10") as ws:
            hello = json.loads(await ws.recv())
            frames, telemetry, snapshots = [], [], {}
            while not telemetry or not (set(struct.unpack_from("<I", f, 4)[0] for f in frames) & set(snapshots)):
                assert len(frames) < 200, "no stream frame matched a snapshot"
                msg = await asyncio.wait_for(ws.recv(), 10.0)
                if isinstance(msg, bytes):
                    frames.append(msg)
                    snap = await asyncio.to_thread(server.http.get, "/api/v1/snapshot/range?format=npy")
                    snapshots[int(snap.headers["x-frame-number"])] = np.load(io.BytesIO(snap.content))
                else:
                    telemetry.append(msg)
            return hello, frames, json.loads(telemetry[0]), snapshots

    hello, frames, telemetry, snapshots = asyncio.run(client())
    assert hello["type"] == "hello" and hello["binary"]["header"] == "<4sIqqHHB3xf"
    frame = next(f for f in frames if struct.unpack_from("<I", f, 4)[0] in snapshots)
    magic, number, captured, sent, w, h, dtype, scale = HEADER.unpack_from(frame)
    assert magic == b"UWR1" and (w, h) == (160, 120) and dtype == 2 and scale == pytest.approx(0.001)
    assert sent >= captured
    numbers = [struct.unpack_from("<I", f, 4)[0] for f in frames]
    assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
    mm = np.frombuffer(frame[HEADER.size:], "<u2").reshape(h, w)
    assert_millimetres(mm, snapshots[number])
    assert telemetry["type"] == "telemetry" and telemetry["frames"]["processed"] > 0


def test_lamp_control_and_dark_frames(server):
    assert server.http.put("/api/v1/lamp", json={"on": False}).json()["on"] is False
    assert wait_for(lambda: server.daemon.pipeline.latest.frame.lamp_on is False)
    dark = np.load(io.BytesIO(server.http.get("/api/v1/snapshot/reasons").content))
    assert (dark != 0).mean() > 0.9  # nothing to range without the lamp
    lamp = server.http.put("/api/v1/lamp", json={"on": True, "intensity": 80}).json()
    assert lamp["on"] is True and lamp["intensity"] == 80 and lamp["health"]["state"] == "ok"
    bad = server.http.put("/api/v1/lamp", json={"intensity": 140})
    assert bad.status_code == 422
    assert server.http.put("/api/v1/lamp", json={"on": True, "intensity": 100}).status_code == 200
    wait_for_lit_frames(server)  # leave the daemon as the other tests expect it


def test_config_patch_is_validated_before_it_applies(server):
    assert server.http.get("/api/v1/config").json()["smoothing"] == "none"
    changed = server.http.patch("/api/v1/config", json={"smoothing": "mean"})
    assert changed.status_code == 200 and changed.json()["smoothing"] == "mean"
    bad = server.http.patch("/api/v1/config", json={"smoothing": "gaussian"})
    assert bad.status_code == 422 and "smoothing" in json.dumps(bad.json())
    assert server.http.patch("/api/v1/config", json={"pair": ["G", "X"]}).status_code == 422
    assert server.http.patch("/api/v1/config", json={"colour": 1}).status_code == 422
    assert server.http.get("/api/v1/config").json()["smoothing"] == "mean"  # the bad ones changed nothing
    server.http.patch("/api/v1/config", json={"smoothing": "none"})


def test_metrics_in_prometheus_text(server):
    text = server.http.get("/metrics").text
    assert "uwcam_frames_processed_total" in text and 'uwcam_frame_latency_seconds_bucket{le="+Inf"}' in text


def test_camera_lost_mid_dive_is_reported_and_recovered(server):
    SimulatedCamera.unplug(SERIAL)
    try:
        assert wait_for(lambda: server.http.get("/api/v1/status").json()["camera"]["health"]["state"] != "ok")
        state = server.http.get("/api/v1/status").json()["camera"]["health"]
        assert state["state"] in ("recovering", "lost") and "unplugged" in state["reason"]
        frozen = server.daemon.pipeline.processed
        assert not wait_for(lambda: server.daemon.pipeline.processed > frozen + 1, 1.0)  # no stale frames as new
    finally:
        SimulatedCamera.plug(SERIAL)
    assert wait_for(lambda: server.http.get("/api/v1/status").json()["camera"]["health"]["state"] == "ok", 20.0)
    n = server.daemon.pipeline.processed
    assert wait_for(lambda: server.daemon.pipeline.processed > n + 3)


def test_state_changes_need_the_token():
    with Server(small_config(token="s3cret")) as s:
        assert s.http.get("/api/v1/status").status_code == 200  # reading stays open
        denied = s.http.put("/api/v1/lamp", json={"on": False})
        assert denied.status_code == 401 and "Authorization: Bearer" in denied.json()["detail"]
        ok = s.http.put("/api/v1/lamp", json={"on": False}, headers={"Authorization": "Bearer s3cret"})
        assert ok.status_code == 200
    config = small_config()
    config.api.host = "0.0.0.0"
    with pytest.raises(UserInputError, match="refusing to listen on 0.0.0.0 without a token"):
        create_app(config)


def test_config_check_command(tmp_path, capsys):
    good = tmp_path / "rig.yaml"
    good.write_text("version: 1\ncamera: {driver: sim}\napi: {port: 9000}\n")
    assert main(["config", "check", str(good)]) == 0
    assert "valid (camera sim, API 127.0.0.1:9000)" in capsys.readouterr().out
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\ncamera: {driver: genicam, queue_size: 0}\n")
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "key 'camera.queue_size': Input should be greater than or equal to 1" in err and str(bad) in err
    open_net = tmp_path / "open.yaml"
    open_net.write_text("version: 1\napi: {host: 0.0.0.0}\n")
    assert main(["config", "check", str(open_net)]) == 2
    assert "without a token" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["sim-rig.yaml", "v4l2-rig.yaml", "gige-rig.yaml"])
def test_deploy_examples_are_valid(name, monkeypatch, capsys):
    from pathlib import Path

    monkeypatch.setenv("UWCAM_TOKEN", "from-the-environment")
    path = Path(__file__).resolve().parent.parent / "deploy" / name
    assert main(["config", "check", str(path)]) == 0, capsys.readouterr().err


def test_calibration_profiles_upload_validate_activate(server):
    import yaml

    profiles = server.http.get("/api/v1/calibration/profiles").json()
    active = [p for p in profiles if p["active"]]
    assert len(active) == 1 and active[0]["channels"] == ["R", "G", "B"]
    original = server.http.get(f"/api/v1/calibration/profiles/{active[0]['name']}").json()
    corrupt = dict(original, channels=original["channels"][:1])
    bad = server.http.put("/api/v1/calibration/profiles/broken", content=yaml.safe_dump(corrupt))
    assert bad.status_code == 422 and "key 'channels': List should have at least 2 items" in bad.json()["detail"]
    assert server.http.put("/api/v1/calibration/profiles/junk", content=b"\x00\xff: [").status_code == 422
    assert server.http.get("/api/v1/status").json()["calibration"]["name"] == active[0]["name"]  # unchanged
    tweaked = dict(original, name="second")
    ok = server.http.put("/api/v1/calibration/profiles/second", content=yaml.safe_dump(tweaked))
    assert ok.status_code == 200 and ok.json()["active"] is False
    assert server.http.post("/api/v1/calibration/profiles/second/activate").json()["active"] is True
    assert server.http.get("/api/v1/status").json()["calibration"]["name"] == "second"
    assert server.http.post("/api/v1/calibration/profiles/nope/activate").status_code == 404
    server.http.post(f"/api/v1/calibration/profiles/{active[0]['name']}/activate")


def test_config_restore_and_pointcloud(server):
    server.http.patch("/api/v1/config", json={"smoothing": "median"})
    server.http.patch("/api/v1/config", json={"smoothing": "mean"})
    assert server.http.post("/api/v1/config/restore").json()["smoothing"] == "median"
    server.http.patch("/api/v1/config", json={"smoothing": "none"})
    wait_for_lit_frames(server)  # and made with the settings restored
    response, npy, var_npy = same_frame(server, "/api/v1/snapshot/pointcloud", "/api/v1/snapshot/range?format=npy",
                                        "/api/v1/snapshot/variance?format=npy")
    assert response.status_code == 200, response.text
    ply = response.content
    head, _, body = ply.partition(b"end_header\n")
    count = int(head.split(b"element vertex ")[1].split(b"\n")[0])
    points = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                                        ("nz", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    r = np.load(io.BytesIO(npy.content)).astype(np.float64)
    ok = np.isfinite(r)
    assert count == len(points) == ok.sum() > 0.9 * 160 * 120
    # Each point is the range along its pixel's ray, to float32 precision.
    profile = server.http.get(f"/api/v1/calibration/profiles/{server.daemon.profile_name}").json()
    rays = pixel_rays_of(profile, *r.shape)
    xyz = r[ok, None] * rays[ok]
    for axis, name in enumerate("xyz"):
        np.testing.assert_allclose(points[name], xyz[:, axis], atol=1e-5)
    # And the seabed where the simulator put it: z of the true points, judged by the published σ.
    truth = server.daemon.rig.world.camera_range
    var = np.load(io.BytesIO(var_npy.content))
    z_err = points["z"] - (truth * rays[..., 2])[ok]
    # Judged away from the image border (a tenth on each side), where the lamp barely reaches and
    # the noise model is least exact (reported apart: bench/accuracy).
    inner = np.zeros_like(ok)
    inner[r.shape[0] // 10 : -(r.shape[0] // 10), r.shape[1] // 10 : -(r.shape[1] // 10)] = True
    inside = inner[ok]
    ratio = np.abs(z_err[inside]) / (np.sqrt(var[ok][inside]) * rays[ok][inside][:, 2])
    assert abs(np.median(z_err)) < 0.1 and np.median(ratio) < 1.2, (np.median(z_err), np.median(ratio))
    assert b"property float nx" in head and np.median(points["nz"]) < -0.9  # the flat seabed's normal faces the camera


@pytest.mark.slow
def test_schemathesis_finds_no_server_errors(tmp_path):
    """Property-based requests from the OpenAPI schema against the live server: no 500s."""
    import subprocess
    import sys
    from pathlib import Path

    # The schemathesis CLI installed beside this interpreter (in .venv), PATH or not.
    st = Path(sys.executable).with_name("st")
    assert st.exists(), "schemathesis is part of the test dependencies"
    cfg = small_config()
    cfg.recording.folder = str(tmp_path / "recordings")  # the fuzzer starts recordings too
    with Server(cfg) as s:
        assert wait_for(lambda: s.daemon.pipeline.latest is not None, 30.0)
        run = subprocess.run([str(st), "run", f"{s.url}/openapi.json", "--checks", "not_a_server_error", "-n", "30",
                              "--generation-deterministic", "--request-timeout", "20"],
                             capture_output=True, text=True, timeout=600, cwd=tmp_path)  # its cache stays out of the tree
    assert run.returncode == 0, run.stdout[-4000:]


def test_rangefinder_fixes_reflectance_and_pauses_when_silent(server):
    def reflectance():
        return server.http.get("/api/v1/status").json()["calibration"]["reflectance"]

    assert wait_for(lambda: reflectance()["state"] == "correcting", 20.0)
    ratio = reflectance()["reflectance_ratio_to_target"]
    # Grey seabed, grey plate: the same hue, so the ratio to the target is ~1 in every channel.
    assert all(abs(v - 1.0) < 0.1 for v in ratio.values()), ratio
    sonar = server.daemon.rangefinder.device
    sonar.disconnect()
    try:
        assert wait_for(lambda: reflectance()["state"].startswith("paused"), 20.0)
        assert "rangefinder" in reflectance()["state"] or "reading" in reflectance()["state"]
        n = server.daemon.pipeline.processed
        assert wait_for(lambda: server.daemon.pipeline.processed > n + 3)  # ranging goes on meanwhile
    finally:
        sonar.reconnect()
    assert wait_for(lambda: reflectance()["state"] == "correcting", 20.0)


def test_uploaded_profiles_persist_in_the_profiles_folder(tmp_path):
    import yaml

    config = small_config()
    config.profiles_dir = str(tmp_path / "profiles")
    with Server(config) as s:
        active = next(p for p in s.http.get("/api/v1/calibration/profiles").json() if p["active"])
        body = s.http.get(f"/api/v1/calibration/profiles/{active['name']}").json()
        assert s.http.put("/api/v1/calibration/profiles/tank-2026", content=yaml.safe_dump(body)).status_code == 200
    saved = tmp_path / "profiles" / "tank-2026.yaml"
    assert saved.exists()
    (tmp_path / "profiles" / "broken.yaml").write_text("format: nonsense\n")
    with Server(config) as s:  # a restart finds it again; the broken file is skipped, not fatal
        names = [p["name"] for p in s.http.get("/api/v1/calibration/profiles").json()]
        assert "tank-2026" in names and "broken" not in names


def test_smoothing_before_the_transform(server):
    assert server.http.patch("/api/v1/config", json={"smoothing": "mean", "smoothing_stage": "before"}).status_code == 200
    n = server.daemon.pipeline.processed
    assert wait_for(lambda: server.daemon.pipeline.processed > n + 2)
    r = np.load(io.BytesIO(server.http.get("/api/v1/snapshot/range").content))
    assert np.isfinite(r[outside_vehicle(server, r.shape)]).mean() > 0.9
    server.http.patch("/api/v1/config", json={"smoothing": "none", "smoothing_stage": "after"})


def test_lamp_off_frames_remove_daylight():
    """With strong daylight, subtracting a lamp-off frame every few frames restores the range."""
    def errors(interval):
        config = small_config()
        # No patch in view and no rangefinder: patch tracking and reflectance correction would
        # absorb daylight bias at their own ranges only, and hide the effect being tested.
        config.simulation["scene"] = "seabed"
        config.rangefinder = None
        config.simulation["ambient"] = [1e-6, 6e-5, 1.2e-4]  # daylight at depth: the red long gone
        config.processing.lamp_off_interval = interval
        with Server(config) as s:
            truth = s.daemon.rig.world.camera_range
            assert wait_for(lambda: s.daemon.pipeline.processed > 8, 30.0)
            if interval:
                assert wait_for(lambda: s.daemon.pipeline.stats()["ambient_frames"] >= 2, 20.0)
                # Back on after each dark frame (the next one may be under way at any moment: wait).
                assert wait_for(lambda: s.daemon.rig.lamp_on, 5.0)
                latest = s.daemon.pipeline.latest
                assert latest.frame.lamp_on is True  # dark frames are not published as ranges
            r = np.load(io.BytesIO(s.http.get("/api/v1/snapshot/range").content))
            return np.nanmedian(np.abs(r - truth))

    plain, corrected = errors(0), errors(4)
    print(f"daylight: median |error| {plain:.3f} m plain, {corrected:.3f} m with lamp-off frames")
    assert corrected < 0.5 * plain and corrected < 0.2, (plain, corrected)


def test_lamp_off_interval_is_live_tunable_and_errors_are_json(server):
    changed = server.http.patch("/api/v1/config", json={"lamp_off_interval": 6})
    assert changed.status_code == 200 and changed.json()["lamp_off_interval"] == 6
    assert wait_for(lambda: server.daemon.pipeline.stats()["ambient_frames"] >= 1, 20.0)
    assert server.http.patch("/api/v1/config", json={"lamp_off_interval": -1}).status_code == 422
    server.http.patch("/api/v1/config", json={"lamp_off_interval": 0})
    assert wait_for(lambda: server.daemon.rig.lamp_on)
    bad = server.http.put("/api/v1/calibration/profiles/x", content=b"[1, 2]")
    assert bad.status_code == 422 and bad.headers["content-type"].startswith("application/json")


def test_lamp_comes_back_on_after_a_failed_switch():
    """A serial glitch when switching back on after a dark frame is retried; the lamp does not stay off."""
    from types import SimpleNamespace

    from uwcam.config import ProcessingConfig
    from uwcam.drivers.base import DeviceLost, Frame
    from uwcam.runtime.pipeline import FramePipeline
    from tests.synthetic import make_profile

    calls = []

    class FlakyLamp:
        last_status = None

        def on(self):
            calls.append("on")
            if calls.count("on") == 1:
                raise DeviceLost("garbled reply")

        def off(self):
            calls.append("off")

    pipeline = FramePipeline(SimpleNamespace(), make_profile([0.46, 0.11, 0.06], [0, 0, 0]),
                             ProcessingConfig(lamp_off_interval=2), lamp=FlakyLamp())
    commander = pipeline._lamp_commander
    commander.backoff_s = (0.01, 0.05)
    commander.start()
    try:
        data = np.full((4, 4, 3), 1000, np.uint16)
        lit = True
        for k in range(12):
            pipeline._process(Frame(data=data, sequence=k, host_monotonic_ns=k, wall_time=0.0, lamp_on=lit))
            # What the lamp really does: off once acknowledged, on once an "on" succeeded.
            assert wait_for(lambda: commander.status()["pending"] is None, 5.0)
            lit = calls[-1:] != ["off"] and (calls.count("on") == 0 or calls.count("on") >= 2)
    finally:
        commander.stop()
    assert calls[:3] == ["off", "on", "on"]  # the failed switch was retried
    assert pipeline.stats()["ambient_frames"] >= 1 and lit


def test_marker_locates_the_patch_in_a_drawn_image():
    from uwcam.config import MarkerConfig, PatchConfig
    from uwcam.runtime.stages.patch_tracker import PatchTracker
    from tests.synthetic import make_profile

    marker = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 7, 60)
    image = np.full((200, 300, 3), 40000, np.uint16)
    image[50:110, 100:160] = (marker.astype(np.uint16) * 200)[:, :, None]
    config = PatchConfig(marker=MarkerConfig(id=7, offset=(1.5, 0.25), size=(0.5, 0.5)), path_length_m=1.0)
    tracker = PatchTracker(config, make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0]))
    x, y, w, h = tracker.locate(image)
    assert abs(x - (100 + 1.5 * 59)) <= 2 and abs(y - (50 + 0.25 * 59)) <= 2 and abs(w - 30) <= 2 and abs(h - 30) <= 2
    assert tracker.locate(np.full((200, 300, 3), 40000, np.uint16)) is None
    with pytest.raises(ValueError, match="either a fixed 'region' or a 'marker'"):
        PatchConfig(region=(0, 0, 4, 4), marker=config.marker, path_length_m=1.0)
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9'"):
        MarkerConfig(dictionary="DICT_9X9", id=1, offset=(1, 0), size=(1, 1))


def test_daemon_tracks_the_patch_found_by_its_marker():
    from uwcam.config import MarkerConfig, PatchConfig
    from uwcam.runtime.simulated_rig import simulated_patch
    from uwcam.drivers.sim import SimulatedRig
    from uwcam.simulation.scene import MARKER_CENTRE_M, MARKER_SIDE_M, PATCH_CENTRE_M, PATCH_SIZE_M

    config = small_config()
    config.simulation["size"] = [640, 480]  # the marker needs a few tens of pixels
    rig = SimulatedRig(scene="seabed-patch", size=(640, 480), lamp_offset=(0.3, 0.0, 0.0))
    fixed = simulated_patch(rig)
    # From the marker's top-left corner to the inner part of the patch, in marker sides.
    corner = np.array(MARKER_CENTRE_M) - MARKER_SIDE_M / 2
    inner = np.array(PATCH_CENTRE_M) - PATCH_SIZE_M / 2 + 0.02
    offset = tuple((inner - corner) / MARKER_SIDE_M)
    config.processing.patch = PatchConfig(marker=MarkerConfig(id=7, offset=offset, size=(0.75, 0.75)),
                                          path_length_m=fixed.path_length_m)
    with Server(config) as s:
        def tracking():
            return s.http.get("/api/v1/status").json()["calibration"]["tracking"]

        assert wait_for(lambda: tracking()["accepted"] >= 3, 30.0), tracking()
        t = tracking()
        assert t["state"] == "tracking" and abs(t["drift"]["G"]) < 0.02
        x, y, w, h = t["region"]
        fx, fy, fw, fh = fixed.region
        assert abs(x - fx) < 0.2 * fw and abs(y - fy) < 0.2 * fh  # where the fixed region says the patch is
