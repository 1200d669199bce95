"""The recording format: a folder of lossless PNG frames with an index, the camera and marker.

DIR/recording.json   {"format": "pose-daemon-recording", "version": 1, "camera": {fx, fy,
                      cx, cy, dist, width, height}, "marker": {type, width, height,
                      dictionary, id}, "source": "...", "fps": 30.0, "created_utc": "..."}
DIR/index.jsonl      one line per frame: {"seq": 0, "file": "frames/000000.png",
                      "t_capture_s": 12.345678} plus, from the synthetic source, the
                      truth: "true_rvec", "true_tvec" (marker in camera frame, rad / m),
                      "true_corners" ([[u, v] x 4], px, TL TR BR BL); and when the
                      frame had one, the vehicle's attitude: "attitude_rpy_rad" ([roll,
                      pitch, yaw], body FRD in local NED, Z-Y-X) and optionally
                      "attitude_sigma_rad" (interface.md)
DIR/frames/NNNNNN.png  8-bit grey frames
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Dict, List, Optional, Union

import cv2
import numpy as np

from ..attitude import Attitude
from ..camera import Camera, Marker
from ..errors import SourceError
from .base import Frame

FORMAT = "pose-daemon-recording"
VERSION = 1
META_FILE = "recording.json"
INDEX_FILE = "index.jsonl"

_log = logging.getLogger(__name__)
TRUTH_KEYS = ("true_rvec", "true_tvec", "true_corners")
ATTITUDE_KEY, ATTITUDE_SIGMA_KEY = "attitude_rpy_rad", "attitude_sigma_rad"
# Every number read from a recording is checked against these: a NaN, an infinity or an absurd
# value is a broken recording, said in one line naming the file, the line and the key.
MAX_TIME_S = 1e10  # a capture time beyond +-317 years is no clock's
MAX_FPS = 10000.0
MAX_ANGLE_RAD = 2 * math.pi
TRUTH_SHAPES = {"true_rvec": (3,), "true_tvec": (3,), "true_corners": (4, 2)}
MAX_TRUTH = 1e6  # rad, m or px: a larger truth value is no scene's


def is_recording(path: Union[str, Path]) -> bool:
    return (Path(path) / INDEX_FILE).is_file()


def camera_to_dict(camera: Camera) -> Dict[str, Any]:
    return {
        "fx": camera.fx,
        "fy": camera.fy,
        "cx": camera.cx,
        "cy": camera.cy,
        "dist": list(camera.dist),
        "width": camera.width,
        "height": camera.height,
    }


def marker_to_dict(marker: Marker) -> Dict[str, Any]:
    return {
        "type": marker.type,
        "width": marker.width,
        "height": marker.height,
        "dictionary": marker.dictionary,
        "id": marker.id,
    }


class RecordingWriter:
    """Writes frames into a new recording folder (which must not hold a recording already)."""

    def __init__(
        self,
        path: Union[str, Path],
        camera: Camera,
        marker: Optional[Marker] = None,
        *,
        source: str = "",
        fps: float = 0.0,
    ) -> None:
        self.path = Path(path)
        if is_recording(self.path):
            raise SourceError(f"{self.path} already holds a recording; choose a new folder")
        if self.path.exists() and not self.path.is_dir():
            raise SourceError(f"{self.path} exists and is not a folder")
        (self.path / "frames").mkdir(parents=True, exist_ok=True)
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "camera": camera_to_dict(camera),
            "marker": marker_to_dict(marker) if marker is not None else None,
            "source": source,
            "fps": fps,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        (self.path / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")
        self._index = open(self.path / INDEX_FILE, "w")
        self.count = 0

    def write(self, frame: Frame) -> None:
        name = f"frames/{frame.seq:06d}.png"
        if not cv2.imwrite(str(self.path / name), frame.image):
            raise SourceError(f"cannot write {self.path / name}")
        entry: Dict[str, Any] = {"seq": int(frame.seq), "file": name, "t_capture_s": float(frame.t_capture_s)}
        for key in TRUTH_KEYS:
            if key in frame.metadata:
                entry[key] = np.asarray(frame.metadata[key], dtype=np.float64).tolist()
        if frame.attitude is not None:
            entry[ATTITUDE_KEY] = [float(v) for v in frame.attitude.rpy_rad]
            if frame.attitude.sigma_rad is not None:
                entry[ATTITUDE_SIGMA_KEY] = float(frame.attitude.sigma_rad)
        self._index.write(json.dumps(entry) + "\n")
        self._index.flush()
        self.count += 1

    def close(self) -> None:
        self._index.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_meta(path: Union[str, Path]) -> Dict[str, Any]:
    """recording.json of a recording ({} when absent); SourceError if it is not valid."""
    meta_path = Path(path) / META_FILE
    if not meta_path.is_file():
        return {}
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as exc:
        raise SourceError(f"{meta_path}: not valid JSON ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise SourceError(f"{meta_path}: not a {FORMAT} file")
    fps = meta.get("fps")
    if fps is not None and fps != 0 and not _is_number(fps, 0.0, MAX_FPS):
        raise SourceError(f"{meta_path}: fps must be a number of frames per second in (0, {MAX_FPS:g}], got {fps!r}")
    return meta


def _is_number(value: Any, lo: float, hi: float) -> bool:
    """A JSON number (no bool, no string), finite, within [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return math.isfinite(value) and lo <= value <= hi


def check_entry_numbers(entry: Dict[str, Any]) -> None:
    """Every number of one index entry, checked: ValueError("KEY must be ..., got ...") for a
    NaN, an infinity, a string or bool where a number belongs, or an absurd value."""
    t = entry["t_capture_s"]
    if not _is_number(t, -MAX_TIME_S, MAX_TIME_S):
        raise ValueError(f"t_capture_s must be a finite number of seconds within +-{MAX_TIME_S:g}, got {t!r}")
    seq = entry.get("seq", 0)
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise ValueError(f"seq must be a whole number >= 0, got {seq!r}")
    rpy, sigma = entry.get(ATTITUDE_KEY), entry.get(ATTITUDE_SIGMA_KEY)
    if rpy is not None and not (
        isinstance(rpy, list) and len(rpy) == 3 and all(_is_number(v, -MAX_ANGLE_RAD, MAX_ANGLE_RAD) for v in rpy)
    ):
        raise ValueError(f"{ATTITUDE_KEY} must be [roll, pitch, yaw], finite radians within +-2 pi, got {rpy!r}")
    if sigma is not None and not _is_number(sigma, 0.0, math.pi):
        raise ValueError(f"{ATTITUDE_SIGMA_KEY} must be a number of radians in [0, pi], got {sigma!r}")
    for key, shape in TRUTH_SHAPES.items():
        if key not in entry:
            continue
        try:
            ok = np.asarray(entry[key]).shape == shape and all(
                _is_number(v, -MAX_TRUTH, MAX_TRUTH) for v in np.asarray(entry[key], dtype=object).ravel()
            )
        except ValueError:  # a ragged list
            ok = False
        if not ok:
            size = " x ".join(str(n) for n in shape)
            raise ValueError(f"{key} must be {size} finite numbers within +-{MAX_TRUTH:g}, got {entry[key]!r}")


def camera_from_meta(meta: Dict[str, Any]) -> Optional[Camera]:
    cam = meta.get("camera")
    if not cam:
        return None
    try:
        return Camera(**cam)
    except (TypeError, ValueError) as exc:
        raise SourceError(f"recording camera model is invalid: {exc}") from exc


def marker_from_meta(meta: Dict[str, Any]) -> Optional[Marker]:
    m = meta.get("marker")
    if not m:
        return None
    try:
        return Marker(**m)
    except (TypeError, ValueError) as exc:
        raise SourceError(f"recording marker is invalid: {exc}") from exc


def _outside(file: str) -> bool:
    """True for an index entry's file that is not inside the recording folder: an absolute path
    or one climbing out with "..". A recording's frames are its own files; an index must not
    make replay read (and ``--annotate`` copy out) any other file."""
    p = PurePosixPath(file.replace("\\", "/"))
    return p.is_absolute() or PureWindowsPath(file).drive != "" or ".." in p.parts


def read_index(path: Union[str, Path]) -> List[Dict[str, Any]]:
    """The index entries; a line that cannot be parsed is a SourceError naming its number, as is
    one whose file lies outside the recording folder.

    The exception is an unfinished last line (no line end): a recording cut off by a power
    loss ends that way, and the frames before it are still good, so that line is skipped."""
    index_path = Path(path) / INDEX_FILE
    entries: List[Dict[str, Any]] = []
    try:
        text = index_path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"cannot read {index_path}: {exc}") from exc
    lines = text.splitlines()
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
            entry["file"] = str(entry["file"])
            if "t_capture_s" not in entry:
                raise KeyError("t_capture_s")
            if _outside(entry["file"]):
                raise SourceError(
                    f"{index_path}:{n}: frame file {json.dumps(entry['file'])} lies outside "
                    "the recording folder (absolute, or with ..)"
                )
        except (ValueError, KeyError, TypeError) as exc:
            if n == len(lines) and not text.endswith("\n"):
                _log.warning("%s:%d: skipping the unfinished last line (recording cut off)", index_path, n)
                break
            raise SourceError(f"{index_path}:{n}: not a frame entry ({exc})") from exc
        try:
            check_entry_numbers(entry)
            entry["t_capture_s"] = float(entry["t_capture_s"])
            entry["seq"] = int(entry.get("seq", len(entries)))
            entry["attitude"] = attitude_from_entry(entry)
        except ValueError as exc:
            raise SourceError(f"{index_path}:{n}: {exc}") from exc
        entries.append(entry)
    return entries


def attitude_from_entry(entry: Dict[str, Any]) -> Optional[Attitude]:
    """The frame's attitude from an index entry (None when the line has none); ValueError
    naming the key for a value that is not an attitude."""
    if ATTITUDE_KEY not in entry:
        if ATTITUDE_SIGMA_KEY in entry:
            raise ValueError(f"{ATTITUDE_SIGMA_KEY} without {ATTITUDE_KEY}")
        return None
    rpy, sigma = entry[ATTITUDE_KEY], entry.get(ATTITUDE_SIGMA_KEY)
    if (
        not isinstance(rpy, list)
        or len(rpy) != 3
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rpy)
    ):
        raise ValueError(f"{ATTITUDE_KEY} must be [roll, pitch, yaw] in radians, got {rpy!r}")
    if sigma is not None and (isinstance(sigma, bool) or not isinstance(sigma, (int, float))):
        raise ValueError(f"{ATTITUDE_SIGMA_KEY} must be a number of radians, got {sigma!r}")
    roll, pitch, yaw = (float(v) for v in rpy)
    return Attitude((roll, pitch, yaw), None if sigma is None else float(sigma))
