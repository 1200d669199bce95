"""``pose-daemon run [--config FILE]``: the daemon, capture -> detect -> estimate -> outputs, until SIGTERM."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..config import Config, ConfigError, load_config_or_default


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("run", help="run the daemon until SIGTERM/SIGINT",
                            description=__doc__.splitlines()[0])
    parser.add_argument("--config", metavar="FILE",
                        help="TOML config (default: the embedded demo config, synthetic source)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..service import run_daemon

    cfg = load_config_or_default(args.config)
    _check_source_path(cfg)
    return run_daemon(cfg)


def _check_source_path(cfg: Config) -> None:
    """A video or recording that is not there will not appear later: refuse it at start (exit 2)
    rather than reopening it for ever as if it were a camera that was unplugged."""
    kind = cfg.camera.source_kind
    if kind in ("video", "replay") and not Path(cfg.camera.source_arg).exists():
        what = "a video file" if kind == "video" else "a recording, image folder or video"
        raise ConfigError(f"{cfg.name}: [camera] source: expected {what} that exists, "
                          f"got {json.dumps(cfg.camera.source)} (no such file or folder)")
