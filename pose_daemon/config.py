"""TOML configuration -> one typed, validated ``Config``; every mistake is one line naming file and key.

Each section is a dataclass whose fields carry their own rule (type, bounds, choices) in
``field(metadata=...)``, so adding a key is one line: the validator, the error messages and
the config reference all read the same declaration.
"""

from __future__ import annotations

import json
import math
import stat
import sys
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.9/3.10 (Raspberry Pi OS Bullseye)
    import tomli as tomllib

from .camera import MARKER_TYPES, Camera, Marker
from .capture.sources import SOURCE_FORMS, parse_source
from .errors import ConfigError
from .geometry import MARKER_PLACEMENTS, MOUNT_PRESETS
from .outputs.mavlink import AUTOPILOTS, parse_connection
from .outputs.mavlink import MESSAGES as MAVLINK_MESSAGES
from .pose.loop import METHODS

__all__ = [
    "Config",
    "CameraConfig",
    "MarkerConfig",
    "EstimatorConfig",
    "DetectorConfig",
    "SyntheticConfig",
    "PipelineConfig",
    "MountConfig",
    "AttitudeConfig",
    "GateConfig",
    "MavlinkOutputConfig",
    "SerialOutputConfig",
    "JsonlOutputConfig",
    "OutputConfig",
    "LoggingConfig",
    "MapConfig",
    "PreviewConfig",
    "ConfigError",
    "DEFAULT_CONFIG_FILE",
    "check_whole",
    "default_config_text",
    "load_config",
    "parse_config",
]

#: The embedded default, shipped as package data (pose_daemon/data/demo.toml, in the wheel
#: too) so that `pose-daemon run` without --config works anywhere. config/demo.toml in the
#: repository is a symbolic link to it: one file, nothing to keep equal.
DEFAULT_CONFIG_FILE = "demo.toml"


def default_config_text() -> str:
    """The TOML text of the embedded default configuration (the demo: synthetic source)."""
    data = resources.files("pose_daemon").joinpath("data")
    return data.joinpath(DEFAULT_CONFIG_FILE).read_text(encoding="utf-8")


# --------------------------------------------------------------------------- rules


class _Invalid(Exception):
    """Raised by a rule or a section check: ``key`` failed, ``expected`` says what was wanted."""

    def __init__(self, key: str, expected: str, got: Any = MISSING) -> None:
        super().__init__(key)
        self.key = key
        self.expected = expected
        self.got = got


@dataclass(frozen=True)
class Rule:
    """What one key accepts.

    kind: "int", "float", "str", "bool", "floats" (list of numbers), "strs" (list of strings).
    lo/hi: bounds (inclusive unless lo_open/hi_open); choices: allowed values (strings compare
    case-insensitively when ``upper`` is set, and are stored upper-case); lengths: allowed list
    lengths.
    """

    kind: str
    lo: Optional[float] = None
    hi: Optional[float] = None
    lo_open: bool = False
    hi_open: bool = False
    choices: Optional[Tuple[Any, ...]] = None
    lengths: Optional[Tuple[int, ...]] = None
    nonempty: bool = False
    unique: bool = False
    upper: bool = False

    def expectation(self) -> str:
        noun = {
            "int": "an integer",
            "float": "a number",
            "str": "a string",
            "bool": "true or false",
            "floats": "a list of numbers",
            "strs": "a list of strings",
        }[self.kind]
        if self.choices is not None and self.kind in ("str", "int"):
            return "one of " + ", ".join(_show(c) for c in self.choices)
        if self.kind in ("floats", "strs"):
            parts = [noun]
            if self.lengths:
                parts = [
                    f"a list of {' or '.join(str(n) for n in self.lengths)} "
                    f"{'numbers' if self.kind == 'floats' else 'strings'}"
                ]
            if self.choices is not None:
                parts.append("each one of " + ", ".join(_show(c) for c in self.choices))
            elif self.lo is not None or self.hi is not None:
                parts.append("each " + self._bounds())
            if self.nonempty:
                parts.append("not empty")
            if self.unique:
                parts.append("no repeats")
            return ", ".join(parts)
        bounds = self._bounds()
        if self.kind == "str" and self.nonempty:
            return "a non-empty string"
        return f"{noun} {bounds}".strip()

    def _bounds(self) -> str:
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            left = "(" if self.lo_open else "["
            right = ")" if self.hi_open else "]"
            return f"in {left}{_num(lo)}, {_num(hi)}{right}"
        if lo is not None:
            return f"{'>' if self.lo_open else '>='} {_num(lo)}"
        if hi is not None:
            return f"{'<' if self.hi_open else '<='} {_num(hi)}"
        return ""

    def _in_bounds(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        return True

    def convert(self, key: str, value: Any) -> Any:
        """The value as stored in the dataclass, or _Invalid."""
        bad = _Invalid(key, self.expectation(), value)
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad
            return value
        if self.kind == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad
            if self.choices is not None and value not in self.choices:
                raise bad
            if not self._in_bounds(value):
                raise bad
            return int(value)
        if self.kind == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad
            value = float(value)
            if not math.isfinite(value) or not self._in_bounds(value):
                raise bad
            return value
        if self.kind == "str":
            if not isinstance(value, str):
                raise bad
            if self.upper:
                value = value.upper()
            if self.choices is not None and value not in self.choices:
                raise bad
            if self.nonempty and not value.strip():
                raise bad
            return value
        if not isinstance(value, list):
            raise bad
        if self.lengths is not None and len(value) not in self.lengths:
            raise bad
        if self.nonempty and not value:
            raise bad
        out: List[Any] = []
        for item in value:
            if self.kind == "floats":
                if isinstance(item, bool) or not isinstance(item, (int, float)):
                    raise bad
                item = float(item)
                if not math.isfinite(item) or not self._in_bounds(item):
                    raise bad
            else:
                if not isinstance(item, str):
                    raise bad
                if self.upper:
                    item = item.upper()
                if self.choices is not None and item not in self.choices:
                    raise bad
            out.append(item)
        if self.unique and len(set(out)) != len(out):
            raise bad
        return tuple(out)


_SHOW_DEPTH = 4


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))


