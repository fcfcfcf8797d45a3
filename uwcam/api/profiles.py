"""/api/v1/calibration/profiles: list, read, upload and activate calibration profiles."""

from __future__ import annotations

import asyncio
import re

from fastapi import APIRouter, Depends, HTTPException, Request

from uwcam.api.common import get_daemon
from uwcam.runtime.daemon import Daemon
from uwcam.fileio import UserInputError
from uwcam.calibration.profile import CalibrationProfile

router = APIRouter(prefix="/api/v1/calibration/profiles", tags=["calibration"])
MAX_PROFILE_BYTES = 1 << 20
"""Bytes; enforced while the upload streams in (:mod:`uwcam.api.limits`). Measured: a profile is
3 kB, 22 kB with an 8-bit response table, 0.3 MB with a 12-bit one, 4.8 MB with a 16-bit one."""
TOO_LARGE_HINT = ("a calibration profile is at most 0.3 MB unless it holds a 16-bit response table; put such a "
                  "profile into the profiles folder (profiles_dir) and restart uwcam instead")
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
"""Not starting with '.': such a file is hidden, and temporary files of atomic writes look so."""


@router.get("")
def list_profiles(d: Daemon = Depends(get_daemon)) -> list[dict]:
    """Known calibration profiles; one is active."""
    return [{"name": name, "active": name == d.profile_name, "created": p.provenance.created,
             "channels": p.channel_names, "method": p.provenance.method} for name, p in list(d.profiles.items())]


@router.get("/{name}")
def get_profile(name: str, d: Daemon = Depends(get_daemon)) -> dict:
    """One calibration profile, as stored."""
    if name not in d.profiles:
        raise HTTPException(status_code=404, detail=f"no profile '{name}'; known: {', '.join(d.profiles)}")
    return d.profiles[name].model_dump(mode="json")


PARSE_TIMEOUT_S = 30.0
"""An upload whose YAML takes longer than this to parse is refused (a real profile: under 0.5 s)."""

# Run by ``python -c`` in a child process: reads YAML or JSON bytes on stdin, writes a pickle of
# ("ok", data) or ("error", kind, message, line, column) to stdout. Only the parent's own child
# writes what the parent unpickles, and safe_load and json make nothing but plain values.
# A JSON body is read as JSON: YAML 1.1 reads a JSON number such as 1e-300 or 1e+308 (no dot) as a
# string, which the profile's strict numbers then refuse.
_PARSER = """
import json, pickle, sys, yaml
from uwcam.fileio import safe_load

class Twice(Exception):
    pass

def unique(pairs):
    out = {}
    for key, value in pairs:
        if key in out:
            raise Twice(f"key {key!r} is given twice; keep one")
        out[key] = value
    return out

try:
    text = sys.stdin.buffer.read().decode("utf-8")
    try:
        answer = ("ok", json.loads(text, object_pairs_hook=unique))
    except json.JSONDecodeError:  # not JSON: YAML
        answer = ("ok", safe_load(text))
except Twice as exc:
    answer = ("error", "json", str(exc), None, None)
except UnicodeDecodeError as exc:
    answer = ("error", "text", str(exc), None, None)
except yaml.YAMLError as exc:
    mark = getattr(exc, "problem_mark", None)
    answer = ("error", "yaml", getattr(exc, "problem", None) or str(exc), mark and mark.line, mark and mark.column)
except RecursionError:
    answer = ("error", "deep", "", None, None)
except ValueError as exc:
    answer = ("error", "value", str(exc), None, None)
sys.stdout.buffer.write(pickle.dumps(answer))
"""


