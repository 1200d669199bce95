"""The [camera] section calibration produces: its TOML text, and the same keys set in place in
an existing config file (its other lines and comments kept)."""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import Dict, Union

import numpy as np

from ...camera import Camera
from ...errors import ConfigError, UserError

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "dist")


def _fmt(value: float, digits: int) -> str:
    text = f"{value:.{digits}f}"
    return text if "." in text else text + ".0"


def camera_values(camera: Camera) -> Dict[str, str]:
    """The [camera] keys CAMERA_KEYS as TOML value text."""
    dist = ", ".join(f"{d:.8g}" if "e" in f"{d:.8g}" or "." in f"{d:.8g}" else f"{d:.8g}.0" for d in camera.dist[:5])
    return {
        "width": str(camera.width),
        "height": str(camera.height),
        "fx": _fmt(camera.fx, 4),
        "fy": _fmt(camera.fy, 4),
        "cx": _fmt(camera.cx, 4),
        "cy": _fmt(camera.cy, 4),
        "dist": f"[{dist}]",
    }


def camera_toml(camera: Camera, comment: str = "") -> str:
    """A [camera] section with the calibrated keys, ready for a pose-daemon config."""
    values = camera_values(camera)
    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines.append("[camera]")
    for key in CAMERA_KEYS:
        note = "   # k1 k2 p1 p2 k3" if key == "dist" else ""
        lines.append(f"{key} = {values[key]}{note}")
    return "\n".join(lines) + "\n"


_HEADER = re.compile(r"^\s*\[\s*(\[)?\s*([^\]]*?)\s*\]")


def _value_end(text: str, start: int) -> int:
    """End offset of the TOML value starting at ``start`` (a number or an array of numbers,
    possibly over several lines with comments); the trailing comment is not included."""
    i, depth, n = start, 0, len(text)
    while i < n:
        c = text[i]
        if c == "#":
            if depth == 0:
                break
            while i < n and text[i] != "\n":
                i += 1
            continue
        if c in "\"'":
            q = text.find(c, i + 1)
            i = n if q < 0 else q + 1
            continue
        if c == "[":
            depth += 1
        elif c == "]":
            depth -= 1
            if depth == 0:
                return i + 1
        elif c == "\n" and depth == 0:
            break
        i += 1
    return len(text[:i].rstrip(" \t")) if depth == 0 else n


def update_camera_text(text: str, camera: Camera, name: str = "<config>") -> str:
    """``text`` (a TOML config) with the [camera] table's width, height, fx, fy, cx, cy and
    dist set to ``camera``'s; every other line, comment and table is kept as it was."""
    values = camera_values(camera)
    nl = "\r\n" if "\r\n" in text else "\n"  # new lines written as the file writes them
    lines = text.splitlines(keepends=True)
    start = end = None
    for k, line in enumerate(lines):
        m = _HEADER.match(line)
        if not m:
            continue
        if start is not None:
            end = k
            break
        if m.group(1) is None and m.group(2) == "camera":
            start = k
    if start is None:
        if re.search(r"^\s*camera\s*[.=]", text, re.M):
            raise UserError(f"{name}: camera is not written as a [camera] table; cannot update it in place")
        sep = "" if not text.strip() else (nl if text.endswith("\n") else nl + nl)
        return text + sep + camera_toml(camera).replace("\n", nl)
    end = len(lines) if end is None else end
    body = "".join(lines[start + 1 : end])
    head = "".join(lines[: start + 1])
    tail = "".join(lines[end:])
    missing = []
    for key in CAMERA_KEYS:
        m = re.search(rf"^([ \t]*{key}[ \t]*=[ \t]*)", body, re.M)
        if m is None:
            missing.append(key)
            continue
        v_end = _value_end(body, m.end())
        body = body[: m.end()] + values[key] + body[v_end:]
    if missing:
        # New keys go after the table's last key line, before trailing blanks and comments.
        body_lines = body.splitlines(keepends=True)
        last = max((k for k, ln in enumerate(body_lines) if ln.strip() and not ln.lstrip().startswith("#")), default=-1)
        if last >= 0 and not body_lines[last].endswith("\n"):
            body_lines[last] += nl
        new = "".join(f"{key} = {values[key]}{nl}" for key in missing)
        body_lines.insert(last + 1, new)
        body = "".join(body_lines)
    return head + body + tail


def update_config_file(path: Union[str, Path], camera: Camera) -> None:
    """Set the [camera] calibration keys of the config file ``path`` in place, keeping its other
    lines and comments; the new text must load as a valid config with exactly these values
    before it atomically replaces the file."""
    from ...config import load_config

    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except OSError as exc:
        raise UserError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise UserError(f"{p}: cannot update: not UTF-8 text") from None
    load_config(p)  # a config that is already broken is reported as it is, not rewritten
    new_text = update_camera_text(text, camera, str(p))
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=str(p.parent.resolve()))
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(new_text)
        try:
            cfg = load_config(tmp)
        except ConfigError as exc:
            detail = str(exc).replace(tmp, "").lstrip(": ")
            raise UserError(f"{p}: the updated file would not load ({detail}); file left unchanged") from None
        got = cfg.camera
        want = camera_values(camera)
        for key in ("fx", "fy", "cx", "cy"):
            if abs(getattr(got, key) - float(want[key])) > 1e-9:
                raise UserError(f"{p}: the updated [camera] {key} did not read back; file left unchanged")
        if (got.width, got.height) != (camera.width, camera.height) or np.max(
            np.abs(np.asarray(got.dist[:5]) - np.asarray(camera.dist[:5]))
        ) > 1e-6:
            raise UserError(f"{p}: the updated [camera] did not read back; file left unchanged")
        try:
            os.chmod(tmp, p.stat().st_mode & 0o7777)
        except OSError:
            pass
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
