"""Preflight's precision-landing checks (tools/preflight/landing.py): ArduPilot's PLND_* and PX4's
PLD_* / RTL_PLD_MD, against the fake autopilot's parameters over real UDP and as pure rules."""

from __future__ import annotations

import re

import pytest
from fake_autopilot import FakeAutopilot

from pose_daemon.cli import main
from pose_daemon.config import parse_config
from pose_daemon.tools.preflight import Observation
from pose_daemon.tools.preflight.findings import Finding
from pose_daemon.tools.preflight.landing import check_landing, merge

LINE = re.compile(r"^(OK .+|PROBLEM .+|FIX: [A-Z0-9_]+ = -?[0-9.]+)$")
PLND_OK = {
    "PLND_ENABLED": 1, "PLND_TYPE": 1, "PLND_EST_TYPE": 1, "PLND_LAG": 0.05, "PLND_ORIENT": 25,
    "PLND_ALT_MIN": 0, "PLND_ALT_MAX": 0, "PLND_CAM_POS_X": 0, "PLND_CAM_POS_Y": 0, "PLND_CAM_POS_Z": 0,
    "RNGFND1_TYPE": 0,
}  # fmt: skip


def _cfg(mount: str = 'preset = "down"', messages: str = '["ODOMETRY", "LANDING_TARGET"]', marker: str = ""):
    return parse_config(
        f'[marker]\nplacement = "floor"\n{marker}\n[mount]\n{mount}\n'
        f'[output.mavlink]\nconnection = "udpout:127.0.0.1:14550"\nmessages = {messages}\n',
        "fc.toml",
    )


def _lines(cfg, autopilot: str, params, delay_s=None):
    obs = Observation(autopilot=autopilot, params={k: (float(v), 9) for k, v in params.items()})
    if delay_s is not None:
        obs.delays_s = [delay_s] * 5
    return [f.line() for f in check_landing(cfg, obs)]


def test_nothing_is_checked_without_landing_target():
    assert _lines(_cfg(messages='["ODOMETRY"]'), "ardupilot", {"PLND_ENABLED": 0}) == []


def test_a_good_ardupilot_setup_is_all_ok():
    lines = _lines(_cfg(), "ardupilot", PLND_OK, delay_s=0.05)
    assert all(ln.startswith("OK ") for ln in lines), lines
    assert "OK PLND_LAG = 0.05 s (measured delay: median 50 ms)" in lines


@pytest.mark.parametrize(
    "change, expected",
    [
        ({"PLND_ENABLED": 0}, "FIX: PLND_ENABLED = 1"),
        ({"PLND_TYPE": 2}, "FIX: PLND_TYPE = 1"),
        ({"PLND_EST_TYPE": 0}, "FIX: PLND_EST_TYPE = 1"),
        ({"PLND_ORIENT": 0}, "FIX: PLND_ORIENT = 25"),
        ({"PLND_LAG": 0.02}, "FIX: PLND_LAG = 0.05"),
        ({"PLND_ALT_MIN": 0.75}, "FIX: PLND_ALT_MIN = 0"),
        ({"PLND_ALT_MAX": 8}, "FIX: PLND_ALT_MAX = 0"),
    ],
)
def test_each_ardupilot_parameter_that_breaks_the_landing_is_fixed(change, expected):
    lines = _lines(_cfg(), "ardupilot", {**PLND_OK, **change}, delay_s=0.05)
    fixes = [ln for ln in lines if ln.startswith("FIX")]
    assert fixes == [expected], lines


def test_plnd_lag_advice_stays_in_ardupilots_range():
    lines = _lines(_cfg(), "ardupilot", {**PLND_OK, "PLND_LAG": 0.1}, delay_s=0.4)
    assert "FIX: PLND_LAG = 0.25" in lines
    lines = _lines(_cfg(), "ardupilot", {**PLND_OK, "PLND_LAG": 0.1}, delay_s=0.004)
    assert "FIX: PLND_LAG = 0.02" in lines


def test_a_rangefinder_keeps_the_altitude_limits():
    lines = _lines(_cfg(), "ardupilot", {**PLND_OK, "PLND_ALT_MIN": 0.75, "PLND_ALT_MAX": 8, "RNGFND1_TYPE": 10})
    assert not any("PLND_ALT" in ln for ln in lines), lines


def test_the_camera_offset_is_set_once():
    both = _lines(
        _cfg(mount='preset = "down"\noffset_m = [0.05, 0.0, 0.02]'), "ardupilot", {**PLND_OK, "PLND_CAM_POS_X": 0.05}
    )
    assert [ln for ln in both if ln.startswith("FIX")] == ["FIX: PLND_CAM_POS_X = 0"]
    assert any(ln.startswith("PROBLEM PLND_CAM_POS_* (X 0.05) and [mount] offset_m") for ln in both)
    once = _lines(_cfg(), "ardupilot", {**PLND_OK, "PLND_CAM_POS_X": 0.05})
    assert "OK PLND_CAM_POS_* camera offset set once: in PLND_CAM_POS_*" in once


