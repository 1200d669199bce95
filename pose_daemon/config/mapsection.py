"""The [map] table: [[map.markers]] entries or a map file, checked against the dictionary; and the
ArUco [marker]'s dictionary and id."""

from __future__ import annotations

import stat
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.9/3.10 (Raspberry Pi OS Bullseye)
    import tomli as tomllib

from ..errors import ConfigError
from .rules import Invalid, build_section, message, show
from .sections import MapConfig, MarkerConfig


def map_config(table: Any, name: str) -> MapConfig:
    """[map] (with [[map.markers]] or ``file``) -> MapConfig; ConfigError naming file, index and key."""
    from ..marker_map import MapError, markers_from_tables

    if not isinstance(table, dict):
        raise ConfigError(f"{name}: map: expected a table [map], got {show(table)}")
    table = dict(table)
    entries = table.pop("markers", None)
    try:
        cfg = build_section(MapConfig, table, "[map]")
    except Invalid as err:
        raise ConfigError(message(name, "[map]", err)) from None
    source, where = name, "[map] "
    dictionary = cfg.dictionary
    if cfg.file is not None:
        if entries is not None:
            raise ConfigError(f"{name}: [map] file: expected either file or [[map.markers]] entries, not both")
        path = Path(cfg.file)
        if not path.is_absolute() and not name.startswith("<"):
            path = Path(name).parent / path
        if path.suffix.lower() == ".json":
            return _layout_config(cfg, path, name)
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
                        f"{path}: [map] dictionary: expected {show(dictionary)} "
                        f"(the dictionary of {name}), got {show(file_dict)}"
                    )
                dictionary = file_dict
            where = "[map] "
        else:
            entries = data.get("markers")
    if cfg.size is not None:
        raise ConfigError(
            f"{name}: [map] size: only with a field layout file (.json); a map's markers each give their size"
        )
    if dictionary is None:
        raise ConfigError(
            f"{name}: [map] dictionary: expected an OpenCV dictionary name such as "
            '"DICT_4X4_50" or "DICT_APRILTAG_36h11"'
        )
    n_ids = None
    try:
        from ..detect import aruco_compat

        n_ids = aruco_compat.dictionary_size(aruco_compat.get_dictionary(dictionary))
    except ImportError:  # an OpenCV build without aruco: the detector reports it
        pass
    except ValueError:
        raise ConfigError(
            f"{name}: [map] dictionary: expected an OpenCV ArUco or AprilTag dictionary name "
            f'such as "DICT_4X4_50", got {show(dictionary)}'
        ) from None
    if entries is None:
        raise ConfigError(
            f"{source}: {where}markers: expected [[{'map.' if where else ''}markers]] entries "
            "(id, size, position, rotation_deg), got none"
        )
    try:
        markers = markers_from_tables(entries, n_ids, dictionary)
    except MapError as err:
        got = f", got {show(err.got)}" if err.has_got else ""
        if err.has_got is False and "unknown" in err.expected:
            raise ConfigError(
                f"{source}: {where}{err.where} {err.key}: unknown key "
                f"(expected {err.expected.replace(' (unknown key)', '')})"
            ) from None
        label = f"{err.where} {err.key}".strip()
        raise ConfigError(f"{source}: {where}{label}: expected {err.expected}{got}") from None
    return replace(cfg, dictionary=dictionary, markers=markers)


def _markers(entries: Any, dictionary: str, source: str, where: str) -> Any:
    """markers_from_tables with its MapError as one ConfigError line."""
    from ..marker_map import MapError, markers_from_tables

    n_ids = None
    try:
        from ..detect import aruco_compat

        n_ids = aruco_compat.dictionary_size(aruco_compat.get_dictionary(dictionary))
    except ImportError:  # an OpenCV build without aruco: the detector reports it
        pass
    except ValueError:
        raise ConfigError(
            f"{source}: [map] dictionary: expected an OpenCV ArUco or AprilTag dictionary name "
            f'such as "DICT_4X4_50", got {show(dictionary)}'
        ) from None
    try:
        return markers_from_tables(entries, n_ids, dictionary, prefix="tags")
    except MapError as err:
        got = f", got {show(err.got)}" if err.has_got else ""
        raise ConfigError(f"{source}: {where}{err.where} {err.key}: expected {err.expected}{got}") from None


def _layout_config(cfg: MapConfig, path: Path, name: str) -> MapConfig:
    """[map] file naming a WPILib / PhotonVision field layout JSON: its tags, [map] size each."""
    from ..map_layout import LAYOUT_DICTIONARY, LayoutError, layout_tables, read_layout_file

    if cfg.size is None:
        raise ConfigError(
            f"{name}: [map] size: expected the tags' size in metres (outer edge of the black border; "
            f"FRC's are 0.1651): the field layout {str(path)!r} holds none"
        )
    dictionary = cfg.dictionary if cfg.dictionary is not None else LAYOUT_DICTIONARY
    try:
        tables = layout_tables(read_layout_file(path), cfg.size, dictionary)
    except LayoutError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return replace(cfg, dictionary=dictionary, markers=_markers(tables, dictionary, str(path), ""))


def check_aruco(marker: MarkerConfig) -> None:
    """The dictionary is one this OpenCV has and the id is one of its ids (Invalid otherwise)."""
    if marker.type != "aruco" or marker.dictionary is None or marker.id is None:
        return
    try:
        from ..detect import aruco_compat
    except ImportError:  # an OpenCV build without aruco: the detector reports it
        return
    try:
        dictionary = aruco_compat.get_dictionary(marker.dictionary)
    except ValueError:
        raise Invalid(
            "dictionary", 'an OpenCV ArUco dictionary name such as "DICT_4X4_50"', marker.dictionary
        ) from None
    n_ids = aruco_compat.dictionary_size(dictionary)
    if marker.id >= n_ids:
        raise Invalid("id", f"an integer in [0, {n_ids - 1}] (the ids of {marker.dictionary})", marker.id)
