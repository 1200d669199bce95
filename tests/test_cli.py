"""The command line as a whole: every subcommand is registered, errors are one line and exit 2."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from pose_daemon.cli import COMMANDS, main


@pytest.mark.parametrize("name", COMMANDS)
def test_every_subcommand_has_help(name, capsys):
    with pytest.raises(SystemExit) as exc:
        main([name.replace("_", "-"), "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "usage: pose-daemon" in out
    assert "``" not in out, "docstring markup leaked into --help"


def test_no_command_prints_help_and_exits_2(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().err


def test_unknown_command_is_one_line_and_exit_2():
    res = subprocess.run([sys.executable, "-m", "pose_daemon", "fly"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert lines[-1].startswith("pose-daemon: error: argument COMMAND: invalid choice: 'fly'")
    assert "Traceback" not in res.stderr


def test_missing_config_file_is_one_line_and_exit_2(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "pose_daemon", "run", "--config", str(tmp_path / "nope.toml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "nope.toml" in res.stderr


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pose_daemon", *args], capture_output=True, text=True, timeout=60)


CONFIG_COMMANDS = [("check-config",), ("run", "--config")]


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
@pytest.mark.parametrize(
    "text",
    [
        "a = " + "[" * 400 + "\n",
        "a = " + "[" * 1000 + "]" * 1000 + "\n",
        "a = " + "{b = " * 1000 + "\n",
        "[camera]\ndist = " + "[" * 450 + "]" * 450 + "\n",
    ],
)
def test_deeply_nested_toml_is_one_line_and_exit_2(tmp_path, command, text):
    # The TOML reader recurses once per level, and so did the error message's rendering of
    # the value: a RecursionError must not become a traceback.
    path = tmp_path / "deep.toml"
    path.write_text(text)
    res = _cli(*command, str(path))
    assert res.returncode == 2, res.stderr
    assert res.stderr.startswith(f"pose-daemon: error: {path}: ")
    assert res.stderr.count("\n") == 1 and res.stdout == ""
    if text.startswith("a = "):
        assert "invalid TOML: " in res.stderr


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
def test_a_fifo_or_folder_as_config_is_refused_without_reading_it(tmp_path, command):
    # Reading a FIFO with no writer would block for ever (check-config in ExecStartPre too).
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    res = _cli(*command, str(fifo))
    assert (res.returncode, res.stdout, res.stderr) == (
        2,
        "",
        f"pose-daemon: error: {fifo}: cannot read config: not a regular file (a FIFO)\n",
    )
    res = _cli(*command, str(tmp_path))
    assert (res.returncode, res.stdout, res.stderr) == (
        2,
        "",
        f"pose-daemon: error: {tmp_path}: cannot read config: not a regular file (a directory)\n",
    )


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


def _subcommands(parser, name="pose-daemon"):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for sub_name, sub in action.choices.items():
                yield f"{name} {sub_name}", sub, helps.get(sub_name)
                yield from _subcommands(sub, f"{name} {sub_name}")


def test_every_command_has_a_whole_description():
    """Each command's --help says what it does in whole sentences: none is missing (map build and
    map check had none) and none is a docstring's first line cut mid-sentence (replay, record);
    a description that is the command's one-line help (bench's) is whole as it is."""
    from pose_daemon.cli import build_parser

    seen = list(_subcommands(build_parser()))
    assert {"pose-daemon replay", "pose-daemon record", "pose-daemon map build", "pose-daemon map check"} <= {
        n for n, _p, _h in seen
    }
    for name, parser, help_text in seen:
        text = (parser.description or "").strip()
        assert text, f"{name}: no description"
        assert text.endswith((".", ")")) or text == help_text, f"{name}: {text!r}"
