"""``pose-daemon plot``: position, attitude, trajectory from above, detection gaps and latency of a pose log."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "plot",
        help="plot a pose log (JSON lines of replay or the daemon) into a PNG/PDF/SVG",
        description=__doc__.splitlines()[0].replace("``", ""),
    )
    parser.add_argument(
        "poses",
        type=Path,
        metavar="POSES.jsonl",
        help="per-frame JSON lines from replay --out, estimate or [output.jsonl]",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="FILE", help="figure file: .png, .pdf, .svg or .jpg")
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="take the marker placement (wall/floor) and latency budget from this config",
    )
    parser.add_argument(
        "--placement",
        choices=("wall", "floor"),
        default=None,
        help="how the marker is mounted, for the view from above (default: from --config, else wall)",
    )
    parser.add_argument(
        "--run",
        type=int,
        default=None,
        metavar="N",
        help="a log the daemon appended to after restarts holds several runs (time "
        "goes back at each): plot run N, 1 = the oldest (default: the last)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..tools.plot import plot_poses, summary_line

    placement, budget_ms = "wall", 100.0
    if args.config is not None:
        from ..config import load_config

        cfg = load_config(args.config)
        placement, budget_ms = cfg.marker.placement, cfg.pipeline.latency_budget_s * 1e3
    if args.placement is not None:
        placement = args.placement
    series, stats, note = plot_poses(
        args.poses, args.out, placement=placement, latency_budget_ms=budget_ms, run=args.run
    )
    if series.skipped:
        line, why = series.skipped[0]
        print(
            f"pose-daemon: {args.poses}: skipped {len(series.skipped)} line(s) that are not per-frame "
            f"JSON objects (first: line {line}: {why})",
            file=sys.stderr,
        )
    if note:
        note += "; --run N picks another"
        print(
            f"pose-daemon: {args.poses}: several runs (time goes back where the daemon restarted); plotting {note}",
            file=sys.stderr,
        )
    print(f"wrote {args.out}: {summary_line(series, stats)}", file=sys.stderr)
    return 0
