"""Config: the schema, its bounds, and one-line errors naming file, key and expectation."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import fields, replace
from pathlib import Path

import pytest

from pose_daemon.config import (
    DEFAULT_CONFIG_FILE,
    Config,
    ConfigError,
    EstimatorConfig,
    MarkerConfig,
    MavlinkOutputConfig,
    MountConfig,
    SyntheticConfig,
    default_config_text,
    load_config,
    parse_config,
    reference,
)
from pose_daemon.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def _error(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_config(text, "config.toml")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("config.toml: ")
    return message


@pytest.mark.pi
def test_demo_file_is_the_embedded_default():
    # One file: the package data, with config/demo.toml a link to it (nothing can drift).
    shipped = ROOT / "pose_daemon" / "data" / DEFAULT_CONFIG_FILE
    assert (ROOT / "config" / "demo.toml").resolve() == shipped.resolve()
    assert default_config_text() == shipped.read_text()
    cfg = Config.default()
    assert replace(load_config(ROOT / "config" / "demo.toml"), name=cfg.name) == cfg
    assert cfg.camera.source == "synthetic"
    assert cfg.output.mavlink.connection == "udpout:127.0.0.1:14550"
    assert cfg.output.jsonl.path == "-"
    assert cfg.output.serial is None


@pytest.mark.pi
def test_pi_config_loads():
    cfg = load_config(ROOT / "config" / "pose-daemon.toml")
    assert cfg.camera.source == "picamera2"
    assert cfg.camera.source_kind == "picamera2"
    assert cfg.output.mavlink.connection == "/dev/serial0"
    assert cfg.output.mavlink.messages == ("ODOMETRY",)
    assert cfg.output.jsonl is None
    assert cfg.mount.preset == "down" and cfg.marker.placement == "floor"


def test_defaults_fill_missing_keys_and_sections():
    cfg = parse_config('[camera]\nsource = "opencv:0"\nfx = 600\n', "c.toml")
    assert cfg.camera.fx == 600.0 and isinstance(cfg.camera.fx, float)
    assert cfg.camera.source_kind == "opencv" and cfg.camera.source_arg == "0"
    assert cfg.estimator.iterations == 5 and cfg.estimator.refine is True
    assert cfg.detector.max_misses == 5 and cfg.detector.min_side_px == 10.0
    assert cfg.synthetic.trajectory == "wall" and cfg.synthetic.frames == 0
    assert cfg.pipeline.latency_budget_s == 0.1 and cfg.pipeline.status_interval_s == 10.0
    assert cfg.mount.preset == "forward" and cfg.mount.offset_m == (0.0, 0.0, 0.0)
    assert cfg.output.mavlink is None and cfg.output.serial is None and cfg.output.jsonl is None
    assert cfg.name == "c.toml"


def test_models():
    cfg = parse_config(
        "[camera]\nfx = 600.0\nfy = 610.0\ndist = [0.1, -0.2, 0.0, 0.0]\n"
        '[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_50"\nid = 7\nwidth = 0.15\n',
        "c.toml",
    )
    cam = cfg.camera.model()
    assert cam.K[0, 0] == 600.0 and cam.K[1, 1] == 610.0
    assert cam.dist == (0.1, -0.2, 0.0, 0.0, 0.0)
    marker = cfg.marker.model()
    assert (marker.width, marker.height, marker.type, marker.dictionary, marker.id) == (
        0.15,
        0.15,
        "aruco",
        "DICT_4X4_50",
        7,
    )


def test_marker_placement_drives_the_synthetic_trajectory():
    cfg = parse_config('[marker]\nplacement = "floor"\n', "c.toml")
    assert cfg.synthetic.trajectory == "floor"
    assert _error('[marker]\nplacement = "floor"\n[synthetic]\ntrajectory = "wall"\n') == (
        'config.toml: [synthetic] trajectory: expected "floor" (the [marker] placement), got "wall"'
    )


@pytest.mark.parametrize(
    "text, expected",
    [
        # wrong type
        ('[camera]\nfx = "abc"\n', 'config.toml: [camera] fx: expected a number > 0, got "abc"'),
        ("[camera]\nwidth = 640.5\n", "config.toml: [camera] width: expected an integer in [16, 8192], got 640.5"),
        ("[estimator]\nrefine = 1\n", "config.toml: [estimator] refine: expected true or false, got 1"),
        ("[camera]\nsource = 0\n", "config.toml: [camera] source: expected a non-empty string, got 0"),
        (
            '[camera]\ndist = [0, 0, "x", 0, 0]\n',
            'config.toml: [camera] dist: expected a list of 4 or 5 or 8 numbers, got [0, 0, "x", 0, 0]',
        ),
        ("camera = 3\n", "config.toml: camera: expected a table [camera], got 3"),
        # out of range
        ("[camera]\nfx = -1.0\n", "config.toml: [camera] fx: expected a number > 0, got -1.0"),
        ("[camera]\nfx = nan\n", "config.toml: [camera] fx: expected a number > 0, got nan"),
        (
            "[camera]\ncy = 480.0\n",
            "config.toml: [camera] cy: expected a number in [0, 480) (inside the image height), got 480.0",
        ),
        (
            "[pipeline]\nlatency_budget_s = 0\n",
            "config.toml: [pipeline] latency_budget_s: expected a number in (0, 10], got 0",
        ),
        (
            "[estimator]\niterations = 0\n",
            "config.toml: [estimator] iterations: expected an integer in [1, 100], got 0",
        ),
        (
            "[synthetic]\njpeg_quality = 101\n",
            "config.toml: [synthetic] jpeg_quality: expected an integer in [0, 100], got 101",
        ),
        (
            "[mount]\noffset_m = [0.0, 0.0]\n",
            "config.toml: [mount] offset_m: expected a list of 3 numbers, each in [-100, 100], got [0.0, 0.0]",
        ),
        (
            "[output.mavlink]\nsource_component = 256\n",
            "config.toml: [output.mavlink] source_component: expected an integer in [1, 255], got 256",
        ),
        # choices
        ('[marker]\ntype = "circle"\n', 'config.toml: [marker] type: expected one of "square", "aruco", got "circle"'),
        (
            '[output.mavlink]\nmessages = ["ODOMETRY", "ODOMETRY"]\n',
            'config.toml: [output.mavlink] messages: expected a list of strings, each one of "ODOMETRY", '
            '"VISION_POSITION_ESTIMATE", "LANDING_TARGET", "TARGET_RELATIVE", not empty, no repeats, '
            'got ["ODOMETRY", "ODOMETRY"]',
        ),
        (
            "[output.mavlink]\nmessages = []\n",
            'config.toml: [output.mavlink] messages: expected a list of strings, each one of "ODOMETRY", '
            '"VISION_POSITION_ESTIMATE", "LANDING_TARGET", "TARGET_RELATIVE", not empty, no repeats, got []',
        ),
        (
            '[camera]\nsource = "webcam"\n',
            'config.toml: [camera] source: expected "picamera2", "synthetic", "sitl", "opencv:N", "video:PATH", '
            '"replay:PATH" or a GStreamer pipeline ("... ! appsink"), got "webcam"',
        ),
        (
            '[camera]\nsource = "opencv:front"\n',
            'config.toml: [camera] source: expected "opencv:N" with a camera index N or a device path, '
            'got "opencv:front"',
        ),
        # unknown keys and sections
        (
            "[camera]\nfps2 = 30\n",
            "config.toml: [camera] fps2: unknown key (expected one of source, width, height, fx, fy, cx, cy, "
            "dist, fps, exposure_us, analogue_gain)",
        ),
        (
            "[cam]\nfx = 1\n",
            "config.toml: [cam]: unknown section (expected one of camera, marker, estimator, detector, "
            "synthetic, pipeline, mount, attitude, gate, logging, preview, sitl, output, map)",
        ),
        (
            "[output.udp]\nport = 1\n",
            "config.toml: [output.udp]: unknown output (expected one of mavlink, serial, jsonl)",
        ),
        ('[output.jsonl]\nfile = "x"\n', "config.toml: [output.jsonl] file: unknown key (expected one of path)"),
        # cross-key rules
        (
            '[marker]\ntype = "aruco"\nid = 3\n',
            'config.toml: [marker] dictionary: expected a dictionary name such as "DICT_4X4_50" '
            '(needed when type = "aruco")',
        ),
        (
            '[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_51"\nid = 3\n',
            "config.toml: [marker] dictionary: expected an OpenCV ArUco dictionary name such as "
            '"DICT_4X4_50", got "DICT_4X4_51"',
        ),
        ("[marker]\nid = 3\n", 'config.toml: [marker] id: expected no id unless type = "aruco", got 3'),
        (
            "[detector]\ngamma = 1.0\ngamma_shoulder = 2.0\n",
            "config.toml: [detector] gamma_shoulder: expected a number below 2 * (gamma - 0.1) (1.8): the exponent "
            "at black stays positive, got 2.0",
        ),
        (
            "[pipeline]\nsource_retry_s = 2.0\nsource_retry_max_s = 1.0\n",
            "config.toml: [pipeline] source_retry_max_s: expected a number >= source_retry_s (2), got 1.0",
        ),
    ],
)
def test_every_error_is_one_line_with_file_key_expectation(text, expected):
    assert _error(text) == expected


def test_toml_syntax_error_is_one_line():
    message = _error("[camera\nfx = 1\n")
    assert message.startswith("config.toml: invalid TOML: ") and "line 1" in message


def test_case_insensitive_choices_are_normalised():
    cfg = parse_config('[logging]\nlevel = "debug"\n[output.mavlink]\nmessages = ["odometry"]\n', "c")
    assert cfg.logging.level == "DEBUG"
    assert cfg.output.mavlink.messages == ("ODOMETRY",)


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.toml: cannot read config: No such file"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bin.toml"
    bad.write_bytes(b"\xff\xfe[camera]")
    with pytest.raises(ConfigError, match=r"bin\.toml: invalid TOML: not UTF-8"):
        load_config(bad)
    assert issubclass(ConfigError, UserError)


def test_effective_config_round_trips_through_toml():
    cfg = Config.default()
    again = parse_config(cfg.to_toml(), cfg.name)
    assert again == cfg


def test_reference_covers_every_key():
    rows = reference()
    keys = {(section, key) for section, key, *_ in rows}
    assert ("[camera]", "fx") in keys and ("[output.mavlink]", "messages") in keys
    assert ("[pipeline]", "latency_budget_s") in keys and ("[logging]", "level") in keys
    assert all(expect and doc for _, _, _, expect, doc in rows)


def _cli(*args: str):
    return subprocess.run([sys.executable, "-m", "pose_daemon", *args], capture_output=True, text=True, timeout=60)


def test_check_config_cli(tmp_path):
    good = _cli("check-config", str(ROOT / "config" / "demo.toml"))
    assert good.returncode == 0, good.stderr
    assert "ok (source synthetic" in good.stdout and "outputs: mavlink, jsonl" in good.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\nfx = "abc"\n')
    res = _cli("check-config", str(bad))
    assert res.returncode == 2
    assert res.stderr == f'pose-daemon: error: {bad}: [camera] fx: expected a number > 0, got "abc"\n'
    assert res.stdout == ""
    shown = _cli("check-config", "--syntax-only", "--print", str(ROOT / "config" / "pose-daemon.toml"))
    assert shown.returncode == 0
    assert 'source = "picamera2"' in shown.stdout and "[output.mavlink]" in shown.stdout


def test_check_config_checks_the_mavlink_connection_string(tmp_path):
    bad = tmp_path / "link.toml"
    bad.write_text('[output.mavlink]\nconnection = "udpout:localhost"\n')
    res = _cli("check-config", str(bad))
    assert res.returncode == 2
    assert res.stderr == (
        f"pose-daemon: error: {bad}: [output.mavlink] connection: expected "
        "udpout:HOST:PORT with a port in 1..65535, got 'udpout:localhost'\n"
    )


@pytest.mark.parametrize("kind, what", [("video", "a video file"), ("replay", "a recording, image folder or video")])
def test_check_config_refuses_a_missing_video_or_recording_as_run_does(tmp_path, kind, what):
    source = f"{kind}:{tmp_path / 'clip'}"
    path = tmp_path / "c.toml"
    path.write_text(f'[camera]\nsource = "{source}"\n')
    # The text alone is valid (`replay PATH --config c.toml` ignores the source) ...
    assert load_config(path).camera.source == source
    # ... but check-config refuses it with run's line: the daemon could never start.
    expected = (
        f"pose-daemon: error: {path}: [camera] source: expected {what} that exists, "
        f'got "{source}" (no such file or folder)\n'
    )
    for args in (["check-config", str(path)], ["run", "--config", str(path)]):
        res = _cli(*args)
        assert (res.returncode, res.stdout, res.stderr) == (2, "", expected)
    (tmp_path / "clip").write_bytes(b"")
    assert _cli("check-config", str(path)).returncode == 0


def test_aruco_id_outside_its_dictionary_is_a_config_error():
    # DICT_4X4_50 has ids 0..49; the detector would otherwise fail at start-up with a traceback.
    base = '[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_50"\n'
    assert parse_config(base + "id = 49\n", "config.toml").marker.id == 49
    assert _error(base + "id = 50\n") == (
        "config.toml: [marker] id: expected an integer in [0, 49] (the ids of DICT_4X4_50), got 50"
    )


def test_unknown_estimator_method_is_a_config_error():
    # Otherwise every frame of a running daemon fails with no pose.
    assert parse_config('[estimator]\nmethod = "paper"\n', "config.toml").estimator.method == "paper"
    assert _error('[estimator]\nmethod = "foo"\n') == (
        'config.toml: [estimator] method: expected one of "iterative", "paper", got "foo"'
    )


def _rule(cls: type, key: str):
    return next(f for f in fields(cls) if f.name == key).metadata["rule"]


def test_every_list_of_choices_is_its_owners():
    # A copied list drifts: a new MAVLink message or pose method must need one edit, not two.
    from pose_daemon.camera import MARKER_TYPES
    from pose_daemon.config.forms import MESSAGES
    from pose_daemon.geometry import MARKER_PLACEMENTS, MOUNT_PRESETS
    from pose_daemon.pose.loop import METHODS

    assert _rule(MarkerConfig, "type").choices is MARKER_TYPES
    assert _rule(MarkerConfig, "placement").choices is MARKER_PLACEMENTS
    assert _rule(SyntheticConfig, "trajectory").choices is MARKER_PLACEMENTS
    assert _rule(MountConfig, "preset").choices is MOUNT_PRESETS
    assert _rule(MavlinkOutputConfig, "messages").choices is MESSAGES
    assert _rule(EstimatorConfig, "method").choices is METHODS


@pytest.mark.parametrize(
    "first", ["pose_daemon.outputs.mavlink", "pose_daemon.pose.loop", "pose_daemon.capture", "pose_daemon.config"]
)
def test_config_and_the_owners_of_its_choices_import_in_any_order(first):
    # config imports from these modules; one importing config back would be a cycle that
    # breaks whichever is imported first.
    res = subprocess.run(
        [sys.executable, "-c", f"import {first}; import pose_daemon.config"], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 0, res.stderr


def test_the_pi2_profile_is_the_pi_config_at_half_size_without_the_blur_model():
    """config/pi2.toml: what it gives up is what its comments say, the rest is the Pi config."""
    pi = load_config(ROOT / "config" / "pose-daemon.toml")
    pi2 = load_config(ROOT / "config" / "pi2.toml")
    assert (pi2.camera.width, pi2.camera.height) == (pi.camera.width // 2, pi.camera.height // 2)
    # The same lens at half the resolution: the same field of view.
    assert pi2.camera.fx == pi.camera.fx / 2 and pi2.camera.fy == pi.camera.fy / 2
    assert (pi2.camera.cx + 0.5, pi2.camera.cy + 0.5) == ((pi.camera.cx + 0.5) / 2, (pi.camera.cy + 0.5) / 2)
    assert pi2.camera.fps == pi.camera.fps == 30.0
    assert pi2.detector.blur_model is False and pi.detector.blur_model is True
    assert pi2.detector.search_budget_ms == 2.0
    assert pi2.estimator == pi.estimator and pi2.marker == pi.marker and pi2.output == pi.output
    assert pi2.mount == pi.mount and pi2.pipeline == pi.pipeline
