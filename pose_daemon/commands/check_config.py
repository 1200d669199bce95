"""``pose-daemon check-config FILE``: validate a config file; one line naming file and key on error (exit 2)."""

from __future__ import annotations

import argparse
import sys

from ..config import check_whole, load_config


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("check-config", help="validate a config file", description=__doc__.splitlines()[0])
    parser.add_argument("config", metavar="FILE", help="TOML config file")
    parser.add_argument(
        "--print", dest="show", action="store_true", help="print the effective configuration (defaults filled in)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    check_whole(cfg)  # what `pose-daemon run` refuses at start, files and links included
    for warning in cfg.start_warnings():
        print(f"{args.config}: warning: {warning}", file=sys.stderr)
    if args.show:
        print(cfg.to_toml(), end="")
    else:
        outputs = [name for name in ("mavlink", "serial", "jsonl") if getattr(cfg.output, name)]
        if cfg.map is not None:
            target = f"map {cfg.map.dictionary} with {len(cfg.map.markers)} markers ({cfg.map.placement})"
        else:
            target = f"marker {cfg.marker.type} {cfg.marker.width:g}x{cfg.marker.height:g} m"
        print(f"{args.config}: ok (source {cfg.camera.source}, {target}, outputs: {', '.join(outputs) or 'none'})")
    return 0
