"""The sections of the config file: one frozen dataclass per table, each key with its rule."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

from ..camera import MARKER_TYPES, Camera, Marker
from ..detect.response import MIN_BLACK_EXPONENT, check_shoulder
from ..geometry import MARKER_PLACEMENTS, MOUNT_PRESETS
from ..pose.loop import METHODS
from .forms import AUTOPILOTS, SOURCE_FORMS, parse_connection, parse_source
from .forms import MESSAGES as MAVLINK_MESSAGES
from .rules import Invalid, Rule, num, setting


@dataclass(frozen=True)
class CameraConfig:
    """The frame source and its intrinsics (pixels at the capture resolution)."""

    source: str = setting("synthetic", Rule("str", nonempty=True), "frame source: " + SOURCE_FORMS)
    width: int = setting(640, Rule("int", lo=16, hi=8192), "capture width, pixels")
    height: int = setting(480, Rule("int", lo=16, hi=8192), "capture height, pixels")
    fx: float = setting(500.0, Rule("float", lo=0, lo_open=True), "focal length x, pixels")
    fy: float = setting(500.0, Rule("float", lo=0, lo_open=True), "focal length y, pixels")
    cx: float = setting(319.5, Rule("float"), "principal point x, pixels (0 = centre of the left pixel)")
    cy: float = setting(239.5, Rule("float"), "principal point y, pixels")
    dist: Tuple[float, ...] = setting(
        [0.0] * 5, Rule("floats", lengths=(4, 5, 8)), "distortion k1 k2 p1 p2 k3 (OpenCV)"
    )
    fps: float = setting(30.0, Rule("float", lo=0, hi=1000, lo_open=True), "frames per second asked of the camera")
    exposure_us: int = setting(0, Rule("int", lo=0, hi=10_000_000), "exposure time, microseconds (0 = auto)")
    analogue_gain: float = setting(0.0, Rule("float", lo=0, hi=64), "sensor analogue gain (0 = auto)")

    def check(self) -> None:
        try:
            parse_source(self.source)
        except ValueError as exc:
            raise Invalid("source", str(exc), self.source) from None
        if not 0.0 <= self.cx < self.width:
            raise Invalid("cx", f"a number in [0, {self.width}) (inside the image width)", self.cx)
        if not 0.0 <= self.cy < self.height:
            raise Invalid("cy", f"a number in [0, {self.height}) (inside the image height)", self.cy)

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

    type: str = setting("square", Rule("str", choices=MARKER_TYPES), "square or aruco")
    width: float = setting(0.20, Rule("float", lo=0, hi=100, lo_open=True), "outer edge of the dark region, metres")
    height: float = setting(0.20, Rule("float", lo=0, hi=100, lo_open=True), "metres", default_from="width")
    dictionary: Optional[str] = setting(
        None, Rule("str", nonempty=True), "aruco only: OpenCV dictionary, e.g. DICT_4X4_50"
    )
    id: Optional[int] = setting(None, Rule("int", lo=0, hi=100_000), "aruco only: marker id")
    placement: str = setting("wall", Rule("str", choices=MARKER_PLACEMENTS), "wall (vertical) or floor (face up)")

    def check(self) -> None:
        if self.type == "aruco":
            if self.dictionary is None:
                raise Invalid("dictionary", 'a dictionary name such as "DICT_4X4_50" (needed when type = "aruco")')
            if self.id is None:
                raise Invalid("id", 'an integer >= 0 (needed when type = "aruco")')
            # Whether OpenCV has the dictionary and the id: check_whole.
        else:
            if self.dictionary is not None:
                raise Invalid("dictionary", 'no dictionary unless type = "aruco"', self.dictionary)
            if self.id is not None:
                raise Invalid("id", 'no id unless type = "aruco"', self.id)

    def model(self) -> Marker:
        return Marker(width=self.width, height=self.height, type=self.type, dictionary=self.dictionary, id=self.id)


@dataclass(frozen=True)
class EstimatorConfig:
    method: str = setting("iterative", Rule("str", choices=METHODS), "pose method (see Pose estimation)")
    iterations: int = setting(5, Rule("int", lo=1, hi=100), "iterations of the correction loop")
    refine: bool = setting(True, Rule("bool"), "final least-squares refinement")


@dataclass(frozen=True)
class DetectorConfig:
    max_misses: int = setting(5, Rule("int", lo=0, hi=10_000), "frames a track survives without the marker")
    min_side_px: float = setting(10.0, Rule("float", lo=1, hi=10_000), "shortest accepted marker side, pixels")
    gamma: float = setting(
        1.0,
        Rule("float", lo=0.2, hi=5),
        "camera response exponent: edges located in linear light (1.0 linear, about 2.2 for sRGB/Rec. 709 cameras)",
    )
    gamma_shoulder: float = setting(
        0.0,
        Rule("float", lo=0, hi=4),
        "rise of the response exponent from black to white, about gamma at mid grey (0 = a power law;"
        " `pose-daemon calibrate` measures both)",
    )
    search_budget_ms: float = setting(
        0.0,
        Rule("float", lo=0, hi=10_000),
        "time cap of a whole-frame search per frame, ms; the rest goes on next frame (0 = no cap)",
    )
    blur_model: bool = setting(
        True,
        Rule("bool"),
        "type aruco: a blurred marker's corners from a model of its whole pattern (false: edge fits only, faster)",
    )

    def check(self) -> None:
        try:
            check_shoulder(self.gamma_shoulder, self.gamma)
        except ValueError:
            limit = 2.0 * (self.gamma - MIN_BLACK_EXPONENT)
            expected = (
                f"a number below 2 * (gamma - {MIN_BLACK_EXPONENT:g}) ({limit:g}): the exponent at black stays positive"
            )
            raise Invalid("gamma_shoulder", expected, self.gamma_shoulder) from None


@dataclass(frozen=True)
class SyntheticConfig:
    trajectory: str = setting(
        "wall",
        Rule("str", choices=MARKER_PLACEMENTS),
        "wall: camera in front of a wall marker; floor: over a floor marker",
    )
    seed: int = setting(0, Rule("int", lo=0, hi=2**32 - 1), "random seed of noise and trajectory")
    blur_px: float = setting(0.8, Rule("float", lo=0, hi=20), "Gaussian blur sigma, pixels")
    noise_gray: float = setting(2.0, Rule("float", lo=0, hi=100), "sensor noise sigma, gray levels")
    motion_blur_px: float = setting(0.0, Rule("float", lo=0, hi=100), "motion blur length, pixels")
    jpeg_quality: int = setting(0, Rule("int", lo=0, hi=100), "JPEG round trip quality (0 = none)")
    frames: int = setting(0, Rule("int", lo=0, hi=10**9), "frames before end of stream (0 = endless)")
    attitude: bool = setting(
        True, Rule("bool"), "frames carry the vehicle's true attitude (plus the noise and lag below)"
    )
    attitude_noise_deg: float = setting(0.5, Rule("float", lo=0, hi=30), "attitude noise sigma per axis, degrees")
    attitude_lag_s: float = setting(0.0, Rule("float", lo=0, hi=1), "attitude lags the frame by this much, seconds")


@dataclass(frozen=True)
class PipelineConfig:
    latency_budget_s: float = setting(
        0.1,
        Rule("float", lo=0, hi=10, lo_open=True),
        "a pose that would leave later than this after capture is dropped",
    )
    status_interval_s: float = setting(10.0, Rule("float", lo=0.1, hi=86400), "seconds between status lines")
    output_buffer: int = setting(
        4, Rule("int", lo=1, hi=1000), "results buffered per output before dropping the oldest"
    )
    source_retry_s: float = setting(0.5, Rule("float", lo=0.01, hi=60), "first pause before reopening a failed source")
    source_retry_max_s: float = setting(5.0, Rule("float", lo=0.01, hi=600), "longest pause (the pause doubles)")

    def check(self) -> None:
        if self.source_retry_max_s < self.source_retry_s:
            raise Invalid(
                "source_retry_max_s",
                f"a number >= source_retry_s ({num(self.source_retry_s)})",
                self.source_retry_max_s,
            )


@dataclass(frozen=True)
class MountConfig:
    preset: str = setting(
        "forward",
        Rule("str", choices=MOUNT_PRESETS),
        "forward: camera looks ahead; down: looks down; custom: rotation_deg + offset_m",
    )
    rotation_deg: Tuple[float, ...] = setting(
        [0.0, 0.0, 0.0],
        Rule("floats", lengths=(3,), lo=-360, hi=360),
        "custom mount: roll, pitch, yaw of the camera on the body, degrees",
    )
    offset_m: Tuple[float, ...] = setting(
        [0.0, 0.0, 0.0],
        Rule("floats", lengths=(3,), lo=-100, hi=100),
        "camera position in the body frame (FRD), metres",
    )


@dataclass(frozen=True)
class AttitudeConfig:
    """The vehicle's attitude at capture time, for the choice of the planar solution."""

    source: str = setting(
        "mavlink",
        Rule("str", nonempty=True),
        '"mavlink": from the [output.mavlink] link (none without one), "none", or a pymavlink '
        "connection string of its own to listen on (udpin:0.0.0.0:14551, /dev/ttyACM0, tcp:HOST:PORT)",
    )
    baud: int = setting(921600, Rule("int", lo=300, hi=20_000_000), "a serial source of its own only")
    max_age_s: float = setting(
        0.5, Rule("float", lo=0, hi=10, lo_open=True), "no attitude message for this long = no attitude"
    )
    max_extrapolation_s: float = setting(
        0.05, Rule("float", lo=0, hi=1), "furthest past the newest attitude sample a capture time may be"
    )
    sigma_deg: float = setting(
        1.0,
        Rule("float", lo=0, hi=30),
        "stated accuracy of roll and pitch, degrees (the image's measurement of it is used where worse)",
    )
    max_error_deg: float = setting(
        15.0,
        Rule("float", lo=0, hi=90, lo_open=True),
        "a pose whose down is further from the attitude's (and 3 sigma) is inconsistent: not sent",
    )
    max_tilt_deg: float = setting(
        0.0,
        Rule("float", lo=0, hi=90, hi_open=True),
        "without attitude: the vehicle tilts at most this much (0 = no tilt prior)",
    )
    polish: bool = setting(
        True,
        Rule("bool"),
        "re-fit the pose with the attitude's roll and pitch (without attitude: level, max_tilt_deg "
        "as 3 sigma) as a weighted prior",
    )
    heading_window_s: float = setting(
        1.5,
        Rule("float", lo=0, hi=10),
        "without attitude, at a wall marker: choose and polish the heading by the last this many "
        "seconds of headings (0 = frame by frame)",
    )

    def check(self) -> None:
        s = self.source.strip()
        if s not in ("mavlink", "none") and not (":" in s or s.startswith("/")):
            raise Invalid(
                "source",
                '"mavlink", "none" or a pymavlink connection string (udpin:HOST:PORT, /dev/ttyACM0, tcp:HOST:PORT)',
                self.source,
            )


