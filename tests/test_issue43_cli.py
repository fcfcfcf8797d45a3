"""Issue #43, the command line and what ships beside it: help texts that tell the truth, one-line
errors for a camera absent at the start and for NaN in calibration frames, the walkthrough run
right after the install, and the Dockerfile's documentation link."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pytest
import yaml

from uwcam.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "UWCAM_TOKEN"}
    return subprocess.run([sys.executable, "-m", "uwcam", *args], capture_output=True, text=True, timeout=300,
                          env=environment, cwd=cwd)


# -- item 10: help ----------------------------------------------------------------------------

def subcommands(parser: argparse.ArgumentParser, path: str = "uwcam"):
    """(``uwcam run``, its parser, its line in the parent's help) for every subcommand, depth first."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            summaries = {choice.dest: choice.help for choice in action._choices_actions}
            for name, sub in action.choices.items():
                yield f"{path} {name}", sub, summaries.get(name)
                yield from subcommands(sub, f"{path} {name}")


def test_every_subcommand_has_a_description_and_every_positional_argument_a_help_text():
    found = list(subcommands(build_parser()))
    assert {"uwcam run", "uwcam range", "uwcam config check", "uwcam repair"} <= {path for path, _, _ in found}
    missing = []
    for path, parser, summary in found:
        if not summary:
            missing.append(f"{path}: no line in the parent's help")
        if not (parser.description or "").strip():
            missing.append(f"{path}: no description")
        for action in parser._actions:
            if action.option_strings or isinstance(action, argparse._SubParsersAction):
                continue
            if action.help in (None, "", argparse.SUPPRESS):
                missing.append(f"{path}: positional {action.metavar or action.dest} has no help")
    assert not missing, missing


def test_the_help_says_which_install_runs_warmup():
    """deploy/install.sh runs ``uwcam warmup`` for a developer's install (an extras argument such as
    ``test``), never for the plain nor the lean one: the help must not claim it always does."""
    script = (ROOT / "deploy/install.sh").read_text()
    assert re.search(r'if \[ -z "\$extras" \].*?elif \[ "\$extras" = "lean" \].*?else.*?uwcam warmup', script, re.S)
    text = build_parser().format_help()
    warmup = " ".join(text[text.index("warmup "):text.index("reprocess")].split())
    assert "install.sh test" in warmup, warmup
    assert "(deploy/install.sh runs it)" not in warmup


# -- item 11: a camera that cannot be opened at the start -------------------------------------

def closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.parametrize("camera, fragment", [
    ({"driver": "v4l2", "options": {"device": "/dev/video99"}}, "/dev/video99 does not exist"),
    ({"driver": "stream", "options": {"url": "rtsp://127.0.0.1:{port}/camera"}}, "cannot open the stream rtsp://127.0.0.1:"),
], ids=["v4l2", "stream"])
def test_a_camera_absent_at_the_start_is_a_one_line_error(tmp_path, monkeypatch, capsys, camera, fragment):
    """A missing /dev/video99 or a stream server that is down raised DeviceLost through ``uwcam run``
    as a 20-line traceback; it is one line naming the device, and exit status 2."""
    from tests.synthetic import make_profile
    from uwcam.calibration.profile import save_profile

    monkeypatch.delenv("UWCAM_TOKEN", raising=False)
    save_profile(make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5], read_noise=2.0), tmp_path / "p.yaml")
    if camera["driver"] == "stream":
        camera = {**camera, "options": {"url": camera["options"]["url"].format(port=closed_port())}}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump({"version": 1, "calibration": str(tmp_path / "p.yaml"),
                                                       "camera": camera}))
    assert main(["run", "--config", str(tmp_path / "rig.yaml"), "--port", "0"]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("uwcam run: error: "), err
    assert fragment in lines[0] and "start uwcam run again" in lines[0], lines[0]
    assert "operator page" not in out


# -- item 12: NaN in a calibration frame ------------------------------------------------------

def test_calibrate_names_the_frame_with_non_finite_pixels_before_fitting(tmp_path):
    """A block of NaN under half the frame reached LAPACK ("On entry to DLASCL ...", then "SVD did
    not converge"), naming no image: now one line names the image and where its NaN are."""
    rng = np.random.default_rng(3)
    near = (rng.random((48, 64, 3)) * 50 + [3000, 2000, 1000]).astype(np.float32)
    far = (rng.random((48, 64, 3)) * 50 + [1500, 1500, 900]).astype(np.float32)
    far[10:20, 30:40] = np.nan
    far[5, 5, 1] = np.inf
    np.save(tmp_path / "near.npy", near)
    np.save(tmp_path / "far.npy", far)
    result = run_cli("calibrate", "near.npy", "far.npy", "--distance", "1", "--distance", "2", "-o", "out.yaml",
                     cwd=tmp_path)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    for fragment in ("image far.npy", "NaN or infinite", "101 pixels", "rows 5–19", "columns 5–39"):
        assert fragment in lines[0], (fragment, lines[0])
    assert "near.npy" not in lines[0] and "SVD" not in result.stderr
    assert not (tmp_path / "out.yaml").exists()


# -- item 9: the walkthrough right after the install ------------------------------------------

@pytest.mark.slow
def test_the_walkthrough_runs_without_uwcam_on_the_path(tmp_path):
    """README: ``bash deploy/install.sh`` puts uwcam in .venv, not on PATH; ``bash
    examples/walkthrough.sh`` then stopped at once with "uwcam: command not found"."""
    venv_bin = Path(sys.executable).parent
    if not (venv_bin / "uwcam").exists() or venv_bin != ROOT / ".venv" / "bin":
        pytest.skip("needs the checkout's .venv, as deploy/install.sh makes it")
    path = os.pathsep.join(d for d in os.environ.get("PATH", "").split(os.pathsep)
                           if d and not (Path(d) / "uwcam").exists())
    assert shutil.which("uwcam", path=path) is None
    environment = {k: v for k, v in os.environ.items() if k not in ("UWCAM_TOKEN", "VIRTUAL_ENV")} | {"PATH": path}
    result = subprocess.run(["bash", str(ROOT / "examples/walkthrough.sh"), str(tmp_path / "work")], capture_output=True,
                            text=True, timeout=600, env=environment, cwd=tmp_path)
    assert result.returncode == 0, (result.stdout[-2000:], result.stderr[-2000:])
    assert "command not found" not in result.stderr
    assert re.search(r"5\. range\.npy: rms error [0-9.]+ cm", result.stdout), result.stdout[-2000:]
    assert (tmp_path / "work" / "profile.yaml").is_file()


# -- item 25: the Dockerfile's documentation link ---------------------------------------------

def github_anchors(markdown: str) -> set[str]:
    """The anchors GitHub makes for a README's headings: the heading's text as rendered, lower case,
    everything but letters, digits, spaces, '-' and '_' dropped, each space a '-'; a repeated
    one gets -1, -2, ..."""
    anchors: set[str] = set()
    counts: dict[str, int] = {}
    fenced = False
    for line in markdown.splitlines():
        if re.match(r"^\s*(```|~~~)", line):
            fenced = not fenced
            continue
        heading = None if fenced else re.match(r"^ {0,3}#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading is None:
            continue
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.group(1))  # a link shows its text
        text = re.sub(r"[`*]", "", text)
        slug = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
        n = counts.get(slug, 0)
        counts[slug] = n + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def test_github_anchors_follow_githubs_rules():
    assert github_anchors("# A `b`: c, d\n## Set-up\n```\n# not a heading\n```\n## Set-up\n") == \
        {"a-b-c-d", "set-up", "set-up-1"}


def test_the_documentation_label_points_at_a_heading_of_the_readme():
    from tests.test_dockerfile import labels

    link = urlparse(json.loads(labels()["links"])["documentation"])
    assert link.fragment, link
    if link.path.endswith(".md"):  # a document of the repository, not the README
        pytest.fail(f"documentation link {link.geturl()} is not the README")
    anchors = github_anchors((ROOT / "README.md").read_text(encoding="utf-8"))
    assert link.fragment in anchors, (link.fragment, sorted(anchors))
