"""Recording dives to MCAP, reading them back with the stock ``mcap`` reader, replaying them
through the daemon, reprocessing them (in one process and on a Dask cluster), and ending a
recording cleanly when the disk fills, the folder goes or the writer is killed."""

import contextlib
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from tests.test_api import small_config
from tests.waiting import wait_for
from uwcam.recording import format as rec
from uwcam.config import CameraConfig, DaemonConfig, RecordingConfig, load_config
from uwcam.runtime.daemon import Daemon
from uwcam.fileio import UserInputError
from uwcam.optics.geometry import pixel_rays
from uwcam.recording.recorder import repair_folder
from uwcam.calibration.profile import profile_from_mapping, save_profile
from uwcam.recording.reprocess import plan, reprocess

SEABED_Z_M = 2.0  # the simulated seabed is a plane square to the optical axis at this distance


def recording_config(tmp_path, **kw) -> DaemonConfig:
    cfg = small_config()
    # Results recorded unless a test says otherwise (the default leaves them to `uwcam reprocess`).
    cfg.recording = RecordingConfig(folder=str(tmp_path / "recordings"), chunk_kb=64, **{"results": True, **kw})
    return cfg


@contextlib.contextmanager
def running(cfg: DaemonConfig):
    d = Daemon(cfg)
    try:
        d.start()
        assert wait_for(lambda: d.pipeline.processed >= 3, 60.0), "the frame loop did not start"
        yield d
    finally:
        d.stop()


def stock(path):
    """The stock mcap reader with the stock protobuf decoder (JSON decoded by hand)."""
    fh = open(path, "rb")
    return fh, make_reader(fh, decoder_factories=[DecoderFactory()])


def decoded(path, topic):
    fh, reader = stock(path)
    with fh:
        if topic in (rec.IMAGE_METADATA, rec.RANGING, rec.RANGEFINDER, rec.STATUS):
            import json
            return [(m.log_time, json.loads(m.data)) for _s, _c, m in reader.iter_messages(topics=[topic])]
        return [(m.log_time, d) for _s, _c, m, d in reader.iter_decoded_messages(topics=[topic])]


def image(msg):
    """A foxglove.RawImage decoded by hand from its documented layout (not uwcam's decoder)."""
    dtype, c = {"16UC3": ("<u2", 3), "32FC1": ("<f4", 1), "mono8": ("u1", 1)}[msg.encoding]
    itemsize = np.dtype(dtype).itemsize
    assert msg.step == msg.width * c * itemsize
    a = np.frombuffer(msg.data, dtype=dtype).reshape(msg.height, msg.width, c)
    return a[..., 0] if c == 1 else a


@pytest.fixture(scope="module")
def dive(tmp_path_factory):
    """About 40 frames of the simulated rig recorded to one file (small chunks: many parts)."""
    tmp = tmp_path_factory.mktemp("dive")
    path = str(tmp / "dive.mcap")
    published = {}
    keep = lambda p: published.setdefault(int(p.frame.wall_time * 1e9), (p.result.range, p.result.variance))  # noqa: E731
    with running(recording_config(tmp)) as d:
        d.pipeline.subscribe(keep)
        status = d.recorder.start(path)
        assert status["state"] == "recording" and d.status()["recording"]["file"] == path
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 40, 60.0)
        final = d.recorder.stop()
        d.pipeline.unsubscribe(keep)
        profile = d.pipeline.profile
        truth = d.rig.world.camera_range.copy()
    assert final["state"] == "idle" and final["last_stop_reason"] == "stopped on request"
    return {"path": path, "profile": profile, "truth": truth, "status": final, "published": published}


