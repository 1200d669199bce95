"""The shipped Pi config is one a first flight survives: an id-checked ArUco marker, so a
chessboard (tiles, windows) in view gives no pose; a plain square, chosen by the user, is
warned about at every start."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List

import numpy as np
import pytest
from pipeline_fakes import FakeProcessor, FakeSource, outputs_of

from pose_daemon.camera import Camera
from pose_daemon.capture.base import Frame
from pose_daemon.cli import main
from pose_daemon.config import load_config, parse_config
from pose_daemon.config.load import SQUARE_WARNING
from pose_daemon.geometry import rot_x, rvec_from_R
from pose_daemon.preview.warnings import Context, evaluate
from pose_daemon.processing.marker import FrameProcessor
from pose_daemon.render import Effects, render_plane
from pose_daemon.service import Service
from pose_daemon.tools import calibrate as cal

ROOT = Path(__file__).resolve().parents[1]
PI_CONFIG = ROOT / "config" / "pose-daemon.toml"
EFFECTS = Effects(blur_px=0.8, noise_gray=2.0, background="plain")


def _chessboard_frames(camera: Camera, n: int = 12) -> List[np.ndarray]:
    """A 9x6-square chessboard of 30 mm squares seen face on and tilted, 0.5-0.9 m away: the
    dark squares are as large in the image as a marker would be."""
    spec = cal.parse_board("chessboard:8x5:0.03")
    texture, size_m = cal.board_image(spec, 40), cal.board_image_size_m(spec)
    frames = []
    for i in range(n):
        tilt = np.radians(-20 + 40 * i / (n - 1))
        rvec = rvec_from_R(rot_x(tilt) @ rot_x(np.pi))  # face to the camera, as the marker
        tvec = np.array([0.02 * (i % 3 - 1), 0.01 * (i % 2), 0.5 + 0.4 * i / (n - 1)])
        frames.append(render_plane(camera, texture, size_m, rvec, tvec, effects=EFFECTS, rng=np.random.default_rng(i)))
    return frames


def _poses(cfg, images: List[np.ndarray]) -> int:
    processor = FrameProcessor.from_config(cfg)
    return sum(
        processor.process(Frame(image=img, t_capture_s=k / 30.0, seq=k)).pose is not None
        for k, img in enumerate(images)
    )


def test_shipped_config_gives_no_pose_on_a_chessboard_a_square_config_does():
    shipped = load_config(PI_CONFIG)
    assert shipped.marker.type == "aruco" and shipped.start_warnings() == []
    images = _chessboard_frames(shipped.camera.model())
    assert _poses(shipped, images) == 0
    # The same frames through a plain-square config: the runaway the shipped config avoids.
    text = PI_CONFIG.read_text()
    square = parse_config(
        text.replace('type = "aruco"', 'type = "square"')
        .replace('dictionary = "DICT_4X4_50"\n', "")
        .replace("id = 0\n", "")
        .replace("width = 0.15", "width = 0.03")
        .replace("height = 0.15", "height = 0.03"),
        "square.toml",
    )
    assert square.marker.type == "square"
    assert _poses(square, images) >= len(images) // 2


def test_shipped_config_says_how_to_print_its_marker_and_when_origin_is_needed(tmp_path, capsys):
    text = PI_CONFIG.read_text()
    cfg = load_config(PI_CONFIG)
    command = next(line for line in text.splitlines() if "pose-daemon marker" in line).lstrip("# ").split()
    out = tmp_path / "marker.pdf"
    assert main([*command[1:-1], str(out)]) == 0
    printed = parse_config(capsys.readouterr().out, "marker output").marker
    assert (printed.type, printed.dictionary, printed.id, printed.width) == (
        "aruco",
        cfg.marker.dictionary,
        cfg.marker.id,
        cfg.marker.width,
    )
    # origin: present, commented out, and the config with it uncommented still loads.
    assert cfg.output.mavlink is not None and cfg.output.mavlink.origin is None
    line = next(line for line in text.splitlines() if line.startswith("# origin = "))
    with_origin = parse_config(text.replace(line, line[2:]), "origin.toml")
    assert with_origin.output.mavlink.origin is not None
    assert "without GPS" in text


SQUARE_PI = '[camera]\nsource = "picamera2"\n[marker]\ntype = "square"\nwidth = 0.2\n'


def test_a_square_marker_on_a_camera_is_warned_about_at_start(caplog):
    cfg = parse_config(SQUARE_PI, "square.toml")
    assert cfg.start_warnings() == [SQUARE_WARNING]
    # The demo's rendered scene holds nothing but its marker: no warning there.
    assert parse_config('[marker]\ntype = "square"\n', "demo.toml").start_warnings() == []
    caplog.set_level(logging.INFO, logger="pose_daemon")
    service = Service(cfg, source=FakeSource(3), outputs=outputs_of(), processor=FakeProcessor())
    assert service.run() == 0
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "any dark square" in r.getMessage()]
    assert len(warned) == 1
    # The preview page and status.json list it too.
    warnings = cfg.start_warnings()
    ctx = Context(
        last=None, history=[], source_state="ok", since_frame_s=0.0, recent_drops={}, config_warnings=warnings
    )
    assert [w.code for w in evaluate(ctx)] == ["config"]


def test_check_config_warns_of_a_square_marker_and_still_accepts_it(tmp_path, capsys):
    path = tmp_path / "square.toml"
    path.write_text('[camera]\nsource = "video:%s"\n[marker]\ntype = "square"\n' % (tmp_path / "v.mp4"))
    (tmp_path / "v.mp4").write_bytes(b"")
    assert main(["check-config", "--syntax-only", str(path)]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "any dark square" in err


@pytest.mark.parametrize("doc", ["troubleshooting.md"])
def test_the_warning_is_listed_for_the_user(doc):
    assert "any dark square in view passes" in (ROOT / "docs" / doc).read_text()
