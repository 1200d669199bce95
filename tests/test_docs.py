"""The documentation works: README.md and every page under docs/.

Every relative link resolves (the file exists; a ``#anchor`` is a heading of the target, slugged
as GitHub does), every ``pose-daemon ...`` command shown names a real subcommand with options
it has (parsed against the real argument parser, never run), every path of the tree named
(``scripts/...``, ``tests/...``, ``pose_daemon/...``) exists, every page is linked from the
README and links back to it, and docs/config.md is what the config schema says.
"""

from __future__ import annotations

import argparse
import re
from functools import cache
from pathlib import Path
from typing import Dict, Iterator, List, Set, Tuple

import pytest

from pose_daemon.config.reference import REGENERATE, page

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md"] + sorted(DOCS.rglob("*.md"))
# The code map is kept by tests/test_architecture.py and says its own job in its first lines.
NO_BACK_LINK = {DOCS / "ARCHITECTURE.md"}
MAX_PAGE_LINES = 600
README_MAX_LINES = 300

FENCE = re.compile(r"^[ \t]*(`{3,}|~{3,})([^\n]*)\n(.*?)^[ \t]*\1[ \t]*$", re.S | re.M)
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
COMMAND_BLOCKS = {"sh", "console", "bash", "shell"}
# `pose-daemon` where a shell would run it: a line's start (after a prompt or sudo), or after a
# pipe, `;`, `&&` or `$(`.
COMMAND = re.compile(r"(?:^|[|;&(]\s*)(?:\$\s+)?(?:sudo\s+)?pose-daemon[ \t]+([^\n]*)")
TREE_PATH = re.compile(
    r"(?<![\w/.~-])((?:scripts|tests|pose_daemon|systemd|docs)/[\w./-]*\w|config/[\w-]+\.toml)(?![*\w])"
)


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _prose(text: str) -> str:
    """The text without fenced blocks and code spans (where links are not links)."""
    return CODE_SPAN.sub("", FENCE.sub("", text))


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: link and code markup dropped, lower case, punctuation
    other than - and _ removed, spaces made hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@cache
def _anchors(path: Path) -> Set[str]:
    anchors: Set[str] = set()
    seen: Dict[str, int] = {}
    for line in FENCE.sub("", _text(path)).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = _slug(m.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def _links(path: Path) -> Iterator[str]:
    for m in LINK.finditer(_prose(_text(path))):
        yield m.group(1)


def test_the_slug_is_githubs() -> None:
    assert _slug("Live preview (`[preview]`)") == "live-preview-preview"
    assert _slug("The Pi 2's own software stack, emulated: `scripts/pi-stack.sh`") == (
        "the-pi-2s-own-software-stack-emulated-scriptspi-stacksh"
    )
    assert _slug("Blurred ArUco markers: the whole pattern fitted (`blur_model`)") == (
        "blurred-aruco-markers-the-whole-pattern-fitted-blur_model"
    )
    assert _slug("Surveying a map: `pose-daemon map build`") == "surveying-a-map-pose-daemon-map-build"


@pytest.mark.parametrize("path", PAGES, ids=_rel)
def test_every_relative_link_resolves(path: Path) -> None:
    broken = []
    for target in _links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto: ...: not ours to check
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            broken.append(f"{target}: no such file {dest}")
            continue
        if anchor:
            if dest.suffix != ".md":
                broken.append(f"{target}: an anchor into a file that is not Markdown")
            elif anchor not in _anchors(dest):
                broken.append(f"{target}: no heading #{anchor} in {_rel(dest)}")
    assert not broken, f"{_rel(path)} has broken links:\n" + "\n".join(broken)


def test_the_readme_links_every_page_and_every_page_links_back() -> None:
    readme = ROOT / "README.md"
    linked = {(ROOT / t.partition("#")[0]).resolve() for t in _links(readme) if not t.startswith("#")}
    unlinked = [_rel(p) for p in PAGES[1:] if p.resolve() not in linked]
    assert not unlinked, f"README.md links no {unlinked}: the README is where every page is found"
    no_way_back = [
        _rel(p)
        for p in PAGES[1:]
        if p not in NO_BACK_LINK and not any((p.parent / t.partition("#")[0]).resolve() == readme for t in _links(p))
    ]
    assert not no_way_back, f"pages without a link back to README.md: {no_way_back}"


def test_pages_stay_readable_in_length() -> None:
    lines = {_rel(p): len(_text(p).splitlines()) for p in PAGES}
    assert lines["README.md"] <= README_MAX_LINES, f"README.md has {lines['README.md']} lines: move detail to docs/"
    long = {k: v for k, v in lines.items() if v > MAX_PAGE_LINES}
    assert not long, f"pages over {MAX_PAGE_LINES} lines (split them, one job per page): {long}"


@pytest.mark.parametrize("path", PAGES, ids=_rel)
def test_every_table_row_has_its_headers_cells(path: Path) -> None:
    """A ``|`` inside a cell must be escaped (``\\|``), even in code: GitHub splits the cell there."""
    bad = []
    rows: List[Tuple[int, str]] = []
    lines = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), _text(path)).splitlines() + [""]
    for n, line in enumerate(lines, 1):
        if line.startswith("|"):
            rows.append((n, line))
            continue
        if rows:
            widths = [(k, len(re.findall(r"(?<!\\)\|", row.strip().strip("|"))) + 1) for k, row in rows]
            bad += [f"line {k}: {w} cells, its header {widths[0][1]}" for k, w in widths if w != widths[0][1]]
            rows = []
    assert not bad, f"{_rel(path)}: table rows with another number of cells than their header:\n" + "\n".join(bad)


