"""Recordings on disk: the write-rate budget, free space, and names for new files."""

from __future__ import annotations

import datetime as dt
import os
import shutil
import time

from uwcam.fileio import UserInputError


class NoRoom(UserInputError):
    """Too little free disk to start a recording (the API answers 507 Insufficient Storage)."""





class DiskBudget:
    """A token bucket in bytes on the frames' capture clock: ``rate`` bytes a second accrue, at
    most ``burst_s`` seconds' worth; each write spends what it costs on disk, estimated from the
    payload by the compression measured so far. A raw frame that would overdraw it is decimated.
    Tokens accrue with capture time, not the writer's clock, so a writer that falls behind does
    not decimate more (the queue's own limits handle that, counted apart)."""

    def __init__(self, rate_bytes_s: float, burst_s: float = 2.0) -> None:
        self.rate = rate_bytes_s
        self.capacity = rate_bytes_s * burst_s
        self.tokens = self.capacity
        self.last_ns: int | None = None

    def accrue(self, t_ns: int) -> None:
        if self.last_ns is not None and t_ns > self.last_ns:
            self.tokens = min(self.capacity, self.tokens + self.rate * (t_ns - self.last_ns) / 1e9)
        self.last_ns = t_ns if self.last_ns is None else max(self.last_ns, t_ns)

    def affords(self, cost_bytes: float) -> bool:
        return self.tokens >= cost_bytes

    def spend(self, cost_bytes: float) -> None:
        self.tokens -= cost_bytes


def disk_free_bytes(path: str) -> int | None:
    """Free bytes (to an unprivileged user) of the file system holding ``path`` or its nearest existing parent."""
    return disk_space_bytes(path)[0]


def disk_space_bytes(path: str) -> tuple[int | None, int | None]:
    """(free to an unprivileged user, total size) in bytes of the file system holding ``path`` or
    its nearest existing parent; (None, None) when it cannot be read."""
    path = os.path.abspath(path)
    while not os.path.exists(path):
        parent = os.path.dirname(path)
        if parent == path:
            return None, None
        path = parent
    try:
        usage = shutil.disk_usage(path)
    except OSError:
        return None, None
    return usage.free, usage.total


def time_name(now: float | None = None) -> str:
    """File name of a recording started at ``now``: uwcam-YYYYmmddTHHMMSSZ.mcap (UTC)."""
    t = dt.datetime.fromtimestamp(time.time() if now is None else now, dt.timezone.utc)
    return f"uwcam-{t:%Y%m%dT%H%M%SZ}.mcap"


def unique_path(path: str) -> str:
    stem, ext = os.path.splitext(path)
    n = 2
    while os.path.exists(path):
        path = f"{stem}-{n}{ext}"
        n += 1
    return path