def _show(value: Any, _depth: int = 0) -> str:
    """A value as it would be written in TOML (for error messages); deep lists end in "[...]"."""
    if value is MISSING:
        return "nothing"
    if isinstance(value, (list, tuple)):
        if _depth >= _SHOW_DEPTH:  # hundreds of levels would exhaust the stack, and say nothing
            return "[...]"
        return "[" + ", ".join(_show(v, _depth + 1) for v in value) + "]"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return str(value)


def _key(default: Any, rule: Rule, doc: str, *, default_from: Optional[str] = None) -> Any:
    """A dataclass field with its rule and its meaning (the config reference's text).

    ``default_from``: when the key is absent but that key of the same table is given, take
    its value (a marker's height is its width unless told otherwise). Mutable defaults
    (lists) are stored as tuples.
    """
    if isinstance(default, list):
        default = tuple(default)
    if default_from is not None:
        doc = f"{doc} (default: {default_from})"
    return field(default=default, metadata={"rule": rule, "doc": doc, "default_from": default_from})


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class CameraConfig:
    """The frame source and its intrinsics (pixels at the capture resolution)."""

    source: str = _key("synthetic", Rule("str", nonempty=True), "frame source: " + SOURCE_FORMS)
    width: int = _key(640, Rule("int", lo=16, hi=8192), "capture width, pixels")
    height: int = _key(480, Rule("int", lo=16, hi=8192), "capture height, pixels")
    fx: float = _key(500.0, Rule("float", lo=0, lo_open=True), "focal length x, pixels")
    fy: float = _key(500.0, Rule("float", lo=0, lo_open=True), "focal length y, pixels")
    cx: float = _key(319.5, Rule("float"), "principal point x, pixels (0 = centre of the left pixel)")
    cy: float = _key(239.5, Rule("float"), "principal point y, pixels")
    dist: Tuple[float, ...] = _key([0.0] * 5, Rule("floats", lengths=(4, 5, 8)), "distortion k1 k2 p1 p2 k3 (OpenCV)")
    fps: float = _key(30.0, Rule("float", lo=0, hi=1000, lo_open=True), "frames per second asked of the camera")
    exposure_us: int = _key(0, Rule("int", lo=0, hi=10_000_000), "exposure time, microseconds (0 = auto)")
    analogue_gain: float = _key(0.0, Rule("float", lo=0, hi=64), "sensor analogue gain (0 = auto)")

    def check(self) -> None:
        try:
            parse_source(self.source)
        except ValueError as exc:
            raise _Invalid("source", str(exc), self.source) from None
        if not 0.0 <= self.cx < self.width:
            raise _Invalid("cx", f"a number in [0, {self.width}) (inside the image width)", self.cx)
        if not 0.0 <= self.cy < self.height:
            raise _Invalid("cy", f"a number in [0, {self.height}) (inside the image height)", self.cy)

    @property
    def source_kind(self) -> str:
        """One of capture.SOURCE_KINDS (from ``capture.parse_source``)."""
        return parse_source(self.source)[0]

    @property
    def source_arg(self) -> str:
        """The source's argument (from ``capture.parse_source``): index, device, path or pipeline."""
        return parse_source(self.source)[1]

    def model(self) -> Camera:
        return Camera(
            fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, dist=tuple(self.dist), width=self.width, height=self.height
        )


@dataclass(frozen=True)
class MarkerConfig:
    """The rectangle looked for (metres) and where it is placed."""

    type: str = _key("square", Rule("str", choices=MARKER_TYPES), "square or aruco")
    width: float = _key(0.20, Rule("float", lo=0, hi=100, lo_open=True), "outer edge of the dark region, metres")
    height: float = _key(0.20, Rule("float", lo=0, hi=100, lo_open=True), "metres", default_from="width")
    dictionary: Optional[str] = _key(
        None, Rule("str", nonempty=True), "aruco only: OpenCV dictionary, e.g. DICT_4X4_50"
    )
    id: Optional[int] = _key(None, Rule("int", lo=0, hi=100_000), "aruco only: marker id")
    placement: str = _key("wall", Rule("str", choices=MARKER_PLACEMENTS), "wall (vertical) or floor (face up)")

    def check(self) -> None:
        if self.type == "aruco":
            if self.dictionary is None:
                raise _Invalid("dictionary", 'a dictionary name such as "DICT_4X4_50" (needed when type = "aruco")')
            if self.id is None:
                raise _Invalid("id", 'an integer >= 0 (needed when type = "aruco")')
            # Whether OpenCV has the dictionary and the id: check_whole.
        else:
            if self.dictionary is not None:
                raise _Invalid("dictionary", 'no dictionary unless type = "aruco"', self.dictionary)
            if self.id is not None:
                raise _Invalid("id", 'no id unless type = "aruco"', self.id)

    def model(self) -> Marker:
        return Marker(width=self.width, height=self.height, type=self.type, dictionary=self.dictionary, id=self.id)


