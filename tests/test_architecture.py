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


def _floors(text: str) -> Dict[str, int]:
    """The Floors table: ``x.py`` or ``x/`` (relative to pose_daemon/) -> its floor."""
    section = text.split("## Floors", 1)[1].split("\n## ", 1)[0]
    floors: Dict[str, int] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or not cells[0].isdigit():
            continue
        for entry in re.findall(r"`([^`]+)`", cells[1]):
            assert entry not in floors, f"{entry} is on two floors of the Floors table"
            floors[entry] = int(cells[0])
    return floors


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(["pose_daemon", *parts])


def _imports() -> Dict[str, Set[str]]:
    """Every pose_daemon module -> the pose_daemon modules it imports anywhere in its text
    (top-level, in functions, under TYPE_CHECKING), ``from package import module`` resolved."""
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: Dict[str, Set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found: Set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target not in modules:
                    continue
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    found.add(sub if sub in modules else target)
        found.discard(name)
        graph[name] = found
    return graph


def _floor_of(module: str, floors: Dict[str, int]) -> int:
    rel = module.split(".")[1:]
    candidates = [f"{rel[0]}/"] if len(rel) > 1 else []
    candidates.append(f"{rel[0]}.py" if rel else "__init__.py")
    if len(rel) == 1 and (PACKAGE / rel[0]).is_dir():
        candidates = [f"{rel[0]}/"]
    for c in candidates:
        if c in floors:
            return floors[c]
    raise AssertionError(f"{module} is on no floor of docs/ARCHITECTURE.md's Floors table")


def test_every_import_runs_down_the_floors():
    floors = _floors(_text())
    assert len(floors) > 10, "the Floors table lists few rooms: has its layout changed?"
    graph = _imports()
    up = []
    for module, targets in sorted(graph.items()):
        here = _floor_of(module, floors)
        for target in sorted(targets):
            if target == "pose_daemon":
                continue  # the package's face is imported by Python before any module of it
            there = _floor_of(target, floors)
            if there > here:
                up.append(f"{module} (floor {here}) imports {target} (floor {there})")
    assert not up, "imports that run up the floors:\n" + "\n".join(up)


def test_no_modules_import_each_other_in_a_circle():
    graph = _imports()
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    circles: List[List[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not circles, f"modules that import each other in a circle: {circles}"
