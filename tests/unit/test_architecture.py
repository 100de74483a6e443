"""The package's shape: no import cycles, no private names across modules, layers that only
import downwards, light top-level import, version from the package metadata."""

from __future__ import annotations

import ast
import importlib.metadata
import subprocess
import sys
from pathlib import Path

import pytest

import afbl_jax

PACKAGE = Path(afbl_jax.__file__).resolve().parent
LAYERS = [
    "_typing",
    "_validation",
    "model",
    "scenario",
    "metrics",
    "sim",
    "io",
    "plotting",
    "studies",
    "cli",
]
"""Import order: a module may import only from its own layer or the layers before it."""


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(imported module, imported names) of every import statement in a file, function-level
    imports included, relative imports resolved."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((target, [a.name for a in node.names]))
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = sorted(PACKAGE.rglob("*.py"))
    modules = {_module_name(p) for p in files}
    edges: dict[str, set[str]] = {m: set() for m in modules}
    for p in files:
        src = _module_name(p)
        for target, names in _imports(p):
            if target in modules and target != src:  # `from . import x` in a package __init__
                edges[src].add(target)
            for n in names:  # `from package import submodule`
                if f"{target}.{n}" in modules:
                    edges[src].add(f"{target}.{n}")
    return edges


def test_no_import_cycles(graph):
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = stack[stack.index(n) :] + [n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if len(parts) < 2:
        return None
    return LAYERS.index(parts[1]) if parts[1] in LAYERS else None


def test_layers_import_downwards(graph):
    bad = []
    for src, targets in graph.items():
        ls = _layer(src)
        for t in targets:
            lt = _layer(t)
            if ls is not None and lt is not None and lt > ls:
                bad.append(f"{src} imports {t}")
    assert not bad, "\n".join(bad)


def test_no_private_names_across_modules():
    bad = []
    for p in sorted(PACKAGE.rglob("*.py")):
        for target, names in _imports(p):
            if target.startswith("afbl_jax"):
                bad += [
                    f"{_module_name(p)}: from {target} import {n}"
                    for n in names
                    if n.startswith("_") and not n.startswith("__")
                ]
    assert not bad, "\n".join(bad)


def test_import_is_light_and_version_from_metadata():
    code = (
        "import sys, afbl_jax; heavy = [m for m in sys.modules if m.split('.')[0] in "
        "('pyarrow', 'matplotlib', 'scipy') or m.startswith('afbl_jax.studies') or "
        "m.startswith('afbl_jax.cli')]; print(heavy); print(afbl_jax.__version__)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    heavy, version = r.stdout.strip().splitlines()
    assert heavy == "[]"
    assert version == importlib.metadata.version("afbl-jax")
    # the study entry points are still reachable from the top level (imported on first use)
    assert callable(afbl_jax.run_tuning)
