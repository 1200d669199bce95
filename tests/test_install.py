"""The systemd unit and the Raspberry Pi installer (--dry-run), as CI can check them."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "pose-daemon.service"
INSTALL = ROOT / "scripts" / "install-pi.sh"


def _unit():
    # Repeated keys (DeviceAllow=, SystemCallFilter=) add up in systemd: keep them all.
    values = {}
    section = None
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        values.setdefault((section, key), []).append(value)
    return values


def test_unit_is_notify_with_watchdog_restart_and_unprivileged_user():
    u = _unit()
    assert u[("Service", "Type")] == ["notify"]
    assert u[("Service", "NotifyAccess")] == ["main"]
    assert float(u[("Service", "WatchdogSec")][0]) >= 2
    assert u[("Service", "Restart")] == ["on-failure"] and float(u[("Service", "RestartSec")][0]) > 0
    assert u[("Service", "User")] == ["pose-daemon"]
    assert u[("Service", "SupplementaryGroups")] == ["video dialout"]
    assert u[("Service", "CapabilityBoundingSet")] == [""]
    for key in (
        "NoNewPrivileges",
        "ProtectHome",
        "PrivateTmp",
        "ProtectKernelTunables",
        "RestrictSUIDSGID",
        "LockPersonality",
    ):
        assert u[("Service", key)] == ["yes"], key
    assert u[("Service", "ProtectSystem")] == ["strict"]
    assert u[("Service", "DevicePolicy")] == ["closed"]
    # The config folder (with the signing key's file in it) is not world-listable.
    assert u[("Service", "ConfigurationDirectory")] == ["pose-daemon"]
    assert u[("Service", "ConfigurationDirectoryMode")] == ["0750"]
    allowed = u[("Service", "DeviceAllow")]
    assert "char-video4linux rw" in allowed and "char-ttyAMA rw" in allowed and "char-ttyUSB rw" in allowed
    assert "AF_PACKET" not in u[("Service", "RestrictAddressFamilies")][0]
    start = u[("Service", "ExecStart")][0]
    assert start.endswith("pose-daemon run --config /etc/pose-daemon/pose-daemon.toml")
    assert u[("Install", "WantedBy")] == ["multi-user.target"]


@pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze missing: scripts/check-unit.sh installs it in CI"
)
def test_unit_exposure_score_is_at_most_2_5():
    res = subprocess.run([str(ROOT / "scripts" / "check-unit.sh")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    score = float(res.stdout.split("exposure ")[1].split()[0])
    assert score <= 2.5


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze missing")
def test_check_unit_fails_on_a_weak_unit(tmp_path):
    weak = tmp_path / "weak.service"
    weak.write_text("[Service]\nType=notify\nExecStart=/bin/true\n")
    res = subprocess.run(
        [str(ROOT / "scripts" / "check-unit.sh"), str(weak)], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 1
    assert "is worse than 2.5" in res.stderr


def _dry_run(*args: str) -> str:
    res = subprocess.run(["bash", str(INSTALL), "--dry-run", *args], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return res.stdout


def _commands(out: str):
    return [line[len("would run: ") :] for line in out.splitlines() if line.startswith("would run: ")]


def test_install_dry_run_lists_every_step_and_changes_nothing(tmp_path):
    out = _dry_run("--root", str(tmp_path), "--prefix", str(tmp_path / "opt"))
    cmds = _commands(out)
    apt = next(c for c in cmds if "apt-get install" in c)
    for pkg in ("python3-picamera2", "python3-opencv", "python3-numpy", "python3-serial"):
        assert pkg in apt.split()
    assert f"python3 -m venv --system-site-packages {tmp_path}/opt/venv" in cmds
    pips = [c for c in cmds if " -m pip install " in c]
    assert len(pips) == 2 and all("--no-deps" in c for c in pips)
    assert pips[0].endswith(" pymavlink") and pips[1].endswith(f" {ROOT}")
    assert any(c.startswith("useradd --system --user-group") and c.endswith(" pose-daemon") for c in cmds)
    assert "usermod -a -G video\\,dialout pose-daemon" in cmds
    assert (
        f"install -m 0640 -o root -g pose-daemon {ROOT}/config/pose-daemon.toml "
        f"{tmp_path}/etc/pose-daemon/pose-daemon.toml"
    ) in cmds
    assert (
        f"install -m 0644 {ROOT}/systemd/pose-daemon.service {tmp_path}/etc/systemd/system/pose-daemon.service"
    ) in cmds
    assert cmds[-3:] == [
        "systemctl daemon-reload",
        "systemctl enable pose-daemon.service",
        "systemctl restart pose-daemon.service",
    ]
    assert list(tmp_path.iterdir()) == []  # a dry run writes nothing


def test_install_frees_the_serial_console_and_is_idempotent(tmp_path):
    boot = tmp_path / "boot" / "firmware"
    boot.mkdir(parents=True)
    cmdline = boot / "cmdline.txt"
    cmdline.write_text("console=serial0,115200 console=tty1 root=PARTUUID=abc rootfstype=ext4 rootwait\n")
    config_txt = boot / "config.txt"
    config_txt.write_text("dtparam=audio=on\n")
    (tmp_path / "etc" / "pose-daemon").mkdir(parents=True)
    (tmp_path / "etc" / "pose-daemon" / "pose-daemon.toml").write_text("# edited by the user\n")
    out = _dry_run("--root", str(tmp_path), "--no-start")
    assert "keeping the existing" in out
    assert "systemctl restart pose-daemon.service" not in _commands(out)
    edits = [c for c in _commands(out) if c.startswith("sed -i")]
    assert len(edits) == 2
    for c in edits:  # the printed commands are exact: run them as printed
        subprocess.run(["bash", "-c", c], check=True)
    assert cmdline.read_text() == "console=tty1 root=PARTUUID=abc rootfstype=ext4 rootwait\n"
    assert config_txt.read_text() == "dtparam=audio=on\nenable_uart=1\n"
    again = _dry_run("--root", str(tmp_path), "--no-start")
    assert not [c for c in _commands(again) if c.startswith("sed -i")]
    assert f"no serial console in {cmdline}" in again and "UART already enabled" in again
    assert not [c for c in _commands(_dry_run("--root", str(tmp_path), "--no-serial")) if c.startswith("sed")]


def _service_group() -> None:
    """The installer's group pose-daemon, as useradd --user-group makes it (kept afterwards:
    removing it could pull it from under a test running beside this one)."""
    subprocess.run(["groupadd", "-f", "--system", "pose-daemon"], check=True, capture_output=True)


@pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("groupadd") is None,
    reason="sets file owners: needs root (CI has it) and groupadd",
)
def test_installed_config_is_readable_by_the_service_group_only(tmp_path):
    # The config may hold the MAVLink signing key: 0640 root:pose-daemon in a 0750 folder.
    import grp
    import stat

    _service_group()
    gid = grp.getgrnam("pose-daemon").gr_gid
    etc = tmp_path / "etc" / "pose-daemon"
    config = etc / "pose-daemon.toml"

    def install_config_as_printed() -> str:
        out = _dry_run("--root", str(tmp_path), "--no-serial", "--no-start")
        cmds = [c for c in _commands(out) if str(etc) in c]
        assert cmds, out
        for c in cmds:  # the printed commands are exact: run them as printed
            subprocess.run(["bash", "-c", c], check=True)
        return out

    install_config_as_printed()
    for path, mode in ((etc, 0o750), (config, 0o640)):
        st = path.stat()
        assert (stat.S_IMODE(st.st_mode), st.st_uid, st.st_gid) == (mode, 0, gid), path
    assert config.read_text() == (ROOT / "config" / "pose-daemon.toml").read_text()
    # An older install left both world-readable: running the installer again closes them
    # and keeps the user's edits.
    config.write_text("# edited by the user\n")
    os.chmod(config, 0o644)
    os.chown(config, 0, 0)
    os.chmod(etc, 0o755)
    assert "keeping the existing" in install_config_as_printed()
    for path, mode in ((etc, 0o750), (config, 0o640)):
        st = path.stat()
        assert (stat.S_IMODE(st.st_mode), st.st_uid, st.st_gid) == (mode, 0, gid), path
    assert config.read_text() == "# edited by the user\n"


def test_install_needs_root_or_dry_run():
    cmd = ["bash", str(INSTALL)]
    if os.geteuid() == 0:
        # As root (CI), run it as an unprivileged user: the check is what a normal user meets.
        if not shutil.which("setpriv"):
            pytest.skip("running as root and setpriv (util-linux) is missing")
        cmd = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", *cmd]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    assert res.returncode == 2 and "run as root" in res.stderr


def test_install_rejects_unknown_arguments():
    res = subprocess.run(["bash", str(INSTALL), "--frobnicate"], capture_output=True, text=True, timeout=30)
    assert res.returncode == 2
    assert res.stderr == "install-pi.sh: unknown argument --frobnicate (see --help)\n"


def test_venv_sh_keeps_one_stamp_per_extras_set(tmp_path):
    """demo.sh (venv.sh) and test.sh (venv.sh --test) one after the other install once each,
    not each time they alternate; a changed pyproject.toml installs again. venv.sh runs on a
    copy of the tree whose .venv/bin/python only notes what it was asked to do."""
    (tmp_path / "scripts").mkdir()
    shutil.copy(ROOT / "scripts" / "venv.sh", tmp_path / "scripts" / "venv.sh")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    log = tmp_path / "pip.log"
    python = tmp_path / ".venv" / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text(f'#!/bin/sh\necho "$*" >> "{log}"\n')
    python.chmod(0o755)

    def installs(*args) -> int:
        before = log.read_text().count("install") if log.exists() else 0
        res = subprocess.run(
            ["bash", str(tmp_path / "scripts" / "venv.sh"), *args], capture_output=True, text=True, timeout=60
        )
        assert res.returncode == 0 and res.stdout == ".venv\n", res.stderr
        return (log.read_text().count("install") if log.exists() else 0) - before

    assert installs() > 0  # the first demo
    assert installs("--test") > 0  # the first tests
    assert [installs(), installs("--test"), installs(), installs("--test")] == [0, 0, 0, 0]
    with open(tmp_path / "pyproject.toml", "a") as fh:
        fh.write("\n# changed\n")
    assert installs() > 0 and installs() == 0
    assert installs("--test") > 0 and installs() == 0