@dataclass(frozen=True)
class GateConfig:
    """The quality gate: poses that fit their corners worse than corner noise explains are not sent."""

    max_rms_px: float = setting(1.0, Rule("float", lo=0, hi=100), "reprojection RMS bound, pixels (0 = no gate)")
    max_rms_frac: float = setting(
        0.01, Rule("float", lo=0, hi=1), "... raised to this fraction of the marker's side for large markers"
    )
    max_view_deg: float = setting(
        55.0,
        Rule("float", lo=0, hi=90),
        "a plain square first seen further off its face than this is not believed (0 = any angle; "
        "a tracked square and an ArUco marker are not held to it)",
    )


@dataclass(frozen=True)
class MavlinkOutputConfig:
    connection: str = setting(
        "udpout:127.0.0.1:14550",
        Rule("str", nonempty=True),
        "pymavlink connection string: udpout:HOST:PORT, /dev/serial0, tcp:HOST:PORT",
    )
    baud: int = setting(921600, Rule("int", lo=300, hi=20_000_000), "serial links only")
    messages: Tuple[str, ...] = setting(
        ["ODOMETRY"],
        Rule("strs", choices=MAVLINK_MESSAGES, nonempty=True, unique=True, upper=True),
        "messages sent per pose",
    )
    source_system: int = setting(1, Rule("int", lo=1, hi=255), "MAVLink system id")
    source_component: int = setting(197, Rule("int", lo=1, hi=255), "MAVLink component id (197 = visual odometry)")
    wait_heartbeat: bool = setting(True, Rule("bool"), "send poses only once the autopilot's HEARTBEAT was heard")
    min_interval_s: float = setting(
        0.02, Rule("float", lo=0.02, hi=0.25), "shortest time between two messages of a type (EKF3 drops closer ones)"
    )
    lost_timeout_s: float = setting(
        0.3,
        Rule("float", lo=0.02, hi=10),
        "no pose for this long = marker lost (STATUSTEXT; reset_counter + 1 when found)",
    )
    jump_m: float = setting(
        0.5,
        Rule("float", lo=0, hi=100, lo_open=True),
        "a pose moving further between two messages is a jump (reset_counter + 1)",
    )
    jump_deg: float = setting(
        30.0,
        Rule("float", lo=0, hi=180, lo_open=True),
        "a pose turning further between two messages is a jump (reset_counter + 1)",
    )
    statustext: bool = setting(True, Rule("bool"), "STATUSTEXT on start, marker lost and marker found")
    origin: Optional[Tuple[float, ...]] = setting(
        None,
        Rule("floats", lengths=(3,)),
        "latitude deg, longitude deg, altitude m: SET_GPS_GLOBAL_ORIGIN sent to the autopilot (flying without GPS)",
    )
    set_home: bool = setting(False, Rule("bool"), "also MAV_CMD_DO_SET_HOME at the origin once it holds")
    autopilot: str = setting(
        "auto",
        Rule("str", choices=AUTOPILOTS),
        "auto (from its HEARTBEAT), ardupilot or px4: the messages' frames it takes",
    )
    signing_key: Optional[str] = setting(
        None, Rule("str", nonempty=True), "MAVLink 2 signing: 64 hex digits, or a passphrase (SHA-256, as MAVProxy)"
    )
    retry_s: float = setting(0.5, Rule("float", lo=0.01, hi=60), "first pause before reopening a failed link")
    retry_max_s: float = setting(5.0, Rule("float", lo=0.01, hi=600), "longest pause (the pause doubles)")

    def check(self) -> None:
        if self.origin is not None:
            lat, lon, alt = self.origin
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and -1000.0 <= alt <= 10000.0):
                raise Invalid(
                    "origin",
                    "[latitude in [-90, 90], longitude in [-180, 180], altitude in [-1000, 10000] m]",
                    list(self.origin),
                )
        if self.set_home and self.origin is None:
            raise Invalid("set_home", "false unless origin is set")
        if self.retry_max_s < self.retry_s:
            raise Invalid("retry_max_s", f"a number >= retry_s ({num(self.retry_s)})", self.retry_max_s)


