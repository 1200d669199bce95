"""``pose-daemon calibrate [IMAGES_OR_RECORDING] --board SPEC``: the camera's intrinsics and lens
distortion from views of a chessboard or ChArUco board, written as a [camera] section."""

from __future__ import annotations

import argparse
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import cv2
import numpy as np

from ..errors import EndOfStream, SourceError, UserError
from ..tools import calibrate as cal

#: Live collection: a status line at least this often, seconds.
STATUS_INTERVAL_S = 5.0
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "calibrate", help="calibrate the camera from views of a chessboard or ChArUco board",
        description="pose-daemon calibrate: the camera's intrinsics and lens distortion from views "
                    "of a chessboard or ChArUco board, written as a [camera] config section.",
        epilog="Without IMAGES_OR_RECORDING the frames come live from the configured camera source.")
    parser.add_argument("input", nargs="?", metavar="IMAGES_OR_RECORDING",
                        help="a folder of images, or a recording made by `pose-daemon record`")
    parser.add_argument("--board", required=True, metavar="SPEC", help=cal.BOARD_SYNTAX)
    parser.add_argument("--config", metavar="FILE",
                        help="config whose camera source is used live, and whose [camera] section is "
                             "updated in place with the result (the rest of the file is kept)")
    parser.add_argument("--out", metavar="FILE",
                        help="write the [camera] section to FILE ('-' = stdout; the default without --config)")
    parser.add_argument("--views", type=int, default=20, metavar="N",
                        help="live/recording: stop after N distinct views (default 20)")
    parser.add_argument("--seconds", type=float, metavar="S", help="live/recording: stop after S seconds")
    parser.add_argument("--save-views", metavar="DIR",
                        help="live/recording: also save the kept frames as PNG files in DIR, to "
                             "calibrate from again later")
    parser.add_argument("--drop-outliers", action="store_true",
                        help="drop the views flagged as outliers and calibrate again")
    parser.add_argument("--min-coverage", type=float, default=cal.DEFAULT_MIN_COVERAGE, metavar="F",
                        help=f"refuse below this share of the image reached by corners (default "
                             f"{cal.DEFAULT_MIN_COVERAGE:g})")
    parser.add_argument("--fit-k3", action="store_true",
                        help="fit the third radial term k3 too (wide-angle lenses); default k3 = 0")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    spec = cal.parse_board(args.board)
    if args.views < cal.MIN_VIEWS:
        raise UserError(f"--views {args.views}: at least {cal.MIN_VIEWS} views are needed")
    if args.seconds is not None and not args.seconds > 0:
        raise UserError(f"--seconds {args.seconds}: expected a positive number of seconds")
    if not 0.0 <= args.min_coverage <= 1.0:
        raise UserError(f"--min-coverage {args.min_coverage}: expected a share between 0 and 1")
    if args.config:
        from ..config import load_config

        load_config(args.config)   # a broken config is reported before the work, not after
    # The TOML goes to stdout when nothing else is asked for: the report then goes to stderr.
    to_stdout = args.out == "-" or (args.out is None and not args.config)
    report = sys.stderr if to_stdout else sys.stdout

    def say(line: str) -> None:
        print(line, file=report, flush=True)

    say(f"board: {spec.describe()}")
    if args.input:
        views, size, name = _views_from_path(Path(args.input), spec, args, say)
    else:
        views, size, name = _views_live(spec, args, say)
    width, height = size
    _refuse_too_few(views, name)

    result = cal.calibrate_views(views, width, height, fit_k3=args.fit_k3)
    _report(result, say)
    if result.outliers and args.drop_outliers:
        keep = [v for k, v in enumerate(result.views) if k not in set(result.outliers)]
        say(f"dropping {len(result.outliers)} outlier view(s) and calibrating again")
        _refuse_too_few(keep, name)
        result = cal.calibrate_views(keep, width, height, fit_k3=args.fit_k3)
        _report(result, say)
    elif result.outliers:
        say(f"{len(result.outliers)} view(s) flagged as outliers: check them, or run again with "
            "--drop-outliers to leave them out")
    if result.coverage < args.min_coverage:
        raise UserError(f"poor coverage: the board's corners reached {result.coverage:.0%} of the image "
                        f"(need {args.min_coverage:.0%}); add views with the board near the edges and corners")

    cam = result.camera
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    comment = (f"pose-daemon calibrate, {stamp}: {len(result.views)} views of {spec.describe()}\n"
               f"RMS reprojection error {result.rms_px:.3f} px, image coverage {result.coverage:.0%}")
    section = cal.camera_toml(cam, comment)
    if args.out and args.out != "-":
        try:
            Path(args.out).write_text(section, encoding="utf-8")
        except OSError as exc:
            raise UserError(f"{args.out}: cannot write: {exc.strerror or exc}") from None
        say(f"wrote [camera] to {args.out}")
    elif to_stdout:
        sys.stdout.write(section)
        sys.stdout.flush()
    if args.config:
        cal.update_config_file(args.config, cam)
        say(f"updated [camera] in {args.config}")
    return 0


