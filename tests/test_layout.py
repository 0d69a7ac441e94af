"""The runtime's layout: no module imports another's private names, no import cycle inside refiner_rt, and every
module imports without torch and without onnx (the wheel's dependencies are numpy, OpenCV, onnxruntime, click)."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "refiner_rt"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imports(path: Path) -> list[tuple[str, list[str], int]]:
    """``(module, names, line)`` of every import in the file, at module level and inside functions alike; relative
    imports resolved; ``names`` empty for ``import x``."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            out.append((base, [a.name for a in node.names], node.lineno))
    return out


def internal_targets(module: str, names: list[str]) -> list[str]:
    """The refiner_rt modules an import loads: the module itself, and ``from pkg import mod`` submodules."""
    if module not in MODULES:
        return []
    return [module] + [f"{module}.{n}" for n in names if f"{module}.{n}" in MODULES]


def import_graph() -> dict[str, set[str]]:
    graph = {}
    for name, path in MODULES.items():
        graph[name] = set()
        for module, names, _ in imports(path):
            for target in internal_targets(module, names):
                if target != name and not name.startswith(target + "."):  # a package's own __init__ is no edge
                    graph[name].add(target)
    return graph


def test_the_graph_sees_the_imports_it_must():
    graph = import_graph()
    assert "refiner_rt.session" in graph["refiner_rt.cascade"]  # module level
    assert "refiner_rt.refiner" in graph["refiner_rt.cli.demo"]  # inside a function


def test_no_module_imports_a_private_name_from_another():
    found = []
    for name, path in MODULES.items():
        for module, names, line in imports(path):
            if module.split(".")[0] != "refiner_rt" or module == name:
                continue
            found += [f"{path.relative_to(ROOT)}:{line}: from {module} import {n}" for n in names
                      if n.startswith("_") and n != "__version__"]
    assert not found, "private names imported across modules:\n" + "\n".join(found)


def test_refiner_rt_has_no_import_cycle():
    graph = import_graph()
    state, cycles = {}, []

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles in refiner_rt:\n" + "\n".join(cycles)


def test_the_cycle_check_finds_a_cycle(tmp_path, monkeypatch):
    """The check itself: two modules importing each other (one inside a function) form a cycle."""
    global MODULES
    pkg = tmp_path / "refiner_rt"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from refiner_rt.b import f\n")
    (pkg / "b.py").write_text("def f():\n    from refiner_rt import a\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "MODULES", {module_name(p): p for p in sorted(pkg.rglob("*.py"))})
    graph = import_graph()
    assert graph["refiner_rt.a"] == {"refiner_rt.b"} and graph["refiner_rt.b"] == {"refiner_rt.a"}
    with pytest.raises(AssertionError, match="refiner_rt.a -> refiner_rt.b -> refiner_rt.a"):
        test_refiner_rt_has_no_import_cycle()


def test_the_runtime_never_imports_training_code():
    found = [f"{path.relative_to(ROOT)}:{line}: {module}" for path in MODULES.values()
             for module, _, line in imports(path) if module.split(".")[0] in ("models", "export", "benchmarks")]
    assert not found, "\n".join(found)


def test_every_module_imports_without_torch_and_onnx():
    code = ("import importlib, sys; sys.modules['torch'] = None; sys.modules['onnx'] = None; "
            f"[importlib.import_module(m) for m in {sorted(m for m in MODULES if not m.endswith('__main__'))!r}]; "
            "import refiner_rt; "
            "[getattr(refiner_rt, n) for n in refiner_rt.__all__]")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
