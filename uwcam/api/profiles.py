"""/api/v1/calibration/profiles: list, read, upload and activate calibration profiles."""

from __future__ import annotations

import re

from fastapi import APIRouter, Depends, HTTPException, Request

from uwcam.api.common import get_daemon
from uwcam.daemon import Daemon
from uwcam.fileio import UserInputError

router = APIRouter(prefix="/api/v1/calibration/profiles", tags=["calibration"])
MAX_PROFILE_BYTES = 1 << 20
NAME = re.compile(r"[A-Za-z0-9._-]{1,64}")


@router.get("")
def list_profiles(d: Daemon = Depends(get_daemon)) -> list[dict]:
    """Known calibration profiles; one is active."""
    return [{"name": name, "active": name == d.profile_name, "created": p.provenance.created,
             "channels": p.channel_names, "method": p.provenance.method} for name, p in d.profiles.items()]


@router.get("/{name}")
def get_profile(name: str, d: Daemon = Depends(get_daemon)) -> dict:
    if name not in d.profiles:
        raise HTTPException(status_code=404, detail=f"no profile '{name}'; known: {', '.join(d.profiles)}")
    return d.profiles[name].model_dump(mode="json")


@router.put("/{name}", openapi_extra={
    "requestBody": {"required": True, "content": {
        "application/x-yaml": {"schema": {"type": "string"}},
        "application/json": {"schema": {"type": "object", "description": "a uwcam calibration profile"}}}}})
async def upload_profile(name: str, request: Request, d: Daemon = Depends(get_daemon)) -> dict:
    """Upload a profile (YAML or JSON body, at most 1 MiB). It is validated in full; a bad one
    is refused with the reason and changes nothing. Uploading does not activate it."""
    import yaml

    from uwcam.profile import profile_from_mapping

    if not NAME.fullmatch(name):
        raise HTTPException(status_code=422, detail="profile names use letters, digits, '.', '_' and '-' (1–64)")
    body = await request.body()
    if len(body) > MAX_PROFILE_BYTES:
        raise HTTPException(status_code=413, detail=f"profile larger than {MAX_PROFILE_BYTES} bytes")
    try:
        data = yaml.safe_load(body.decode("utf-8"))
    except (UnicodeDecodeError, yaml.YAMLError) as exc:
        raise HTTPException(status_code=422, detail=f"profile is not valid YAML or JSON: {exc}") from None
    if not isinstance(data, dict):
        raise HTTPException(status_code=422, detail="profile must be a mapping of keys to values")
    try:
        profile = profile_from_mapping(data, f"profile {name}")
    except UserInputError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    d.save_profile(name, profile)
    return {"name": name, "active": name == d.profile_name, "channels": profile.channel_names}


@router.post("/{name}/activate")
def activate_profile(name: str, d: Daemon = Depends(get_daemon)) -> dict:
    if name not in d.profiles:
        raise HTTPException(status_code=404, detail=f"no profile '{name}'; known: {', '.join(d.profiles)}")
    try:
        d.activate(name)
    except UserInputError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    return {"name": name, "active": True}
