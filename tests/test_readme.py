"""The README stays true to the code: its quick start and CI command (its links and commands:
tests/test_docs.py; the config reference, docs/config.md, is kept there too)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_quick_start_is_two_commands_and_ci_runs_the_test_one():
    quick = README.split("## Quick start", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    commands = [line.split("#")[0].strip() for line in quick.strip().splitlines()]
    assert commands == ["scripts/demo.sh", "scripts/test.sh"]
    ci = (ROOT / ".ci" / "run").read_text()
    # The README's command on the whole suite: options only where its files go, no selection.
    runs = re.findall(r"^scripts/test\.sh\b(.*)$", ci, re.M)
    whole = [r for r in runs if re.fullmatch(r"( -p no:cacheprovider| --basetemp \S+)*( >\S+ 2>&1 &)?", r)]
    assert whole, runs
    for script in commands:
        assert (ROOT / script).stat().st_mode & 0o111, f"{script} is not executable"
