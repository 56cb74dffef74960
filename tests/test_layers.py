"""The package's layers: each subpackage imports only from the layers below it.

Parses every module with :mod:`ast` (imports inside functions included), resolves
relative imports and checks them against :data:`ALLOWED`. The picture and the reasons
are in ``docs/architecture.md``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import eifslam

PACKAGE = Path(eifslam.__file__).resolve().parent

#: layer -> the layers it may import (besides itself, the base modules ``eifslam.errors`` and
#: ``eifslam.settings``, and ``eifslam``)
ALLOWED: dict[str, set[str]] = {
    "geometry": set(),
    "estimation": {"geometry"},
    "baselines": {"geometry", "estimation"},
    "frontend": {"geometry", "estimation"},
    "io": {"geometry"},
    "sim": {"geometry", "estimation", "frontend", "system"},
    "system": {"geometry", "estimation", "baselines", "frontend"},
    "evaluation": {"geometry", "estimation", "io", "system", "sim"},
    "viz": {"geometry", "io", "system", "evaluation"},
    "cli": {"geometry", "estimation", "baselines", "frontend", "io", "sim", "system", "evaluation", "viz"},
}

#: layers whose modules may not import OpenCV or matplotlib at all
PURE = {"geometry", "estimation", "baselines"}


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py"))


def _imports(path: Path) -> list[tuple[int, str]]:
    """``(line, absolute module)`` of every import in *path* (relative ones resolved)."""
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod in ("eifslam",) or (node.level and not node.module):
                out += [(node.lineno, f"{mod}.{a.name}") for a in node.names]
            else:
                out.append((node.lineno, mod))
    return out


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "eifslam" else None


def test_every_module_sits_in_a_layer():
    top = sorted(p.name for p in PACKAGE.iterdir() if p.suffix == ".py" and p.name not in ("__init__.py", "errors.py",
                                                                                            "settings.py"))
    assert top == [], f"modules outside any layer: {top}"
    dirs = sorted(p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists())
    assert set(dirs) == set(ALLOWED), f"subpackages {dirs} vs layers {sorted(ALLOWED)}"


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layer_imports_only_from_below(layer):
    bad = []
    for path in (PACKAGE / layer).rglob("*.py"):
        for line, mod in _imports(path):
            target = _layer(mod)
            if target is None or target in ("errors", "settings", "__version__") or target == layer:
                if layer in PURE and mod.split(".")[0] in ("cv2", "faiss", "matplotlib"):
                    bad.append(f"{path.relative_to(PACKAGE)}:{line} imports {mod}")
                continue
            if target not in ALLOWED[layer]:
                bad.append(f"{path.relative_to(PACKAGE)}:{line} imports {mod}")
    assert not bad, f"layer {layer!r} reaches above itself:\n" + "\n".join(bad)


def _runtime_imports(path: Path) -> list[tuple[int, str]]:
    """:func:`_imports` without those under ``if TYPE_CHECKING:`` (never executed)."""
    tree = ast.parse(path.read_text(), str(path))
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {n.lineno for stmt in node.body for n in ast.walk(stmt) if hasattr(n, "lineno")}
    return [(line, mod) for line, mod in _imports(path) if line not in skip]


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_cycles() -> list[list[str]]:
    """Cycles of the graph of eifslam's modules (an edge for every import that runs,
    imports inside functions included; a package's ``__init__`` counts as its own node),
    as strongly connected components with more than one module."""
    mods = {_module_name(p): p for p in _modules()}
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, p in mods.items():
        for _, target in _runtime_imports(p):
            while target and target not in mods:  # `from pkg import name`: the module or the package
                target = target.rpartition(".")[0]
            if target and target != m and not m.startswith(target + "."):  # a package's own modules
                graph[m].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    cycles = import_cycles()
    assert not cycles, "import cycles (imports inside functions included):\n" + "\n".join(" <-> ".join(c) for c in cycles)
