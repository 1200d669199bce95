"""AprilTag field layouts (WPILib's and PhotonVision's JSON) as map markers: what
``pose-daemon map import`` writes and what ``[map] file`` reads when it names a ``.json``.

The layout: ``{"tags": [{"ID": n, "pose": {"translation": {"x", "y", "z"}, "rotation":
{"quaternion": {"W", "X", "Y", "Z"}}}}, ...], "field": {"length", "width"}}``, metres, in the
field frame (x along the field, y to its left, z up). It holds no tag size and no tag family.

A tag's own frame there (WPILib's AprilTagFieldLayout, PhotonVision's "AprilTag coordinate
frame"): x out of the tag's printed face (towards whoever looks at it), y to that viewer's
right, z up: the top of the tag as the AprilTag library draws it (the official images,
apriltag-imgs, that fields print). The marker frame of marker_map: x right, y up (the top edge,
corners 0 -> 1), z out of the face, where OpenCV's detector puts corner 0; for OpenCV's AprilTag
dictionaries that is the official image's bottom-right corner (OpenCV's DICT_APRILTAG_* images
are the official ones turned 180 deg; an ArUco dictionary's is its own image's top-left). So
the marker frame's axes in the tag frame are (-tag y, -tag z, tag x) for an AprilTag
dictionary (R_TAG_MARKER) and (tag y, tag z, tag x) for an ArUco one (R_TAG_MARKER_ARUCO). The
map frame is the field frame (z up: placement floor).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List

import numpy as np

from .geometry import R_from_quaternion, euler_rpy_from_R_3x3

__all__ = [
    "LAYOUT_DICTIONARY",
    "R_TAG_MARKER",
    "R_TAG_MARKER_ARUCO",
    "R_tag_marker",
    "LayoutError",
    "is_layout",
    "layout_tables",
    "read_layout_file",
]

#: The tag family of FRC fields since 2024 (and PhotonVision's default), as OpenCV names it.
LAYOUT_DICTIONARY = "DICT_APRILTAG_36h11"
#: The marker frame's axes (columns: x right, y up, z out of the face) in a layout tag's frame,
#: for OpenCV's AprilTag dictionaries (corner 0 at the official image's bottom-right)...
R_TAG_MARKER = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: ... and for ArUco dictionaries (corner 0 at the printed image's top-left).
R_TAG_MARKER_ARUCO = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
for _R in (R_TAG_MARKER, R_TAG_MARKER_ARUCO):
    _R.setflags(write=False)


class LayoutError(ValueError):
    """A layout that cannot be read: the message names the entry and the key."""


def is_layout(data: Any) -> bool:
    """Is this parsed JSON a field layout (a "tags" list)?"""
    return isinstance(data, dict) and isinstance(data.get("tags"), list)


def read_layout_file(path: Path) -> Any:
    """The parsed JSON of ``path``; LayoutError (naming what is wrong, not the file) otherwise."""
    try:
        text = path.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise LayoutError(f"cannot read it: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise LayoutError(f"invalid JSON: {exc}") from None
    if not is_layout(data):
        raise LayoutError('expected an AprilTag field layout: a JSON object with a "tags" list')
    return data


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise LayoutError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _table(parent: Any, key: str, where: str) -> Dict[str, Any]:
    value = parent.get(key) if isinstance(parent, dict) else None
    if not isinstance(value, dict):
        raise LayoutError(f"{where}.{key}: expected an object, got {value!r}")
    return value


def R_tag_marker(dictionary: str) -> np.ndarray:
    """The marker frame's axes in a layout tag's frame for the tags of ``dictionary``."""
    return R_TAG_MARKER if dictionary.upper().startswith("DICT_APRILTAG") else R_TAG_MARKER_ARUCO


def layout_tables(data: Any, size_m: float, dictionary: str = LAYOUT_DICTIONARY) -> List[Dict[str, Any]]:
    """The layout's tags as [[map.markers]] tables (id, size, position, rotation_deg) in its order,
    every tag ``size_m`` metres (outer edge of the black border), printed in ``dictionary``.
    LayoutError names the tag."""
    R_tm = R_tag_marker(dictionary)
    if not is_layout(data):
        raise LayoutError('expected an AprilTag field layout: a JSON object with a "tags" list')
    if not data["tags"]:
        raise LayoutError('"tags": expected at least one tag, got none')
    out = []
    for k, tag in enumerate(data["tags"]):
        where = f"tags[{k}]"
        if not isinstance(tag, dict):
            raise LayoutError(f"{where}: expected an object with ID and pose, got {tag!r}")
        tag_id = tag.get("ID")
        if isinstance(tag_id, bool) or not isinstance(tag_id, int) or tag_id < 0:
            raise LayoutError(f"{where}.ID: expected an integer >= 0, got {tag_id!r}")
        pose = _table(tag, "pose", where)
        tr = _table(pose, "translation", f"{where}.pose")
        q = _table(_table(pose, "rotation", f"{where}.pose"), "quaternion", f"{where}.pose.rotation")
        position = [_number(tr.get(a), f"{where}.pose.translation.{a}") for a in ("x", "y", "z")]
        w, x, y, z = (_number(q.get(a), f"{where}.pose.rotation.quaternion.{a}") for a in ("W", "X", "Y", "Z"))
        try:
            R_field_tag = R_from_quaternion(w, x, y, z)
        except ValueError as exc:
            raise LayoutError(f"{where}.pose.rotation.quaternion: {exc}") from None
        rpy = euler_rpy_from_R_3x3(R_field_tag @ R_tm)
        out.append({"id": tag_id, "size": size_m, "position": position, "rotation_deg": [math.degrees(a) for a in rpy]})
    return out
