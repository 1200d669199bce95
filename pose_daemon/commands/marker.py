"""``pose-daemon marker``: a printable marker sheet (PDF, SVG or PNG) at true physical size."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "marker",
        help="print a marker: PDF/SVG/PNG at true size with scale bar and config lines",
        description=__doc__.splitlines()[0].replace("``", ""),
    )
    parser.add_argument(
        "--type",
        choices=("square", "aruco"),
        default="aruco",
        help="plain black square or ArUco marker (default aruco)",
    )
    parser.add_argument(
        "--size",
        type=float,
        required=True,
        metavar="METRES",
        help="outer edge of the black border, metres (e.g. 0.15); with --pad the outer marker's",
    )
    parser.add_argument(
        "--pad",
        action="store_true",
        help="a nested landing pad: a small marker inside the white centre of the large one "
        "(--id: the large one's, which needs its four centre bits white); prints its [map]",
    )
    parser.add_argument("--dictionary", default=None, help="ArUco dictionary, OpenCV's name (default DICT_4X4_50)")
    parser.add_argument("--id", type=int, default=None, help="ArUco marker id (default 0)")
    parser.add_argument(
        "--paper",
        choices=("a4", "letter"),
        default="a4",
        help="paper size (default a4); a marker that does not fit is refused",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="FILE", help="FILE.pdf, FILE.svg or FILE.png")
    parser.add_argument("--dpi", type=float, default=300.0, help="resolution of a PNG (default 300)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import UserError
    from ..tools.marker_sheet import check_out_path, layout, pad_layout, write_sheet

    check_out_path(args.out)
    if args.pad:
        if args.type != "aruco":
            raise UserError("--pad is made of ArUco markers: no --type square")
        sheet = pad_layout(args.size, dictionary=args.dictionary, outer_id=args.id, paper=args.paper)
        what = "nested landing pad"
    else:
        sheet = layout(args.type, args.size, dictionary=args.dictionary, marker_id=args.id, paper=args.paper)
        what = f"{args.type} marker"
    write_sheet(sheet, args.out, dpi=args.dpi)
    print(
        f"wrote {args.out}: {what}, {args.size * 1000:g} mm, {args.paper}; print at 100% and check the 10 cm bar",
        file=sys.stderr,
    )
    print("\n".join(sheet.config))
    return 0
