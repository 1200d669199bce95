"""pose-daemon sim against the fake simulator (tests/fake_sitl.py): the rehearsal flies, judges
and reports; a wrong mount or a refused arming fails it with the reason; no simulator is exit 2."""

from __future__ import annotations

import json

import pytest
from fake_sitl import FakeSitl

from pose_daemon.cli import main

CONFIG = """
[camera]
source = "picamera2"
width = 320
height = 240
fx = 260.0
fy = 260.0
cx = 159.5
cy = 119.5
fps = 10
{target}
[mount]
preset = "{mount}"
[synthetic]
blur_px = 0.6
noise_gray = 1.0
[sitl]
connection = "{gcs}"
marker_below_m = {below}
[output.mavlink]
connection = "{daemon}"
[pipeline]
latency_budget_s = 0.5  # a loaded test machine: the rehearsal's mechanics are tested, not its speed
[logging]
level = "WARNING"
"""
KEYS = (
    "autopilot", "armed", "hold_err_rms_m", "hold_err_max_m", "hold_track_rms_m", "ignored_share",
    "touchdown_err_m", "reasons",
)  # fmt: skip


SQUARE = '[marker]\nwidth = 0.2\nplacement = "floor"'


def _pad() -> str:
    from pose_daemon.maps.pad import landing_pad

    return "\n".join(landing_pad().to_toml_lines())


