"""uwcam as a new user gets it: a copy of this checkout as a fresh clone has it, installed and
started with the README's first set-up command as written, in an environment of its own.

Used by tests/test_installed.py and bench/bench_first_start.py. Nothing here imports uwcam: the
daemon runs from the copy's own ``.venv``, which has no test extras, and is reached over HTTP.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

from tests.ports import free_port

ROOT = Path(__file__).resolve().parents[1]


def readme_run_command(readme: Path = ROOT / "README.md") -> str:
    """The first shell block under the README's "Set-up" heading: the command that installs uwcam
    and runs the daemon on its embedded default."""
    text = readme.read_text(encoding="utf-8")
    setup = text.split("## Set-up", 1)[1]
    block = re.search(r"```sh\n(.*?)```", setup, re.S)
    assert block, "README.md: no ```sh block under '## Set-up'"
    command = block.group(1).strip()
    assert "\n" not in command and command.endswith("uwcam run"), \
        f"README.md's set-up command should be one line ending in 'uwcam run', got {command!r}"
    return command


def copy_checkout(destination: Path) -> Path:
    """The files a clone of this checkout would hold (tracked and not ignored; the working tree's
    versions), without .venv, caches or build outputs."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            cwd=ROOT, check=True, capture_output=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = ROOT / name
        if source.is_file():  # a tracked file deleted in the working tree is not in a clone
            target = destination / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    return destination


def user_environment(home: Path) -> dict[str, str]:
    """A new user's environment: an empty home (so an empty ~/.cache/uwcam), no virtual
    environment active, none of this test run's variables. pip and uv keep their download caches:
    what is tested is what gets installed, not how fast the registry is."""
    keep = ("PATH", "LANG", "LC_ALL", "TERM", "TZ", "PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL",
            "PIP_FIND_LINKS", "PIP_CONSTRAINT", "PIP_CERT", "PIP_DEFAULT_TIMEOUT", "http_proxy",
            "https_proxy", "no_proxy", "HTTP_PROXY", "HTTPS_PROXY", "NO_PROXY")
    env = {k: os.environ[k] for k in keep if k in os.environ}
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "/usr/bin:/bin").split(os.pathsep)
                                  if ".venv" not in p)
    env["HOME"] = str(home)
    pip_cache = os.environ.get("PIP_CACHE_DIR") or os.path.expanduser("~/.cache/pip")
    env["PIP_CACHE_DIR"] = pip_cache
    env["UV_CACHE_DIR"] = os.environ.get("UV_CACHE_DIR") or os.path.expanduser("~/.cache/uv")  # likewise uv's
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    env["PIP_ROOT_USER_ACTION"] = "ignore"
    return env


class UserDaemon:
    """``bash -c "<README command> --port N"`` in its own process group, as in a terminal; its
    output is collected line by line with the time each line came."""

    def __init__(self, clone: Path, home: Path, command: str) -> None:
        self.clone, self.home, self.port = clone, home, free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.command = f"{command} --port {self.port}"
        self.lines: list[tuple[float, str]] = []
        self.started = time.monotonic()
        self.process = subprocess.Popen(["bash", "-c", self.command], cwd=clone, env=user_environment(home),
                                        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        start_new_session=True)
        self._reader = threading.Thread(target=self._read, name="user-daemon-output", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for raw in self.process.stdout:
            self.lines.append((time.monotonic() - self.started, raw.decode(errors="replace").rstrip()))

    @property
    def output(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def seconds_until(self, pattern: str) -> float | None:
        """Seconds from the command's start to its first output line matching ``pattern``."""
        return next((t for t, line in self.lines if re.search(pattern, line)), None)

    def get(self, path: str, timeout: float = 5.0) -> bytes:
        with urllib.request.urlopen(self.url + path, timeout=timeout) as answer:
            return answer.read()

    def wait_until(self, condition, timeout: float, what: str) -> float:
        """Poll ``condition()`` until true; seconds since the command started. Fails with the
        daemon's output when it exits or the time runs out."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise AssertionError(f"the README command exited ({self.process.returncode}) before {what}:\n"
                                     f"{self.output[-4000:]}")
            try:
                if condition():
                    return time.monotonic() - self.started
            except OSError:
                pass  # not listening yet
            time.sleep(0.2)
        raise AssertionError(f"no {what} within {timeout:.0f} s:\n{self.output[-4000:]}")

    def ctrl_c(self, timeout: float = 60.0) -> int:
        """Ctrl-C as a terminal sends it (SIGINT to the foreground process group); the exit status."""
        os.killpg(self.process.pid, signal.SIGINT)
        try:
            code = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
            raise AssertionError(f"Ctrl-C did not stop the daemon within {timeout:.0f} s:\n{self.output[-4000:]}")
        self._reader.join(10.0)
        return code

    def kill(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
        self._reader.join(10.0)
        self.process.stdout.close()
