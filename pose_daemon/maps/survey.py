"""``pose-daemon map build``: a marker map surveyed from walk-through recordings (or image
folders); the sources and the map file that ``map check`` (maps/check.py) reads too.

build: every frame's markers (detect/multi.MapDetector over every id of the dictionary), then
map_build.build_map; the report names the markers placed (with their uncertainty), those not
placed and why, the RMS reprojection error and the frames left out; the map is written in the
[map] format (interface.md) that ``[map] file`` names.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Dict, Iterator, List, Optional, Sequence, TextIO

import numpy as np

from ..camera import Camera
from ..capture import recording
from ..capture.base import Frame
from ..capture.replay import ReplaySource
from ..config import load_config
from ..errors import ConfigError, EndOfStream, SourceError, UserError
from ..marker_map import MapMarker, MarkerMap
from .build import MapBuild, build_map, require_scipy

if TYPE_CHECKING:
    from ..detect.multi import MapDetector

#: map build's detector drops a track missed this many frames in a row (see survey_detector).
SURVEY_MAX_MISSES = 0


@dataclass
class Walkthrough:
    """The frames' detections of every source: per frame {id: corners}, a label, the camera."""

    camera: Camera
    observations: List[Dict[int, np.ndarray]]
    labels: List[str]
    duration_s: float
    detect_s: float


def _open(path: str) -> ReplaySource:
    source = ReplaySource(path, realtime=False)
    try:
        source.open()
    except SourceError as exc:
        raise UserError(str(exc)) from None
    return source


def _camera_of(source: ReplaySource, path: str, config_camera: Optional[Camera]) -> Camera:
    try:
        cam = recording.camera_from_meta(source.meta)
    except SourceError as exc:
        raise UserError(f"{path}: {exc}") from None
    if cam is not None:
        return cam
    if config_camera is None:
        raise UserError(f"{path} holds no camera model: give the calibrated camera with --config FILE")
    return config_camera


def config_camera(config: Optional[str]) -> Optional[Camera]:
    """The [camera] of ``config`` (None without one)."""
    if config is None:
        return None
    return load_config(config).camera.model()


def _frames(source: ReplaySource) -> Iterator[Frame]:
    while True:
        try:
            yield source.read()
        except EndOfStream:
            return


def detect_placeholder_map(dictionary: str, sizes: Dict[int, float], default_size_m: float) -> MarkerMap:
    """A map of every id of ``dictionary`` (far apart, none nested) for MapDetector: the
    detector needs the ids and sizes, not where they are."""
    from ..detect import aruco_compat

    try:
        n = aruco_compat.dictionary_size(aruco_compat.get_dictionary(dictionary))
    except ValueError:
        raise UserError(
            f"--dictionary: expected an OpenCV ArUco or AprilTag dictionary name such as "
            f'"DICT_4X4_50", got {dictionary!r}'
        ) from None
    for i in sizes:
        if not 0 <= i < n:
            raise UserError(f"--sizes: marker id {i} is not an id of {dictionary} (0 to {n - 1})")
    markers = tuple(MapMarker(i, float(sizes.get(i, default_size_m)), (1000.0 * i, 0.0, 0.0)) for i in range(n))
    return MarkerMap(dictionary, markers, "floor")


def survey_detector(placeholder: MarkerMap, camera: Camera) -> MapDetector:
    """The MapDetector of a walk-through (``placeholder``: ``detect_placeholder_map``).

    A marker missed in one frame is dropped at once (``max_misses=0``) instead of searched for
    around where it was for five frames: a frame that loses a marker is searched whole anyway
    (and a walk loses markers at the frame's edges all the time), which finds it again where it
    still is. The same detections (the bench's walk-throughs, corner for corner) in 40 % less
    time.
    """
    from ..detect.multi import MapDetector

    return MapDetector(placeholder, camera=camera, max_misses=SURVEY_MAX_MISSES)


