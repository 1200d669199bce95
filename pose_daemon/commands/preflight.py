"""``pose-daemon preflight [--config FILE] [--apply]``: would the autopilot use the feed? One line per finding."""

from __future__ import annotations

import argparse

from ..config import check_whole, load_config_or_default


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "preflight",
        help="check the autopilot's parameters and that it uses the feed",
        description=__doc__.splitlines()[0] + " Lines: OK ..., PROBLEM ..., "
        "FIX: <parameter> = <value>. Exit 0 when the autopilot would use the feed, "
        "1 when not, 2 for a config or link that cannot be used.",
    )
    parser.add_argument("--config", metavar="FILE", help="TOML config file (default: the embedded demo)")
    parser.add_argument("--apply", action="store_true", help="set every FIX parameter (PARAM_SET) after listing them")
    parser.add_argument(
        "--seconds", type=float, default=8.0, help="how long the feed runs while the autopilot is watched (default 8)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import UserError
    from ..tools.preflight import run_preflight

    if not 1.0 <= args.seconds <= 600.0:
        raise UserError(f"--seconds must be in [1, 600], got {args.seconds:g}")
    cfg = load_config_or_default(args.config)
    check_whole(cfg)
    return run_preflight(cfg, seconds=args.seconds, apply=args.apply)