@dataclass(frozen=True)
class SerialOutputConfig:
    port: str = setting("/dev/ttyUSB0", Rule("str", nonempty=True), "serial device (or a pyserial URL)")
    baud: int = setting(115200, Rule("int", lo=300, hi=20_000_000), "baud rate")
    min_interval_s: float = setting(
        0.0, Rule("float", lo=0, hi=60), "shortest time between two lines (0 = every frame)"
    )
    send_lost: bool = setting(True, Rule("bool"), "a line with empty pose fields and quality -1 when no pose")
    retry_s: float = setting(0.5, Rule("float", lo=0.01, hi=60), "first pause before reopening a failed port")
    retry_max_s: float = setting(5.0, Rule("float", lo=0.01, hi=600), "longest pause (the pause doubles)")

    def check(self) -> None:
        if self.retry_max_s < self.retry_s:
            raise Invalid("retry_max_s", f"a number >= retry_s ({num(self.retry_s)})", self.retry_max_s)


@dataclass(frozen=True)
class JsonlOutputConfig:
    path: str = setting("-", Rule("str", nonempty=True), 'file to append to, or "-" for stdout')


@dataclass(frozen=True)
class OutputConfig:
    """Each output is None unless its table is present."""

    mavlink: Optional[MavlinkOutputConfig] = None
    serial: Optional[SerialOutputConfig] = None
    jsonl: Optional[JsonlOutputConfig] = None


