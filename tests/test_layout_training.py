"""The layout of the training side (docs/design.md §11): libraries below scripts, read from the source with `ast`.

``models`` (PyTorch training), ``export`` (ONNX) and ``benchmarks`` (scripts a user reruns, and the studies) import
in one direction only: ``benchmarks`` -> ``export`` -> ``models`` (-> the runtime). No module imports itself back
through others, no script imports another script, nothing edits ``sys.path``, and no private name (``_x``) is
imported from another module. Every import counts, also one inside a function: a lazy import hides a circle from
the interpreter, not from the reader.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("models", "export", "benchmarks")
# The one allowed sys.path edit: the Blender worker runs inside Blender's own Python, which has neither the
# repository nor its installed packages on its path.
SYS_PATH_ALLOWED = {"models/data/render/cycles_worker.py"}
# Which top-level packages each one may import (the runtime, refiner_rt, is below all three).
ALLOWED = {"models": {"models", "refiner_rt"},
           "export": {"export", "models", "refiner_rt"},
           "benchmarks": {"benchmarks", "export", "models", "refiner_rt"}}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def source_files(*packages: str) -> dict[str, Path]:
    """``{module name: file}`` of every .py file under the given top-level folders."""
    return {module_name(p): p for pkg in packages for p in sorted((ROOT / pkg).rglob("*.py"))}


def imports(path: Path, name: str) -> list[tuple[str, list[str], int]]:
    """Every import of a file, at any depth: ``(module, [names imported from it], line)``; relative imports resolved."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name, [], node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            out.append((module, [alias.name for alias in node.names], node.lineno))
    return out


def resolve(module: str, names: list[str], known: dict[str, Path]) -> list[str]:
    """The project modules an import statement loads: ``from a.b import c`` is ``a.b.c`` when that is a module,
    else ``a.b``."""
    if not names:
        return [module] if module in known else []
    out = []
    for n in names:
        if f"{module}.{n}" in known:
            out.append(f"{module}.{n}")
        elif module in known:
            out.append(module)
    return out


def graph(known: dict[str, Path]) -> dict[str, set[str]]:
    edges = {}
    for name, path in known.items():
        targets = set()
        for module, names, _ in imports(path, name):
            targets.update(t for t in resolve(module, names, known) if t != name)
        edges[name] = targets
    return edges


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import circle among the modules (a list that starts and ends with the same module), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(edges):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def is_script(name: str, path: Path) -> bool:
    """A benchmark or study script: a module of ``benchmarks`` with a ``__main__`` block."""
    return name.startswith("benchmarks.") and "__name__ == \"__main__\"" in path.read_text()


KNOWN = source_files(*PACKAGES)


def test_the_scan_sees_the_packages():
    """A guard on the scan itself: it finds the modules it is meant to check and their imports."""
    assert {"models.train.recipe", "export.onnx_export", "benchmarks.report"} <= set(KNOWN)
    assert "models.data.objects" in graph(KNOWN)["models.train.recipe"]


def test_no_import_cycle():
    cycle = find_cycle(graph(KNOWN))
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_no_upward_import():
    """models imports neither export nor benchmarks; export does not import benchmarks; no library imports a
    script and no script imports another script."""
    bad = []
    for name, path in KNOWN.items():
        top = name.split(".")[0]
        for module, names, line in imports(path, name):
            target_top = (module or "").split(".")[0]
            if target_top in PACKAGES and target_top not in ALLOWED[top]:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {top} imports {module}")
            for target in resolve(module, names, KNOWN):
                if target.startswith("benchmarks") and (KNOWN[target].name != "__init__.py") and (
                        is_script(target, KNOWN[target])):
                    bad.append(f"{path.relative_to(ROOT)}:{line}: imports the script {target}")
    assert not bad, "\n".join(bad)


def test_no_script_imported_by_its_bare_name():
    """``import tracking`` or ``from pretrained import ...`` works only with a script's folder on ``sys.path``: every
    import of the project's code names its package."""
    bare = {p.stem for p in (ROOT / "benchmarks").rglob("*.py")} | {p.stem for p in (ROOT / "tests").glob("*.py")}
    bare -= {"__init__"}
    bad = []
    for folder in (*PACKAGES, "tests"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for module, _, line in imports(path, module_name(path)):
                if module and module.split(".")[0] in bare:
                    bad.append(f"{path.relative_to(ROOT)}:{line}: import {module}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("folder", [*PACKAGES, "tests"])
def test_no_sys_path_edit(folder):
    bad = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel in SYS_PATH_ALLOWED or rel == "tests/test_layout_training.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=rel)):
            if isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name) and (
                    node.value.id == "sys"):
                bad.append(f"{rel}:{node.lineno}: sys.path")
    assert not bad, "run scripts as `python -m benchmarks.NAME` from the repository root instead:\n" + "\n".join(bad)


def test_the_one_allowed_sys_path_edit_says_why():
    for rel in SYS_PATH_ALLOWED:
        text = (ROOT / rel).read_text()
        assert "sys.path" in text and "Blender" in text[: text.index("sys.path")], rel


def test_no_private_name_imported_across_modules():
    """``from a import _x`` (a name private to ``a``) in models, export and benchmarks."""
    bad = []
    for name, path in KNOWN.items():
        for module, names, line in imports(path, name):
            if module and module.split(".")[0] in (*PACKAGES, "refiner_rt"):
                private = [n for n in names if n.startswith("_") and not n.startswith("__")]
                if private and module != name:
                    bad.append(f"{path.relative_to(ROOT)}:{line}: from {module} import {', '.join(private)}")
    assert not bad, "\n".join(bad)


def test_no_code_commits_to_git():
    """A build writes files and lists them; committing is the builder's step (no ``git commit`` run from code)."""
    bad = []
    for name, path in KNOWN.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.List, ast.Tuple)):
                words = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
                if "git" in words and "commit" in words:
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not bad, "\n".join(bad)
