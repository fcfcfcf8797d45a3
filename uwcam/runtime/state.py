"""State that survives a restart: live processing settings, the active profile, lamp intensity.

Kept as one small JSON file (``uwcam-state.json``) in the state folder (``state_dir``, else the
profiles folder), rewritten atomically after every change, so a kill or a power cut leaves either
the old file or the new one. At start the daemon restores it and removes temporary files that an
interrupted atomic write left behind.
"""

from __future__ import annotations

import glob
import json
import logging
import os
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from uwcam.config import Whole
from uwcam.fileio import atomic_write

log = logging.getLogger(__name__)
STATE_FILE = "uwcam-state.json"
STATE_VERSION = 1


class SavedState(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    version: Literal[1] = STATE_VERSION
    processing: dict[str, Any] | None = None
    """Live processing settings (validated as ``processing`` of the configuration when restored)."""
    profile: Annotated[str, Field(max_length=256)] | None = None
    """Name of the active calibration profile."""
    lamp_percent: Annotated[Whole, Field(ge=0, le=100)] | None = None
    """Lamp intensity, percent."""


def state_path(folder: str) -> str:
    return os.path.join(folder, STATE_FILE)


def load_state(folder: str) -> SavedState | None:
    """The saved state, or None if there is none or it cannot be read (logged, never fatal)."""
    path = state_path(folder)
    try:
        with open(path, encoding="utf-8") as handle:
            return SavedState.model_validate(json.load(handle))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, ValidationError) as exc:  # a bad file must not stop the camera
        log.warning("ignoring saved state %s: %s", path, str(exc).splitlines()[0])
        return None


def save_state(folder: str, state: SavedState) -> None:
    """Write atomically (temporary file, fsync, rename)."""
    os.makedirs(folder, exist_ok=True)
    with atomic_write(state_path(folder), "w") as handle:
        handle.write(state.model_dump_json(indent=1))


def remove_stale_temporaries(folder: str) -> list[str]:
    """Delete what an atomic write interrupted by a kill left in ``folder`` (``.NAME.*.tmp``)."""
    removed = []
    for path in glob.glob(os.path.join(glob.escape(folder), ".*.tmp")):
        try:
            os.unlink(path)
            removed.append(path)
        except OSError as exc:
            log.warning("cannot remove stale temporary file %s: %s", path, exc)
    if removed:
        log.info("removed %d temporary file(s) left by an interrupted write in %s", len(removed), folder)
    return removed
