"""/api/v1/calibration/profiles: list, read, upload and activate calibration profiles."""

from __future__ import annotations

import asyncio
import re

from fastapi import APIRouter, Depends, HTTPException, Request

from uwcam.api.common import get_daemon
from uwcam.daemon import Daemon
from uwcam.fileio import UserInputError
from uwcam.profile import CalibrationProfile

router = APIRouter(prefix="/api/v1/calibration/profiles", tags=["calibration"])
MAX_PROFILE_BYTES = 1 << 20
"""Bytes; enforced while the upload streams in (:mod:`uwcam.api.limits`)."""
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


def parse_profile(body: bytes, name: str) -> CalibrationProfile:
    """YAML or JSON bytes → a validated profile; HTTPException 422 saying what is wrong."""
    import yaml

    from uwcam.profile import profile_from_mapping

    try:
        # The pure-Python parser, not libyaml's: an upload is parsed in a worker thread, and
        # libyaml composes a whole document without letting go of the interpreter (a 1 MB upload
        # held status requests for 0.6-0.7 s of its 1.3 s); the pure-Python one yields every few ms.
        data = yaml.safe_load(body.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise HTTPException(status_code=422, detail=f"profile is not valid YAML or JSON: {exc}") from None
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc)
        if "nesting depth" in problem:  # libyaml's own limit: a profile is a few levels deep
            raise HTTPException(status_code=422, detail="profile is nested too deeply to be a calibration profile") from None
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise HTTPException(status_code=422, detail=f"profile is not valid YAML or JSON{where}: {problem}") from None
    except RecursionError:
        raise HTTPException(status_code=422, detail="profile is nested too deeply to be a calibration profile") from None
    except ValueError as exc:  # e.g. an integer of thousands of digits
        raise HTTPException(status_code=422, detail=f"profile holds a value that cannot be read: {exc}") from None
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
    """Upload a profile (YAML or JSON body, at most 1 MiB). It is validated in full; a bad one
    is refused with the reason and changes nothing. Uploading does not activate it; uploading
    over the active profile is checked as activating it would be, and applies at once."""
    if not NAME.fullmatch(name):
        raise HTTPException(status_code=422, detail="profile names use letters, digits, '.', '_' and '-' (1–64), "
                                                    "starting with a letter or digit")
    chunks, size = [], 0
    async for chunk in request.stream():  # the body limit middleware stops an oversized one here
        size += len(chunk)
        chunks.append(chunk)
    # Parsing and saving take time: in a worker thread, so the event loop (status, streams) runs on.
    profile = await asyncio.to_thread(parse_profile, b"".join(chunks), name)
    try:
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
