"""docs/ARCHITECTURE.md, the code map, is held true: its tree names every module under
pose_daemon/ once and nothing else, and every ``file.py`` or ``file.py:Name.attr`` it names
exists (the function or class defined in that file)."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import Dict, List, Set

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "pose_daemon"
MAP = ROOT / "docs" / "ARCHITECTURE.md"
# `detect/square.py` or `detect/square.py:SquareFinder.search`: paths relative to pose_daemon/
# (tests/... and scripts/... relative to the repository).
REFERENCE = re.compile(r"`((?:[a-z_0-9]+/)*[a-z_0-9]+\.py)(?::([A-Za-z_][A-Za-z_0-9.]*))?`")


def _text() -> str:
    return MAP.read_text(encoding="utf-8")


def _tree_entries(text: str) -> List[str]:
    """Paths (relative to pose_daemon/) of the files in the tree block, from its indentation."""
    block = re.search(r"^```text\npose_daemon/\n(.*?)^```", text, re.S | re.M)
    assert block, "docs/ARCHITECTURE.md has no ```text block starting with pose_daemon/"
    stack: List[str] = []
    files = []
    for line in block.group(1).splitlines():
        indent = len(line) - len(line.lstrip(" "))
        assert indent % 2 == 0 and indent >= 2, f"tree line not indented by a multiple of 2: {line!r}"
        depth = indent // 2 - 1
        name = line.split()[0]
        assert depth <= len(stack), f"tree line deeper than its folder: {line!r}"
        del stack[depth:]
        if name.endswith("/"):
            stack.append(name)
        else:
            assert len(line.split()) > 1, f"tree line without a description: {line!r}"
            files.append("".join(stack) + name)
    return files


def _modules() -> Set[str]:
    return {p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py")}


def _defined(path: Path) -> Dict[str, Set[str]]:
    """Top-level names of a module -> the names defined in their bodies (methods of a class)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: Dict[str, Set[str]] = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out[node.name] = {
                n.name
                for n in getattr(node, "body", [])
                if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
            }
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                if isinstance(t, ast.Name):
                    out[t.id] = set()
    return out


def test_the_tree_names_every_module_once():
    entries = _tree_entries(_text())
    modules = [e for e in entries if e.endswith(".py")]
    repeated = sorted({m for m in modules if modules.count(m) > 1})
    assert not repeated, f"named twice in the tree: {repeated}"
    missing = sorted(_modules() - set(modules))
    assert not missing, f"modules missing from docs/ARCHITECTURE.md's tree: {missing}"
    gone = sorted(e for e in entries if not (PACKAGE / e).is_file())
    assert not gone, f"docs/ARCHITECTURE.md's tree names files that do not exist: {gone}"


def test_every_file_and_function_the_map_names_exists():
    text = _text()
    refs = REFERENCE.findall(text)
    assert len(refs) > 20, "the map names few modules: is the reference pattern out of date?"
    problems = []
    for module, symbol in refs:
        # tests/ and scripts/ are named from the repository's root, the rest from pose_daemon/.
        path = (ROOT if module.split("/")[0] in ("tests", "scripts") else PACKAGE) / module
        if not path.is_file():
            problems.append(f"{module}: no such module")
            continue
        if not symbol:
            continue
        head, _, member = symbol.partition(".")
        names = _defined(path)
        if head not in names:
            problems.append(f"{module}:{symbol}: {module} defines no {head}")
        elif member and member not in names[head]:
            problems.append(f"{module}:{symbol}: {head} has no {member}")
    assert not problems, "docs/ARCHITECTURE.md names what does not exist:\n" + "\n".join(problems)


def test_the_readme_links_the_map():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "(docs/ARCHITECTURE.md)" in readme