def _sim(tmp_path, fake: FakeSitl, *extra: str, mount: str = "down", pad: bool = False):
    config = tmp_path / "sim.toml"
    # The camera 0.3 m above the pad when landed: on a loaded machine the touchdown can be 5 cm
    # off the centre, where 0.15 m would leave the inner marker at the edge of the view.
    target, below = (_pad(), 0.3) if pad else (SQUARE, 0.4)  # the square fills the view lower down
    text = CONFIG.format(mount=mount, gcs=fake.gcs_connection, daemon=fake.daemon_connection, target="", below=below)
    config.write_text(text + "\n" + target + "\n")
    out = tmp_path / "out"
    code = main(["sim", "--config", str(config), "--out", str(out), "--hold-s", "3", *extra])
    return code, json.loads((out / "summary.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("kind, pad", [("ardupilot", True), ("px4", False)], ids=["ardupilot-pad", "px4-square"])
def test_a_short_landing_rehearsal_passes_and_reports(tmp_path, capsys, kind, pad):
    """On ArduPilot over the nested pad (ArUco map), on PX4 over a plain square marker."""
    fake = FakeSitl(kind, yaw_deg=20.0)
    try:
        code, summary = _sim(tmp_path, fake, "--fly", "land", "--ekf-wait-s", "20", pad=pad)
    finally:
        fake.close()
    assert code == 0, summary["reasons"]
    assert set(KEYS) <= set(summary)
    assert summary["autopilot"] == kind and summary["armed"] is True and summary["reasons"] == []
    # The EKF follows the daemon's poses of the simulator's truth: mm to cm, never exactly 0.
    assert 0.0 < summary["hold_err_rms_m"] <= summary["hold_err_max_m"] < 0.05
    assert 0.0 < summary["hold_track_rms_m"] < 0.1
    assert summary["ignored_share"] == 0.0
    assert 0.0 <= summary["touchdown_err_m"] < 0.1
    assert summary["descent_pose_share"] > 0.9
    assert fake.tally.modes[-1] in ("LAND", "AUTO.LAND") and fake.tally.fused > 50
    assert capsys.readouterr().out.strip().endswith("PASSED")
    assert (tmp_path / "out" / "sim.png").stat().st_size > 0


@pytest.mark.slow
def test_a_landing_from_higher_up_holds_there_and_lands_on_the_pad(tmp_path):
    """--climb-m: the hover (and so the landing's start) over the nested pad 3 m up, not 1 m."""
    fake = FakeSitl("ardupilot", yaw_deg=-15.0)
    try:
        code, summary = _sim(tmp_path, fake, "--fly", "land", "--ekf-wait-s", "20", "--climb-m", "3", pad=True)
    finally:
        fake.close()
    assert code == 0, summary["reasons"]
    assert abs(summary["hold_height_m"] - 3.0) < 0.15
    assert 0.0 <= summary["touchdown_err_m"] < 0.1
    assert summary["descent_pose_share"] > 0.9


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ardupilot", "px4"])
def test_a_wrong_mount_fails_with_the_reason(tmp_path, capsys, kind):
    """No pose, no fusion: PX4's EKF2 sets its horizontal position flags on the ground all the
    same (0xff), and only its bit 8 says a position is fused."""
    fake = FakeSitl(kind)
    try:
        code, summary = _sim(tmp_path, fake, "--fly", "land", "--ekf-wait-s", "4", mount="forward")
    finally:
        fake.close()
    assert code == 1
    assert summary["armed"] is False and summary["touchdown_err_m"] is None
    assert summary["reasons"][0].startswith(
        "the EKF did not use the vision feed in 4 s (the daemon found a pose in 0 of"
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("pose-daemon sim: failed: the EKF did not use the vision feed")


@pytest.mark.slow
def test_an_arming_refusal_is_retried_then_reported_with_the_autopilots_words(tmp_path):
    fake = FakeSitl("ardupilot", prearm_failure="PreArm: Compass not calibrated")
    try:
        code, summary = _sim(tmp_path, fake, "--fly", "hold", "--ekf-wait-s", "20", "--arm-wait-s", "3")
    finally:
        fake.close()
    assert code == 1
    assert summary["armed"] is False
    (reason,) = summary["reasons"]
    assert reason.startswith("not armed in 3 s (") and reason.endswith(" tries): PreArm: Compass not calibrated")
    assert summary["arm_refusals"] == ["PreArm: Compass not calibrated"] * len(fake.tally.arm_refusals)
    assert len(fake.tally.arm_refusals) >= 1
    assert "PreArm: Compass not calibrated" in summary["statustext"]


@pytest.mark.slow
def test_arming_refused_while_the_accels_settle_is_retried_until_it_arms(tmp_path, capsys):
    """ArduPilot refuses "Arm: Accels inconsistent" until its IMUs have agreed 10 s after boot: a
    rehearsal started right after the simulator must retry as a ground station's user would.
    The fake's settling ends after it has refused twice (not on a clock: the test does not race the machine)."""
    import threading

    fake = FakeSitl("ardupilot", accels_settle_s=1e9)

    def settle() -> None:
        while len(fake.tally.arm_refusals) < 2 and not fake._stop:
            threading.Event().wait(0.05)
        fake.accels_settle_s = 0.0

    watcher = threading.Thread(target=settle, daemon=True)
    watcher.start()
    try:
        code, summary = _sim(tmp_path, fake, "--fly", "hold", "--ekf-wait-s", "20", "--arm-wait-s", "60")
    finally:
        fake.close()
        watcher.join(1.0)
    assert code == 0, summary["reasons"]
    assert summary["armed"] is True and summary["reasons"] == []
    refusals = fake.tally.arm_refusals
    assert len(refusals) >= 2 and summary["arm_refusals"] == ["Arm: Accels inconsistent"] * len(refusals)
    shown = f"{'armed after':<20} {len(refusals):>10}   refusals, the last: Arm: Accels inconsistent"
    assert shown in capsys.readouterr().out


def test_no_simulator_is_exit_2_with_one_line(tmp_path, capsys, monkeypatch):
    import pose_daemon.tools.sim as sim

    monkeypatch.setattr(sim, "LINK_TIMEOUT_S", 0.5)
    config = tmp_path / "sim.toml"
    text = CONFIG.format(mount="down", gcs="udpout:127.0.0.1:9", daemon="udpout:127.0.0.1:9", target=SQUARE, below=0.3)
    config.write_text(text)
    assert main(["sim", "--config", str(config), "--fly", "land", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "[sitl] connection udpout:127.0.0.1:9: no autopilot HEARTBEAT in 0.5 s" in err[0]


@pytest.mark.slow
def test_without_a_mission_sim_runs_the_daemon_until_stopped(tmp_path, capsys):
    import os
    import signal
    import threading

    fake = FakeSitl("ardupilot")
    config = tmp_path / "sim.toml"
    text = CONFIG.format(mount="down", gcs=fake.gcs_connection, daemon=fake.daemon_connection, target=SQUARE, below=0.4)
    config.write_text(text)
    stopper = threading.Timer(6.0, lambda: os.kill(os.getpid(), signal.SIGINT))
    stopper.start()
    try:
        code = main(["sim", "--config", str(config)])
    finally:
        stopper.cancel()
        fake.close()
    assert code == 0
    assert fake.tally.fused > 0  # the daemon's poses of the rendered frames reached the autopilot
    assert capsys.readouterr().out == ""  # no mission: no report


def test_a_mission_without_the_mavlink_output_is_refused_before_anything_opens(tmp_path, capsys):
    config = tmp_path / "sim.toml"
    text = CONFIG.format(mount="down", gcs="udpout:127.0.0.1:9", daemon="udpout:127.0.0.1:9", target=SQUARE, below=0.4)
    config.write_text(text.split("[output.mavlink]")[0] + '[logging]\nlevel = "WARNING"\n')
    assert main(["sim", "--config", str(config), "--fly", "hold", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"pose-daemon: error: {config}: sim --fly needs an [output.mavlink] table (the feed the autopilot flies on)"
    ]


def test_a_px4_refusal_longer_than_one_statustext_is_reported_whole(tmp_path):
    """PX4 sends a text over 50 characters in chunks of one id (a real PX4 SIH: "Arming denied:
    Resolve system health failures firs" then "t<TAB>"): the reason is the whole text."""
    text = "Arming denied: Resolve system health failures first\t"
    fake = FakeSitl("px4", prearm_failure=text)
    try:
        code, summary = _sim(tmp_path, fake, "--fly", "hold", "--ekf-wait-s", "20", "--arm-wait-s", "0")
    finally:
        fake.close()
    assert code == 1 and summary["armed"] is False
    assert summary["reasons"] == ["not armed in 0 s (1 try): Arming denied: Resolve system health failures first"]
    assert "Arming denied: Resolve system health failures first" in summary["statustext"]