@dataclass(frozen=True)
class LoggingConfig:
    level: str = setting("INFO", Rule("str", choices=("DEBUG", "INFO", "WARNING", "ERROR"), upper=True), "log level")


@dataclass(frozen=True)
class MapConfig:
    """Many markers in one map frame (interface.md "Marker maps"); exclusive with [marker]."""

    dictionary: Optional[str] = setting(
        None, Rule("str", nonempty=True), "OpenCV dictionary of every map marker (ArUco or AprilTag)"
    )
    placement: str = setting(
        "floor", Rule("str", choices=MARKER_PLACEMENTS), "how the map frame sits in the room, as [marker] placement"
    )
    file: Optional[str] = setting(
        None,
        Rule("str", nonempty=True),
        "a TOML file holding the [[markers]] (or [[map.markers]]) entries, or a WPILib / PhotonVision "
        "AprilTag field layout (.json; dictionary then defaults to DICT_APRILTAG_36h11)",
    )
    size: Optional[float] = setting(
        None,
        Rule("float", lo=0, lo_open=True, hi=100.0),
        "metres, outer edge of the black border of every tag of a field layout `file` (required "
        "with one: the layout holds no tag size; FRC's tags are 0.1651)",
    )
    markers: Tuple[Any, ...] = ()  # MapMarker entries, from [[map.markers]] or the file

    def model(self) -> Any:
        """The MarkerMap (marker_map.MarkerMap)."""
        from ..marker_map import MarkerMap

        return MarkerMap(str(self.dictionary), tuple(self.markers), self.placement)


