"""The whole config: ``Config``, read from TOML and validated (each section, then the rules that
join sections, links and paths); every mistake is one ConfigError line naming file and key."""

from __future__ import annotations

import stat
import sys
from dataclasses import asdict, dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.9/3.10 (Raspberry Pi OS Bullseye)
    import tomli as tomllib

from ..camera import Marker
from ..errors import ConfigError
from .forms import parse_connection, parse_source
from .mapsection import check_aruco, map_config
from .rules import Invalid, build_section, message, show
from .sections import (
    OPTIONAL_SECTIONS,
    OUTPUTS,
    SECTIONS,
    AttitudeConfig,
    CameraConfig,
    DetectorConfig,
    EstimatorConfig,
    GateConfig,
    LoggingConfig,
    MapConfig,
    MarkerConfig,
    MountConfig,
    OutputConfig,
    PipelineConfig,
    PreviewConfig,
    SitlConfig,
    SyntheticConfig,
)

#: The embedded default, shipped as package data (pose_daemon/data/demo.toml, in the wheel
#: too) so that `pose-daemon run` without --config works anywhere. config/demo.toml in the
#: repository is a symbolic link to it: one file, nothing to keep equal.
DEFAULT_CONFIG_FILE = "demo.toml"

#: Sources whose frames are rendered: nothing but the marker is in view.
RENDERED = ("synthetic",)
#: Said at start (log, check-config, the preview) while a camera looks for a plain square.
SQUARE_WARNING = (
    '[marker] type = "square": any dark square in view passes (floor tiles, windows, a chessboard) '
    'and its pose is sent; type = "aruco" passes only its id (docs/markers.md)'
)


def default_config_text() -> str:
    """The TOML text of the embedded default configuration (the demo: synthetic source)."""
    data = resources.files("pose_daemon").joinpath("data")
    return data.joinpath(DEFAULT_CONFIG_FILE).read_text(encoding="utf-8")


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
    sitl: Optional[SitlConfig] = None
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

    def start_warnings(self) -> List[str]:
        """Choices in this config a user should hear about at every start (one line each)."""
        out = []
        # A rendered scene holds only the marker; a camera's may hold any dark square.
        if self.map is None and self.marker.type == "square" and parse_source(self.camera.source)[0] not in RENDERED:
            out.append(SQUARE_WARNING)
        return out

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
            out[name] = plain(asdict(getattr(self, name)))
        for name in OPTIONAL_SECTIONS:
            if getattr(self, name) is not None:
                out[name] = plain(asdict(getattr(self, name)))
        outputs = {k: plain(asdict(v)) for k, v in asdict_shallow(self.output).items() if v is not None}
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
                    lines.extend(f"{k} = {show(v)}" for k, v in sub.items())
                    lines.append("")
                continue
            lines.append(f"[{section}]")
            lines.extend(f"{k} = {show(v)}" for k, v in values.items())
            lines.append("")
        return "\n".join(lines)


def asdict_shallow(obj: Any) -> Dict[str, Any]:
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


def plain(d: Dict[str, Any]) -> Dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if v is not None}


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
        map_cfg = map_config(data.pop("map"), name)
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
            raise ConfigError(f"{name}: {section}: expected a table [{section}], got {show(table)}")
        if section == "output":
            for out_name, out_table in table.items():
                if out_name not in OUTPUTS:
                    raise ConfigError(
                        f"{name}: [output.{out_name}]: unknown output (expected one of {', '.join(OUTPUTS)})"
                    )
                if not isinstance(out_table, dict):
                    raise ConfigError(
                        f"{name}: [output] {out_name}: expected a table [output.{out_name}], got {show(out_table)}"
                    )
                where = f"[output.{out_name}]"
                try:
                    outputs[out_name] = build_section(OUTPUTS[out_name], out_table, where)
                except Invalid as err:
                    raise ConfigError(message(name, where, err)) from None
            continue
        where = f"[{section}]"
        try:
            sections[section] = build_section(known_sections[section], table, where)
        except Invalid as err:
            raise ConfigError(message(name, where, err)) from None
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
    - the ``sitl`` source's marker or map lies on the floor (under the simulated vehicle);
    - with ``files``: a ``video:``/``replay:`` source exists. A missing file will not appear
      later, so it is refused at start rather than reopened for ever like an unplugged camera.

    ``parse_config`` runs it with files=False, so every Config is whole wherever it is read
    (``replay PATH --config`` ignores the config's source). ``pose-daemon run`` and
    ``pose-daemon check-config`` run all of it, so check-config refuses what run refuses.
    """
    if cfg.camera.source_kind == "synthetic" and cfg.placement != cfg.synthetic.trajectory:
        where = "[map]" if cfg.map is not None else "[marker]"
        raise ConfigError(
            f"{cfg.name}: [synthetic] trajectory: expected {show(cfg.placement)} "
            f"(the {where} placement), got {show(cfg.synthetic.trajectory)}"
        )
    try:
        check_aruco(cfg.marker)
    except Invalid as err:
        raise ConfigError(message(cfg.name, "[marker]", err)) from None
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
                f'{cfg.name}: [attitude] source: expected "mavlink", "none" or {exc}, got {show(cfg.attitude.source)}'
            ) from None
        if (
            m is not None
            and parse_connection(m.connection, m.baud)[:2] == parse_connection(source, cfg.attitude.baud)[:2]
        ):
            raise ConfigError(
                f'{cfg.name}: [attitude] source: expected "mavlink" for the [output.mavlink] link '
                f"itself, got its connection {show(cfg.attitude.source)} again (it cannot be opened twice)"
            )
    kind, arg = parse_source(cfg.camera.source)
    if kind == "sitl" and cfg.placement != "floor":
        where = "[map]" if cfg.map is not None else "[marker]"
        raise ConfigError(
            f'{cfg.name}: {where} placement: expected "floor" for [camera] source = "sitl" (the simulated '
            f"vehicle starts over its marker), got {show(cfg.placement)}"
        )
    if files and kind in ("video", "replay") and not Path(arg).exists():
        what = "a video file" if kind == "video" else "a recording, image folder or video"
        raise ConfigError(
            f"{cfg.name}: [camera] source: expected {what} that exists, "
            f"got {show(cfg.camera.source)} (no such file or folder)"
        )


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
