"""The container image's recipe, checked without building it (no registry is reachable here).

Parses the Dockerfile as Docker does (backslash-newline continuations, shell-like quoting, ARG
defaults), checks every BlueOS extension label and its JSON, that everything COPY'd exists
and is let through by .dockerignore, and runs the image's own helper scripts.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import stat
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from uwcam.config import load_config

ROOT = Path(__file__).resolve().parents[1]
BLUEOS_LABELS = {"version", "permissions", "authors", "company", "readme", "links", "type", "tags", "requirements"}
PORT = 6480
BLUEOS_PORTS = {22, 80, 81, 2748, 2770, 5201, 5555, 5777, 6020, 6021, 6030, 6040, 7000, 7777, 8000, 8081, 8088, 8554, 9000,
                9002, 9090, 9100, 9101, 9110, 9111, 9120, 9134, 9150, 9151, 9152, 27353, 7117, 7118, 8080}
"""Ports BlueOS's own services use (bluerobotics/BlueOS 8e16119: core/services/helper/main.py
BLUEOS_SYSTEM_SERVICES_PORTS and SKIP_PORTS, core/tools/nginx/nginx.conf's proxy_pass targets),
and 8080, from which its MAVLink inspector view loads an iframe (core/frontend/src/views/MavlinkInspectorView.vue)."""


def instructions() -> list[tuple[str, str]]:
    text = (ROOT / "Dockerfile").read_text()
    logical, current = [], ""
    for line in text.splitlines():
        if not current and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.endswith("\\"):
            current += line[:-1]
            continue
        logical.append(current + line)
        current = ""
    assert not current, "the Dockerfile ends inside a continued line"
    out = []
    for line in logical:
        keyword, _, rest = line.strip().partition(" ")
        out.append((keyword.upper(), rest.strip()))
    return out


def labels() -> dict[str, str]:
    args = {}
    found: dict[str, str] = {}
    for keyword, rest in instructions():
        if keyword == "ARG" and "=" in rest:
            name, _, default = rest.partition("=")
            args[name] = default
        if keyword == "LABEL":
            for word in shlex.split(rest, posix=True):
                key, sep, value = word.partition("=")
                assert sep, f"LABEL {word!r} is not key=value"
                found[key] = re.sub(r"\$\{(\w+)\}", lambda m: args[m.group(1)], value)
    return found


def test_every_blueos_label_is_there_and_its_json_parses():
    found = labels()
    assert BLUEOS_LABELS <= set(found), BLUEOS_LABELS - set(found)
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert found["version"] == version
    assert found["type"] == "device-integration"
    assert re.fullmatch(r"core >= \d+(\.\d+)*", found["requirements"])
    assert found["readme"].startswith("https://raw.githubusercontent.com/") and "{tag}" in found["readme"]

    permissions = json.loads(found["permissions"])
    # Docker's container-create options: NetworkMode belongs in HostConfig, nowhere else.
    assert set(permissions) <= {"ExposedPorts", "HostConfig", "Env", "Labels"}, set(permissions)
    assert permissions["ExposedPorts"] == {f"{PORT}/tcp": {}}
    host = permissions["HostConfig"]
    assert host["NetworkMode"] == "host"  # GigE Vision discovery is UDP broadcast
    assert host["Privileged"] is True and "/dev:/dev" in host["Binds"]
    assert any(b.endswith(":/etc/uwcam") for b in host["Binds"])

    authors = json.loads(found["authors"])
    assert authors and all({"name", "email"} <= set(a) for a in authors)
    company = json.loads(found["company"])
    assert {"name", "about", "email"} <= set(company)
    links = json.loads(found["links"])
    assert {"website", "source", "support", "documentation"} <= set(links)
    assert all(url.startswith("https://") for url in links.values())
    tags = json.loads(found["tags"])
    assert isinstance(tags, list) and tags and all(isinstance(t, str) for t in tags)


def test_what_the_image_copies_exists_and_is_not_ignored():
    ignore = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    assert ignore[0] == "*", "the context starts empty and lets named paths in"
    allowed = [p[1:].rstrip("/") for p in ignore if p.startswith("!")]
    copies = [rest for keyword, rest in instructions() if keyword == "COPY" and "--from" not in rest]
    assert copies
    for rest in copies:
        *sources, _ = rest.split()
        for source in sources:
            assert (ROOT / source).exists(), source
            assert any(source == a or source.startswith(a + "/") for a in allowed), f"{source} is left out by .dockerignore"
    # The build needs the package's sources; none of them is ignored.
    for package in ("uwcam", "drivers", "calibration_rigs", "pyproject.toml", "README.md"):
        assert package in allowed
    entry = [rest for keyword, rest in instructions() if keyword == "ENTRYPOINT"]
    assert entry == ['["/usr/local/bin/uwcam-entrypoint"]']
    assert os.stat(ROOT / "deploy/blueos/entrypoint.sh").st_mode & stat.S_IXUSR


@pytest.mark.parametrize("arch", ["amd64", "arm64", "arm"])
def test_requirements_per_architecture(arch):
    out = subprocess.run([sys.executable, str(ROOT / "deploy/blueos/requirements.py"), arch],
                         capture_output=True, text=True, check=True).stdout.splitlines()  # markers hold spaces
    names = {re.split(r"[<>=!~]", d)[0].lower() for d in out}
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = project["dependencies"] + project["optional-dependencies"]["reports"] + project["optional-dependencies"]["zenoh"]
    assert len(out) == len(declared) - (3 if arch == "arm" else 0)
    # The image serves the page's live view: uvicorn needs a WebSocket library beside it.
    assert {"numpy", "opencv-python-headless", "fastapi", "uvicorn", "websockets"} <= names
    # A tank calibration from the page draws plots; a vehicle may be watched on Zenoh; it does
    # not reprocess dives on a Dask cluster.
    assert {"matplotlib", "eclipse-zenoh"} <= names and "distributed" not in names
    if arch == "arm":
        assert not names & {"numba", "harvesters", "pymavlink"}
    else:
        assert {"numba", "harvesters", "pymavlink"} <= names


def test_requirements_refuse_an_unknown_architecture():
    done = subprocess.run([sys.executable, str(ROOT / "deploy/blueos/requirements.py"), "riscv64"],
                          capture_output=True, text=True)
    assert done.returncode != 0 and "unknown target architecture 'riscv64'" in done.stderr


def test_the_image_listens_on_a_port_no_blueos_service_uses():
    assert PORT not in BLUEOS_PORTS
    exposed = [rest for keyword, rest in instructions() if keyword == "EXPOSE"]
    health = next(rest for keyword, rest in instructions() if keyword == "HEALTHCHECK")
    assert exposed == [str(PORT)] and f"'UWCAM_PORT', '{PORT}'" in health
    assert f"{PORT}" in (ROOT / "docs/blueos.md").read_text()


def test_entrypoint_seeds_the_configuration_and_a_token(tmp_path):
    """Run the entry point with a stand-in ``uwcam`` that records how it was started."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "python").symlink_to(sys.executable)
    (bin_dir / "uwcam").write_text('#!/bin/sh\necho "$@" > "$RECORD"\necho "$UWCAM_TOKEN" >> "$RECORD"\n')
    (bin_dir / "uwcam").chmod(0o755)
    conf = tmp_path / "conf"
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "UWCAM_CONFIG_DIR": str(conf), "RECORD": str(tmp_path / "record"),
           "UWCAM_DEFAULT_CONFIG": str(ROOT / "deploy/blueos/uwcam.yaml")}
    script = str(ROOT / "deploy/blueos/entrypoint.sh")
    subprocess.run(["sh", script], env=env, check=True, capture_output=True)
    args, token = (tmp_path / "record").read_text().splitlines()
    assert args == f"run --config {conf}/uwcam.yaml --host 0.0.0.0 --port {PORT}"
    assert len(token) >= 32 and (conf / "token").read_text().strip() == token
    assert oct((conf / "token").stat().st_mode & 0o777) == "0o600"
    # A second start keeps the token and the (edited) configuration.
    (conf / "uwcam.yaml").write_text("version: 1\n")
    subprocess.run(["sh", script], env={**env, "UWCAM_PORT": "8090"}, check=True, capture_output=True)
    args, again = (tmp_path / "record").read_text().splitlines()
    assert again == token and args.endswith("--port 8090") and (conf / "uwcam.yaml").read_text() == "version: 1\n"


def test_the_shipped_configuration_is_valid_and_sends_nothing_to_the_autopilot():
    config = load_config(ROOT / "deploy/blueos/uwcam.yaml")
    assert config.camera.driver == "sim" and config.mavlink is None  # simulated ranges never reach an autopilot
