"""Marker maps: many ArUco (or OpenCV AprilTag) markers, each with its own size and pose in one
map frame (interface.md, "Marker maps (config)").

The map frame is the marker frame of a marker at position 0 with rotation 0 (x right, y up,
z out of its face); ``placement`` relates it to the vehicle's local frame exactly as for a
single marker. A marker's ``rotation_deg`` is (roll, pitch, yaw) of its frame in the map frame,
applied as R_map_marker = Rz(yaw) Ry(pitch) Rx(roll) (geometry.R_from_euler_rpy).

Parsing errors are ``MapError(key, expected, got)``; config.py turns them into one line naming
the file, the table index and the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .camera import Marker
from .geometry import MARKER_PLACEMENTS, R_from_euler_rpy

__all__ = ["MapMarker", "MarkerMap", "MapError", "markers_from_tables", "floor_grid", "MARKER_KEYS"]

MARKER_KEYS = ("id", "size", "position", "rotation_deg")


class MapError(ValueError):
    """One map entry is wrong: ``where`` (e.g. "markers[3]"), ``key``, what was ``expected``."""

    def __init__(self, where: str, key: str, expected: str, got: Any = None, has_got: bool = True) -> None:
        super().__init__(f"{where} {key}: expected {expected}")
        self.where, self.key, self.expected, self.got, self.has_got = where, key, expected, got, has_got


@dataclass(frozen=True)
class MapMarker:
    """One marker of a map: ``id``, ``size_m`` (outer edge of the black border), its centre
    ``position_m`` and ``rotation_deg`` (roll, pitch, yaw) in the map frame."""

    id: int
    size_m: float
    position_m: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: Tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def R_map_marker(self) -> np.ndarray:
        r, p, y = np.radians(np.asarray(self.rotation_deg, dtype=np.float64))
        return R_from_euler_rpy(r, p, y)

    def corners_map(self) -> np.ndarray:
        """Corners TL, TR, BR, BL in the map frame (4, 3), metres."""
        h = self.size_m / 2.0
        local = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        return local @ self.R_map_marker.T + np.asarray(self.position_m, dtype=np.float64)


@dataclass(frozen=True)
class MarkerMap:
    """Markers of one dictionary in one map frame; ids unique."""

    dictionary: str
    markers: Tuple[MapMarker, ...]
    placement: str = "floor"
    _by_id: Dict[int, MapMarker] = field(init=False, repr=False, compare=False)
    _corners: Dict[int, np.ndarray] = field(init=False, repr=False, compare=False)
    _T: Dict[int, Tuple[np.ndarray, np.ndarray]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.placement not in MARKER_PLACEMENTS:
            raise ValueError(f"map placement must be one of {', '.join(MARKER_PLACEMENTS)}, got {self.placement!r}")
        if not self.markers:
            raise ValueError("a map needs at least one marker")
        by_id: Dict[int, MapMarker] = {}
        for m in self.markers:
            if m.id in by_id:
                raise ValueError(f"marker id {m.id} appears twice in the map")
            if not (math.isfinite(m.size_m) and m.size_m > 0):
                raise ValueError(f"marker {m.id}: size must be > 0 metres, got {m.size_m}")
            by_id[m.id] = m
        object.__setattr__(self, "markers", tuple(self.markers))
        object.__setattr__(self, "_by_id", by_id)
        corners = {m.id: m.corners_map() for m in self.markers}
        for c in corners.values():
            c.setflags(write=False)
        object.__setattr__(self, "_corners", corners)
        T = {}
        for m in self.markers:
            R, p = m.R_map_marker, np.asarray(m.position_m, dtype=np.float64)
            R.setflags(write=False)
            p.setflags(write=False)
            T[m.id] = (R, p)
        object.__setattr__(self, "_T", T)

    @property
    def ids(self) -> Tuple[int, ...]:
        return tuple(m.id for m in self.markers)

    def marker(self, marker_id: int) -> MapMarker:
        return self._by_id[int(marker_id)]

    def __contains__(self, marker_id: object) -> bool:
        return marker_id in self._by_id

    def corners_map(self, marker_id: int) -> np.ndarray:
        """Corners TL, TR, BR, BL of marker ``marker_id`` in the map frame (4, 3), read-only."""
        return self._corners[int(marker_id)]

    def single(self, marker_id: int) -> Marker:
        """The marker as a single pose_daemon.Marker (its own frame, its own size)."""
        m = self._by_id[int(marker_id)]
        return Marker(width=m.size_m, height=m.size_m, type="aruco", dictionary=self.dictionary, id=m.id)

    def T_map_marker(self, marker_id: int) -> Tuple[np.ndarray, np.ndarray]:
        """(R_map_marker, p_map_marker): X_map = R X_marker + p (read-only arrays)."""
        return self._T[int(marker_id)]

    def down_map(self) -> np.ndarray:
        """Gravity (down) in the map frame for its placement: -z on a floor, -y on a wall."""
        return np.array([0.0, 0.0, -1.0]) if self.placement == "floor" else np.array([0.0, -1.0, 0.0])

    def contains_others(self, marker_id: int) -> bool:
        """Does another map marker lie inside this one's square (a nested pad)?"""
        m = self._by_id[int(marker_id)]
        R, p = self.T_map_marker(marker_id)
        h = m.size_m / 2.0
        for other in self.markers:
            if other.id == m.id or other.size_m >= m.size_m:
                continue
            local = R.T @ (np.asarray(other.position_m) - p)
            if abs(local[2]) < 1e-6 and abs(local[0]) < h and abs(local[1]) < h:
                return True
        return False

    def to_toml_lines(self, with_header: bool = True, exact: bool = False) -> List[str]:
        """The map in the config's [map] format (interface.md); ``exact``: every number with
        all its digits (the shortest text that reads back as the same float), else 6 decimals."""
        g = _exact if exact else _g
        lines: List[str] = []
        if with_header:
            lines += ["[map]", f'dictionary = "{self.dictionary}"', f'placement = "{self.placement}"', ""]
        for m in self.markers:
            lines += [
                "[[map.markers]]",
                f"id = {m.id}",
                f"size = {g(m.size_m)}",
                "position = [" + ", ".join(g(v) for v in m.position_m) + "]",
                "rotation_deg = [" + ", ".join(g(v) for v in m.rotation_deg) + "]",
                "",
            ]
        return lines


