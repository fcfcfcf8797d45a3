"""The tank workflow end to end through the API on the simulated tank: a real uvicorn server,
the simulated camera, lamp and sonar sharing one world whose marker plate the test moves between
captures (SimulatedRig.place, as a crew moves the plate)."""

import pytest

from tests.served import Server
from tests.waiting import wait_for
from uwcam.config import ApiConfig, CameraConfig, DaemonConfig, DeviceConfig

pytestmark = pytest.mark.slow


def tank_config() -> DaemonConfig:
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 20.0, "serial_number": "SIM-TANK"}, watchdog_s=2.0),
        lamp=DeviceConfig(driver="sim"),
        rangefinder=DeviceConfig(driver="sim-ping1d", options={"rate_hz": 20}),
        simulation={"scene": "plate", "plate_rig": "charuco-plate", "distance": 1.0, "size": [320, 240],
                    "water": "jerlov-IB", "lamp_offset": [0.3, 0.0, 0.0]},
        api=ApiConfig(),
    )


@pytest.fixture(scope="module")
def tank():
    with Server(tank_config()) as s:
        assert wait_for(lambda: s.http.get("/api/v1/status").json()["frames"]["processed"] > 2, 60.0)
        yield s


URL = "/api/v1/calibration/session"


def move_plate(tank, distance):
    tank.daemon.rig.place(distance)

    def there():
        live = tank.http.get(URL, params={"distance": distance}).json()["live"]
        return live["plate_found"] and abs(live["marker_distance_m"] - distance) < 0.03 * distance

    assert wait_for(there, 30.0, 0.2), f"plate never seen at {distance} m"


def profiles(tank):
    return {p["name"]: p["active"] for p in tank.http.get("/api/v1/calibration/profiles").json()}


def test_guided_calibration_validated_accepted_and_activated(tank):
    before = profiles(tank)
    assert tank.http.get(URL).status_code == 404
    r = tank.http.post(URL, json={"rig": "charuco-plate", "frames_per_capture": 3})
    assert r.status_code == 201, r.text
    assert tank.http.post(URL, json={}).status_code == 409  # one session at a time

    move_plate(tank, 1.0)
    # The simulated sonar answers at its own pace: its first reading of the moved plate may take
    # a moment on a loaded machine (the feedback says None until then, never a stale range).
    assert wait_for(lambda: tank.http.get(URL, params={"distance": 1.0}).json()["live"]["rangefinder_m"] is not None, 20.0, 0.2)
    status = tank.http.get(URL, params={"distance": 1.0}).json()
    live = status["live"]
    assert live["plate_found"] and live["typed_agrees"] and live["tilt_deg"] < 3
    assert live["rangefinder_m"] == pytest.approx(1.0, abs=0.05) and live["rangefinder_agrees"]
    assert all(ch["above_floor"] for ch in live["channels"].values())
    assert 0.2 < live["coverage"] < 0.9 and live["saturated_fraction"] == 0
    assert status["session"]["exposure"]["locked"] is False and "reports its exposure" in status["session"]["exposure"]["how"]

    # A wrong distance is refused with the markers' figure and changes nothing.
    bad = tank.http.post(URL + "/captures", json={"distance_m": 1.5})
    assert bad.status_code == 422 and "the markers put the plate at 1.0" in bad.json()["detail"]
    assert tank.http.get(URL).json()["session"]["captures"] == []
    assert tank.http.post(URL + "/fit").status_code == 409

    assert tank.http.post(URL + "/captures", json={"distance_m": 1.0}).status_code == 201
    # (The renderer samples one ray per pixel: at 320×240 the markers' 1.9-pixel cells alias at
    # 2 m, so the far distance here is 1.8 m.)
    move_plate(tank, 1.8)
    r = tank.http.post(URL + "/captures", json={"distance_m": 1.8})
    assert r.status_code == 201, r.text
    assert tank.http.post(URL + "/accept", json={"name": "tank-1"}).status_code == 409  # no fit yet
    move_plate(tank, 1.4)
    r = tank.http.post(URL + "/captures", json={"distance_m": 1.4, "held_back": True})
    assert r.status_code == 201, r.text
    assert [c["held_back"] for c in r.json()["session"]["captures"]] == [False, False, True]

    fit = tank.http.post(URL + "/fit")
    assert fit.status_code == 200, fit.text
    result = fit.json()
    assert result["frames_per_distance"] == [3, 3]
    # Jerlov IB at 675/575/475 nm: the differences the simulated water was built with.
    water = tank.daemon.rig.world.water.attenuation
    v = result["channels"]
    assert v["G"]["attenuation_difference"] == pytest.approx(water[1] - water[0], abs=5 * v["G"]["attenuation_difference_std"] + 2e-3)
    (check,) = result["validation"]
    assert check["distance_m"] == 1.4 and check["passed"], check
    assert abs(check["median_range_error_m"]) < 0.03
    for name in ("log-ratio", "residuals", "noise", "overlay", "range-sigma"):
        png = tank.http.get(f"{URL}/plots/{name}.png")
        assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    missing = tank.http.get(f"{URL}/plots/nothing.png")
    assert missing.status_code == 404 and "log-ratio" in missing.json()["detail"]

    accepted = tank.http.post(URL + "/accept", json={"name": "tank-1"})
    assert accepted.status_code == 200, accepted.text
    after = profiles(tank)
    assert after["tank-1"] is True and set(after) == set(before) | {"tank-1"}
    assert tank.daemon.profile_name == "tank-1"
    assert tank.daemon.profiles["tank-1"].covariance is not None
    # The profile records the per-channel exposure it was made at (the simulated camera's, 10 ms).
    assert tank.daemon.profiles["tank-1"].calibration_exposure()[0].tolist() == [10000.0] * 3
    assert tank.http.get(URL).status_code == 404  # the session ended


def test_bad_captures_and_cancel_change_nothing(tank):
    before = profiles(tank)
    active = tank.daemon.profile_name
    assert tank.http.post(URL, json={"rig": "grey-plate"}).status_code == 422  # no markers to find it by
    assert tank.http.post(URL, json={"rig": "no-such-rig"}).status_code == 422
    assert tank.http.post(URL, json={"frames_per_capture": 0}).status_code == 422
    assert tank.http.post(URL, json={"frames_per_capture": 2}).status_code == 201
    # Too close: the exposure held from 1 m saturates the plate.
    tank.daemon.rig.place(0.7)
    assert wait_for(lambda: tank.http.get(URL).json()["live"].get("marker_distance_m", 0) < 0.8, 30.0, 0.2)
    r = tank.http.post(URL + "/captures", json={"distance_m": 0.7})
    assert r.status_code == 422 and "saturated" in r.json()["detail"], r.text
    # Out of view: no marker, no plate.
    tank.daemon.rig.place(0.25)
    assert wait_for(lambda: not tank.http.get(URL).json()["live"]["plate_found"], 30.0, 0.2)
    r = tank.http.post(URL + "/captures", json={"distance_m": 0.25})
    assert r.status_code == 422 and "plate not found" in r.json()["detail"]
    assert tank.http.get(URL).json()["session"]["captures"] == []
    move_plate(tank, 1.0)
    assert tank.http.post(URL + "/captures", json={"distance_m": 1.0}).status_code == 201
    assert tank.http.post(URL + "/captures", json={"distance_m": 1.0, "held_back": True}).status_code == 422
    assert tank.http.delete(URL).json()["state"] == "cancelled"
    assert profiles(tank) == before and tank.daemon.profile_name == active
    assert tank.http.get(URL).status_code == 404