def test_recording_reads_back_with_the_stock_reader(dive):
    path, profile = dive["path"], dive["profile"]
    fh, reader = stock(path)
    with fh:
        summary = reader.get_summary()
        schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    assert schemas[rec.IMAGE] == schemas[rec.DEPTH] == schemas[rec.VARIANCE] == schemas[rec.REASONS] == "foxglove.RawImage"
    assert schemas[rec.CALIBRATION] == "foxglove.CameraCalibration"
    attached = profile_from_mapping(yaml.safe_load(attachments[f"profile/{profile.name}.yaml"]))
    assert attached == profile

    images = decoded(path, rec.IMAGE)
    meta = dict(decoded(path, rec.IMAGE_METADATA))
    assert len(images) == dive["status"]["frames_written"] and dive["status"]["frames_dropped"] == 0
    sequences = [meta[t]["sequence"] for t, _ in images]
    assert sequences == sorted(sequences) and len(set(sequences)) == len(sequences)
    for t, msg in images[:3]:
        raw = image(msg)
        assert raw.shape == (120, 160, 3) and raw.dtype == np.uint16 and raw.max() > 4095  # full 16 bits, not 8
        m = meta[t]
        assert m["lamp_on"] is True and m["bit_depth"] == 16 and m["channel_names"] == ["R", "G", "B"]
        assert m["host_monotonic_ns"] > 0 and abs(m["wall_time"] * 1e9 - t) < 1e3

    depth = {t: image(msg) for t, msg in decoded(path, rec.DEPTH)}
    variance = {t: image(msg) for t, msg in decoded(path, rec.VARIANCE)}
    reasons = {t: image(msg) for t, msg in decoded(path, rec.REASONS)}
    ranged = [t for t, m in meta.items() if m["ranged"] == "ranged"]
    assert sorted(depth) == sorted(variance) == sorted(reasons) == sorted(ranged) and len(ranged) >= 30
    t = ranged[-1]
    z, var, why = depth[t], variance[t], reasons[t]
    assert np.array_equal(np.isfinite(z), why == 0) and np.all(var[why == 0] > 0)
    # Depth is along the optical axis (REP 118): the range the loop published along each pixel's
    # ray times that ray's z component, u_z = 1/sqrt(1 + ((x−cx)/fx)² + ((y−cy)/fy)²).
    intr = profile.camera_intrinsics()
    y, x = np.mgrid[0:120, 0:160]
    uz = 1.0 / np.sqrt(1.0 + ((x - intr.cx) / intr.fx) ** 2 + ((y - intr.cy) / intr.fy) ** 2)
    assert uz.min() < 0.85  # the conversion matters at the corners
    checked = 0
    for when, (range_m, range_var) in dive["published"].items():
        if when in depth:
            np.testing.assert_allclose(depth[when], range_m * uz, rtol=1e-6, equal_nan=True)
            np.testing.assert_allclose(variance[when], range_var * uz**2, rtol=1e-5, equal_nan=True)
            checked += 1
    assert checked >= 30
    # and the flat seabed, square to the axis, reads its distance in the middle of the image
    assert np.nanmedian(z[40:80, 60:100]) == pytest.approx(SEABED_Z_M, rel=0.02)

    (_, cal), = decoded(path, rec.CALIBRATION)
    intr = profile.camera_intrinsics()
    assert (cal.width, cal.height) == (160, 120) and list(cal.K) == pytest.approx([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1])
    readings = decoded(path, rec.RANGEFINDER)
    assert len(readings) > 10 and all(r["range_m"] == pytest.approx(SEABED_Z_M, abs=0.01) for _, r in readings)
    status = decoded(path, rec.STATUS)
    assert status and status[-1][1]["recording"]["state"] == "recording" and status[-1][1]["camera"]["health"]["state"] == "ok"
    ranging = dict(decoded(path, rec.RANGING))
    assert ranging[t]["profile"] == profile.name and len(ranging[t]["attenuation_differences"]) == 3


def test_reprocess_with_the_recorded_profile_reproduces_the_recorded_depth(dive, tmp_path):
    out = str(tmp_path / "again.mcap")
    assert len(plan(dive["path"], part_mb=1)) >= 3  # several parts, so the cut between them is exercised
    reprocess([dive["path"]], out, progress=False, part_mb=1)
    for topic in (rec.DEPTH, rec.VARIANCE, rec.REASONS):
        recorded, again = decoded(dive["path"], topic), decoded(out, topic)
        assert [t for t, _ in recorded] == [t for t, _ in again]
        for (_, a), (_, b) in zip(recorded, again):
            assert np.array_equal(image(a), image(b), equal_nan=True)
    with pytest.raises(UserInputError, match="exists"):
        reprocess([dive["path"]], out, progress=False)


