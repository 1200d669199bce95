"""``pose-daemon replay PATH [--config FILE] [--out FILE] [--annotate DIR]``: the pipeline over
a recording, a folder of images or a video, as fast as it goes; one JSON object per frame."""

from __future__ import annotations

import argparse

from . import describe


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "replay",
        help="run detection and pose over a recording, image folder or video",
        description=describe(__doc__),
    )
    parser.add_argument("path", metavar="PATH", help="recording folder, folder of images or video file")
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="TOML config: camera and marker when the recording has none, estimator, detector",
    )
    parser.add_argument("--out", metavar="FILE", help="write the JSON lines here (default, or -: stdout)")
    parser.add_argument("--annotate", metavar="DIR", help="also write each frame with corners, axes and pose")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..tools.replay import replay

    return replay(args.path, args.config, args.out, args.annotate)
