"""``pose-daemon record [--config FILE] --out DIR [--seconds N | --frames N]``: save frames
from the configured source losslessly, with capture times, camera model and (synthetic) truth."""

from __future__ import annotations

import argparse

from ..errors import UserError
from . import describe


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "record", help="record frames from the camera source into a folder", description=describe(__doc__)
    )
    parser.add_argument(
        "--config", metavar="FILE", help="TOML config (default: the embedded demo config, synthetic source)"
    )
    parser.add_argument("--out", metavar="DIR", required=True, help="new folder for the recording")
    limit = parser.add_mutually_exclusive_group()
    limit.add_argument("--seconds", type=float, metavar="N", help="stop after N seconds of frames")
    limit.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..tools.record import record

    if args.frames is not None and args.frames <= 0:
        raise UserError(f"--frames must be a positive number of frames, got {args.frames}")
    if args.seconds is not None and not args.seconds > 0:
        raise UserError(f"--seconds must be a positive number of seconds, got {args.seconds}")
    return record(args.out, args.config, seconds=args.seconds, frames=args.frames, progress_bar=not args.quiet)