def _refuse_too_few(views: List[cal.BoardView], name: str) -> None:
    if len(views) < cal.MIN_VIEWS:
        raise UserError(f"{name}: only {len(views)} usable view(s) of the board; calibration needs at "
                        f"least {cal.MIN_VIEWS} (show the board at more places, tilts and distances)")


def _report(result: cal.CalibrationResult, say: Callable[[str], None]) -> None:
    cam = result.camera
    say(f"RMS reprojection error: {result.rms_px:.3f} px over {len(result.views)} views")
    median = float(np.median(result.view_errors_px))
    for k, (view, err) in enumerate(zip(result.views, result.view_errors_px)):
        flag = f"  OUTLIER (> {max(cal.OUTLIER_FACTOR * median, cal.OUTLIER_FLOOR_PX):.2f} px)" \
            if k in result.outliers else ""
        say(f"  view {k + 1:3d} {view.name:<28s} {len(view.image_points):4d} corners  {err:6.3f} px{flag}")
    if result.rejected_corners:
        whole = sum(1 for v, n in zip(result.views, result.rejected) if n == len(v.image_points))
        say(f"{result.rejected_corners} corner(s) in {sum(1 for n in result.rejected if n)} view(s) left out of "
            f"the fit, their residual far above the rest ({whole} view(s) left out whole)")
    cov = cal.Coverage(cam.width, cam.height)
    for v in result.views:
        cov.add(v.image_points)
    say(f"coverage of the image: {result.coverage:.0%} of {cal.COVERAGE_GRID[0]}x{cal.COVERAGE_GRID[1]} cells")
    for line in cov.map():
        say("  " + line)
    d = ", ".join(f"{x:.5f}" for x in cam.dist[:5])
    say(f"fx {cam.fx:.2f} fy {cam.fy:.2f} cx {cam.cx:.2f} cy {cam.cy:.2f} px; dist [{d}] "
        f"({cam.width}x{cam.height})")


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    if image.dtype != np.uint8:
        image = (image >> 8).astype(np.uint8) if image.dtype == np.uint16 else image.astype(np.uint8)
    return image


