"""``pose-daemon marker``: a printable marker sheet (PDF, SVG or PNG) at true physical size."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import List, Tuple


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
        default=None,
        metavar="METRES",
        help="outer edge of the black border, metres (e.g. 0.15); with --pad the outer marker's; "
        "with --grid a comma list the markers take in turn (0.2,0.15)",
    )
    parser.add_argument(
        "--pad",
        action="store_true",
        help="a nested landing pad: a small marker inside the white centre of the large one "
        "(--id: the large one's, which needs its four centre bits white); prints its [map]",
    )
    parser.add_argument(
        "--tiled",
        action="store_true",
        help="a marker or --pad larger than a sheet on several sheets, with cut lines, registration "
        "crosses, sheet numbers and a plan page",
    )
    parser.add_argument(
        "--grid",
        metavar="ROWSxCOLS",
        default=None,
        help="map sheets for a floor grid (e.g. 3x4): ids row by row from --id (or --ids), the first "
        "at the map origin; one or several markers per sheet, a plan page; prints the [map] lines",
    )
    parser.add_argument(
        "--spacing",
        metavar="METRES[,METRES]",
        default=None,
        help="--grid: centre-to-centre distance along x (columns) [and y (rows)], metres",
    )
    parser.add_argument(
        "--map",
        type=Path,
        default=None,
        metavar="MAP.toml",
        help="map sheets for the markers of a map file ([map] with [[map.markers]], as --grid or "
        "`map build` print, or a [[markers]] list with --dictionary); every marker flat in the z = 0 plane",
    )
    boards = parser.add_mutually_exclusive_group()
    boards.add_argument(
        "--chessboard",
        nargs="?",
        const="6x9",
        default=None,
        metavar="COLSxROWS",
        help="a calibration chessboard instead of a marker: COLSxROWS inner corners (default 6x9); "
        "--size the square's side (default the largest whole mm that fits); prints its calibrate line",
    )
    boards.add_argument(
        "--charuco",
        nargs="?",
        const="5x7",
        default=None,
        metavar="COLSxROWS",
        help="a ChArUco calibration board: COLSxROWS squares (default 5x7); --size the square's side, "
        "--marker-size its markers' (default 0.75 of it), --dictionary; prints its calibrate line",
    )
    parser.add_argument(
        "--marker-size", type=float, default=None, metavar="METRES", help="--charuco: the markers' side, metres"
    )
    parser.add_argument("--ids", metavar="LIST", default=None, help="--grid: the ids, comma-separated, row by row")
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


def _numbers(option: str, text: str, what: str = "a positive number of metres") -> List[float]:
    from ..errors import UserError

    out = []
    for part in text.split(","):
        try:
            v = float(part)
        except ValueError:
            raise UserError(f"{option} must be {what}, got {text!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{option} must be {what}, got {text!r}")
        out.append(v)
    return out


def run(args: argparse.Namespace) -> int:
    from ..errors import UserError
    from ..maps.pad import pad_layout
    from ..tools.marker_sheet import DEFAULT_DICTIONARY, check_out_path, layout, write_pages

    check_out_path(args.out)
    if args.chessboard is not None or args.charuco is not None:
        return _print_board(args)
    if args.marker_size is not None:
        raise UserError("--marker-size applies to --charuco only")
    if args.map is not None:
        return _print_map(args)
    if args.size is None:
        raise UserError("--size is required (the outer edge of the black border, metres), except with --map")
    sizes = _numbers("--size", args.size)
    if args.grid is None and len(sizes) > 1:
        raise UserError("--size takes one number (a comma list only with --grid)")
    for option in ("spacing", "ids"):
        if getattr(args, option) is not None and args.grid is None:
            raise UserError(f"--{option} applies to --grid only")
    dictionary = (args.dictionary or DEFAULT_DICTIONARY).strip().upper()
    names: List[str] = []
    if args.grid is not None:
        sheets, names, config, what = _grid(args, sizes, dictionary)
    elif args.tiled:
        from ..maps.pad import landing_pad
        from ..maps.tiles import tiled_sheets
        from ..marker_map import MapMarker, MarkerMap
        from ..tools.marker_sheet import config_lines

        size = sizes[0]
        if args.pad:
            if args.type != "aruco":
                raise UserError("--pad is made of ArUco markers: no --type square")
            try:
                mmap = landing_pad(dictionary, outer_m=size, outer_id=args.id)
            except ValueError as exc:
                raise UserError(str(exc)) from None
            what = f"the nested landing pad {size * 1000:g} mm (ids {mmap.markers[0].id}, {mmap.markers[1].id})"
            config = mmap.to_toml_lines()
        elif args.type == "aruco":
            marker_id = 0 if args.id is None else args.id
            mmap = MarkerMap(dictionary, (MapMarker(marker_id, size),), "floor")
            what = f"ArUco marker {dictionary} id {marker_id}, {size * 1000:g} mm"
            config = config_lines("aruco", size, dictionary, marker_id)
        else:
            if args.dictionary is not None or args.id is not None:
                raise UserError("--dictionary and --id apply to --type aruco only")
            mmap = None
            what = f"a {size * 1000:g} mm black square"
            config = config_lines("square", size, None, None)
        while config and not config[-1]:
            config.pop()
        pages, tiling = tiled_sheets(mmap, args.paper, what=what, config=config, square_m=size)
        sheets = pages
        names = ["plan"] + [str(k) for k in range(1, len(pages))]
        what = f"{what} on {len(pages) - 1} sheets ({tiling.rows} x {tiling.cols}) and a plan page"
    else:
        try:
            if args.pad:
                if args.type != "aruco":
                    raise UserError("--pad is made of ArUco markers: no --type square")
                sheet = pad_layout(sizes[0], dictionary=args.dictionary, outer_id=args.id, paper=args.paper)
                what = "nested landing pad"
            else:
                sheet = layout(args.type, sizes[0], dictionary=args.dictionary, marker_id=args.id, paper=args.paper)
                what = f"{args.type} marker"
        except UserError as exc:
            if "does not fit" in str(exc):
                raise UserError(f"{exc}; --tiled prints it on several sheets") from None
            raise
        what = f"{what}, {sizes[0] * 1000:g} mm"
        sheets, config = [sheet], sheet.config
    files = write_pages(sheets, args.out, dpi=args.dpi, names=names)
    shown = str(files[0]) if len(files) == 1 else f"{files[0]} ... {files[-1]} ({len(files)} files)"
    print(f"wrote {shown}: {what}, {args.paper}; print at 100% and check the 10 cm bar", file=sys.stderr)
    print("\n".join(config))
    return 0


def _print_board(args: argparse.Namespace) -> int:
    """A calibration board at true size; its ``calibrate`` line on stdout."""
    from ..errors import UserError
    from ..tools.board_sheet import board_spec, layout_board
    from ..tools.marker_sheet import write_pages

    kind = "chessboard" if args.chessboard is not None else "charuco"
    for option in ("pad", "tiled"):
        if getattr(args, option):
            raise UserError(f"--{kind} prints a calibration board: no --{option}")
    if args.type != "aruco":
        raise UserError(f"--{kind} prints a calibration board: no --type {args.type}")
    for option in ("grid", "spacing", "map", "ids", "id"):
        if getattr(args, option) is not None:
            raise UserError(f"--{kind} prints a calibration board: no --{option}")
    square_m = None
    if args.size is not None:
        square_m = _numbers("--size", args.size, "the square's side, a positive number of metres")
        if len(square_m) > 1:
            raise UserError("--size takes one number with --" + kind)
    marker_m = args.marker_size
    if marker_m is not None and not (math.isfinite(marker_m) and marker_m > 0):
        raise UserError(f"--marker-size must be a positive number of metres, got {marker_m:g}")
    spec = board_spec(
        kind,
        args.chessboard if kind == "chessboard" else args.charuco,
        square_m=square_m[0] if square_m else None,
        marker_m=marker_m,
        dictionary=args.dictionary,
        paper=args.paper,
    )
    sheet = layout_board(spec, args.paper)
    files = write_pages([sheet], args.out, dpi=args.dpi)
    print(
        f"wrote {files[0]}: {spec.describe()}, {args.paper}; print at 100% and check the 10 cm bar",
        file=sys.stderr,
    )
    print("\n".join(sheet.config))
    return 0


def _print_map(args: argparse.Namespace) -> int:
    import json

    from ..config import parse_config
    from ..errors import UserError
    from ..maps.tiles import grid_sheets
    from ..tools.marker_sheet import write_pages

    for option in ("size", "grid", "spacing", "ids", "id"):
        if getattr(args, option) is not None:
            raise UserError(f"--map takes its markers from the file: no --{option}")
    if args.pad or args.tiled or args.type != "aruco":
        raise UserError("--map prints the map's ArUco markers: no --pad, --tiled or --type square")
    path = args.map.resolve()
    text = f"[map]\nfile = {json.dumps(str(path))}\n"
    if args.dictionary is not None:
        text += f"dictionary = {json.dumps(args.dictionary.strip().upper())}\n"
    try:
        from ..config import tomllib

        inner = tomllib.loads(path.read_text(encoding="utf-8")).get("map")
        if isinstance(inner, dict) and isinstance(inner.get("placement"), str):
            text += f"placement = {json.dumps(inner['placement'])}\n"
    except (OSError, UnicodeDecodeError, ValueError):
        pass  # the map loader below names what is wrong with the file
    from ..errors import ConfigError

    try:
        cfg = parse_config(text, "--map")
    except ConfigError as exc:
        if args.dictionary is None and "[map] dictionary: expected an OpenCV dictionary name such as" in str(exc):
            raise UserError(f"--map {args.map}: the file names no [map] dictionary; give --dictionary") from None
        raise
    if cfg.map is None:
        raise UserError(f"--map {args.map}: no [map] in the file")
    mmap = cfg.map.model()
    pages, plan = grid_sheets(mmap, args.paper)
    config = mmap.to_toml_lines()
    while config and not config[-1]:
        config.pop()
    names = ["plan"] + [str(k) for k in range(1, len(pages))]
    files = write_pages(pages, args.out, dpi=args.dpi, names=names)
    print(
        f"wrote {files[0]} ... {files[-1]} ({len(files)} files)" if len(files) > 1 else f"wrote {files[0]}",
        f"map of {len(mmap.markers)} markers on {len(plan.groups)} sheets and a plan page, {args.paper}; "
        "print at 100% and check the 10 cm bar",
        sep=": ",
        file=sys.stderr,
    )
    print("\n".join(config))
    return 0


def _grid(args: argparse.Namespace, sizes: List[float], dictionary: str) -> Tuple[list, List[str], List[str], str]:
    from ..errors import UserError
    from ..maps.tiles import grid_map, grid_sheets

    if args.pad or args.tiled or args.type != "aruco":
        raise UserError("--grid prints ArUco markers, one or several a sheet: no --pad, --tiled or --type square")
    parts = args.grid.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() and int(p) > 0 for p in parts):
        raise UserError(f"--grid must be ROWSxCOLS such as 3x4, got {args.grid!r}")
    rows, cols = int(parts[0]), int(parts[1])
    if args.spacing is None:
        raise UserError("--grid needs --spacing (centre to centre, metres)")
    spacing = _numbers("--spacing", args.spacing, "one or two positive numbers of metres (x,y)")
    if len(spacing) > 2:
        raise UserError(f"--spacing must be one or two positive numbers of metres (x,y), got {args.spacing!r}")
    if args.ids is not None:
        if args.id is not None:
            raise UserError("give either --id (the first of the grid) or --ids, not both")
        try:
            ids = [int(p) for p in args.ids.split(",")]
        except ValueError:
            raise UserError(f"--ids must be comma-separated integers, got {args.ids!r}") from None
    else:
        first = 0 if args.id is None else args.id
        ids = list(range(first, first + rows * cols))
    from ..tools.marker_sheet import aruco_cells

    for i in ids:
        aruco_cells(dictionary, i)  # the dictionary and every id exist
    mmap = grid_map(dictionary, rows, cols, (spacing[0], spacing[-1]), sizes, ids)
    pages, plan = grid_sheets(mmap, args.paper)
    config = mmap.to_toml_lines()
    while config and not config[-1]:
        config.pop()
    names = ["plan"] + [str(k) for k in range(1, len(pages))]
    what = f"floor map of {len(ids)} markers on {len(plan.groups)} sheets and a plan page"
    return pages, names, config, what
