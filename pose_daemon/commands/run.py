"""``pose-daemon run [--config FILE]``: the daemon, capture -> detect -> estimate -> outputs, until SIGTERM."""

from __future__ import annotations

import argparse

from ..config import Config, check_whole, load_config_or_default


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
    check_recording(cfg)
    return run_daemon(cfg)


def check_recording(cfg: Config) -> None:
    """A recording given as the source is read once before the start: a broken index or
    recording.json is the user's to fix (one line, exit 2), not a camera to reopen for ever."""
    from ..capture import recording
    from ..config.forms import parse_source
    from ..errors import SourceError, UserError

    kind, path = parse_source(cfg.camera.source)
    if kind != "replay" or not recording.is_recording(path):
        return
    try:
        recording.read_meta(path)
        recording.read_index(path)
    except SourceError as exc:
        raise UserError(f"{cfg.name}: [camera] source: {exc}") from None