@dataclass(frozen=True)
class EstimatorConfig:
    method: str = _key("iterative", Rule("str", choices=METHODS), "pose method (see Pose estimation)")
    iterations: int = _key(5, Rule("int", lo=1, hi=100), "iterations of the correction loop")
    refine: bool = _key(True, Rule("bool"), "final least-squares refinement")


@dataclass(frozen=True)
class DetectorConfig:
    max_misses: int = _key(5, Rule("int", lo=0, hi=10_000), "frames a track survives without the marker")
    min_side_px: float = _key(10.0, Rule("float", lo=1, hi=10_000), "shortest accepted marker side, pixels")
    gamma: float = _key(
        1.0,
        Rule("float", lo=0.2, hi=5),
        "camera response exponent: edges located in linear light (1.0 linear, about 2.2 for sRGB/Rec. 709 cameras)",
    )
    search_budget_ms: float = _key(
        0.0,
        Rule("float", lo=0, hi=10_000),
        "time cap of a whole-frame search per frame, ms; the rest goes on next frame (0 = no cap)",
    )
    blur_model: bool = _key(
        True,
        Rule("bool"),
        "type aruco: a blurred marker's corners from a model of its whole pattern (false: edge fits only, faster)",
    )


@dataclass(frozen=True)
class SyntheticConfig:
    trajectory: str = _key(
        "wall",
        Rule("str", choices=MARKER_PLACEMENTS),
        "wall: camera in front of a wall marker; floor: over a floor marker",
    )
    seed: int = _key(0, Rule("int", lo=0, hi=2**32 - 1), "random seed of noise and trajectory")
    blur_px: float = _key(0.8, Rule("float", lo=0, hi=20), "Gaussian blur sigma, pixels")
    noise_gray: float = _key(2.0, Rule("float", lo=0, hi=100), "sensor noise sigma, gray levels")
    motion_blur_px: float = _key(0.0, Rule("float", lo=0, hi=100), "motion blur length, pixels")
    jpeg_quality: int = _key(0, Rule("int", lo=0, hi=100), "JPEG round trip quality (0 = none)")
    frames: int = _key(0, Rule("int", lo=0, hi=10**9), "frames before end of stream (0 = endless)")
    attitude: bool = _key(True, Rule("bool"), "frames carry the vehicle's true attitude (plus the noise and lag below)")
    attitude_noise_deg: float = _key(0.5, Rule("float", lo=0, hi=30), "attitude noise sigma per axis, degrees")
    attitude_lag_s: float = _key(0.0, Rule("float", lo=0, hi=1), "attitude lags the frame by this much, seconds")


@dataclass(frozen=True)
class PipelineConfig:
    latency_budget_s: float = _key(
        0.1,
        Rule("float", lo=0, hi=10, lo_open=True),
        "a pose that would leave later than this after capture is dropped",
    )
    status_interval_s: float = _key(10.0, Rule("float", lo=0.1, hi=86400), "seconds between status lines")
    output_buffer: int = _key(4, Rule("int", lo=1, hi=1000), "results buffered per output before dropping the oldest")
    source_retry_s: float = _key(0.5, Rule("float", lo=0.01, hi=60), "first pause before reopening a failed source")
    source_retry_max_s: float = _key(5.0, Rule("float", lo=0.01, hi=600), "longest pause (the pause doubles)")

    def check(self) -> None:
        if self.source_retry_max_s < self.source_retry_s:
            raise _Invalid(
                "source_retry_max_s",
                f"a number >= source_retry_s ({_num(self.source_retry_s)})",
                self.source_retry_max_s,
            )


@dataclass(frozen=True)
class MountConfig:
    preset: str = _key(
        "forward",
        Rule("str", choices=MOUNT_PRESETS),
        "forward: camera looks ahead; down: looks down; custom: rotation_deg + offset_m",
    )
    rotation_deg: Tuple[float, ...] = _key(
        [0.0, 0.0, 0.0],
        Rule("floats", lengths=(3,), lo=-360, hi=360),
        "custom mount: roll, pitch, yaw of the camera on the body, degrees",
    )
    offset_m: Tuple[float, ...] = _key(
        [0.0, 0.0, 0.0],
        Rule("floats", lengths=(3,), lo=-100, hi=100),
        "camera position in the body frame (FRD), metres",
    )