@dataclass(frozen=True)
class SitlConfig:
    """The simulated camera of ``[camera] source = "sitl"``: frames rendered from a simulator's truth."""

    connection: str = setting(
        "tcp:127.0.0.1:5763",
        Rule("str", nonempty=True),
        "MAVLink link to the simulator, its own (ArduPilot SITL: tcp:127.0.0.1:5763 = SERIAL2; "
        "PX4 SITL: udpin:0.0.0.0:14550, its GCS link)",
    )
    baud: int = setting(921600, Rule("int", lo=300, hi=20_000_000), "serial links only")
    source_system: int = setting(
        255, Rule("int", lo=1, hi=255), "our MAVLink system id on that link (ArduPilot drops its own 1/1)"
    )
    source_component: int = setting(190, Rule("int", lo=1, hi=255), "our MAVLink component id (190 = GCS)")
    lag_s: float = setting(
        0.0,
        Rule("float", lo=0, hi=1),
        "a slow camera: each frame shows the truth this much older than its capture time, seconds",
    )
    marker_below_m: float = setting(
        0.4,
        Rule("float", lo=0, hi=10),
        "the marker (map, pad) origin lies this far below the vehicle where it stood when the "
        "source started: the camera's height over the pad on the ground, metres (the default "
        "camera sees the default 0.2 m marker whole from 0.4 m at any heading, not from 0.1)",
    )
    truth_timeout_s: float = setting(
        2.0, Rule("float", lo=0.1, hi=60), "no truth message for this long = the source failed (reopened)"
    )

    def check(self) -> None:
        try:
            parse_connection(self.connection, self.baud)
        except ValueError as exc:
            raise Invalid("connection", str(exc), self.connection) from None


@dataclass(frozen=True)
class PreviewConfig:
    """The live preview web page (pose_daemon.preview); None unless the table is present."""

    listen: str = setting(
        "127.0.0.1:8080",
        Rule("str", nonempty=True),
        "HOST:PORT the page is served on (port 0 = any free port); another host than 127.0.0.1 opens it to the network",
    )
    max_fps: float = setting(
        5.0, Rule("float", lo=0, hi=30, lo_open=True), "most annotated frames per second a viewer gets"
    )
    max_width: int = setting(
        640, Rule("int", lo=64, hi=4096), "annotated frames wider than this are scaled down, pixels"
    )
    data_dir: str = setting(
        ".",
        Rule("str", nonempty=True),
        "folder for the page's snapshots and recordings (relative: to the working "
        "directory, /var/lib/pose-daemon under systemd)",
    )

    def check(self) -> None:
        host, port = self.address
        if not host or port is None:
            raise Invalid("listen", '"HOST:PORT" with a port in [0, 65535], e.g. "127.0.0.1:8080"', self.listen)

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
    "sitl": SitlConfig,
}
OUTPUTS: Dict[str, type] = {
    "mavlink": MavlinkOutputConfig,
    "serial": SerialOutputConfig,
    "jsonl": JsonlOutputConfig,
}
