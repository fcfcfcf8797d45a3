"""The embedded simulated tank (``uwcam run --simulate tank``) through the API alone: the rail
(PUT/GET /api/v1/simulation/plate, bounds, 404 for a real camera), the whole calibration at three
distances and a held-back one, the new profile ranging the plate at a fourth distance within 2 %,
a session surviving a daemon restart, and the vehicle's patch marker never taken for the plate.
Real uvicorn servers on the simulated devices; the truth is the simulated plate's geometry."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from tests.served import Server
from tests.waiting import wait_for
from uwcam.config import CameraConfig, DaemonConfig, tank_config
from uwcam.optics.geometry import Intrinsics, pixel_rays, plane_camera_range

pytestmark = pytest.mark.slow

URL = "/api/v1/calibration/session"
RAIL = "/api/v1/simulation/plate"


def tank_with_state(folder) -> DaemonConfig:
    return tank_config().model_copy(update={"state_dir": str(folder)})


@contextmanager
def started(config: DaemonConfig) -> Iterator[Server]:
    with Server(config) as s:
        assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["processed"] > 2, 90.0)
        yield s


def move(s: Server, distance: float) -> None:
    r = s.http.put(RAIL, json={"distance_m": distance})
    assert r.status_code == 202, r.text
    assert r.json()["moving_to_m"] == distance
    assert wait_for(lambda: s.http.get(RAIL).json() == {**r.json(), "distance_m": distance, "moving_to_m": None}, 120.0, 0.1)


def live(s: Server, distance: float | None = None, held_back: bool = False) -> dict:
    params = {"held_back": held_back} | ({} if distance is None else {"distance": distance})
    r = s.http.get(URL, params=params)
    assert r.status_code == 200, r.text
    return r.json()["live"]


def capture(s: Server, distance: float, held_back: bool = False) -> dict:
    # The page's rule: capture only when the live feedback says it would be accepted.
    assert wait_for(lambda: live(s, distance, held_back)["capture_ok"], 30.0, 0.2), live(s, distance, held_back)
    r = s.http.post(URL + "/captures", json={"distance_m": distance, "held_back": held_back}, timeout=60.0)
    assert r.status_code == 201, r.text
    return r.json()


def test_the_rail_moves_the_plate_and_refuses_numbers_outside_it(tmp_path):
    with started((tank_with_state(tmp_path))) as s:
        assert s.http.get("/api/v1/simulation").json() == {"camera_simulated": True, "scene": "plate", "tank": True}
        assert s.http.get(RAIL).json() == {"distance_m": 1.0, "moving_to_m": None, "rig": "charuco-plate",
                                           "rail_m": [0.5, 4.0]}
        move(s, 1.5)
        assert s.http.get(RAIL).json()["distance_m"] == 1.5
        first = s.http.put(RAIL, json={"distance_m": 2.0})
        again = s.http.put(RAIL, json={"distance_m": 2.5})  # one move at a time
        assert first.status_code == 202 and again.status_code == 409 and "still moving to 2 m" in again.json()["detail"]
        assert wait_for(lambda: s.http.get(RAIL).json()["moving_to_m"] is None, 120.0, 0.1)
        move(s, 1.5)
        assert s.daemon.rig.true_range() == pytest.approx(1.5, rel=1e-6)
        # The markers see the plate where the rail put it (the session's live feedback).
        assert s.http.get("/api/v1/status").json()["calibration_session"] is None
        started_session = s.http.post(URL, json={}).json()
        assert s.http.get("/api/v1/status").json()["calibration_session"] == {"id": started_session["id"],
                                                                             "state": "positioning", "captures": 0}
        # Frames rendered before the rail arrived may still be the newest for a moment (the loop's
        # latency on a loaded machine): the feedback follows the plate within the next frames.
        assert wait_for(lambda: abs(live(s, 1.5)["marker_distance_m"] - 1.5) <= 0.02, 30.0, 0.2), live(s, 1.5)
        for body in ({"distance_m": 0.49}, {"distance_m": 4.01}, {"distance_m": -1}, {"distance_m": "near"}, {},
                     {"distance_m": 2.0, "tilt_deg": 3}, {"distance_m": 1e308}):
            r = s.http.put(RAIL, json=body)
            assert r.status_code == 422, (body, r.text)
        for raw in (b'{"distance_m": NaN}', b'{"distance_m": Infinity}', b'{"distance_m": -Infinity}'):
            r = s.http.put(RAIL, content=raw, headers={"Content-Type": "application/json"})
            assert r.status_code == 422, (raw, r.text)
        assert s.http.get(RAIL).json()["distance_m"] == 1.5  # nothing refused moved it
        assert s.http.delete(URL).status_code == 200


def test_no_rail_without_the_simulated_tank(tmp_path):
    from tests.synthetic import make_profile
    from uwcam.config import default_config
    from uwcam.calibration.profile import save_profile

    # A real camera (frames replayed from files), a calibration profile from a file.
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        np.save(frames / f"f{i}.npy", np.full((60, 80, 3), 1000 + i, np.uint16))
    save_profile(make_profile([0.46, 0.11, 0.06], [0.0, 0.0, 0.0]), tmp_path / "p.yaml")
    real = DaemonConfig(camera=CameraConfig(driver="replay", options={"source": str(frames), "fps": 10.0}),
                        calibration=str(tmp_path / "p.yaml"))
    with Server(real) as s:
        assert s.http.get("/api/v1/simulation").json() == {"camera_simulated": False, "scene": None, "tank": False}
        for r in (s.http.get(RAIL), s.http.put(RAIL, json={"distance_m": 1.0})):
            assert r.status_code == 404
            assert r.json()["detail"] == ("the camera is not simulated, so there is no simulated plate to move; "
                                          "move the real plate and type its distance")
    vehicle = default_config().model_copy(update={"simulation": {**default_config().simulation, "size": [320, 180]}})
    with Server(vehicle) as s:
        assert s.http.get("/api/v1/simulation").json() == {"camera_simulated": True, "scene": "survey", "tank": False}
        r = s.http.put(RAIL, json={"distance_m": 1.0})
        assert r.status_code == 404 and "uwcam run --simulate tank" in r.json()["detail"]


def test_whole_calibration_on_the_simulated_tank_then_a_fourth_distance_ranges_within_two_percent(tmp_path):
    with started((tank_with_state(tmp_path))) as s:
        before = s.daemon.profile_name
        r = s.http.post(URL, json={})
        assert r.status_code == 201, r.text
        for d in (1.0, 1.5, 2.0):
            move(s, d)
            capture(s, d)
        move(s, 1.75)
        capture(s, 1.75, held_back=True)
        fit = s.http.post(URL + "/fit", timeout=120.0)
        assert fit.status_code == 200, fit.text
        result = fit.json()
        assert result["distances_m"] == [1.0, 1.5, 2.0]
        (check,) = result["validation"]
        assert check["passed"], check
        assert result["warnings"] == [], result["warnings"]
        report = s.http.get(URL + "/report.html", timeout=120.0)
        assert report.status_code == 200 and report.text.startswith("<!DOCTYPE html>")
        assert "attachment" in report.headers["content-disposition"] and report.text.count("data:image/png;base64,") == 5
        accepted = s.http.post(URL + "/accept", json={"name": "tank-sim"}, timeout=60.0)
        assert accepted.status_code == 200, accepted.text
        assert s.daemon.profile_name == "tank-sim" != before
        assert {p["name"]: p["active"] for p in s.http.get("/api/v1/calibration/profiles").json()}["tank-sim"] is True
        assert not (tmp_path / "calibration-session").exists()  # accepted: nothing kept

        # A fourth distance, never captured: the daemon ranges the plate with the new profile.
        move(s, 1.25)
        frame_at_move = s.daemon.pipeline.latest.number  # (ranged after the move, or soon)
        assert wait_for(lambda: s.daemon.pipeline.latest.number > frame_at_move + 3, 30.0)
        published = s.daemon.pipeline.latest
        intr = s.daemon.profiles["tank-sim"].camera_intrinsics()
        h, w = published.result.range.shape
        # The target region: the plate's middle, from its true geometry (0.44 m square about the axis).
        half = int(0.2 * intr.fx / 1.25)
        ys, xs = slice(int(intr.cy) - half, int(intr.cy) + half), slice(int(intr.cx) - half, int(intr.cx) + half)
        truth = plane_camera_range(1.25, pixel_rays(Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy), h, w))[ys, xs]
        measured = published.result.range[ys, xs]
        ok = np.isfinite(measured)
        assert ok.mean() > 0.9
        error = np.median(measured[ok] - truth[ok]) / 1.25
        assert abs(error) < 0.02, f"median range error {error:+.2%} at 1.25 m"


def test_a_session_survives_a_daemon_restart_and_goes_on(tmp_path):
    config = tank_with_state(tmp_path)
    with started((config)) as s:
        assert s.http.post(URL, json={"frames_per_capture": 2}).status_code == 201
        first = s.http.get(URL).json()["session"]["id"]
        for d in (1.0, 1.5):
            move(s, d)
            capture(s, d)
    assert (tmp_path / "calibration-session" / "session.json").exists()
    with started((config)) as s:
        session = s.http.get(URL).json()["session"]
        assert session["id"] == first and session["state"] == "positioning"
        assert [(c["distance_m"], c["frames"]) for c in session["captures"]] == [(1.0, 2), (1.5, 2)]
        assert s.http.post(URL, json={}).status_code == 409  # still running: cancel it first
        move(s, 2.0)
        capture(s, 2.0)
        fit = s.http.post(URL + "/fit", timeout=120.0)
        assert fit.status_code == 200 and fit.json()["distances_m"] == [1.0, 1.5, 2.0], fit.text
        assert s.http.delete(URL).status_code == 200
        assert not (tmp_path / "calibration-session").exists()
    with started((config)) as s:
        assert s.http.get(URL).status_code == 404  # cancelled: not resumed


def test_the_vehicles_patch_marker_is_never_taken_for_the_plate(tmp_path):
    """The simulated vehicle (survey) with its patch and ArUco marker 7 on a bracket in view, no plate."""
    from uwcam.config import default_config

    vehicle = default_config().model_copy(update={"state_dir": str(tmp_path),
                                                  "simulation": {**default_config().simulation, "size": [640, 360]}})
    with started((vehicle)) as s:
        assert s.http.post(URL, json={}).status_code == 201
        ignored = set()
        for _ in range(5):
            seen = live(s, 0.8)
            assert seen["plate_found"] is False and seen["capture_ok"] is False, seen
            assert 7 not in seen["markers_found"]
            ignored |= set(seen["markers_ignored"])
        assert 7 in ignored  # the marker is in view and seen, and left out
        r = s.http.post(URL + "/captures", json={"distance_m": 0.8})
        assert r.status_code == 422 and r.json()["detail"].startswith("plate not found"), r.text
        assert s.http.get(URL).json()["session"]["captures"] == []


def test_run_takes_a_config_or_a_simulation_not_both(tmp_path, capsys):
    from uwcam.cli import main

    assert main(["run", "--simulate", "tank", "--config", str(tmp_path / "rig.yaml")]) == 2
    assert capsys.readouterr().err.strip() == ("uwcam run: error: give either --config FILE or --simulate NAME, not both")
    with pytest.raises(SystemExit):
        main(["run", "--simulate", "pool"])
    assert "invalid choice: 'pool' (choose from 'vehicle', 'tank')" in capsys.readouterr().err