async def parse_yaml(body: bytes) -> object:
    """YAML or JSON bytes → plain values, parsed by libyaml in a child process; HTTPException 422
    saying what is wrong.

    In a child process because libyaml composes a whole document without letting go of the
    interpreter (a 1 MB upload held status requests for 0.6-0.7 s), and PyYAML's pure-Python
    parser, which does let go, costs about nine times the CPU (16-21 s for 1 MB: the frame rate
    fell from 30 to 16). In the child, libyaml's second or so of CPU delays nothing here."""
    import pickle
    import sys

    child = await asyncio.create_subprocess_exec(sys.executable, "-c", _PARSER, stdin=asyncio.subprocess.PIPE,
                                                 stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        out, err = await asyncio.wait_for(child.communicate(body), PARSE_TIMEOUT_S)
    except TimeoutError:
        child.kill()
        await child.wait()
        raise HTTPException(status_code=422, detail=f"profile took over {PARSE_TIMEOUT_S:.0f} s to parse; "
                                                    "a calibration profile parses in under a second") from None
    if child.returncode != 0 or not out:
        last = (err.decode("utf-8", "replace").strip().splitlines() or ["no answer"])[-1]
        raise HTTPException(status_code=422, detail=f"profile could not be parsed: {last}")
    answer = pickle.loads(out)  # noqa: S301 (our own child's answer, plain values only)
    if answer[0] == "ok":
        return answer[1]
    _, kind, problem, line, column = answer
    if kind == "deep" or "nesting depth" in problem:  # libyaml's own limit: a profile is a few levels deep
        raise HTTPException(status_code=422, detail="profile is nested too deeply to be a calibration profile")
    if kind == "value":  # e.g. an integer of thousands of digits
        raise HTTPException(status_code=422, detail=f"profile holds a value that cannot be read: {problem}")
    where = f" at line {line + 1}, column {column + 1}" if line is not None else ""
    raise HTTPException(status_code=422, detail=f"profile is not valid YAML or JSON{where}: {problem}")


def profile_from_upload(data: object, name: str) -> CalibrationProfile:
    """Parsed values → a validated profile; HTTPException 422 saying what is wrong."""
    from uwcam.calibration.profile import profile_from_mapping

    if not isinstance(data, dict):
        raise HTTPException(status_code=422, detail="profile must be a mapping of keys to values")
    try:
        return profile_from_mapping(data, f"profile {name}")
    except UserInputError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    except RecursionError:
        raise HTTPException(status_code=422, detail="profile is nested too deeply to be a calibration profile") from None


@router.put("/{name}", openapi_extra={
    "requestBody": {"required": True, "content": {
        "application/x-yaml": {"schema": {"type": "string"}},
        "application/json": {"schema": {"type": "object", "description": "a uwcam calibration profile"}}}}})
async def upload_profile(name: str, request: Request, d: Daemon = Depends(get_daemon)) -> dict:
    """Upload a profile (YAML or JSON body, at most 1 MiB). It is validated in full, and checked
    as activating it would check it (this camera's channels and image, the live settings); a bad
    one is refused with the reason and changes nothing. Uploading does not activate it; uploading
    over the active profile applies at once."""
    if not NAME.fullmatch(name):
        raise HTTPException(status_code=422, detail="profile names use letters, digits, '.', '_' and '-' (1–64), "
                                                    "starting with a letter or digit")
    chunks, size = [], 0
    async for chunk in request.stream():  # the body limit middleware stops an oversized one here
        size += len(chunk)
        chunks.append(chunk)
    # Parsing and saving take time: in a child process and a worker thread, so the event loop
    # (status, streams) and the frame loop run on.
    data = await parse_yaml(b"".join(chunks))
    profile = await asyncio.to_thread(profile_from_upload, data, name)
    try:
        # The checks activation makes (Daemon.activate), here too: a profile that could never be put
        # in use (fx of 1e-300 px, quantisation_step 0 for an integer camera) is refused now, not stored.
        await asyncio.to_thread(d.check_profile, name, profile)
        await asyncio.to_thread(d.save_profile, name, profile)
    except UserInputError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    return {"name": name, "active": name == d.profile_name, "channels": profile.channel_names}


@router.post("/{name}/activate")
def activate_profile(name: str, d: Daemon = Depends(get_daemon)) -> dict:
    """Range with this profile from the next frame on (kept across restarts)."""
    if name not in d.profiles:
        raise HTTPException(status_code=404, detail=f"no profile '{name}'; known: {', '.join(d.profiles)}")
    try:
        d.activate(name)
    except UserInputError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    return {"name": name, "active": True}
