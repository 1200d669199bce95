"""The README stays true to the code: its config reference, quick start and CI command."""

from __future__ import annotations

import re
from pathlib import Path

from pose_daemon.config import reference

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_config_reference_lists_every_key_with_its_default_and_bounds():
    for table, key, default, expectation, meaning in reference():
        row = f"| `{table}` | `{key}` | `{default}` | {expectation} | {meaning} |"
        assert row in README, f"README config reference is out of date for {table} {key}:\n{row}"


def test_quick_start_is_two_commands_and_ci_runs_the_test_one():
    quick = README.split("## Quick start", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    commands = [line.split("#")[0].strip() for line in quick.strip().splitlines()]
    assert commands == ["scripts/demo.sh", "scripts/test.sh"]
    ci = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"^scripts/test\.sh$", ci, re.M)
    for script in commands:
        assert (ROOT / script).stat().st_mode & 0o111, f"{script} is not executable"
