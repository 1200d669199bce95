"""``pose-daemon estimate [--config FILE] [FILE]``: corners as JSON lines in, one pose object per line out."""

from __future__ import annotations

import argparse
import json
import sys
from typing import IO, Any, Dict

from ..errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "estimate",
        help="poses for corner sets given as JSON lines",
        description=__doc__.splitlines()[0].split(": ", 1)[1],
        epilog='Each input line: {"corners": [[u, v], [u, v], [u, v], [u, v]], ...} in pixels, '
        "order TL, TR, BR, BL; other keys are copied to the output. A bad line gives "
        '{"ok": false, "error": "..."} and processing goes on.',
    )
    parser.add_argument(
        "file", nargs="?", metavar="FILE", default="-", help="JSON lines to read (default: standard input)"
    )
    parser.add_argument(
        "--config", metavar="FILE", help="TOML config: camera, marker and estimator (default: the embedded demo config)"
    )
    parser.add_argument("--method", choices=("iterative", "paper"), help="override [estimator] method")
    parser.set_defaults(func=run)


def _pose_line(line: str, lineno: int, estimate, camera, marker, opts: Dict[str, Any]) -> Dict[str, Any]:
    from ..pose.types import EstimationError

    try:
        item = json.loads(line)
    except ValueError as exc:
        return {"ok": False, "error": f"line {lineno}: not JSON: {exc}"}
    if not isinstance(item, dict):
        return {"ok": False, "error": f'line {lineno}: expected a JSON object with "corners"'}
    out = {k: v for k, v in item.items() if k != "corners"}
    if "corners" not in item:
        out.update(ok=False, error=f'line {lineno}: no "corners" key')
        return out
    corners = item["corners"]
    try:
        pose = estimate(corners, camera, marker, **opts)
    except EstimationError as exc:
        out.update(ok=False, error=f"line {lineno}: {exc}")
        return out
    out["ok"] = True
    out["corners"] = [[float(u), float(v)] for u, v in corners]
    out.update(pose.to_dict())
    return out


def run(args: argparse.Namespace) -> int:
    from ..config import Config, load_config
    from ..pose.estimator import estimate_pose

    cfg = load_config(args.config) if args.config else Config.default()
    camera, marker = cfg.camera.model(), cfg.marker.model()
    opts = {
        "method": args.method or cfg.estimator.method,
        "iterations": cfg.estimator.iterations,
        "refine": cfg.estimator.refine,
    }
    if args.file == "-":
        stream: IO[str] = sys.stdin
    else:
        try:
            stream = open(args.file, encoding="utf-8")
        except OSError as exc:
            raise UserError(f"{args.file}: cannot read: {exc.strerror or exc}") from None
    try:
        for lineno, line in enumerate(stream, 1):
            if not line.strip():
                continue
            out = _pose_line(line, lineno, estimate_pose, camera, marker, opts)
            sys.stdout.write(json.dumps(out, allow_nan=False) + "\n")
            sys.stdout.flush()
    except UnicodeDecodeError as exc:
        raise UserError(f"{args.file}: not UTF-8 text (byte {exc.start})") from None
    finally:
        if stream is not sys.stdin:
            stream.close()
    return 0
