"""The config reference, docs/config.md: every key of every table, written from the schema itself.

``reference()`` lists the keys; ``page()`` is the whole Markdown page, regenerated with
``.venv/bin/python scripts/make_config_page.py`` (tests/test_docs.py fails when the page and the schema
differ). The prose around the tables lives here, beside the tables it introduces.
"""

from __future__ import annotations

from dataclasses import MISSING, fields
from typing import Dict, List, Sequence, Tuple

from ..marker_map import MARKER_KEYS
from .rules import show
from .sections import OPTIONAL_SECTIONS, OUTPUTS, SECTIONS, MapConfig

# The command that rewrites docs/config.md (said by the page and by the test that keeps it).
REGENERATE = ".venv/bin/python scripts/make_config_page.py"

# Per table: what it is for, and the page that explains it (relative to docs/).
_ABOUT: Dict[str, Tuple[str, str]] = {
    "[camera]": ("The frame source and its intrinsics (pixels at the capture resolution).", "calibration.md"),
    "[marker]": ("The rectangle looked for (metres) and where it is placed.", "markers.md"),
    "[estimator]": ("The pose method.", "design/estimator.md"),
    "[detector]": ("The corner detector.", "design/detector.md"),
    "[synthetic]": (
        'The rendered frames of `source = "synthetic"` (the demo).',
        "recording-replay.md#frame-sources-camera-source",
    ),
    "[pipeline]": ("Latency budget, status lines, output queues, reopening a failed source.", "outputs.md"),
    "[mount]": ("How the camera sits on the vehicle.", "outputs.md#the-pose-that-is-sent-frames-and-mounting"),
    "[attitude]": (
        "The vehicle's attitude at capture time, for the choice of the planar solution.",
        "outputs.md#the-autopilots-attitude-attitude",
    ),
    "[gate]": (
        "The quality gate: poses that fit their corners worse than corner noise explains are not sent.",
        "design/planar-solution.md",
    ),
    "[logging]": ("The log level of the lines on stderr (the journal under systemd).", "troubleshooting.md"),
    "[map]": (
        "Many markers in one map frame; exclusive with `[marker]`.",
        "markers.md#marker-maps-many-markers-one-pose",
    ),
    "[preview]": ("The live preview web page; off unless the table is present.", "outputs.md#live-preview-preview"),
    "[sitl]": (
        'The simulated camera of `source = "sitl"` (its defaults apply without the table): frames '
        "rendered from a simulator's true vehicle pose, the marker, map or pad lying under where "
        "the vehicle stood when the source started, its top edge to the north.",
        "simulation.md",
    ),
    "[output.mavlink]": (
        "MAVLink to ArduPilot or PX4; on when the table is present.",
        "outputs.md#mavlink-outputmavlink",
    ),
    "[output.serial]": (
        "One `$POSE` line per frame to a microcontroller; on when the table is present.",
        "outputs.md#plain-serial-outputserial",
    ),
    "[output.jsonl]": ("Per-frame JSON lines; on when the table is present.", "outputs.md#json-lines-outputjsonl"),
}

_INTRO = f"""\
# Config reference

Every key of the config file, its default and what it accepts. This page is generated from the
config schema (`pose_daemon/config/sections.py`): do not edit it by hand, regenerate it with
`{REGENERATE}`. Back to the [README](../README.md).

`pose-daemon check-config FILE` checks a file as `run` does at start, down to the MAVLink
connection string and whether a `video:`/`replay:` source exists; an unknown key, a wrong type
or a value out of range stops the daemon with one line naming the file, the key and what was
expected, exit 2, e.g. `daemon.toml: [camera] fx: expected a number > 0, got "abc"`
(`--print` shows every key with its value). It then checks the hardware the file names on
this machine, one `OK`/`PROBLEM` line each (the camera source, each serial device, the user's
group), exit 1 if any fails; `--syntax-only` checks the file alone (exit 0 or 2, for CI).
Missing keys take the default; `[output.*]` tables and `[preview]` are enabled by being present.
`[camera] cx`/`cy` must lie inside the image;
`[marker] dictionary`/`id` are required for `type = "aruco"` and refused otherwise, and `id` must
be one of the dictionary's ids; `[estimator] method` must be "iterative" or "paper";
`[synthetic] trajectory` follows `[marker] placement` unless set. `[map]` and `[marker]` are
exclusive. A `-` default means the key is unset unless given.

The config the installer puts in `/etc/pose-daemon/pose-daemon.toml` is `config/pose-daemon.toml`
(the Pi's); `pose-daemon run` without `--config` runs the demo config, `config/demo.toml`.
"""

_MAP_MARKERS = f"""\
Each `[[map.markers]]` entry (or `[[markers]]` in a map `file`) has the keys
{", ".join(f"`{k}`" for k in MARKER_KEYS)}: `id` (required, an id of the map's dictionary, each
used once), `size` (required, metres, outer edge of the black border, in (0, 100]),
`position` (the marker centre in the map frame, metres, default `[0.0, 0.0, 0.0]`) and
`rotation_deg` (roll, pitch, yaw of the marker frame in the map frame, Z-Y-X, degrees, default
`[0.0, 0.0, 0.0]`).
"""


def _tables() -> Sequence[Tuple[str, type]]:
    return (
        [(f"[{k}]", v) for k, v in SECTIONS.items()]
        + [("[map]", MapConfig)]
        + [(f"[{k}]", v) for k, v in OPTIONAL_SECTIONS.items()]
        + [(f"[output.{k}]", v) for k, v in OUTPUTS.items()]
    )


def reference() -> List[Tuple[str, str, str, str, str]]:
    """(section, key, default, expectation, meaning) for every key of every table, in page order."""
    rows: List[Tuple[str, str, str, str, str]] = []
    for where, cls in _tables():
        for f in fields(cls):
            if "rule" not in f.metadata:
                continue
            default = f.default if f.default is not MISSING else None
            rows.append(
                (
                    where,
                    f.name,
                    "-" if default is None else show(default),
                    f.metadata["rule"].expectation(),
                    f.metadata["doc"],
                )
            )
    return rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def page() -> str:
    """docs/config.md: the intro, then one table per config table (key, default, accepts, meaning)."""
    parts = [_INTRO]
    by_table: Dict[str, List[Tuple[str, str, str, str, str]]] = {}
    for row in reference():
        by_table.setdefault(row[0], []).append(row)
    for where, rows in by_table.items():
        about, link = _ABOUT.get(where, ("", ""))
        parts.append(f"\n## `{where}`\n\n")
        if about:
            parts.append(about + (f" See [{link.split('#')[0]}]({link})." if link else "") + "\n\n")
        parts.append("| key | default | accepts | meaning |\n|---|---|---|---|\n")
        for _where, key, default, expectation, meaning in rows:
            parts.append(f"| `{key}` | `{_cell(default)}` | {_cell(expectation)} | {_cell(meaning)} |\n")
        if where == "[map]":
            parts.append("\n" + _MAP_MARKERS)
    return "".join(parts)
