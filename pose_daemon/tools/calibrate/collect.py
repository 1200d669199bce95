"""Calibration views: where the board's corners have reached (Coverage), which views are new
enough to keep (ViewSelector), and collecting views from a folder of images, a recording or
the live camera."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable, List, Optional, Tuple, Union

import cv2
import numpy as np

from ...capture.replay import IMAGE_EXTENSIONS
from ...errors import EndOfStream, SourceError, UserError
from ...geometry import R_from_rvec
from ...image import as_gray
from .board import BoardDetector, BoardSpec, BoardView

#: Coverage is counted on this grid of cells over the image (columns, rows).
COVERAGE_GRID = (8, 6)
#: Live collection: a status line at least this often, seconds.
STATUS_INTERVAL_S = 5.0


class Coverage:
    """Which cells of a COVERAGE_GRID over the image the board's corners have reached."""

    def __init__(self, width: int, height: int, grid: Tuple[int, int] = COVERAGE_GRID) -> None:
        self.width, self.height, self.grid = width, height, grid
        self.hits = np.zeros((grid[1], grid[0]), dtype=int)

    def add(self, image_points: np.ndarray) -> None:
        gx = np.clip((image_points[:, 0] / self.width * self.grid[0]).astype(int), 0, self.grid[0] - 1)
        gy = np.clip((image_points[:, 1] / self.height * self.grid[1]).astype(int), 0, self.grid[1] - 1)
        np.add.at(self.hits, (gy, gx), 1)

    @property
    def fraction(self) -> float:
        """Share of the cells reached by at least one corner, 0..1."""
        return float((self.hits > 0).mean())

    def map(self) -> List[str]:
        """The grid as text lines: '#' reached, '.' not."""
        return ["|" + "".join("#" if h else "." for h in row) + "|" for row in self.hits]


def view_signature(view: BoardView, width: int, height: int) -> np.ndarray:
    """Where the board is: (centre x, centre y) as fractions of the image, log of its apparent
    size, and its tilt about the camera's x and y axes in radians, from a rough pose."""
    pts = view.image_points
    f = 0.9 * max(width, height)  # a typical lens; the signature only compares views
    K = np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])
    ok, rvec, tvec = cv2.solvePnP(view.object_points.astype(np.float64), pts, K, None)
    centre = pts.mean(axis=0)
    hull = cv2.convexHull(pts.astype(np.float32))
    size = math.sqrt(max(cv2.contourArea(hull), 1.0) / (width * height))
    tilt_x = tilt_y = 0.0
    if ok:
        normal = R_from_rvec(rvec.reshape(3))[:, 2]
        normal = normal if normal[2] < 0 else -normal  # the face turned towards the camera
        tilt_x, tilt_y = math.asin(float(np.clip(normal[1], -1, 1))), math.asin(float(np.clip(normal[0], -1, 1)))
    return np.array([centre[0] / width, centre[1] / height, math.log(size), tilt_x, tilt_y])


#: How far apart (centre fraction, log size, radians) two views must be to count as different.
_SIGNATURE_SCALE = np.array([0.12, 0.12, 0.25, 0.17, 0.17])