@dataclass(frozen=True)
class AttitudeConfig:
    """The vehicle's attitude at capture time, for the choice of the planar solution."""

    source: str = _key(
        "mavlink",
        Rule("str", nonempty=True),
        '"mavlink": from the [output.mavlink] link (none without one), "none", or a pymavlink '
        "connection string of its own to listen on (udpin:0.0.0.0:14551, /dev/ttyACM0, tcp:HOST:PORT)",
    )
    baud: int = _key(921600, Rule("int", lo=300, hi=20_000_000), "a serial source of its own only")
    max_age_s: float = _key(
        0.5, Rule("float", lo=0, hi=10, lo_open=True), "no attitude message for this long = no attitude"
    )
    max_extrapolation_s: float = _key(
        0.05, Rule("float", lo=0, hi=1), "furthest past the newest attitude sample a capture time may be"
    )
    sigma_deg: float = _key(
        1.0,
        Rule("float", lo=0, hi=30),
        "stated accuracy of roll and pitch, degrees (the image's measurement of it is used where worse)",
    )
    max_error_deg: float = _key(
        15.0,
        Rule("float", lo=0, hi=90, lo_open=True),
        "a pose whose down is further from the attitude's (and 3 sigma) is inconsistent: not sent",
    )
    max_tilt_deg: float = _key(
        0.0,
        Rule("float", lo=0, hi=90, hi_open=True),
        "without attitude: the vehicle tilts at most this much (0 = no tilt prior)",
    )
    polish: bool = _key(
        True,
        Rule("bool"),
        "re-fit the pose with the attitude's roll and pitch (without attitude: level, max_tilt_deg "
        "as 3 sigma) as a weighted prior",
    )
    heading_window_s: float = _key(
        1.5,
        Rule("float", lo=0, hi=10),
        "without attitude, at a wall marker: choose and polish the heading by the last this many "
        "seconds of headings (0 = frame by frame)",
    )

    def check(self) -> None:
        s = self.source.strip()
        if s not in ("mavlink", "none") and not (":" in s or s.startswith("/")):
            raise _Invalid(
                "source",
                '"mavlink", "none" or a pymavlink connection string (udpin:HOST:PORT, /dev/ttyACM0, tcp:HOST:PORT)',
                self.source,
            )


@dataclass(frozen=True)
class GateConfig:
    """The quality gate: poses that fit their corners worse than corner noise explains are not sent."""

    max_rms_px: float = _key(1.0, Rule("float", lo=0, hi=100), "reprojection RMS bound, pixels (0 = no gate)")
    max_rms_frac: float = _key(
        0.01, Rule("float", lo=0, hi=1), "... raised to this fraction of the marker's side for large markers"
    )
    max_view_deg: float = _key(
        55.0, Rule("float", lo=0, hi=90), "a marker seen further off its face than this is not believed (0 = any angle)"
    )


@dataclass(frozen=True)
class MavlinkOutputConfig:
    connection: str = _key(
        "udpout:127.0.0.1:14550",
        Rule("str", nonempty=True),
        "pymavlink connection string: udpout:HOST:PORT, /dev/serial0, tcp:HOST:PORT",
    )
    baud: int = _key(921600, Rule("int", lo=300, hi=20_000_000), "serial links only")
    messages: Tuple[str, ...] = _key(
        ["ODOMETRY"],
        Rule("strs", choices=MAVLINK_MESSAGES, nonempty=True, unique=True, upper=True),
        "messages sent per pose",
    )
    source_system: int = _key(1, Rule("int", lo=1, hi=255), "MAVLink system id")
    source_component: int = _key(197, Rule("int", lo=1, hi=255), "MAVLink component id (197 = visual odometry)")
    wait_heartbeat: bool = _key(True, Rule("bool"), "send poses only once the autopilot's HEARTBEAT was heard")
    min_interval_s: float = _key(
        0.02, Rule("float", lo=0.02, hi=0.25), "shortest time between two messages of a type (EKF3 drops closer ones)"
    )
    lost_timeout_s: float = _key(
        0.3,
        Rule("float", lo=0.02, hi=10),
        "no pose for this long = marker lost (STATUSTEXT; reset_counter + 1 when found)",
    )
    jump_m: float = _key(
        0.5,
        Rule("float", lo=0, hi=100, lo_open=True),
        "a pose moving further between two messages is a jump (reset_counter + 1)",
    )
    jump_deg: float = _key(
        30.0,
        Rule("float", lo=0, hi=180, lo_open=True),
        "a pose turning further between two messages is a jump (reset_counter + 1)",
    )
    statustext: bool = _key(True, Rule("bool"), "STATUSTEXT on start, marker lost and marker found")
    origin: Optional[Tuple[float, ...]] = _key(
        None,
        Rule("floats", lengths=(3,)),
        "latitude deg, longitude deg, altitude m: SET_GPS_GLOBAL_ORIGIN sent to the autopilot (flying without GPS)",
    )
    set_home: bool = _key(False, Rule("bool"), "also MAV_CMD_DO_SET_HOME at the origin once it holds")
    autopilot: str = _key(
        "auto",
        Rule("str", choices=AUTOPILOTS),
        "auto (from its HEARTBEAT), ardupilot or px4: the messages' frames it takes",
    )
    signing_key: Optional[str] = _key(
        None, Rule("str", nonempty=True), "MAVLink 2 signing: 64 hex digits, or a passphrase (SHA-256, as MAVProxy)"
    )
    retry_s: float = _key(0.5, Rule("float", lo=0.01, hi=60), "first pause before reopening a failed link")
    retry_max_s: float = _key(5.0, Rule("float", lo=0.01, hi=600), "longest pause (the pause doubles)")

    def check(self) -> None:
        if self.origin is not None:
            lat, lon, alt = self.origin
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and -1000.0 <= alt <= 10000.0):
                raise _Invalid(
                    "origin",
                    "[latitude in [-90, 90], longitude in [-180, 180], altitude in [-1000, 10000] m]",
                    list(self.origin),
                )
        if self.set_home and self.origin is None:
            raise _Invalid("set_home", "false unless origin is set")
        if self.retry_max_s < self.retry_s:
            raise _Invalid("retry_max_s", f"a number >= retry_s ({_num(self.retry_s)})", self.retry_max_s)


