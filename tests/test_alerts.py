"""The alert rules and their evaluation (uwcam/runtime/alerts.py), on made-up observations and times:
raised once after the rule's time, cleared once after ``clear_s``, no evidence changes nothing."""

from datetime import datetime, timedelta, timezone

import pytest

from uwcam.runtime.alerts import (AlertEvaluator, DropWindow, calibration_conditions, device_conditions, disk_condition,
                          dropped_condition, range_condition)
from uwcam.config import (AlertsConfig, CalibrationAlertConfig, DaemonConfig, DeviceAlertConfig,
                          FramesDroppedAlertConfig, RangeAlertConfig, load_config)
from uwcam.fileio import UserInputError

WALL0 = 1_800_000_000.0


def run(evaluator, steps):
    """steps: (monotonic s, conditions) → every event, in order."""
    events = []
    for t, conditions in steps:
        events += evaluator.update(conditions, t, WALL0 + t)
    return events


def summary(minimum):
    return {"frame": 1, "minimum_m": minimum, "centre_m": 2.0}


def test_range_alert_is_raised_once_after_its_time_and_cleared_once_after_clear_s():
    cfg = AlertsConfig(range=RangeAlertConfig(below_m=0.5, for_s=1.0), clear_s=2.0)
    ev = AlertEvaluator(cfg)
    # 10 readings a second: above, then below from t=1.0, back above from t=4.0
    steps = [(t / 10, range_condition(cfg, summary(0.8 if t < 10 or t >= 40 else 0.3))) for t in range(0, 80)]
    events = run(ev, steps)
    assert [(e.state, e.key) for e in events] == [("raised", "range"), ("cleared", "range")]
    raised, cleared = events
    assert raised.time == pytest.approx(WALL0 + 2.0) and raised.since == pytest.approx(WALL0 + 1.0)
    assert raised.values == {"minimum_m": 0.3, "below_m": 0.5, "frame": 1} and raised.severity == "critical"
    assert raised.message == "range 0.30 m < 0.5 m"
    assert cleared.time == pytest.approx(WALL0 + 6.0) and cleared.since == pytest.approx(WALL0 + 4.0)
    assert cleared.values["minimum_m"] == 0.8 and cleared.message.startswith("cleared: range 0.80 m")
    assert ev.active() == [] and list(ev.history) == events


def test_a_reading_that_breaks_the_wait_starts_it_afresh_both_ways():
    cfg = AlertsConfig(range=RangeAlertConfig(below_m=0.5, for_s=1.0), clear_s=1.0)
    ev = AlertEvaluator(cfg)
    low, high = range_condition(cfg, summary(0.3)), range_condition(cfg, summary(0.9))
    # below for 0.9 s, one reading above, below again: raised 1 s after the second start
    assert run(ev, [(0.0, low), (0.9, low), (1.0, high), (1.1, low), (2.0, low)]) == []
    assert [e.state for e in run(ev, [(2.1, low)])] == ["raised"]
    # above for 0.9 s, one reading below: still raised; then above for 1 s: cleared
    assert run(ev, [(3.0, high), (3.9, high), (4.0, low), (4.5, high), (5.4, high)]) == []
    assert [e.state for e in run(ev, [(5.5, high)])] == ["cleared"]


def test_no_evidence_changes_nothing():
    cfg = AlertsConfig(range=RangeAlertConfig(below_m=0.5, for_s=0.0), clear_s=0.0)
    ev = AlertEvaluator(cfg)
    assert [e.state for e in run(ev, [(0.0, range_condition(cfg, summary(0.2)))])] == ["raised"]
    unknown = range_condition(cfg, summary(None))
    assert unknown[0].active is None
    assert run(ev, [(t, unknown) for t in range(1, 10)]) == [] and len(ev.active()) == 1
    assert ev.current("range").values["minimum_m"] == 0.2  # the last figure with evidence


def health(state, reason="x"):
    return {"health": {"state": state, "reason": reason, "for_s": 1.0}}


def test_devices_lost_or_recovering_each_their_own_alert():
    cfg = AlertsConfig(device=DeviceAlertConfig(for_s=5.0), clear_s=0.0)
    ev = AlertEvaluator(cfg)

    def status(camera, lamp):
        return {"camera": health(camera, "no frame for 0.5 s"), "lamp": health(lamp), "rangefinder": None}

    steps = [(0.0, device_conditions(cfg, status("ok", "ok"))),
             (1.0, device_conditions(cfg, status("lost", "ok"))),
             (3.0, device_conditions(cfg, status("recovering", "ok"))),  # still down: the wait goes on
             (5.9, device_conditions(cfg, status("lost", "recovering"))),
             (6.0, device_conditions(cfg, status("lost", "recovering"))),
             (10.0, device_conditions(cfg, status("ok", "stopped"))),  # stopped is not lost
             (10.9, device_conditions(cfg, status("ok", "lost")))]
    events = run(ev, steps)
    assert [(e.state, e.key, e.time - WALL0) for e in events] == [("raised", "device/camera", 6.0),
                                                                  ("cleared", "device/camera", 10.0)]
    assert events[0].values["state"] == "lost" and events[0].severity == "error"
    assert events[0].message == "camera lost: no frame for 0.5 s"
    assert {c.subject for c in device_conditions(cfg, status("ok", "ok"))} == {"camera", "lamp"}