def _views_from_path(path: Path, spec: cal.BoardSpec, args: argparse.Namespace,
                     say: Callable[[str], None]) -> Tuple[List[cal.BoardView], Tuple[int, int], str]:
    from ..capture import recording

    if not path.exists():
        raise UserError(f"{path}: no such folder or recording")
    if path.is_dir() and recording.is_recording(path):
        from ..capture.replay import ReplaySource

        return _views_from_source(ReplaySource(path, realtime=False), spec, args, say, str(path))
    if not path.is_dir():
        raise UserError(f"{path}: expected a folder of images or a recording folder")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise UserError(f"{path}: holds no images ({', '.join(IMAGE_EXTENSIONS)})")
    detector = cal.BoardDetector(spec)
    views: List[cal.BoardView] = []
    size: Optional[Tuple[int, int]] = None
    unreadable = 0
    for f in files:
        image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if image is None or image.size == 0:
            unreadable += 1
            say(f"  {f.name}: unreadable image, skipped")
            continue
        gray = _gray(image)
        this = (gray.shape[1], gray.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise UserError(f"{f}: image is {this[0]}x{this[1]}, the others {size[0]}x{size[1]}; "
                            "calibrate one resolution at a time")
        view = detector.detect(gray, f.name)
        if view is None:
            say(f"  {f.name}: no board found")
            continue
        views.append(view)
    if size is None:
        raise UserError(f"{path}: none of its {len(files)} image file(s) could be read")
    if not views:
        raise UserError(f"{path}: no {spec.noun} found in any of its {len(files) - unreadable} "
                        f"image(s) (check --board: {spec.describe()})")
    say(f"board found in {len(views)} of {len(files)} image(s)")
    return views, size, str(path)


def _views_live(spec: cal.BoardSpec, args: argparse.Namespace,
                say: Callable[[str], None]) -> Tuple[List[cal.BoardView], Tuple[int, int], str]:
    from ..capture import open_source
    from ..config import load_config_or_default

    cfg = load_config_or_default(args.config)
    try:
        source = open_source(cfg.camera, cfg)
    except SourceError as exc:
        raise UserError(str(exc)) from None
    if args.seconds is None:
        say(f"live from {cfg.camera.source}: move the board around until {args.views} views are "
            "kept (Ctrl-C stops)")
    else:
        say(f"live from {cfg.camera.source}: up to {args.views} views or {args.seconds:g} s")
    return _views_from_source(source, spec, args, say, f"camera {cfg.camera.source}")


def _views_from_source(source, spec: cal.BoardSpec, args: argparse.Namespace, say: Callable[[str], None],
                       name: str, clock: Callable[[], float] = time.monotonic) -> Tuple[List[cal.BoardView], Tuple[int, int], str]:
    """Views from a frame source, kept only when the board is somewhere new."""
    detector = cal.BoardDetector(spec, fast=True)
    views: List[cal.BoardView] = []
    selector: Optional[cal.ViewSelector] = None
    coverage: Optional[cal.Coverage] = None
    size: Optional[Tuple[int, int]] = None
    frames = seen = 0
    save_dir = Path(args.save_views) if getattr(args, "save_views", None) else None
    if save_dir is not None:
        try:
            save_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"{save_dir}: cannot create: {exc.strerror or exc}") from None
    try:
        source.open()
    except SourceError as exc:
        raise UserError(f"{name}: {exc}") from None
    t0 = last_status = clock()
    try:
        while len(views) < args.views and (args.seconds is None or clock() - t0 < args.seconds):
            try:
                frame = source.read()
            except EndOfStream:
                break
            except SourceError as exc:
                raise UserError(f"{name}: {exc}") from None
            frames += 1
            gray = _gray(frame.image)
            if size is None:
                size = (gray.shape[1], gray.shape[0])
                selector, coverage = cal.ViewSelector(*size), cal.Coverage(*size)
            elif (gray.shape[1], gray.shape[0]) != size:
                raise UserError(f"{name}: frame {frame.seq} is {gray.shape[1]}x{gray.shape[0]}, the first was "
                                f"{size[0]}x{size[1]}; calibrate one resolution at a time")
            now = clock()
            if now - last_status >= STATUS_INTERVAL_S:
                # Something on screen while nobody holds the board up.
                last_status = now
                say(f"  {frames} frame(s), board seen in {seen}, {len(views)} view(s) kept")
            view = detector.detect(gray, f"frame {frame.seq}")
            if view is None:
                continue
            seen += 1
            assert selector is not None and coverage is not None
            if not selector.is_new(view):
                continue
            views.append(view)
            coverage.add(view.image_points)
            if save_dir is not None:
                view.name = f"view{len(views):03d}.png"
                if not cv2.imwrite(str(save_dir / view.name), gray):
                    raise UserError(f"{save_dir}: cannot write {view.name}")
            sig = selector.signatures[-1]
            say(f"  kept view {len(views):3d}/{args.views} (frame {frame.seq}): centre "
                f"({sig[0]:.2f}, {sig[1]:.2f}) size {np.exp(sig[2]):.2f} tilt "
                f"({np.degrees(sig[3]):+.0f}, {np.degrees(sig[4]):+.0f}) deg; coverage {coverage.fraction:.0%}")
    except KeyboardInterrupt:
        # Ctrl-C ends the collection; the views kept so far are calibrated.
        say(f"stopped after {frames} frame(s)")
    finally:
        source.close()
    if size is None:
        raise UserError(f"{name}: no frames")
    if not views:
        raise UserError(f"{name}: no {spec.noun} found in any of {frames} frame(s) "
                        f"(check --board: {spec.describe()})")
    say(f"board seen in {seen} of {frames} frame(s); {len(views)} distinct view(s) kept")
    return views, size, name