def _exact(v: float) -> str:
    return repr(float(v) + 0.0)  # + 0.0: no "-0.0"


def _g(v: float) -> str:
    v = float(v)
    if v == 0.0:
        return "0.0"
    s = f"{v:.6f}".rstrip("0")
    return s + "0" if s.endswith(".") else s


def _number_list(where: str, key: str, value: Any, n: int) -> Tuple[float, ...]:
    expected = f"a list of {n} numbers"
    if not isinstance(value, list) or len(value) != n:
        raise MapError(where, key, expected, value)
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise MapError(where, key, expected, value)
        out.append(float(v))
    return tuple(out)


def markers_from_tables(
    tables: Any, n_ids: Optional[int], dictionary: str, prefix: str = "markers"
) -> Tuple[MapMarker, ...]:
    """Map markers from a TOML array of tables; MapError names ``prefix[i]`` and the key.

    ``n_ids``: how many ids the dictionary has (None: not checked here).
    """
    if not isinstance(tables, list) or not tables:
        raise MapError("", prefix, "a non-empty array of tables [[map.markers]]", tables)
    out: List[MapMarker] = []
    seen: Dict[int, int] = {}
    for i, table in enumerate(tables):
        where = f"{prefix}[{i}]"
        if not isinstance(table, dict):
            raise MapError("", where, "a table with " + ", ".join(MARKER_KEYS), table)
        for key in table:
            if key not in MARKER_KEYS:
                raise MapError(where, key, "one of " + ", ".join(MARKER_KEYS) + " (unknown key)", None, False)
        if "id" not in table:
            raise MapError(where, "id", "an integer >= 0 (every marker needs its id)", None, False)
        mid = table["id"]
        if isinstance(mid, bool) or not isinstance(mid, int) or mid < 0:
            raise MapError(where, "id", "an integer >= 0", mid)
        if n_ids is not None and mid >= n_ids:
            raise MapError(where, "id", f"an integer in [0, {n_ids - 1}] (the ids of {dictionary})", mid)
        if mid in seen:
            raise MapError(where, "id", f"an id not used before ({prefix}[{seen[mid]}] has id {mid})", mid)
        seen[mid] = i
        if "size" not in table:
            raise MapError(where, "size", "a number > 0 (metres; every marker needs its size)", None, False)
        size = table["size"]
        if (
            isinstance(size, bool)
            or not isinstance(size, (int, float))
            or not math.isfinite(float(size))
            or not 0.0 < float(size) <= 100.0
        ):
            raise MapError(where, "size", "a number in (0, 100] (metres)", size)
        position = _number_list(where, "position", table.get("position", [0.0, 0.0, 0.0]), 3)
        rotation = _number_list(where, "rotation_deg", table.get("rotation_deg", [0.0, 0.0, 0.0]), 3)
        out.append(MapMarker(int(mid), float(size), position, rotation))
    return tuple(out)


# --------------------------------------------------------------------------- map layouts


def floor_grid(
    dictionary: str = "DICT_4X4_50",
    rows: int = 3,
    cols: int = 3,
    spacing_m: float = 1.0,
    sizes_m: Sequence[float] = (0.20,),
    first_id: int = 0,
    placement: str = "floor",
) -> MarkerMap:
    """A rows x cols grid centred on the map origin, ids row by row from ``first_id``; sizes
    cycle through ``sizes_m``. Every marker's top edge points along the map's +y."""
    markers = []
    k = 0
    for r in range(rows):
        for c in range(cols):
            x = (c - (cols - 1) / 2.0) * spacing_m
            y = ((rows - 1) / 2.0 - r) * spacing_m
            markers.append(MapMarker(first_id + k, float(sizes_m[k % len(sizes_m)]), (x, y, 0.0)))
            k += 1
    return MarkerMap(dictionary, tuple(markers), placement)
