"""The command line as a whole: every subcommand is registered, errors are one line and exit 2."""

from __future__ import annotations

import subprocess
import sys

import pytest

from pose_daemon.cli import COMMANDS, main


@pytest.mark.parametrize("name", COMMANDS)
def test_every_subcommand_has_help(name, capsys):
    with pytest.raises(SystemExit) as exc:
        main([name.replace("_", "-"), "--help"])
    assert exc.value.code == 0
    assert "usage: pose-daemon" in capsys.readouterr().out


def test_no_command_prints_help_and_exits_2(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().err


def test_unknown_command_is_one_line_and_exit_2():
    res = subprocess.run([sys.executable, "-m", "pose_daemon", "fly"], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert lines[-1].startswith("pose-daemon: error: argument COMMAND: invalid choice: 'fly'")
    assert "Traceback" not in res.stderr


def test_missing_config_file_is_one_line_and_exit_2(tmp_path):
    res = subprocess.run([sys.executable, "-m", "pose_daemon", "run", "--config",
                          str(tmp_path / "nope.toml")], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "nope.toml" in res.stderr


def test_argparse_only_in_the_command_line():
    """cli.py's rule: argparse lives in cli.py and commands/ alone; tools/ and the library
    are plain functions."""
    import pathlib
    import re

    package = pathlib.Path(__file__).resolve().parent.parent / "pose_daemon"
    offenders = []
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package).as_posix()
        if rel == "cli.py" or rel.startswith("commands/"):
            continue
        if re.search(r"^\s*(import argparse|from argparse import)", path.read_text(encoding="utf-8"), re.M):
            offenders.append(rel)
    assert offenders == []
