"""The package's import structure: every module imports on its own, and no import loops, neither between
modules nor between subpackages (a subpackage that imports another is above it; nothing reaches back).

The graph comes from the sources (``ast``), and counts function-local imports too: a loop hidden inside a
function is still a loop for a reader.
"""

import ast
import importlib
from collections import defaultdict
from pathlib import Path

import pytest

import genesis_rl

ROOT = Path(genesis_rl.__file__).parent
#: the layers, lowest first: a package imports only from its own layer and those before it (docs/architecture.md)
LAYERS = (("core",), ("world",), ("sim", "distributed"), ("sut",), ("loop",), ("env", "labels"), ("training",),
          ("adversaries",), ("campaigns",), ("analysis", "exports"), ("benchmark", "estimation", "harden"),
          ("commands",))
SUBPACKAGES = tuple(p for layer in LAYERS for p in layer)
LEVEL = {p: i for i, layer in enumerate(LAYERS) for p in layer}


def _module_name(path: Path) -> str:
    parts = ("genesis_rl",) + path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _imports(path: Path) -> set[str]:
    """The package's modules that ``path`` imports anywhere in it (``from a.b import c`` counts a.b, and
    a.b.c when that is a module)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        out |= {n for n in names if n in MODULES}
    return out


GRAPH = {m: _imports(p) - {m} for m, p in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in SUBPACKAGES) else None


def test_the_subpackage_list_is_complete():
    assert {p.parent.name for p in ROOT.glob("*/__init__.py")} == set(SUBPACKAGES)


@pytest.mark.parametrize("module", sorted(MODULES))  # __main__ too: importing it runs nothing
def test_every_module_imports(module):
    importlib.import_module(module)


def test_no_import_loop_between_subpackages():
    graph: dict[str, set[str]] = defaultdict(set)
    where: dict[tuple[str, str], str] = {}
    for module, targets in GRAPH.items():
        a = _subpackage(module)
        for target in targets:
            b = _subpackage(target)
            if a and b and a != b and a in SUBPACKAGES and b in SUBPACKAGES:
                graph[a].add(b)
                where.setdefault((a, b), f"{module} -> {target}")
    loops = _cycles(graph)
    assert not loops, [(loop, [where[e] for e in where if e[0] in loop and e[1] in loop]) for loop in loops]


def test_every_import_points_down_the_layers():
    """The data flow as the code's own imports draw it: nothing imports a layer above its own, so a reader can
    start at ``core`` and read upwards, and a change in ``commands`` can never break ``sim``."""
    upward = []
    for module, targets in GRAPH.items():
        a = _subpackage(module)
        for target in targets:
            b = _subpackage(target)
            if a in LEVEL and b in LEVEL and LEVEL[b] > LEVEL[a]:
                upward.append(f"{module} ({a}) -> {target} ({b})")
    assert upward == []
    # the top of the package holds only its face, the command entry and the old-path table
    assert sorted(p.name for p in ROOT.glob("*.py")) == ["__init__.py", "__main__.py", "compat.py"]


def test_the_layer_checker_finds_an_upward_import(monkeypatch):
    monkeypatch.setitem(GRAPH, "genesis_rl.core.errors", {"genesis_rl.commands.cli"})
    with pytest.raises(AssertionError, match="core.errors"):
        test_every_import_points_down_the_layers()


def test_no_private_name_is_imported_across_packages():
    """A leading underscore says "only this package uses it"; importing one from another package hides a
    dependency the layers should show."""
    crossing = []
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("genesis_rl."):
                private = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                if private and _subpackage(node.module) != _subpackage(module):
                    crossing.append(f"{module} imports {private} from {node.module}")
    assert crossing == []


def test_no_import_loop_between_modules():
    assert _cycles(GRAPH) == []


def test_the_checker_finds_a_loop():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
