"""REST and WebSocket API (FastAPI): one router per resource, assembled by :func:`create_app`."""

from uwcam.api.app import create_app
from uwcam.api.security import is_loopback, required_token
from uwcam.api.snapshots import range_millimetres
from uwcam.api.stream import HEADER, encode_range

__all__ = ["HEADER", "create_app", "encode_range", "is_loopback", "range_millimetres", "required_token"]
