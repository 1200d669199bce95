"""``pose-daemon run [--config FILE]``: the daemon, capture -> detect -> estimate -> outputs, until SIGTERM."""

from __future__ import annotations

import argparse

from ..config import check_whole, load_config_or_default


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("run", help="run the daemon until SIGTERM/SIGINT", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--config", metavar="FILE", help="TOML config (default: the embedded demo config, synthetic source)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..service import run_daemon

    cfg = load_config_or_default(args.config)
    check_whole(cfg)  # links and files too, as check-config does
    return run_daemon(cfg)