def test_a_raw_only_recording_has_no_results_and_reprocesses_to_the_live_depth(tmp_path):
    """recording.results: false writes the raw frames, their metadata and the ranging records but
    no depth, variance or reasons; reprocessing it makes the depth the loop published live (range
    along each ray times u_z, computed here from the intrinsics), and reading it back needs no
    more than what was written."""
    published = {}
    keep = lambda p: published.setdefault(int(p.frame.wall_time * 1e9), p.result.range.copy())  # noqa: E731
    path = str(tmp_path / "raw.mcap")
    with running(recording_config(tmp_path, results=False)) as d:
        d.pipeline.subscribe(keep)
        d.recorder.start(path)
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 20, 60.0)
        final = d.recorder.stop()
        d.pipeline.unsubscribe(keep)
        profile = d.pipeline.profile
    fh, reader = stock(path)
    with fh:
        topics = {ch.topic for ch in reader.get_summary().channels.values()}
    assert {rec.IMAGE, rec.IMAGE_METADATA, rec.RANGING, rec.CALIBRATION} <= topics
    assert not topics & {rec.DEPTH, rec.VARIANCE, rec.REASONS}
    meta = dict(decoded(path, rec.IMAGE_METADATA))
    assert len(meta) == final["frames_written"] and final["frames_dropped"] == 0
    ranged = sorted(t for t, m in meta.items() if m["ranged"] == "ranged")
    assert sorted(t for t, _ in decoded(path, rec.RANGING)) == ranged

    out = str(tmp_path / "ranged.mcap")
    reprocess([path], out, progress=False)
    depth = dict(decoded(out, rec.DEPTH))
    assert sorted(depth) == ranged
    intr = profile.camera_intrinsics()
    y, x = np.mgrid[0:120, 0:160]
    uz = 1.0 / np.sqrt(1.0 + ((x - intr.cx) / intr.fx) ** 2 + ((y - intr.cy) / intr.fy) ** 2)
    checked = [t for t in ranged if t in published]
    assert len(checked) >= 15
    for t in checked:
        np.testing.assert_allclose(image(depth[t]), published[t] * uz, rtol=1e-6, equal_nan=True)


def test_reprocess_with_another_profile(dive, tmp_path):
    """A profile file with the same calibration under another name: the recorded corrections are
    carried over relative to it, so the depth is the recorded one to rounding."""
    same = dive["profile"].model_copy(update={"name": "same calibration, new file"})
    save_profile(same, tmp_path / "p.yaml")
    out = tmp_path / "out"
    reprocess([dive["path"]], str(out), profile=str(tmp_path / "p.yaml"), progress=False)
    again = decoded(str(out / "dive.mcap"), rec.DEPTH)
    recorded = decoded(dive["path"], rec.DEPTH)
    assert len(again) == len(recorded)
    for (_, a), (_, b) in zip(recorded, again):
        np.testing.assert_allclose(image(b), image(a), rtol=1e-5, equal_nan=True)
    assert decoded(str(out / "dive.mcap"), rec.RANGING)[0][1]["profile"] == "same calibration, new file"
    two = same.model_dump(mode="json") | {"name": "two channels", "channels": same.model_dump(mode="json")["channels"][:2],
                                          "backscatter": None, "covariance": None}
    save_profile(profile_from_mapping(two), tmp_path / "two.yaml")
    with pytest.raises(UserInputError, match="3-channel frames but profile 'two channels' has 2 channels"):
        reprocess([dive["path"]], str(tmp_path / "x.mcap"), profile=str(tmp_path / "two.yaml"), progress=False)
    assert not (tmp_path / "x.mcap").exists() and not list(tmp_path.glob(".reprocess-*"))


def _messages_digest(path):
    h = hashlib.sha256()
    fh, reader = stock(path)
    with fh:
        for _s, c, m in reader.iter_messages():
            h.update(c.topic.encode() + m.log_time.to_bytes(8, "little") + m.data)
    return h.hexdigest()


