"""/api/v1/recordings: start and stop MCAP recordings of the dive, their state, list and download.

Recordings started here go into the configured folder, named by their start time (UTC); a size
or duration limit starts a new file (rotation). Writing happens in the recorder's own thread.
"""

from __future__ import annotations

import os

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse

from uwcam.recording import format as rec
from uwcam.api.common import get_daemon
from uwcam.runtime.daemon import Daemon
from uwcam.fileio import UserInputError
from uwcam.recording.disk import NoRoom

router = APIRouter(prefix="/api/v1/recordings", tags=["recordings"])


def _recorder(d: Daemon):
    if d.recorder is None:
        raise HTTPException(status_code=503, detail="the daemon is not running yet; see /api/v1/status")
    return d.recorder


@router.get("")
def list_recordings(d: Daemon = Depends(get_daemon)) -> dict:
    """Recordings in the folder: name, size in bytes, last change (s since the epoch), and whether
    the file is finished (false while being written or if cut short and not yet repaired)."""
    folder = d.config.recording.folder
    current = set(_recorder(d).status()["files"]) if _recorder(d).status()["state"] == "recording" else set()
    items = []
    if os.path.isdir(folder):
        for name in sorted(os.listdir(folder)):
            path = os.path.join(folder, name)
            if name.endswith(".mcap") and os.path.isfile(path):
                st = os.stat(path)
                items.append({"name": name, "bytes": st.st_size, "modified": st.st_mtime,
                              "recording": path in current, "complete": rec.is_complete(path)})
    return {"folder": folder, "recordings": items}


@router.get("/status")
def recording_status(d: Daemon = Depends(get_daemon)) -> dict:
    """State (recording or idle), current file and its parts, frames written and dropped, bytes,
    and why the last recording stopped (on request, disk full, folder removed...)."""
    return _recorder(d).status()


@router.post("/start")
def start_recording(d: Daemon = Depends(get_daemon)) -> dict:
    """Start recording into a new time-named file; 409 if a recording is running."""
    r = _recorder(d)
    if r.status()["state"] == "recording":
        raise HTTPException(status_code=409, detail=f"already recording into {r.status()['file']}; stop it first")
    try:
        return r.start()
    except NoRoom as exc:  # a full disk: 507 with the reason, and no file left behind
        raise HTTPException(status_code=507, detail=str(exc)) from None
    except UserInputError as exc:
        raise HTTPException(status_code=409, detail=str(exc)) from None
    except OSError as exc:
        raise HTTPException(status_code=507, detail=f"cannot record into {d.config.recording.folder}: {exc.strerror}") from None


@router.post("/stop")
def stop_recording(d: Daemon = Depends(get_daemon)) -> dict:
    """Stop recording (writes what is queued and finishes the file); harmless when idle."""
    return _recorder(d).stop()


@router.get("/{name}", responses={200: {"content": {"application/octet-stream": {}}}})
def download(name: str, d: Daemon = Depends(get_daemon)) -> FileResponse:
    """One recording of the folder, as MCAP."""
    if os.path.basename(name) != name or not name.endswith(".mcap") or name.startswith("."):
        raise HTTPException(status_code=404, detail=f"no recording '{name}'; GET /api/v1/recordings lists them")
    path = os.path.join(d.config.recording.folder, name)
    if not os.path.isfile(path):
        raise HTTPException(status_code=404, detail=f"no recording '{name}'; GET /api/v1/recordings lists them")
    return FileResponse(path, media_type="application/octet-stream", filename=name)
