"""The ``pose-daemon`` command: parses arguments, calls into the packages, maps user errors to exit 2.

Each subcommand lives in ``pose_daemon/commands/<name>.py`` and exposes
``register(subparsers)``, which adds its parser and sets ``func(args) -> int``.

The rule that splits the command line from the library (kept by tests/test_cli.py):

- ``commands/X.py`` = argparse + one call into the library + the exit status, under about 80
  lines. No loops over frames, no evaluators, no hand-built processors.
- ``tools/`` and the rest of the library have no argparse: plain functions, parameters in and
  results out (a benchmark returns its report, and has a formatter for it).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import List, Optional

from . import __version__, startup
from .errors import UserError

# Order = order in --help.
COMMANDS = (
    "run",
    "replay",
    "estimate",
    "record",
    "check_config",
    "preflight",
    "sim",
    "calibrate",
    "marker",
    "plot",
    "map",
    "bench",
    "paper",
)


class _Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line and exit status 2 (its own default).

    Descriptions come from the modules' docstrings, whose ````literal```` markup is for the
    source reader: it is dropped from ``--help``.
    """

    def __init__(self, *args: object, **kwargs: object) -> None:
        description = kwargs.get("description")
        if isinstance(description, str):
            kwargs["description"] = description.replace("``", "")
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="pose-daemon",
        description=(
            "Camera pose from the four corners of a known rectangle, streamed to a flight "
            "controller over MAVLink or to a microcontroller over a serial line."
        ),
    )
    parser.add_argument("--version", action="version", version=f"pose-daemon {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        module = importlib.import_module(f"pose_daemon.commands.{name}")
        module.register(sub)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # The daemon holds its stop signals before anything heavy loads (numpy, OpenCV: seconds on
    # a Pi 2), so a SIGTERM/SIGINT/SIGHUP while it starts is a clean stop, not a traceback.
    daemon = next((a for a in argv if not a.startswith("-")), None) == "run"
    if daemon:
        startup.hold()
    try:
        try:
            parser = build_parser()
            args = parser.parse_args(argv)
            if not getattr(args, "func", None):
                parser.print_help(sys.stderr)
                return 2
            return int(args.func(args) or 0)
        except UserError as exc:
            print(f"pose-daemon: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return 130
        except BrokenPipeError:
            # Output piped into `head` and the like: not an error of ours.
            return 0
    except startup.StartupStop as stop:
        return startup.finish(stop)
    finally:
        if daemon:
            startup.handed_over()


if __name__ == "__main__":
    sys.exit(main())