class ViewSelector:
    """Keeps a view only when the board is in a new place, at a new distance or tilt."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self.signatures: List[np.ndarray] = []

    def is_new(self, view: BoardView) -> bool:
        sig = view_signature(view, self.width, self.height)
        if self.signatures:
            d = np.abs((np.array(self.signatures) - sig) / _SIGNATURE_SCALE)
            if float(d.max(axis=1).min()) < 1.0:
                return False
        self.signatures.append(sig)
        return True


def views_from_path(
    path: Path,
    spec: BoardSpec,
    *,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    say: Callable[[str], None] = print,
) -> Tuple[List[BoardView], Tuple[int, int], str]:
    """Views of the board in a folder of images (every image a view) or in a recording
    (``views_from_source``): (views, (width, height), name for messages)."""
    from ...capture import recording

    if not path.exists():
        raise UserError(f"{path}: no such folder or recording")
    if path.is_dir() and recording.is_recording(path):
        from ...capture.replay import ReplaySource

        return views_from_source(
            ReplaySource(path, realtime=False),
            spec,
            max_views=max_views,
            seconds=seconds,
            save_views=save_views,
            say=say,
            name=str(path),
        )
    if not path.is_dir():
        raise UserError(f"{path}: expected a folder of images or a recording folder")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise UserError(f"{path}: holds no images ({', '.join(IMAGE_EXTENSIONS)})")
    detector = BoardDetector(spec)
    views: List[BoardView] = []
    size: Optional[Tuple[int, int]] = None
    unreadable = 0
    for f in files:
        image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if image is None or image.size == 0:
            unreadable += 1
            say(f"  {f.name}: unreadable image, skipped")
            continue
        try:
            gray = as_gray(image)
        except ValueError as exc:
            raise UserError(f"{f}: {exc}") from None
        this = (gray.shape[1], gray.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise UserError(
                f"{f}: image is {this[0]}x{this[1]}, the others {size[0]}x{size[1]}; calibrate one resolution at a time"
            )
        view = detector.detect(gray, f.name)
        if view is None:
            say(f"  {f.name}: no board found")
            continue
        views.append(view)
    if size is None:
        raise UserError(f"{path}: none of its {len(files)} image file(s) could be read")
    if not views:
        raise UserError(
            f"{path}: no {spec.noun} found in any of its {len(files) - unreadable} "
            f"image(s) (check --board: {spec.describe()})"
        )
    say(f"board found in {len(views)} of {len(files)} image(s)")
    return views, size, str(path)


def views_live(
    spec: BoardSpec,
    config: Optional[str] = None,
    *,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    say: Callable[[str], None] = print,
) -> Tuple[List[BoardView], Tuple[int, int], str]:
    """Views from the camera source of ``config`` (the default config without one)."""
    from ...capture import open_source
    from ...config import load_config_or_default

    cfg = load_config_or_default(config)
    try:
        source = open_source(cfg.camera, cfg)
    except SourceError as exc:
        raise UserError(str(exc)) from None
    if seconds is None:
        say(f"live from {cfg.camera.source}: move the board around until {max_views} views are kept (Ctrl-C stops)")
    else:
        say(f"live from {cfg.camera.source}: up to {max_views} views or {seconds:g} s")
    return views_from_source(
        source,
        spec,
        max_views=max_views,
        seconds=seconds,
        save_views=save_views,
        say=say,
        name=f"camera {cfg.camera.source}",
    )


def views_from_source(
    source,
    spec: BoardSpec,
    *,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    say: Callable[[str], None] = print,
    name: str = "source",
    clock: Callable[[], float] = time.monotonic,
) -> Tuple[List[BoardView], Tuple[int, int], str]:
    """Views from a frame source, kept only when the board is somewhere new; stops after
    ``max_views`` views, ``seconds`` s on ``clock``, the end of the stream or Ctrl-C. With
    ``save_views`` the kept frames are also written there as PNG files."""
    detector = BoardDetector(spec, fast=True)
    views: List[BoardView] = []
    selector: Optional[ViewSelector] = None
    coverage: Optional[Coverage] = None
    size: Optional[Tuple[int, int]] = None
    frames = seen = 0
    save_dir = Path(save_views) if save_views else None
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
        while len(views) < max_views and (seconds is None or clock() - t0 < seconds):
            try:
                frame = source.read()
            except EndOfStream:
                break
            except SourceError as exc:
                raise UserError(f"{name}: {exc}") from None
            frames += 1
            try:
                gray = as_gray(frame.image)
            except ValueError as exc:
                raise UserError(f"{name}: frame {frame.seq}: {exc}") from None
            if size is None:
                size = (gray.shape[1], gray.shape[0])
                selector, coverage = ViewSelector(*size), Coverage(*size)
            elif (gray.shape[1], gray.shape[0]) != size:
                raise UserError(
                    f"{name}: frame {frame.seq} is {gray.shape[1]}x{gray.shape[0]}, the first was "
                    f"{size[0]}x{size[1]}; calibrate one resolution at a time"
                )
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
            say(
                f"  kept view {len(views):3d}/{max_views} (frame {frame.seq}): centre "
                f"({sig[0]:.2f}, {sig[1]:.2f}) size {np.exp(sig[2]):.2f} tilt "
                f"({np.degrees(sig[3]):+.0f}, {np.degrees(sig[4]):+.0f}) deg; coverage {coverage.fraction:.0%}"
            )
    except KeyboardInterrupt:
        # Ctrl-C ends the collection; the views kept so far are calibrated.
        say(f"stopped after {frames} frame(s)")
    finally:
        source.close()
    if size is None:
        raise UserError(f"{name}: no frames")
    if not views:
        raise UserError(f"{name}: no {spec.noun} found in any of {frames} frame(s) (check --board: {spec.describe()})")
    say(f"board seen in {seen} of {frames} frame(s); {len(views)} distinct view(s) kept")
    return views, size, name
