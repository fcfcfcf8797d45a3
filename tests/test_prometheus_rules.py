"""The Prometheus alerting rules shipped in deploy/prometheus/: valid for Prometheus's own
``promtool check rules``, proven to fire (and not to fire) by ``promtool test rules`` on the unit
tests beside them, and written on metrics a running daemon really exports."""

import re
import subprocess
from pathlib import Path

import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from tests.served import Server
from tests.test_api import small_config
from tests.test_metrics import PROMTOOL
from tests.waiting import wait_for
from uwcam.config import RecordingConfig

RULES = Path(__file__).resolve().parent.parent / "deploy" / "prometheus"


def promtool(*args: str, cwd: Path = RULES) -> subprocess.CompletedProcess:
    assert Path(PROMTOOL).exists(), "promtool is needed: .ci/run installs Debian's prometheus package"
    return subprocess.run([PROMTOOL, *args], cwd=cwd, capture_output=True, text=True, timeout=120)


def test_the_rules_pass_promtool_check_rules():
    checked = promtool("check", "rules", "uwcam-alerts.yml")
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "SUCCESS: 7 rules found" in checked.stdout


def test_the_rules_fire_as_their_unit_tests_say():
    tested = promtool("test", "rules", "uwcam-alerts.test.yml")
    assert tested.returncode == 0, tested.stdout + tested.stderr


def test_the_unit_tests_would_catch_a_wrong_threshold(tmp_path):
    """The unit tests are live: the same tests on a rule with another threshold fail."""
    (tmp_path / "uwcam-alerts.test.yml").write_text((RULES / "uwcam-alerts.test.yml").read_text())
    rules = (RULES / "uwcam-alerts.yml").read_text()
    changed = rules.replace("uwcam_range_minimum_meters < 0.5", "uwcam_range_minimum_meters < 0.2")
    assert changed != rules
    (tmp_path / "uwcam-alerts.yml").write_text(changed)
    tested = promtool("test", "rules", "uwcam-alerts.test.yml", cwd=tmp_path)
    assert tested.returncode != 0 and "UwcamRangeBelow" in tested.stdout + tested.stderr


def rule_metrics() -> set[str]:
    """Every uwcam metric name the rules' expressions use."""
    groups = yaml.safe_load((RULES / "uwcam-alerts.yml").read_text())["groups"]
    names = set()
    for group in groups:
        for rule in group["rules"]:
            names |= set(re.findall(r"\buwcam_[a-z_]+", rule["expr"]))
    return names


@pytest.mark.slow
def test_every_metric_the_rules_use_is_exported_by_a_running_daemon(tmp_path):
    config = small_config().model_copy(update={"recording": RecordingConfig(folder=str(tmp_path))})
    with Server(config) as s:
        assert wait_for(lambda: s.http.get("/api/v1/status").json()["calibration"]["tracking"]["accepted"] > 2, 60.0)
        text = s.http.get("/metrics").text
    exported = {sample.name for family in text_string_to_metric_families(text) for sample in family.samples}
    used = rule_metrics()
    assert len(used) >= 8 and "uwcam_range_minimum_meters" in used
    assert used <= exported, f"the rules use metrics the daemon does not export: {sorted(used - exported)}"
