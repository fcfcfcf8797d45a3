"""The live feedback and the capture judge a frame alike: whatever the feedback says of a frame
(capture_ok, and the first refusal), a capture of that frame answers the same, for saturation on
the target, a plate out of view, a wrong distance and no plate at all. Frames from the simulator
(the marker plate at 1.5 m), altered where the test needs a fault."""

from __future__ import annotations

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.calibration.fit import MAX_SATURATED_FRACTION
from uwcam.calibration.session import CalibrationSession, SessionError
from uwcam.calibration.rig import builtin_rig_path, load_rig
from uwcam.simulation import Lamp, SimulatedWorld

LEVEL = 65535.0


@pytest.fixture(scope="module")
def scene():
    rig = load_rig(builtin_rig_path("charuco-plate"))
    world = SimulatedWorld(scene="plate", distance=1.5, size=(640, 360), rig=rig, lamp=Lamp(position=(0.3, -0.8, 0)))
    return rig, world


def session(scene) -> CalibrationSession:
    rig, world = scene
    base = make_profile([0.4, 0.05, 0.0], [0.0, 0.0, 0.0], noise_floor=20.0, dark_level=100.0, saturation_level=LEVEL)
    return CalibrationSession("charuco-plate", rig, world.intrinsics, base)


def verdicts(s: CalibrationSession, frame, distance: float) -> tuple[list[str], str | None]:
    live = s.feedback(frame, distance, None)
    try:
        s.capture([frame] * 3, distance, False, None, [None] * 3)
        answer = None
    except SessionError as exc:
        answer = f"{exc.status} {exc}"
    assert live["capture_ok"] == (answer is None)
    return live["refusals"], answer


def saturate(frame, target_box, fraction: float, channel: int):
    """``frame`` with the first ``fraction`` of the target box's rows clipped in one channel."""
    out = frame.copy()
    x, y, w, h = target_box
    rows = int(round(fraction * h))
    out[y : y + rows, x : x + w, channel] = int(LEVEL)
    return out


def test_feedback_and_capture_agree_on_every_frame(scene):
    rig, world = scene
    frame = world.frame(0)
    s = session(scene)
    live = s.feedback(frame, 1.5, None)
    assert live["capture_ok"] and live["refusals"] == [] and live["saturated_fraction"] == 0
    box = live["target_box"]

    # Clipped on a little of the target in one channel (allowed), then on more (refused by both).
    # The black patch is not plate: the fraction counts the target region without it.
    refusals, answer = verdicts(session(scene), saturate(frame, box, 0.5 * MAX_SATURATED_FRACTION, 2), 1.5)
    assert refusals == [] and answer is None
    s = session(scene)
    clipped = saturate(frame, box, 0.05, 2)
    live = s.feedback(clipped, 1.5, None)
    assert live["saturated_fraction"] == pytest.approx(live["channels"]["B"]["saturated_fraction"])
    assert 0.04 < live["saturated_fraction"] < 0.07 and live["channels"]["R"]["saturated_fraction"] == 0
    refusals, answer = verdicts(s, clipped, 1.5)
    assert answer == f"422 {refusals[0]}" and "saturated in channel B" in answer

    # A distance the markers disagree with, then no plate (the lamp-lit water alone).
    refusals, answer = verdicts(session(scene), frame, 1.7)
    assert answer == f"422 {refusals[0]}" and "but 1.700 m was given" in answer
    empty = np.full_like(frame, 500)
    refusals, answer = verdicts(session(scene), empty, 1.5)
    assert answer == f"422 {refusals[0]}" and answer.startswith("422 plate not found: no marker")


def test_a_plate_cut_by_the_edge_is_refused_by_both(scene):
    rig, world = scene
    frame = world.frame(0)
    cut = np.ascontiguousarray(frame[:, 250:])
    from uwcam.optics.geometry import Intrinsics

    intr = world.intrinsics
    s = CalibrationSession("charuco-plate", rig, Intrinsics(intr.fx, intr.fy, intr.cx - 250, intr.cy), session(scene).base)
    live = s.feedback(cut, 1.5, None)
    assert live["plate_found"] and live["target_in_view"] is False
    refusals, answer = verdicts(s, cut, 1.5)
    assert answer == f"422 {refusals[0]}" and "runs off the image" in answer


def test_a_kept_session_comes_back_whole_and_a_foreign_or_damaged_one_is_set_aside(scene, tmp_path):
    from uwcam.calibration.session_store import load_session, save_session

    rig, world = scene
    s = session(scene)
    frames = [world.frame(k) for k in range(2)]
    s.capture(frames, 1.5, False, 1.49, [None, None])
    folder = tmp_path / "calibration-session"
    save_session(s, str(folder))
    back = load_session(str(folder), frames[0].shape)
    assert back.id == s.id and back.rig_name == "charuco-plate" and back.state == "positioning"
    (c,) = back.captures
    assert c.distance_m == 1.5 and c.rangefinder_m == 1.49 and not c.held_back
    assert all(np.array_equal(a, b) for a, b in zip(c.frames, frames))
    assert c.pose.target_box == s.captures[0].pose.target_box and c.pose.markers_found == s.captures[0].pose.markers_found
    assert back.base.model_dump() == s.base.model_dump()
    # The session goes on where it was: the next capture is checked against the kept ones.
    with pytest.raises(SessionError, match="already used for the fit"):
        back.capture(frames, 1.5, True, None, [None, None])

    # Another camera's captures (another image size): not resumed, and not lost.
    assert load_session(str(folder), (480, 640, 3)) is None
    (aside,) = tmp_path.glob("calibration-session.unreadable-*")
    assert (aside / "capture-0.npy").exists() and not folder.exists()
    # A damaged record likewise.
    save_session(s, str(folder))
    (folder / "session.json").write_text("{not json")
    assert load_session(str(folder), frames[0].shape) is None
    assert len(list(tmp_path.glob("calibration-session.unreadable-*"))) == 2 and not folder.exists()


def test_a_fit_on_two_close_distances_says_why_it_is_poor(scene):
    rig, world = scene
    s = session(scene)
    s.base = s.base.model_copy(update={"channels": [c.model_copy(update={"dark_level": world.camera.dark_level_dn})
                                                    for c in s.base.channels]})
    for d in (1.5, 1.6):
        w = SimulatedWorld(scene="plate", distance=d, size=(640, 360), rig=rig, lamp=Lamp(position=(0.3, -0.8, 0)),
                           fixed_exposure=world.exposure)
        s.capture([w.frame(k) for k in range(3)], d, False, None, [None] * 3)
    result = s.fit()
    warnings = result["warnings"]
    assert any(w.startswith("only 2 distances") for w in warnings), warnings
    assert any(w.startswith("the distances span only 0.10 m") for w in warnings), warnings
    assert not any("changed colour" in w for w in warnings)  # the simulated lamp is steady