def test_a_forward_camera_cannot_land_on_a_pad_below():
    lines = _lines(_cfg(mount='preset = "forward"'), "ardupilot", PLND_OK)
    assert any(
        ln.startswith("PROBLEM [mount] preset forward: the camera looks 90 deg from straight down") for ln in lines
    )


def test_px4_final_approach_altitude_follows_the_marker_and_camera():
    # A 0.2 m marker, 480 px high at fy = 500: it fills the view below 0.21 m.
    lines = _lines(_cfg(), "px4", {"PLD_FAPPR_ALT": 0.1, "RTL_PLD_MD": 0, "PLD_HACC_RAD": 0.2, "LTEST_MODE": 0})
    assert "FIX: PLD_FAPPR_ALT = 0.25" in lines and "FIX: RTL_PLD_MD = 1" in lines
    assert any(ln.startswith("OK LTEST_* play no part") for ln in lines)
    fine = _lines(_cfg(), "px4", {"PLD_FAPPR_ALT": 0.3, "RTL_PLD_MD": 1})
    assert all(ln.startswith("OK ") for ln in fine), fine


def test_merge_keeps_one_finding_per_parameter():
    base = [
        Finding("PROBLEM", "PLND_ENABLED = 0: precision landing is off"),
        Finding("FIX", param="PLND_ENABLED", value=1),
    ]
    extra = [
        Finding("PROBLEM", "PLND_ENABLED = 0: off"),
        Finding("FIX", param="PLND_ENABLED", value=1),
        Finding("OK", "PLND_TYPE = 1"),
    ]
    assert [f.line() for f in merge(base, extra)] == [f.line() for f in base] + ["OK PLND_TYPE = 1"]


def _config_file(tmp_path, connection: str, extra: str = "") -> str:
    path = tmp_path / "fc.toml"
    path.write_text(f"""
[camera]
source = "synthetic"
fx = 500.0
fy = 500.0
[marker]
width = 0.2
[synthetic]
trajectory = "wall"
[mount]
offset_m = [0.05, 0.0, 0.0]
[output.mavlink]
connection = "{connection}"
messages = ["ODOMETRY", "LANDING_TARGET"]
{extra}
""")
    return str(path)


def _run(capsys, *argv):
    code = main(["preflight", "--seconds", "2.5", *argv])
    lines = capsys.readouterr().out.splitlines()
    assert all(LINE.match(ln) for ln in lines), lines
    return code, lines


@pytest.mark.slow
def test_preflight_reads_and_fixes_the_ardupilot_landing_parameters(tmp_path, capsys):
    wrong = {**PLND_OK, "PLND_EST_TYPE": 0, "PLND_ORIENT": 0, "PLND_ALT_MIN": 0.75, "PLND_CAM_POS_X": 0.05}
    fc = FakeAutopilot("ardupilot", ekf_start_s=0.0, heartbeat_s=0.2, params=wrong)
    cfg = _config_file(tmp_path, fc.connection, "origin = [47.397742, 8.545594, 488.0]")
    try:
        code, lines = _run(capsys, "--config", cfg)
        assert code == 1
        for fix in ("PLND_EST_TYPE = 1", "PLND_ORIENT = 25", "PLND_ALT_MIN = 0", "PLND_CAM_POS_X = 0"):
            assert f"FIX: {fix}" in lines, lines
        assert sum(ln.startswith("FIX: PLND_ENABLED") or ln == "OK PLND_ENABLED = 1" for ln in lines) == 1
        assert any(ln.startswith("PROBLEM [mount] preset forward") for ln in lines)
        _run(capsys, "--config", cfg, "--apply")
        assert fc.param("PLND_ORIENT") == 25 and fc.param("PLND_EST_TYPE") == 1 and fc.param("PLND_CAM_POS_X") == 0
    finally:
        fc.close()


def test_preflight_reads_the_px4_precision_landing_parameters(tmp_path, capsys):
    fc = FakeAutopilot("px4", heartbeat_s=0.2, timesync_s=0.5, params={"PLD_FAPPR_ALT": 0.1, "RTL_PLD_MD": 0})
    try:
        code, lines = _run(capsys, "--config", _config_file(tmp_path, fc.connection))
    finally:
        fc.close()
    assert code == 1
    assert "FIX: PLD_FAPPR_ALT = 0.25" in lines and "FIX: RTL_PLD_MD = 1" in lines, lines
