"""``uwcam reprocess`` and ``uwcam repair``: recorded dives."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from uwcam.fileio import UserInputError


def cmd_reprocess(args: argparse.Namespace) -> int:
    from uwcam.recording.reprocess import reprocess

    if args.workers is not None and not 1 <= args.workers <= 1024:
        raise UserInputError(f"--workers must be 1 to 1024, got {args.workers}")
    if not 0.01 <= args.part_mb <= 1e5:
        raise UserInputError(f"--part-mb must be 0.01 to 100000, got {args.part_mb}")
    outputs = reprocess(args.inputs, args.output, profile=args.profile, scheduler=args.scheduler,
                        workers=args.workers, progress=not args.quiet, part_mb=args.part_mb,
                        skip_corrupt=args.skip_corrupt, warn=lambda text: print(f"uwcam reprocess: warning: {text}",
                                                                               file=sys.stderr))
    for path in outputs:
        print(f"wrote {path}")
    return 0


def cmd_repair(args: argparse.Namespace) -> int:
    from uwcam.recording import format as rec

    for path in args.recordings:
        if not Path(path).is_file():
            raise UserInputError(f"recording {path} does not exist")
        if rec.is_complete(path):
            print(f"{path} is complete; left as it is")
            continue
        try:
            kept = rec.repair(path)
        except rec.RecordingError as exc:
            raise UserInputError(str(exc)) from None
        except OSError as exc:
            raise UserInputError(f"cannot repair {path}: {exc.strerror}") from None
        print(f"repaired {path}: {kept} bytes of complete records kept, the unfinished rest removed")
    return 0
