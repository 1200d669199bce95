"""``pose-daemon check-config FILE``: validate a config file (one line naming file and key on
error, exit 2), then check the hardware it names on this machine (one line each, exit 1 when
any fails); ``--syntax-only`` stops after the first part, for CI and scripts."""

from __future__ import annotations

import argparse
import sys

from ..config import check_whole, load_config


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "check-config",
        help="validate a config file and check the camera and serial devices it names",
        description=__doc__.splitlines()[0].replace("``", "") + " " + " ".join(__doc__.splitlines()[1:3]),
        epilog="Exit status: 0 all good, 1 a device or module is missing or cannot be opened, "
        "2 the config itself is invalid.",
    )
    parser.add_argument("config", metavar="FILE", help="TOML config file")
    parser.add_argument(
        "--print", dest="show", action="store_true", help="print the effective configuration (defaults filled in)"
    )
    parser.add_argument(
        "--syntax-only",
        action="store_true",
        help="check the file alone (keys, values, files it names), not the camera or serial devices: "
        "exit 0 or 2, touches no hardware",
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
    if args.syntax_only:
        return 0
    from ..tools.hardware import check_hardware

    checks = check_hardware(cfg)
    stream = sys.stderr if args.show else sys.stdout  # --print's stdout stays the TOML alone
    for check in checks:
        print(check.line(), file=stream)
    problems = sum(not c.ok for c in checks)
    if problems:
        print(f"{args.config}: {problems} problem(s) with the hardware above: `run` would wait for it", file=stream)
        return 1
    return 0
