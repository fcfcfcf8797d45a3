"""``uwcam monitor``: the topside fleet view of every vehicle publishing on Zenoh."""

from __future__ import annotations

import argparse

from uwcam.fileio import UserInputError


def cmd_monitor(args: argparse.Namespace) -> int:
    """The topside fleet view (uwcam.fleet.monitor): subscribe to every vehicle on Zenoh, serve the page."""
    import math
    import re
    import socket

    from uwcam.config import _KEY_SEGMENT, _ZENOH_ENDPOINT

    for option, endpoints in (("--connect", args.connect), ("--listen", args.listen)):
        for endpoint in endpoints:
            if not _ZENOH_ENDPOINT.match(endpoint):
                raise UserInputError(f"{option} {endpoint}: not a Zenoh endpoint; e.g. tcp/192.168.2.2:7447")
    if not (math.isfinite(args.stale_s) and 0 < args.stale_s <= 3600):
        raise UserInputError(f"--stale-s {args.stale_s}: give seconds between 0 and 3600, e.g. 5")
    if not 0 <= args.port <= 65535:
        raise UserInputError(f"--port {args.port}: give a port 0–65535")
    if not all(_KEY_SEGMENT.match(part) for part in args.root.split("/")) or re.search(r"[*$?#]", args.root):
        raise UserInputError(f"--root {args.root}: give the vehicles' key root without wildcards, e.g. uwcam")
    if not args.connect and not args.scouting:
        raise UserInputError("nothing to listen to: give --connect ENDPOINT... or leave scouting on")
    try:  # a port in use is one line, before Zenoh starts
        with socket.create_server((args.host, args.port), family=socket.AF_INET6 if ":" in args.host else socket.AF_INET):
            pass
    except OSError as exc:
        raise UserInputError(f"cannot listen on {args.host}:{args.port}: {exc.strerror or exc}; choose another --port") from None
    from uwcam.fleet.monitor import run_monitor
    from uwcam.outputs.zenoh_publisher import require_zenoh

    require_zenoh()
    print(f"uwcam monitor: fleet page http://{args.host}:{args.port}/ (vehicles under {args.root}/)", flush=True)
    run_monitor(args.connect, args.listen, args.scouting, args.host, args.port, args.stale_s, args.root)
    return 0