def test_calibration_age_and_drift_beyond_sigma():
    cfg = AlertsConfig(calibration=CalibrationAlertConfig(max_age_days=30, drift_sigmas=3.0, drift_for_s=0.0), clear_s=0.0)
    now = datetime(2026, 11, 25, 12, 0, tzinfo=timezone.utc)
    made = (now - timedelta(days=31)).isoformat()
    tracking = {"accepted": 10, "drift": {"R": 0.004, "G": 0.0, "B": -0.02},
                "drift_std": {"R": 0.002, "G": 0.0, "B": 0.005}}
    conditions = calibration_conditions(cfg, {"calibration": {"name": "p", "created": made, "tracking": tracking}},
                                        now.timestamp())
    by_rule = {c.rule: c for c in conditions}
    assert by_rule["calibration_age"].active and by_rule["calibration_age"].values["age_days"] == pytest.approx(31.0)
    drift = by_rule["attenuation_drift"]  # B: 0.02 / 0.005 = 4 σ > 3; R: 2 σ; G: no σ, not judged
    assert drift.active and drift.values["channel"] == "B" and drift.values["sigmas"] == pytest.approx(4.0)
    fresh = {"calibration": {"created": (now - timedelta(days=29)).isoformat(),
                             "tracking": {**tracking, "drift": {"R": 0.004, "G": 0.5, "B": 0.01}}}}
    assert [c.active for c in calibration_conditions(cfg, fresh, now.timestamp())] == [False, False]
    # no tracking accepted yet, or an unreadable date: no evidence, no condition
    assert calibration_conditions(cfg, {"calibration": {"created": "yesterday",
                                                        "tracking": {**tracking, "accepted": 0}}}, now.timestamp()) == []


def test_disk_below_its_share():
    cfg = AlertsConfig(disk_free_below_percent=10.0)
    low = disk_condition(cfg, {"recording": {"disk_free_bytes": 9, "disk_total_bytes": 100}})
    ok = disk_condition(cfg, {"recording": {"disk_free_bytes": 11, "disk_total_bytes": 100}})
    assert low[0].active and low[0].values["free_percent"] == 9.0 and not ok[0].active
    assert disk_condition(cfg, {"recording": {"disk_free_bytes": None, "disk_total_bytes": None}}) == []


def test_frames_dropped_over_the_window():
    cfg = AlertsConfig(frames_dropped=FramesDroppedAlertConfig(above_percent=20.0, window_s=10.0))
    window = DropWindow(10.0)
    # 10 frames a second; 1 in 10 dropped for 10 s, then 3 in 10
    verdicts = []
    captured = dropped = 0
    for t in range(0, 31):
        verdicts.append(dropped_condition(cfg, window, {"frames": {"captured": captured, "dropped": dropped}}, float(t)))
        captured += 10
        dropped += 1 if t < 10 else 3
    assert all(v == [] for v in verdicts[:10])  # the window is not full yet
    assert verdicts[10][0].active is False and verdicts[10][0].values["dropped_percent"] == pytest.approx(10.0)
    assert verdicts[30][0].active is True and verdicts[30][0].values["dropped_percent"] == pytest.approx(30.0)
    # a restarted counter starts the window afresh instead of giving a negative share
    assert dropped_condition(cfg, window, {"frames": {"captured": 5, "dropped": 0}}, 31.0) == []


def test_rules_from_a_configuration_are_checked(tmp_path):
    path = tmp_path / "uwcam.yaml"
    path.write_text("alerts:\n  range: {below_m: -1}\n")
    with pytest.raises(UserInputError, match=r"alerts\.range\.below_m") as bad:
        load_config(path)
    assert "\n" not in str(bad.value)
    with pytest.raises(ValueError, match="disk_free_below_percent"):
        DaemonConfig.model_validate({"alerts": {"disk_free_below_percent": float("nan")}})
    cfg = DaemonConfig.model_validate({"alerts": {"range": {"below_m": 0.5, "for_s": 2}, "device": None}})
    assert cfg.alerts.range.below_m == 0.5 and cfg.alerts.device is None