@pytest.mark.slow
def test_dask_local_cluster_with_two_workers_equals_one_process(dive, tmp_path):
    # In a child process: Dask's client keeps threads of its own that outlive a test.
    assert len(plan(dive["path"], part_mb=1)) >= 4
    base = [sys.executable, "-m", "uwcam", "reprocess", dive["path"], "--quiet", "--part-mb", "1"]
    one = subprocess.run(base + ["-o", str(tmp_path / "one.mcap")], capture_output=True, text=True, timeout=300)
    assert one.returncode == 0, one.stderr
    two = subprocess.run(base + ["-o", str(tmp_path / "two.mcap"), "--scheduler", "--workers", "2"],
                         capture_output=True, text=True, timeout=300)
    assert two.returncode == 0, two.stderr
    assert _messages_digest(str(tmp_path / "one.mcap")) == _messages_digest(str(tmp_path / "two.mcap"))
    assert len(decoded(str(tmp_path / "two.mcap"), rec.DEPTH)) == len(decoded(dive["path"], rec.DEPTH))
    gone = subprocess.run(base + ["-o", str(tmp_path / "three.mcap"), "--scheduler", "tcp://127.0.0.1:9"],
                          capture_output=True, text=True, timeout=120)
    assert gone.returncode == 2 and "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in gone.stderr
    assert not (tmp_path / "three.mcap").exists()


def test_several_inputs_go_to_a_folder_one_output_each(dive, tmp_path):
    second = tmp_path / "second.mcap"
    shutil.copy(dive["path"], second)
    outputs = reprocess([dive["path"], str(second)], str(tmp_path / "out"), progress=False)
    assert outputs == [str(tmp_path / "out" / "dive.mcap"), str(tmp_path / "out" / "second.mcap")]
    assert _messages_digest(outputs[0]) == _messages_digest(outputs[1])