def detect_walkthrough(
    sources: Sequence[str],
    dictionary: str,
    sizes: Dict[int, float],
    default_size_m: float,
    config: Optional[str] = None,
    every: int = 1,
) -> Walkthrough:
    """Every map marker in every ``every``-th frame of each source (one camera for all)."""
    placeholder = detect_placeholder_map(dictionary, sizes, default_size_m)
    cfg_camera = config_camera(config)
    opened = [(path, _open(path)) for path in sources]
    camera: Optional[Camera] = None
    for path, source in opened:
        cam = _camera_of(source, path, cfg_camera)
        if camera is None:
            camera = cam
        elif recording.camera_to_dict(cam) != recording.camera_to_dict(camera):
            raise UserError(f"{path} was taken with another camera model than {opened[0][0]}: survey with one camera")
    assert camera is not None
    observations: List[Dict[int, np.ndarray]] = []
    labels: List[str] = []
    duration = 0.0
    t0 = time.perf_counter()
    for path, source in opened:
        detector = survey_detector(placeholder, camera)
        first = last = None
        for k, frame in enumerate(_frames(source)):
            first = frame.t_capture_s if first is None else first
            last = frame.t_capture_s
            if k % every:
                continue
            if frame.image.shape[:2] != (camera.height, camera.width):
                raise UserError(
                    f"{path}: frame {frame.seq} is {frame.image.shape[1]}x{frame.image.shape[0]} but the camera "
                    f"model is {camera.width}x{camera.height}"
                )
            observations.append(detector.detect(frame.image))
            labels.append(f"{Path(path).name}:{frame.seq}")
        source.close()
        if first is not None and last is not None:
            duration += last - first + 1.0 / source.fps
    return Walkthrough(camera, observations, labels, duration, time.perf_counter() - t0)


def parse_sizes(text: Optional[str]) -> Dict[int, float]:
    """``--sizes 3=0.15,7=0.3`` -> {3: 0.15, 7: 0.3}; UserError naming the bad entry."""
    out: Dict[int, float] = {}
    if not text:
        return out
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            key, value = part.split("=")
            marker_id, size = int(key), float(value)
        except ValueError:
            raise UserError(f"--sizes: expected ID=METRES entries such as 3=0.15, got {part!r}") from None
        if marker_id < 0 or not (math.isfinite(size) and 0.0 < size <= 100.0):
            raise UserError(f"--sizes: expected an id >= 0 and a size in (0, 100] metres, got {part!r}")
        out[marker_id] = size
    return out


def write_map(build: MapBuild, out: Path) -> None:
    lines = [
        f"# pose-daemon map build: {len(build.placed)} markers, anchor {build.anchor}, "
        f"RMS reprojection error {build.rms_px:.3f} px",
    ]
    lines += build.marker_map.to_toml_lines()
    try:
        out.write_text("\n".join(lines))
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None


def report_lines(build: MapBuild, walk: Optional[Walkthrough] = None) -> List[str]:
    """The build's report, one finding a line."""
    lines = []
    if walk is not None:
        lines.append(
            f"frames: {len(walk.observations)} read ({walk.duration_s:.1f} s of recording), "
            f"detection {walk.detect_s:.1f} s"
        )
    lines.append(
        f"placed: {len(build.placed)} markers in the frame of marker {build.anchor} (the anchor), "
        f"from {build.frames_used} frames, {build.observations_used} marker views; "
        f"RMS reprojection error {build.rms_px:.3f} px; one plane: {build.plane}"
    )
    lines.append(
        f"  {'id':>4} {'size m':>7} {'x m':>8} {'y m':>8} {'z m':>8} {'yaw deg':>8} "
        f"{'views':>6} {'rms px':>7} {'sd mm':>6} {'sd deg':>7}"
    )
    for p in build.placed:
        x, y, z = p.position_m
        lines.append(
            f"  {p.id:>4} {p.size_m:>7.3f} {x:>8.4f} {y:>8.4f} {z:>8.4f} {p.rotation_deg[2]:>8.2f} "
            f"{p.views:>6} {p.rms_px:>7.3f} {1e3 * p.position_std_m:>6.2f} {p.rotation_std_deg:>7.3f}"
        )
    if build.unplaced:
        lines.append(f"not placed: {len(build.unplaced)} markers")
        for i, why in build.unplaced.items():
            lines.append(f"  {i}: {why}")
    else:
        lines.append("not placed: none")
    left = sum(len(v) for v in build.frames_left_out.values())
    lines.append(f"frames left out of the solve: {left}")
    for why, frames in build.frames_left_out.items():
        shown = ", ".join(frames[:5]) + (", ..." if len(frames) > 5 else "")
        lines.append(f"  {len(frames)}: {why} ({shown})")
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in build.stage_s.items())
    lines.append(f"time: {stages}")
    return lines


