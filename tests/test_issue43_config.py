"""Issue #43, files: YAML that says a key twice, response files' errors, and the names a tank
calibration may be saved under."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from uwcam.fileio import UserInputError, load_yaml_mapping, safe_load

ROOT = Path(__file__).resolve().parents[1]


# -- item 24: duplicate keys ------------------------------------------------------------------

def test_a_key_given_twice_is_refused_with_the_key_and_both_lines(tmp_path):
    """PyYAML keeps the last of two ``api:`` sections silently; uwcam's loader says which key and where."""
    path = tmp_path / "rig.yaml"
    path.write_text("version: 1\napi: {port: 8081}\ncamera: {driver: sim}\napi: {port: 8082}\n")
    with pytest.raises(UserInputError) as caught:
        load_yaml_mapping(path, "configuration")
    message = str(caught.value)
    assert "\n" not in message
    for fragment in (str(path), "'api'", "line 4", "first at line 2"):
        assert fragment in message, (fragment, message)


def test_a_nested_key_given_twice_is_refused_too():
    with pytest.raises(yaml.YAMLError, match="'port' is given twice"):
        safe_load("api:\n  port: 1\n  host: 127.0.0.1\n  port: 2\n")


def test_the_config_command_refuses_a_key_given_twice_in_one_line(tmp_path, capsys):
    from uwcam.cli import main

    path = tmp_path / "rig.yaml"
    path.write_text("version: 1\ncamera: {driver: sim}\ncamera: {driver: sim}\n")
    assert main(["config", "check", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'camera' is given twice" in err[0], err


def test_merge_keys_may_still_be_overridden_and_equal_values_in_other_mappings_are_fine():
    data = safe_load("base: &b {port: 1, host: h}\napi:\n  <<: *b\n  port: 2\nother: {port: 2}\n")
    assert data["api"] == {"port": 2, "host": "h"} and data["other"] == {"port": 2}


@pytest.mark.parametrize("path", sorted(
    [*ROOT.glob("deploy/**/*.yaml"), *ROOT.glob("deploy/*.yml"), *ROOT.glob("calibration_rigs/*.yaml"),
     *ROOT.glob("drivers/lamp_protocols/*.yaml")]), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_shipped_yaml_file_says_each_key_once(path):
    """deploy/blueos/uwcam.yaml said ``api:`` twice: strict parsers (BlueOS's among them) refuse such a file."""
    assert isinstance(safe_load(path.read_text(encoding="utf-8")), (dict, list))


def test_the_blueos_configuration_keeps_its_cockpit_token_setting():
    from uwcam.config import load_config

    config = load_config(ROOT / "deploy/blueos/uwcam.yaml")
    assert config.api.cockpit_actions_token is True


# -- item 13: response files ------------------------------------------------------------------

@pytest.mark.parametrize("body, fragments", [
    ("kind: gamma\n", ("key 'kind'", "'srgb', 'rec709' or 'table'", "'gamma'")),
    ("kind: srgb\nbits: 9\n", ("key 'bits'", "8, 10, 12 or 16", "9")),
    ("kind: table\ntable: [[-1.0, 2.0]]\n", ("key 'table.0.0'", "greater than or equal to 0")),
    ("kind: srgb\ncolour: red\n", ("key 'colour'", "unknown key")),
])
def test_a_bad_response_file_names_the_key_and_what_it_may_hold(tmp_path, body, fragments):
    from uwcam.imaging.response import RESPONSE_FORMAT, load_response

    path = tmp_path / "response.yaml"
    path.write_text(f"format: {RESPONSE_FORMAT}\nversion: 1\n{body}")
    with pytest.raises(UserInputError) as caught:
        load_response(str(path), 3)
    message = str(caught.value)
    assert "validation error" not in message and "\n" not in message, message
    assert message.startswith(f"response file {path}: "), message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


# -- item 8: the name a tank calibration is accepted under ------------------------------------

@pytest.mark.parametrize("name", [".hidden", "..", ".", "-dash", "_under", "tank-1", "tank.2024_06", "T", "x" * 64,
                                  "x" * 65, "", "a/b", "tank\n"])
def test_a_tank_calibration_is_named_by_the_profiles_rule(name):
    """A name starting with '.' was saved and activated, then skipped at the next start (hidden
    files are not profiles); the accept request now takes exactly the names the profiles route takes."""
    from uwcam.api.calibration_session import Accept
    from uwcam.api.profiles import NAME

    try:
        Accept(name=name)
        accepted = True
    except ValidationError:
        accepted = False
    assert accepted == bool(NAME.fullmatch(name)), name
    if name.startswith("."):
        assert not accepted


def test_a_number_written_without_a_dot_is_a_number():
    """YAML 1.1 reads 1e-5 as a string; numbers users write are strict (a string is refused), so uwcam's
    loader reads it as YAML 1.2 and JSON do. A quoted one stays a string."""
    from uwcam.fileio import safe_load

    assert safe_load("a: 1e-5\nb: -2E+3\nc: 1.0e-05\nd: '1e-5'\ne: 7\n") == {"a": 1e-5, "b": -2000.0, "c": 1e-5, "d": "1e-5", "e": 7}