def test_reprocess_shows_progress_and_rejects_bad_input(dive, tmp_path, capsys):
    from uwcam.cli import main

    assert main(["reprocess", dive["path"], "-o", str(tmp_path / "o.mcap")]) == 0
    err = capsys.readouterr().err
    n = len(decoded(dive["path"], rec.DEPTH))
    assert f"{n}/{n}" in err and "frame/s" in err
    assert main(["reprocess", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    assert main(["reprocess", str(tmp_path / "junk.mcap"), "-o", str(tmp_path / "y.mcap"), "--quiet"]) == 2
    assert "not a readable MCAP recording" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "y.mcap").exists()


def test_replayed_recording_drives_the_daemon(dive, tmp_path):
    fh, reader = stock(dive["path"])
    with fh:
        profile_yaml = next(a.data for a in reader.iter_attachments() if a.name.startswith("profile/"))
    (tmp_path / "profile.yaml").write_bytes(profile_yaml)
    raw = {decoded_meta["sequence"]: t for t, decoded_meta in decoded(dive["path"], rec.IMAGE_METADATA)}
    frames = {t: image(m) for t, m in decoded(dive["path"], rec.IMAGE)}
    cfg = DaemonConfig(camera=CameraConfig(driver="replay", options={"source": dive["path"], "fast": True, "loop": True}),
                       calibration=str(tmp_path / "profile.yaml"))
    seen = []
    with running(cfg) as d:
        d.pipeline.subscribe(seen.append)
        assert wait_for(lambda: len(seen) >= 10, 30.0)
        d.pipeline.unsubscribe(seen.append)
    for p in seen[:10]:
        assert p.frame.sequence in raw and np.array_equal(p.frame.data, frames[raw[p.frame.sequence]])
        assert p.frame.lamp_on is True and p.frame.bit_depth == 16
        rays = pixel_rays(dive["profile"].camera_intrinsics(), 120, 160)
        # Without the rangefinder's correction for the sand's hue (none configured here) the
        # seabed reads a few per cent short; the live loop with it reads within 2 %.
        assert np.nanmedian((p.result.range * rays[..., 2])[40:80, 60:100]) == pytest.approx(SEABED_Z_M, rel=0.05)


def test_replay_keeps_the_recorded_pace(dive):
    from uwcam.drivers.replay import ReplayCamera

    cam = ReplayCamera(dive["path"], loop=False)
    cam.open()
    cam.start()
    try:
        began = time.monotonic()
        got = [cam.read(timeout_s=5.0) for _ in range(6)]
        elapsed = time.monotonic() - began
    finally:
        cam.close()
    times = [t for t, _ in decoded(dive["path"], rec.IMAGE)][:6]
    assert [f.sequence for f in got] == [m["sequence"] for _, m in decoded(dive["path"], rec.IMAGE_METADATA)][:6]
    assert elapsed >= (times[-1] - times[0]) / 1e9 * 0.95


def test_rotation_by_size_makes_complete_self_contained_files(tmp_path):
    with running(recording_config(tmp_path, max_size_mb=0.5)) as d:
        d.recorder.start()
        assert wait_for(lambda: len(d.recorder.status()["files"]) >= 3, 60.0)
        status = d.recorder.stop()
    files = status["files"]
    assert all(os.path.dirname(f) == str(tmp_path / "recordings") and os.path.basename(f).startswith("uwcam-") for f in files)
    total = 0
    for f in files:
        assert rec.is_complete(f)
        fh, reader = stock(f)
        with fh:
            assert any(a.name.startswith("profile/") for a in reader.iter_attachments())
        assert len(decoded(f, rec.CALIBRATION)) == 1
        total += len(decoded(f, rec.IMAGE))
        assert os.path.getsize(f) < 0.5e6 + 400e3  # one limit plus at most a frame's messages and a chunk
    assert total == status["frames_written"]


def mount_tmpfs(path, size):
    path.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {done.stderr.strip()}")


def test_full_disk_ends_the_recording_cleanly(tmp_path):
    small = tmp_path / "small"
    mount_tmpfs(small, "2m")
    try:
        with running(recording_config(tmp_path)) as d:
            d.recorder.start(str(small / "dive.mcap"))
            assert wait_for(lambda: d.recorder.status()["state"] == "idle", 60.0)
            status = d.status()["recording"]
            assert d.pipeline.processed > 0  # the loop went on
        assert status["last_stop_reason"].startswith("disk full") and status["frames_written"] > 0
        path = str(small / "dive.mcap")
        assert rec.is_complete(path)
        images = decoded(path, rec.IMAGE)  # the stock reader reads it to the end without error
        assert len(images) >= 1 and all(image(m).shape == (120, 160, 3) for _, m in images)
        depth = decoded(path, rec.DEPTH)
        assert all(np.isfinite(image(m)).any() for _, m in depth)
    finally:
        subprocess.run(["umount", str(small)], check=True)


def test_removed_folder_ends_the_recording(tmp_path):
    folder = tmp_path / "gone"
    folder.mkdir()
    with running(recording_config(tmp_path)) as d:
        d.recorder.start(str(folder / "dive.mcap"))
        assert wait_for(lambda: d.recorder.status()["frames_written"] > 2, 30.0)
        for f in folder.iterdir():
            f.unlink()
        folder.rmdir()
        assert wait_for(lambda: d.recorder.status()["state"] == "idle", 10.0)
        status = d.status()["recording"]
    assert "removed" in status["last_stop_reason"]


def test_start_refuses_to_overwrite_or_run_twice(tmp_path):
    (tmp_path / "exists.mcap").write_bytes(b"precious")
    with running(recording_config(tmp_path)) as d:
        with pytest.raises(UserInputError, match="exists"):
            d.recorder.start(str(tmp_path / "exists.mcap"))
        with pytest.raises(UserInputError, match="does not exist"):
            d.recorder.start(str(tmp_path / "no" / "such" / "x.mcap"))
        d.recorder.start()
        with pytest.raises(UserInputError, match="already recording"):
            d.recorder.start()
        d.recorder.stop()
    assert (tmp_path / "exists.mcap").read_bytes() == b"precious"


def test_recording_config_is_strict(tmp_path):
    bad = tmp_path / "c.yaml"
    bad.write_text("recording:\n  max_size_mb: -1\n")
    with pytest.raises(UserInputError, match="recording.max_size_mb"):
        load_config(bad)
    bad.write_text("recording:\n  max_duration_s: .nan\n")
    with pytest.raises(UserInputError, match="recording.max_duration_s"):
        load_config(bad)
    bad.write_text("foxglove:\n  port: 70000\n")
    with pytest.raises(UserInputError, match="foxglove.port"):
        load_config(bad)
    bad.write_text("foxglove:\n  enable: true\n")
    with pytest.raises(UserInputError, match="foxglove.enable"):
        load_config(bad)


@pytest.mark.slow
def test_killed_daemon_leaves_a_recording_that_is_repaired_and_read(tmp_path):
    """``uwcam run --record`` killed with SIGKILL mid-dive: the next recorder start in the folder
    (or rec.repair) closes the file at its last complete record, and the stock reader reads it."""
    cfg = small_config().model_dump(mode="json")
    cfg["api"]["port"] = 0
    cfg["recording"] = {"chunk_kb": 64}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(cfg))
    path = tmp_path / "recordings" / "dive.mcap"
    path.parent.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "uwcam", "run", "--config", str(tmp_path / "rig.yaml"), "--record", str(path)],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert wait_for(lambda: path.exists() and path.stat().st_size > 1_500_000, 120.0), "nothing recorded"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert not rec.is_complete(str(path))
    assert repair_folder(str(path.parent)) == [str(path)]
    assert rec.is_complete(str(path))
    images = decoded(str(path), rec.IMAGE)
    assert len(images) >= 3 and all(image(m).shape == (120, 160, 3) for _, m in images)