@dataclass(frozen=True)
class SerialOutputConfig:
    port: str = _key("/dev/ttyUSB0", Rule("str", nonempty=True), "serial device (or a pyserial URL)")
    baud: int = _key(115200, Rule("int", lo=300, hi=20_000_000), "baud rate")
    min_interval_s: float = _key(0.0, Rule("float", lo=0, hi=60), "shortest time between two lines (0 = every frame)")
    send_lost: bool = _key(True, Rule("bool"), "a line with empty pose fields and quality -1 when no pose")
    retry_s: float = _key(0.5, Rule("float", lo=0.01, hi=60), "first pause before reopening a failed port")
    retry_max_s: float = _key(5.0, Rule("float", lo=0.01, hi=600), "longest pause (the pause doubles)")

    def check(self) -> None:
        if self.retry_max_s < self.retry_s:
            raise _Invalid("retry_max_s", f"a number >= retry_s ({_num(self.retry_s)})", self.retry_max_s)


@dataclass(frozen=True)
class JsonlOutputConfig:
    path: str = _key("-", Rule("str", nonempty=True), 'file to append to, or "-" for stdout')


@dataclass(frozen=True)
class OutputConfig:
    """Each output is None unless its table is present."""

    mavlink: Optional[MavlinkOutputConfig] = None
    serial: Optional[SerialOutputConfig] = None
    jsonl: Optional[JsonlOutputConfig] = None


@dataclass(frozen=True)
class LoggingConfig:
    level: str = _key("INFO", Rule("str", choices=("DEBUG", "INFO", "WARNING", "ERROR"), upper=True), "log level")


@dataclass(frozen=True)
class MapConfig:
    """Many markers in one map frame (interface.md "Marker maps"); exclusive with [marker]."""

    dictionary: Optional[str] = _key(
        None, Rule("str", nonempty=True), "OpenCV dictionary of every map marker (ArUco or AprilTag)"
    )
    placement: str = _key(
        "floor", Rule("str", choices=MARKER_PLACEMENTS), "how the map frame sits in the room, as [marker] placement"
    )
    file: Optional[str] = _key(
        None, Rule("str", nonempty=True), "a TOML file holding the [[markers]] (or [[map.markers]]) entries"
    )
    markers: Tuple[Any, ...] = ()  # MapMarker entries, from [[map.markers]] or the file

    def model(self) -> Any:
        """The MarkerMap (marker_map.MarkerMap)."""
        from .marker_map import MarkerMap

        return MarkerMap(str(self.dictionary), tuple(self.markers), self.placement)


@dataclass(frozen=True)
class PreviewConfig:
    """The live preview web page (pose_daemon.preview); None unless the table is present."""

    listen: str = _key(
        "127.0.0.1:8080",
        Rule("str", nonempty=True),
        "HOST:PORT the page is served on (port 0 = any free port); another host than 127.0.0.1 opens it to the network",
    )
    max_fps: float = _key(
        5.0, Rule("float", lo=0, hi=30, lo_open=True), "most annotated frames per second a viewer gets"
    )
    max_width: int = _key(640, Rule("int", lo=64, hi=4096), "annotated frames wider than this are scaled down, pixels")
    data_dir: str = _key(
        ".",
        Rule("str", nonempty=True),
        "folder for the page's snapshots and recordings (relative: to the working "
        "directory, /var/lib/pose-daemon under systemd)",
    )

    def check(self) -> None:
        host, port = self.address
        if not host or port is None:
            raise _Invalid("listen", '"HOST:PORT" with a port in [0, 65535], e.g. "127.0.0.1:8080"', self.listen)

    @property
    def address(self) -> Tuple[str, Optional[int]]:
        """(host, port) of ``listen`` ("[::1]:8080" -> ("::1", 8080)); port None if unusable."""
        host, _, port = self.listen.strip().rpartition(":")
        host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
        if not port.isdigit() or not 0 <= int(port) <= 65535:
            return host, None
        return host, int(port)


SECTIONS: Dict[str, type] = {
    "camera": CameraConfig,
    "marker": MarkerConfig,
    "estimator": EstimatorConfig,
    "detector": DetectorConfig,
    "synthetic": SyntheticConfig,
    "pipeline": PipelineConfig,
    "mount": MountConfig,
    "attitude": AttitudeConfig,
    "gate": GateConfig,
    "logging": LoggingConfig,
}
# Sections that are None unless present (enabled by their table, like the outputs).
OPTIONAL_SECTIONS: Dict[str, type] = {
    "preview": PreviewConfig,
}
OUTPUTS: Dict[str, type] = {
    "mavlink": MavlinkOutputConfig,
    "serial": SerialOutputConfig,
    "jsonl": JsonlOutputConfig,
}