@cache
def _parser() -> argparse.ArgumentParser:
    from pose_daemon.cli import build_parser

    return build_parser()


def _subparsers(parser: argparse.ArgumentParser) -> Dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _commands() -> Iterator[Tuple[str, str]]:
    """(page, the words after `pose-daemon`) of every command shown: lines of sh/console/bash
    blocks (backslash continuations joined, comments and redirections cut), and code spans in
    the prose that start with `pose-daemon `."""
    for path in PAGES:
        text = _text(path)
        for m in FENCE.finditer(text):
            if m.group(2).strip().lower() not in COMMAND_BLOCKS:
                continue
            for line in m.group(3).replace("\\\n", " ").splitlines():
                for c in COMMAND.finditer(line.strip()):
                    yield _rel(path), c.group(1)
        for m in CODE_SPAN.finditer(FENCE.sub("", text)):
            if m.group(2).startswith("pose-daemon "):
                yield _rel(path), m.group(2)[len("pose-daemon ") :]


def _check_command(words: str) -> List[str]:
    words = re.split(r"\s#|\s>|\s2>|\s\|\s(?![^\[]*\])", words)[0]  # comment, redirection, pipe on
    tokens = words.split()
    parser = _parser()
    names: List[str] = []
    while tokens and _subparsers(parser):
        choices = _subparsers(parser)
        word = tokens.pop(0)
        if word == "...":  # `pose-daemon bench ...`: any of them
            return []
        alternatives = [w for w in re.split(r"[{},|]", word) if w]
        unknown = [w for w in alternatives if w not in choices]
        if not alternatives or unknown:
            return [f"pose-daemon {' '.join(names)} {word}: no such subcommand (one of {', '.join(choices)})"]
        names.append(alternatives[0])
        parser = choices[alternatives[0]]
    known = {o for a in parser._actions for o in a.option_strings}
    problems = []
    for token in tokens:
        for option in re.findall(r"(?:^|[\[(|])(--?[A-Za-z][\w-]*)", token):
            if option not in known:
                problems.append(f"pose-daemon {' '.join(names)}: no option {option}")
    return problems


def test_every_pose_daemon_command_shown_parses() -> None:
    commands = list(_commands())
    assert len(commands) > 50, f"found only {len(commands)} commands in the docs: is the scan broken?"
    shown = {c[0] for c in commands}
    assert {"README.md", "docs/markers.md", "docs/ardupilot.md"} <= shown, shown
    problems = [
        f"{where}: {p}  (in: pose-daemon {words.strip()})" for where, words in commands for p in _check_command(words)
    ]
    assert not problems, "commands in the docs that the CLI does not take:\n" + "\n".join(problems)


def test_the_command_check_can_fail() -> None:
    assert _check_command("run --config x.toml") == []
    assert _check_command("bench {estimator,detector} --json") == []
    assert _check_command("record [--config FILE] --out DIR [--seconds N | --frames N] [--quiet]") == []
    assert _check_command("map build walk --dictionary D --size 0.2 --out m.toml") == []
    assert _check_command("fly --now")[0].startswith("pose-daemon  fly: no such subcommand")
    assert _check_command("run --confg x.toml") == ["pose-daemon run: no option --confg"]
    assert _check_command("bench everything") and _check_command("map build --anchr 0")


def test_every_path_of_the_tree_named_exists() -> None:
    missing = []
    for path in PAGES:
        for m in TREE_PATH.finditer(_text(path)):
            named = m.group(1)
            if not (ROOT / named).exists():
                missing.append(f"{_rel(path)}: {named}")
    assert not missing, "the docs name files that do not exist:\n" + "\n".join(sorted(set(missing)))


def test_the_config_reference_page_is_the_schemas() -> None:
    assert (DOCS / "config.md").read_text(encoding="utf-8") == page(), (
        f"docs/config.md differs from the config schema: regenerate it with `{REGENERATE}`"
    )


def test_every_mavproxy_command_shown_says_where_its_log_goes() -> None:
    """MAVProxy writes mav.tlog (and .raw) into the current folder unless told otherwise: each
    mavproxy.py command the docs or scripts give a user names its --logfile or has --no-state,
    so that watching the demo leaves no log in the repository."""
    shown = []
    for path in PAGES + sorted((ROOT / "scripts").glob("*.sh")):
        for line in path.read_text(encoding="utf-8").splitlines():
            for cmd in re.findall(r"mavproxy\.py [^`\n]*", line):
                shown.append((_rel(path), cmd))
    assert len(shown) >= 3, shown
    bare = [(p, c) for p, c in shown if "--logfile" not in c and "--no-state" not in c]
    assert not bare, bare