def test_recordings_api_starts_stops_lists_and_downloads(tmp_path):
    from tests.served import Server

    cfg = recording_config(tmp_path)
    cfg.api.token = "s3cret"
    auth = {"Authorization": "Bearer s3cret"}
    with Server(cfg) as s:
        assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["processed"] > 2, 60.0)
        assert s.http.get("/api/v1/status").json()["recording"]["state"] == "idle"
        assert s.http.post("/api/v1/recordings/start").status_code == 401  # state changes need the token
        started = s.http.post("/api/v1/recordings/start", headers=auth)
        assert started.status_code == 200 and started.json()["state"] == "recording"
        name = os.path.basename(started.json()["file"])
        assert name.startswith("uwcam-") and name.endswith("Z.mcap")
        again = s.http.post("/api/v1/recordings/start", headers=auth)
        assert again.status_code == 409 and "already recording" in again.json()["detail"]
        assert wait_for(lambda: s.http.get("/api/v1/recordings/status").json()["frames_written"] >= 5, 30.0)
        assert s.http.get("/api/v1/status").json()["recording"]["state"] == "recording"
        listed = s.http.get("/api/v1/recordings").json()["recordings"]
        assert [(r["name"], r["recording"], r["complete"]) for r in listed] == [(name, True, False)]
        stopped = s.http.post("/api/v1/recordings/stop", headers=auth).json()
        assert stopped["state"] == "idle" and stopped["last_stop_reason"] == "stopped on request"
        listed = s.http.get("/api/v1/recordings").json()["recordings"]
        assert [(r["name"], r["recording"], r["complete"]) for r in listed] == [(name, False, True)]
        got = s.http.get(f"/api/v1/recordings/{name}")
        assert got.status_code == 200 and got.content == (tmp_path / "recordings" / name).read_bytes()
        for bad in ("..%2Frig.yaml", "nothing.mcap", ".hidden.mcap"):
            assert s.http.get(f"/api/v1/recordings/{bad}").status_code == 404
    (tmp_path / "dl.mcap").write_bytes(got.content)
    metadata = [m for _t, m in decoded(str(tmp_path / "dl.mcap"), rec.IMAGE_METADATA)]
    assert len(metadata) == stopped["frames_written"]
    # Results for every ranged frame; a loaded machine may also hand over frames it skipped for a newer one.
    assert len(decoded(str(tmp_path / "dl.mcap"), rec.DEPTH)) == sum(m["ranged"] == "ranged" for m in metadata)