@dataclass(frozen=True)
class Config:
    """The whole validated configuration; ``name`` is the file it came from (for messages)."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    marker: MarkerConfig = field(default_factory=MarkerConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    mount: MountConfig = field(default_factory=MountConfig)
    attitude: AttitudeConfig = field(default_factory=AttitudeConfig)
    gate: GateConfig = field(default_factory=GateConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    map: Optional[MapConfig] = None
    preview: Optional[PreviewConfig] = None
    name: str = "<default config>"

    @property
    def placement(self) -> str:
        """How the pose's frame (the [map], else the [marker]) sits in the room."""
        return self.map.placement if self.map is not None else self.marker.placement

    def target_marker(self) -> Marker:
        """The [marker], or for a [map] a square as large as its largest marker (the size
        LANDING_TARGET reports; the map's pose is that of its origin)."""
        if self.map is not None:
            size = max(m.size_m for m in self.map.markers)
            return Marker(width=size, height=size)
        return self.marker.model()

    @classmethod
    def default(cls) -> Config:
        """The embedded demo configuration (pose_daemon/data/demo.toml = config/demo.toml)."""
        return parse_config(default_config_text(), "<default config>")

    def to_dict(self) -> Dict[str, Any]:
        """Plain data in the TOML layout (absent outputs and unset optional keys left out)."""
        out: Dict[str, Any] = {}
        for name in SECTIONS:
            if name == "marker" and self.map is not None:
                continue  # exclusive with [map]
            out[name] = _plain(asdict(getattr(self, name)))
        for name in OPTIONAL_SECTIONS:
            if getattr(self, name) is not None:
                out[name] = _plain(asdict(getattr(self, name)))
        outputs = {k: _plain(asdict(v)) for k, v in asdict_shallow(self.output).items() if v is not None}
        out["output"] = outputs
        if self.map is not None:
            m: Dict[str, Any] = {"dictionary": self.map.dictionary, "placement": self.map.placement}
            m["markers"] = [
                {"id": k.id, "size": k.size_m, "position": list(k.position_m), "rotation_deg": list(k.rotation_deg)}
                for k in self.map.markers
            ]
            out["map"] = m
        return out

    def to_toml(self) -> str:
        """The effective configuration as TOML text (what check-config --print shows)."""
        lines: List[str] = []
        data = self.to_dict()
        for section, values in data.items():
            if section == "map" and self.map is not None:
                lines.extend(self.map.model().to_toml_lines())
                continue
            if section == "output":
                for name, sub in values.items():
                    lines.append(f"[output.{name}]")
                    lines.extend(f"{k} = {_show(v)}" for k, v in sub.items())
                    lines.append("")
                continue
            lines.append(f"[{section}]")
            lines.extend(f"{k} = {_show(v)}" for k, v in values.items())
            lines.append("")
        return "\n".join(lines)


def asdict_shallow(obj: Any) -> Dict[str, Any]:
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


def _plain(d: Dict[str, Any]) -> Dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if v is not None}


# --------------------------------------------------------------------------- parsing


def _build(cls: type, table: Dict[str, Any], where: str) -> Any:
    """One section's dataclass from its TOML table; _Invalid names the key (with ``where``)."""
    known = {f.name: f for f in fields(cls) if "rule" in f.metadata}
    kwargs: Dict[str, Any] = {}
    for key, value in table.items():
        f = known.get(key)
        if f is None:
            raise _Invalid(key, "one of " + ", ".join(known), _Unknown)
        kwargs[key] = f.metadata["rule"].convert(key, value)
    for f in known.values():
        source = f.metadata["default_from"]
        if source is not None and f.name not in kwargs and source in kwargs:
            kwargs[f.name] = kwargs[source]
    obj = cls(**kwargs)
    check = getattr(obj, "check", None)
    if check is not None:
        check()
    return obj


_Unknown = object()


def _message(name: str, where: str, err: _Invalid) -> str:
    if err.got is _Unknown:
        return f"{name}: {where} {err.key}: unknown key (expected {err.expected})"
    got = "" if err.got is MISSING else f", got {_show(err.got)}"
    return f"{name}: {where} {err.key}: expected {err.expected}{got}"


