"""``pose-daemon calibrate [IMAGES_OR_RECORDING] --board SPEC``: the camera's intrinsics and lens
distortion from views of a chessboard or ChArUco board, written as a [camera] section."""

from __future__ import annotations

import argparse

from ..errors import UserError
from ..tools import calibrate as cal


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "calibrate",
        help="calibrate the camera from views of a chessboard or ChArUco board",
        description="pose-daemon calibrate: the camera's intrinsics and lens distortion from views "
        "of a chessboard or ChArUco board, written as a [camera] config section.",
        epilog="Without IMAGES_OR_RECORDING the frames come live from the configured camera source.",
    )
    parser.add_argument(
        "input",
        nargs="?",
        metavar="IMAGES_OR_RECORDING",
        help="a folder of images, or a recording made by `pose-daemon record`",
    )
    parser.add_argument("--board", required=True, metavar="SPEC", help=cal.BOARD_SYNTAX)
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="config whose camera source is used live, and whose [camera] section is "
        "updated in place with the result (the rest of the file is kept)",
    )
    parser.add_argument(
        "--out", metavar="FILE", help="write the [camera] section to FILE ('-' = stdout; the default without --config)"
    )
    parser.add_argument(
        "--views", type=int, default=20, metavar="N", help="live/recording: stop after N distinct views (default 20)"
    )
    parser.add_argument("--seconds", type=float, metavar="S", help="live/recording: stop after S seconds")
    parser.add_argument(
        "--save-views",
        metavar="DIR",
        help="live/recording: also save the kept frames as PNG files in DIR, to calibrate from again later",
    )
    parser.add_argument(
        "--drop-outliers", action="store_true", help="drop the views flagged as outliers and calibrate again"
    )
    parser.add_argument(
        "--min-coverage",
        type=float,
        default=cal.DEFAULT_MIN_COVERAGE,
        metavar="F",
        help=f"refuse below this share of the image reached by corners (default {cal.DEFAULT_MIN_COVERAGE:g})",
    )
    parser.add_argument(
        "--fit-k3", action="store_true", help="fit the third radial term k3 too (wide-angle lenses); default k3 = 0"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    spec = cal.parse_board(args.board)
    if args.views < cal.MIN_VIEWS:
        raise UserError(f"--views {args.views}: at least {cal.MIN_VIEWS} views are needed")
    if args.seconds is not None and not args.seconds > 0:
        raise UserError(f"--seconds {args.seconds}: expected a positive number of seconds")
    if not 0.0 <= args.min_coverage <= 1.0:
        raise UserError(f"--min-coverage {args.min_coverage}: expected a share between 0 and 1")
    return cal.run_calibration(
        spec,
        args.input,
        config=args.config,
        out=args.out,
        max_views=args.views,
        seconds=args.seconds,
        save_views=args.save_views,
        drop_outliers=args.drop_outliers,
        min_coverage=args.min_coverage,
        fit_k3=args.fit_k3,
    )