@pytest.mark.parametrize("protocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
def test_foxglove_server_carries_the_topics_and_a_point_cloud(tmp_path, protocol):
    """A real client of the Foxglove WebSocket protocol: subscribe, receive, decode with the
    advertised protobuf schema (stock protobuf runtime)."""
    import asyncio
    import base64
    import json
    import struct

    import websockets
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from uwcam.config import FoxgloveConfig

    cfg = small_config()
    cfg.foxglove = FoxgloveConfig(enabled=True, port=0, rate_hz=20, point_stride=4)

    def decoder(channel):
        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for fd in fds.file:
            pool.Add(fd)
        return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"].lstrip(".")))

    async def client(port):
        # foxglove.sdk.v1: Foxglove with the SDK; foxglove.websocket.v1: Lichtblick and older Foxglove.
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[protocol], max_size=None) as ws:
            assert ws.subprotocol == protocol
            channels = {}
            while not {rec.DEPTH, "/uwcam/points", rec.IMAGE, rec.CALIBRATION, rec.STATUS, rec.RANGEFINDER} <= set(channels):
                msg = json.loads(await ws.recv())
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
            wanted = [rec.DEPTH, "/uwcam/points", rec.IMAGE, rec.STATUS]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[t]["id"]} for i, t in enumerate(wanted)]}))
            got = {}
            while len(got) < len(wanted):
                data = await ws.recv()
                if isinstance(data, bytes) and data[0] == 0x01:  # message data
                    sub, _t = struct.unpack_from("<IQ", data, 1)
                    topic = wanted[sub]
                    if channels[topic]["encoding"] == "json":
                        got.setdefault(topic, json.loads(data[13:]))
                    else:
                        got.setdefault(topic, decoder(channels[topic]).FromString(data[13:]))
            return channels, got, d.status()["foxglove"]["clients"]

    with running(cfg) as d:
        channels, got, clients_while_connected = asyncio.run(client(d.foxglove.port))
        status = d.status()["foxglove"]
        assert wait_for(lambda: d.status()["foxglove"]["clients"] == 0, 10.0)
        intr = d.pipeline.profile.camera_intrinsics()
    assert channels[rec.DEPTH]["schemaName"] == "foxglove.RawImage" and channels["/uwcam/points"]["schemaName"] == "foxglove.PointCloud"
    assert status["frames_sent"] > 0 and status["error"] is None
    assert status["connections_by_protocol"][protocol] == 1 and clients_while_connected == 1
    assert got[rec.STATUS]["camera"]["health"]["state"] == "ok" and got[rec.STATUS]["foxglove"]["url"].startswith("ws://")
    depth = got[rec.DEPTH]
    assert (depth.width, depth.height, depth.encoding) == (160, 120, "32FC1")
    z = np.frombuffer(depth.data, "<f4").reshape(120, 160)
    assert np.nanmedian(z[40:80, 60:100]) == pytest.approx(SEABED_Z_M, rel=0.02)
    raw = got[rec.IMAGE]
    assert raw.encoding == "16UC3" and len(raw.data) == 160 * 120 * 3 * 2
    cloud = got["/uwcam/points"]
    fields = {f.name: f.offset for f in cloud.fields}
    assert fields == {"x": 0, "y": 4, "z": 8, "red": 12, "green": 13, "blue": 14} and cloud.point_stride == 16
    pts = np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3), ("pad", "u1")])
    assert 0.5 * (120 // 4) * (160 // 4) < len(pts) <= (120 // 4) * (160 // 4)
    # every point lies on its pixel's ray: x/z = (u − cx)/fx for a pixel u on the 4-pixel grid
    u = pts["xyz"][:, 0] / pts["xyz"][:, 2] * intr.fx + intr.cx
    assert np.allclose(u / 4, np.round(u / 4), atol=1e-3)
    assert np.median(pts["xyz"][:, 2]) == pytest.approx(SEABED_Z_M, rel=0.05)


def test_a_slow_disk_drops_counted_frames_and_stop_is_prompt(tmp_path, monkeypatch):
    """Writing slower than the camera delivers: the queue stays bounded, losses are counted,
    and stop() finishes what is queued instead of chasing new frames."""
    write = rec.McapFile.write

    def slow_write(self, *args, **kwargs):
        time.sleep(0.01)  # ~90 ms a frame against a frame every 50 ms
        write(self, *args, **kwargs)

    monkeypatch.setattr(rec.McapFile, "write", slow_write)
    with running(recording_config(tmp_path, queue_frames=4)) as d:
        d.recorder.start(str(tmp_path / "slow.mcap"))
        peak = 0
        deadline = time.monotonic() + 60.0
        while d.recorder.status()["frames_dropped"] < 5 and time.monotonic() < deadline:
            peak = max(peak, d.recorder.status()["queued"])
            time.sleep(0.01)
        began = time.monotonic()
        status = d.recorder.stop()
        took = time.monotonic() - began
    assert status["state"] == "idle" and status["frames_dropped"] >= 5 and peak <= 4
    assert took < 5.0  # at most the 4 queued frames (~0.4 s) plus closing the file
    metadata = [m for _t, m in decoded(str(tmp_path / "slow.mcap"), rec.IMAGE_METADATA)]
    # Every frame handed over has its metadata; the dropped ones say so and have no raw image.
    assert len(metadata) == status["frames_written"] and sum(not m["raw_kept"] for m in metadata) >= 5
    assert len(decoded(str(tmp_path / "slow.mcap"), rec.IMAGE)) == sum(m["raw_kept"] for m in metadata)


def test_lamp_off_frames_and_ambient_are_recorded_and_reprocessed(tmp_path):
    """With daylight and a lamp-off frame every 4, the dark frames are recorded too, the ambient
    light subtracted is recorded when it changes, and reprocessing (cut into parts that begin
    after an ambient update) reproduces the recorded depth exactly."""
    cfg = recording_config(tmp_path)
    cfg.simulation["ambient"] = [0.05, 0.05, 0.05]
    cfg.processing = cfg.processing.model_copy(update={"lamp_off_interval": 4})
    path = str(tmp_path / "daylight.mcap")
    with running(cfg) as d:
        d.recorder.start(path)
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 40, 180.0)
        d.recorder.stop()
    meta = [m for _, m in decoded(path, rec.IMAGE_METADATA)]
    dark = [m for m in meta if m["ranged"] == "lamp off"]
    assert len(dark) >= 3 and all(m["lamp_on"] is False for m in dark)
    ambient = decoded(path, rec.AMBIENT)
    assert len(ambient) >= 2 and ambient[0][1].encoding == "32FC3"
    ranging = [r for _, r in decoded(path, rec.RANGING)]
    assert sum(r["ambient_subtracted"] for r in ranging) >= 10
    assert len(plan(path, part_mb=1)) >= 3
    reprocess([path], str(tmp_path / "again.mcap"), progress=False, part_mb=1)
    recorded, again = decoded(path, rec.DEPTH), decoded(str(tmp_path / "again.mcap"), rec.DEPTH)
    assert len(recorded) == len(again)
    for (_, a), (_, b) in zip(recorded, again):
        assert np.array_equal(image(a), image(b), equal_nan=True)


def test_foxglove_port_taken_and_bad_record_paths_give_one_line_errors(tmp_path, capsys):
    import socket

    from uwcam.cli import main
    from uwcam.config import FoxgloveConfig

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        cfg = small_config()
        cfg.foxglove = FoxgloveConfig(enabled=True, port=taken.getsockname()[1])
        d = Daemon(cfg)
        with pytest.raises(UserInputError, match="cannot start the Foxglove server on 127.0.0.1:.*choose another foxglove.port"):
            d.start()
    (tmp_path / "old.mcap").write_bytes(b"x")
    for record, message in ((tmp_path / "old.mcap", "exists"), (tmp_path / "no" / "x.mcap", "folder does not exist"),
                            (tmp_path / "x.bag", "must end in .mcap")):
        assert main(["run", "--record", str(record)]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