def parse_config(text: str, name: str = "<config>") -> Config:
    """Config from TOML text; ``name`` (the file name) starts every error message."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{name}: invalid TOML: {' '.join(str(exc).split())}") from None
    except RecursionError:  # the reader recurses once per level of nested arrays/inline tables
        raise ConfigError(f"{name}: invalid TOML: arrays or inline tables nested too deeply") from None
    return config_from_dict(data, name)


def config_from_dict(data: Dict[str, Any], name: str = "<config>") -> Config:
    """Config from an already-parsed TOML document (a dict of tables)."""
    sections: Dict[str, Any] = {}
    outputs: Dict[str, Any] = {}
    map_cfg = None
    if "map" in data:
        data = dict(data)
        map_cfg = _map_config(data.pop("map"), name)
        if "marker" in data:
            raise ConfigError(
                f"{name}: [map]: [map] and [marker] are exclusive (a map names its markers; remove one of the two)"
            )
    known_sections = {**SECTIONS, **OPTIONAL_SECTIONS}
    allowed = ", ".join(list(known_sections) + ["output", "map"])
    for section, table in data.items():
        if section not in known_sections and section != "output":
            raise ConfigError(f"{name}: [{section}]: unknown section (expected one of {allowed})")
        if not isinstance(table, dict):
            raise ConfigError(f"{name}: {section}: expected a table [{section}], got {_show(table)}")
        if section == "output":
            for out_name, out_table in table.items():
                if out_name not in OUTPUTS:
                    raise ConfigError(
                        f"{name}: [output.{out_name}]: unknown output (expected one of {', '.join(OUTPUTS)})"
                    )
                if not isinstance(out_table, dict):
                    raise ConfigError(
                        f"{name}: [output] {out_name}: expected a table [output.{out_name}], got {_show(out_table)}"
                    )
                where = f"[output.{out_name}]"
                try:
                    outputs[out_name] = _build(OUTPUTS[out_name], out_table, where)
                except _Invalid as err:
                    raise ConfigError(_message(name, where, err)) from None
            continue
        where = f"[{section}]"
        try:
            sections[section] = _build(known_sections[section], table, where)
        except _Invalid as err:
            raise ConfigError(_message(name, where, err)) from None
    synthetic_table = data.get("synthetic", {})
    marker = sections.get("marker", MarkerConfig())
    placement = map_cfg.placement if map_cfg is not None else marker.placement
    if "trajectory" not in synthetic_table and placement != SyntheticConfig().trajectory:
        # The synthetic camera moves over the marker as it is placed unless told otherwise.
        sections["synthetic"] = replace(sections.get("synthetic", SyntheticConfig()), trajectory=placement)
    cfg = Config(output=OutputConfig(**outputs), name=name, map=map_cfg, **sections)
    check_whole(cfg, files=False)
    return cfg


def check_whole(cfg: Config, *, files: bool = True) -> None:
    """Every rule that joins sections or concerns links and paths; ConfigError (one line) otherwise.

    - the synthetic source's [synthetic] trajectory is the [marker] placement;
    - an ArUco [marker] dictionary is one of OpenCV's, and its id one of the dictionary's;
    - the [output.mavlink] connection is a link ``outputs.mavlink.parse_connection`` accepts;
    - an [attitude] source of its own is a link ``parse_connection`` accepts, and not the
      [output.mavlink] connection (that one is ``source = "mavlink"``);
    - with ``files``: a ``video:``/``replay:`` source exists. A missing file will not appear
      later, so it is refused at start rather than reopened for ever like an unplugged camera.

    ``parse_config`` runs it with files=False, so every Config is whole wherever it is read
    (``replay PATH --config`` ignores the config's source). ``pose-daemon run`` and
    ``pose-daemon check-config`` run all of it, so check-config refuses what run refuses.
    """
    if cfg.camera.source_kind == "synthetic" and cfg.placement != cfg.synthetic.trajectory:
        where = "[map]" if cfg.map is not None else "[marker]"
        raise ConfigError(
            f"{cfg.name}: [synthetic] trajectory: expected {_show(cfg.placement)} "
            f"(the {where} placement), got {_show(cfg.synthetic.trajectory)}"
        )
    try:
        _check_aruco(cfg.marker)
    except _Invalid as err:
        raise ConfigError(_message(cfg.name, "[marker]", err)) from None
    m = cfg.output.mavlink
    if m is not None:
        try:
            parse_connection(m.connection, m.baud)
        except ValueError as exc:
            raise ConfigError(
                f"{cfg.name}: [output.mavlink] connection: expected {exc}, got {m.connection!r}"
            ) from None
    source = cfg.attitude.source.strip()
    if source not in ("mavlink", "none"):
        try:
            parse_connection(source, cfg.attitude.baud)
        except ValueError as exc:
            raise ConfigError(
                f'{cfg.name}: [attitude] source: expected "mavlink", "none" or {exc}, got {_show(cfg.attitude.source)}'
            ) from None
        if (
            m is not None
            and parse_connection(m.connection, m.baud)[:2] == parse_connection(source, cfg.attitude.baud)[:2]
        ):
            raise ConfigError(
                f'{cfg.name}: [attitude] source: expected "mavlink" for the [output.mavlink] link '
                f"itself, got its connection {_show(cfg.attitude.source)} again (it cannot be opened twice)"
            )
    kind, arg = parse_source(cfg.camera.source)
    if files and kind in ("video", "replay") and not Path(arg).exists():
        what = "a video file" if kind == "video" else "a recording, image folder or video"
        raise ConfigError(
            f"{cfg.name}: [camera] source: expected {what} that exists, "
            f"got {_show(cfg.camera.source)} (no such file or folder)"
        )


def _map_config(table: Any, name: str) -> MapConfig:
    """[map] (with [[map.markers]] or ``file``) -> MapConfig; ConfigError naming file, index and key."""
    from .marker_map import MapError, markers_from_tables

    if not isinstance(table, dict):
        raise ConfigError(f"{name}: map: expected a table [map], got {_show(table)}")
    table = dict(table)
    entries = table.pop("markers", None)
    try:
        cfg = _build(MapConfig, table, "[map]")
    except _Invalid as err:
        raise ConfigError(_message(name, "[map]", err)) from None
    source, where = name, "[map] "
    dictionary = cfg.dictionary
    if cfg.file is not None:
        if entries is not None:
            raise ConfigError(f"{name}: [map] file: expected either file or [[map.markers]] entries, not both")
        path = Path(cfg.file)
        if not path.is_absolute() and not name.startswith("<"):
            path = Path(name).parent / path
        try:
            mode = path.stat().st_mode
            if not stat.S_ISREG(mode):
                raise OSError("not a regular file")
            data = tomllib.loads(path.read_bytes().decode("utf-8"))
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(
                f"{name}: [map] file: cannot read {str(path)!r}: {getattr(exc, 'strerror', None) or exc}"
            ) from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML: {' '.join(str(exc).split())}") from None
        source, where = str(path), ""
        if "map" in data and isinstance(data["map"], dict):
            inner = dict(data["map"])
            entries = inner.pop("markers", None)
            file_dict = inner.get("dictionary")
            if isinstance(file_dict, str):
                if dictionary is not None and file_dict.upper() != dictionary.upper():
                    raise ConfigError(
                        f"{path}: [map] dictionary: expected {_show(dictionary)} "
                        f"(the dictionary of {name}), got {_show(file_dict)}"
                    )
                dictionary = file_dict
            where = "[map] "
        else:
            entries = data.get("markers")
    if dictionary is None:
        raise ConfigError(
            f"{name}: [map] dictionary: expected an OpenCV dictionary name such as "
            '"DICT_4X4_50" or "DICT_APRILTAG_36h11"'
        )
    n_ids = None
    try:
        from .detect import aruco_compat

        n_ids = aruco_compat.dictionary_size(aruco_compat.get_dictionary(dictionary))
    except ImportError:  # an OpenCV build without aruco: the detector reports it
        pass
    except ValueError:
        raise ConfigError(
            f"{name}: [map] dictionary: expected an OpenCV ArUco or AprilTag dictionary name "
            f'such as "DICT_4X4_50", got {_show(dictionary)}'
        ) from None
    if entries is None:
        raise ConfigError(
            f"{source}: {where}markers: expected [[{'map.' if where else ''}markers]] entries "
            "(id, size, position, rotation_deg), got none"
        )
    try:
        markers = markers_from_tables(entries, n_ids, dictionary)
    except MapError as err:
        got = f", got {_show(err.got)}" if err.has_got else ""
        if err.has_got is False and "unknown" in err.expected:
            raise ConfigError(
                f"{source}: {where}{err.where} {err.key}: unknown key "
                f"(expected {err.expected.replace(' (unknown key)', '')})"
            ) from None
        label = f"{err.where} {err.key}".strip()
        raise ConfigError(f"{source}: {where}{label}: expected {err.expected}{got}") from None
    return replace(cfg, dictionary=dictionary, markers=markers)


def _check_aruco(marker: MarkerConfig) -> None:
    """The dictionary is one this OpenCV has and the id is one of its ids (_Invalid otherwise)."""
    if marker.type != "aruco" or marker.dictionary is None or marker.id is None:
        return
    try:
        from .detect import aruco_compat
    except ImportError:  # an OpenCV build without aruco: the detector reports it
        return
    try:
        dictionary = aruco_compat.get_dictionary(marker.dictionary)
    except ValueError:
        raise _Invalid(
            "dictionary", 'an OpenCV ArUco dictionary name such as "DICT_4X4_50"', marker.dictionary
        ) from None
    n_ids = aruco_compat.dictionary_size(dictionary)
    if marker.id >= n_ids:
        raise _Invalid("id", f"an integer in [0, {n_ids - 1}] (the ids of {marker.dictionary})", marker.id)


_NOT_REGULAR = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def load_config(path: Union[str, Path]) -> Config:
    """Read and validate a TOML file; ConfigError (one line: file, key, expectation) otherwise."""
    p = Path(path)
    try:
        mode = p.stat().st_mode  # follows links; never opens the file
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        # A FIFO would block the read for ever, a device could be endless: refuse, unread.
        what = next((name for test, name in _NOT_REGULAR if test(mode)), "not a file")
        raise ConfigError(f"{p}: cannot read config: not a regular file ({what})")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: invalid TOML: not UTF-8 text (byte {exc.start})") from None
    return parse_config(text, str(p))


def load_config_or_default(path: Optional[Union[str, Path]]) -> Config:
    """``load_config(path)``, or the embedded default when no path is given."""
    return Config.default() if path is None else load_config(path)


def reference() -> List[Tuple[str, str, str, str, str]]:
    """(section, key, default, expectation, meaning) for every key: the README's config reference."""
    rows: List[Tuple[str, str, str, str, str]] = []
    tables: Sequence[Tuple[str, type]] = (
        list((f"[{k}]", v) for k, v in SECTIONS.items())
        + list((f"[{k}]", v) for k, v in OPTIONAL_SECTIONS.items())
        + list((f"[output.{k}]", v) for k, v in OUTPUTS.items())
    )
    for where, cls in tables:
        for f in fields(cls):
            if "rule" not in f.metadata:
                continue
            default = f.default if f.default is not MISSING else None
            rows.append(
                (
                    where,
                    f.name,
                    "-" if default is None else _show(default),
                    f.metadata["rule"].expectation(),
                    f.metadata["doc"],
                )
            )
    return rows
