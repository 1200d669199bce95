"""``pose-daemon map {build,check,import}``: survey a marker map from a walk-through, check a map
against a recording (a moved, turned, mirrored or mis-sized marker), and read a field layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..geometry import MARKER_PLACEMENTS


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("map", help="marker maps: survey one from a walk-through, check one", description=__doc__)
    maps = parser.add_subparsers(dest="map_command", metavar="ACTION", required=True, parser_class=type(parser))
    b = maps.add_parser(
        "build",
        help="survey every marker's pose from walk-through recordings or image folders",
        description="pose-daemon map build: every ArUco marker's pose in one map frame (the anchor's), "
        "solved jointly from the frames of walk-through recordings or image folders that see two "
        "markers or more, and written as a map file ([map] with [[map.markers]]) for the daemon's "
        "[map] table.",
    )
    b.add_argument("sources", nargs="+", metavar="SOURCE", help="recording folders or folders of images")
    b.add_argument("--config", metavar="FILE", help="TOML config whose [camera] is used when a source has none")
    b.add_argument("--dictionary", required=True, help="OpenCV dictionary of the markers, e.g. DICT_4X4_50")
    b.add_argument("--size", type=float, required=True, metavar="METRES", help="marker size (outer black border)")
    b.add_argument("--sizes", metavar="ID=S,...", help="markers of other sizes, e.g. 3=0.15,7=0.30")
    b.add_argument("--anchor", type=int, metavar="ID", help="marker whose frame is the map frame (default: lowest id)")
    b.add_argument("--placement", choices=MARKER_PLACEMENTS, default="floor", help="the map's [map] placement")
    b.add_argument("--out", type=Path, required=True, metavar="MAP.toml", help="the map file to write")
    b.add_argument("--plot", type=Path, metavar="FILE", help="also draw the map from above with the camera path")
    b.add_argument("--every", type=int, default=1, metavar="N", help="use every N-th frame (default 1: all)")
    b.add_argument(
        "--max-frames", type=int, default=600, metavar="N", help="frames in the joint solve at most (default 600)"
    )
    b.add_argument("--no-plane", action="store_true", help="leave the markers free of the anchor's plane")
    b.set_defaults(func=run_build)
    c = maps.add_parser(
        "check",
        help="hold a map against a recording's frames: turned, mirrored, mis-sized or moved markers",
        description="pose-daemon map check: replay a recording through the map's own pose pipeline, with "
        "the whole config (mount, attitude) as run and replay use it, and judge each marker on what the "
        "frames say: one line per marker that is turned, mirrored, mis-sized or moved (exit 1); exit 0 "
        "only when every marker the frames show was checked and agrees.",
    )
    c.add_argument("map", metavar="MAP.toml", help="a map file ([map] with [[map.markers]])")
    c.add_argument("source", metavar="SOURCE", help="recording folder or folder of images")
    c.add_argument(
        "--config",
        metavar="FILE",
        help="the daemon's TOML config: its [mount], [attitude], [estimator], [detector] (and [camera] when the "
        "source has none), as run and replay use them",
    )
    c.set_defaults(func=run_check)
    i = maps.add_parser(
        "import",
        help="a WPILib / PhotonVision AprilTag field layout (JSON) as a map file",
        description="pose-daemon map import: read a WPILib / PhotonVision AprilTag field layout (JSON: each "
        "tag's id and pose as translation + quaternion) and write it as a map file ([map] with "
        "[[map.markers]]) that [map] file can name; the layout holds no tag size, so --size is required.",
    )
    i.add_argument("layout", type=Path, metavar="LAYOUT.json", help="the field layout JSON")
    i.add_argument("--out", type=Path, required=True, metavar="MAP.toml", help="the map file to write")
    i.add_argument(
        "--size",
        type=float,
        required=True,
        metavar="METRES",
        help="the tags' size, outer edge of the black border (the layout holds none; FRC's: 0.1651)",
    )
    i.add_argument(
        "--dictionary",
        default="DICT_APRILTAG_36h11",
        help="OpenCV dictionary of the tags (default DICT_APRILTAG_36h11)",
    )
    i.set_defaults(func=run_import)


def run_build(a: argparse.Namespace) -> int:
    from ..maps.survey import build

    build(
        a.sources,
        dictionary=a.dictionary,
        size_m=a.size,
        sizes=a.sizes,
        anchor=a.anchor,
        placement=a.placement,
        out=a.out,
        plot=a.plot,
        config=a.config,
        every=a.every,
        max_frames=a.max_frames,
        plane=not a.no_plane,
    )
    return 0


def run_check(a: argparse.Namespace) -> int:
    from ..maps.check import check

    return check(a.map, a.source, a.config)


def run_import(a: argparse.Namespace) -> int:
    from ..maps.layout import import_layout

    import_layout(a.layout, a.out, a.size, a.dictionary)
    return 0