def plot_build(build: MapBuild, path: Path, title: str = "") -> None:
    """The map from above (each marker's outline and id) with the camera path."""
    from ..plotting import new_figure, save_figure
    from ..tools.plot import top_view_axes

    placement = build.marker_map.placement
    h, v, hlabel, vlabel = top_view_axes(placement)
    fig, ax = new_figure(size_in=(7.0, 7.0))
    cam = build.camera_path_m
    if len(cam):
        ax.plot(cam[:, h], cam[:, v], color="0.6", lw=0.8, zorder=1, label="camera path")
    for p in build.placed:
        c = build.marker_map.corners_map(p.id)
        ring = np.vstack([c, c[:1]])
        colour = "tab:red" if p.id == build.anchor else "tab:blue"
        ax.plot(ring[:, h], ring[:, v], color=colour, lw=1.5, zorder=2)
        ax.plot([c[0, h], c[1, h]], [c[0, v], c[1, v]], color="k", lw=2.5, zorder=3)  # top edge
        ax.text(p.position_m[h], p.position_m[v], str(p.id), ha="center", va="center", fontsize="small", zorder=4)
    ax.plot([], [], color="tab:red", label=f"anchor {build.anchor}")
    ax.plot([], [], color="tab:blue", label="markers (thick: top edge)")
    ax.set(
        title=title or f"surveyed map from above: {len(build.placed)} markers, RMS {build.rms_px:.2f} px",
        xlabel=hlabel,
        ylabel=vlabel,
    )
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize="small")
    save_figure(fig, path)


def check_out(out: Path) -> Path:
    if out.is_dir():
        raise UserError(f"--out {out} is a folder; name the map file to write")
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise UserError(f"--out {out}: folder {parent} does not exist")
    return out


def build(
    sources: Sequence[str],
    *,
    dictionary: str,
    size_m: float,
    sizes: Optional[str] = None,
    anchor: Optional[int] = None,
    placement: str = "floor",
    out: Path,
    plot: Optional[Path] = None,
    config: Optional[str] = None,
    every: int = 1,
    max_frames: int = 600,
    plane: bool = True,
    stream: Optional[TextIO] = None,
) -> MapBuild:
    """``pose-daemon map build``: detect, build, write ``out`` (and ``plot``), print the report."""
    stream = stream if stream is not None else sys.stdout
    require_scipy()
    if not (math.isfinite(size_m) and 0.0 < size_m <= 100.0):
        raise UserError(f"--size: expected a marker size in (0, 100] metres, got {size_m}")
    if every < 1 or max_frames < 2:
        raise UserError("--every must be >= 1 and --max-frames >= 2")
    check_out(out)
    if plot is not None:
        from ..plotting import check_plot_path, require_matplotlib

        require_matplotlib()
        check_plot_path(plot)
    size_table = parse_sizes(sizes)
    if anchor is not None and anchor < 0:
        raise UserError(f"--anchor: expected a marker id >= 0, got {anchor}")
    n_ids = len(detect_placeholder_map(dictionary, size_table, size_m).ids)
    if anchor is not None and anchor >= n_ids:
        raise UserError(f"--anchor: marker id {anchor} is not an id of {dictionary} (0 to {n_ids - 1})")
    walk = detect_walkthrough(sources, dictionary, size_table, size_m, config, every)
    result = build_map(
        walk.observations,
        walk.camera,
        dictionary,
        size_table,
        default_size_m=size_m,
        anchor=anchor,
        placement=placement,
        plane=plane,
        labels=walk.labels,
        max_frames=max_frames,
    )
    write_map(result, out)
    if plot is not None:
        plot_build(result, plot)
    for line in report_lines(result, walk):
        print(line, file=stream)
    print(f"wrote {out}" + (f" and {plot}" if plot is not None else ""), file=stream)
    return result


# ----------------------------------------------------------------------------- map check


def load_map_file(path: str) -> MarkerMap:
    """A map file in the [map] format (what map build writes); UserError naming the problem."""
    from ..config import config_from_dict, tomllib

    p = Path(path)
    try:
        data = tomllib.loads(p.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{p}: cannot read map: {getattr(exc, 'strerror', None) or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{p}: invalid TOML: {' '.join(str(exc).split())}") from None
    if not isinstance(data.get("map"), dict):
        raise UserError(f"{p}: expected a [map] table with [[map.markers]] entries")
    try:
        cfg = config_from_dict({"map": data["map"]}, name=str(p))
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    assert cfg.map is not None
    return cfg.map.model()
