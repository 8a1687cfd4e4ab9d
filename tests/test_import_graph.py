"""The house rules of the code's imports (docs/architecture.md), checked over the whole source tree.

Every ``import`` counts, those inside functions too: a module that imports another only when called
still depends on it.

- No import circles between modules.
- Floors: each topic of ``tasks/`` imports only the topics below it (:data:`FLOORS`); ``tasks/``
  imports neither ``flows/`` nor ``fivecal/``, and ``flows/`` does not import ``fivecal/``.
- Science imports no Prefect: only ``tasks/steps`` and ``flows/`` (and the CLI) do.
- No private name (``_x``) of one module is used by another.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tasks", "flows", "fivecal")

# lowest first: a package may import its own floor and the floors below
FLOORS = ("tasks.core", "tasks.machine", "tasks.lake", "tasks.campaign", "tasks.vision", "tasks.identification",
          "tasks.analysis", "tasks.simulation", "tasks.dispensing", "tasks.dispense_job", "tasks.report",
          "tasks.steps", "tasks", "flows", "fivecal")
PREFECT_AWARE = ("tasks.steps", "flows", "fivecal")


@cache
def modules() -> dict[str, Path]:
    """{dotted module name: file} of every module of the three packages."""
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


@cache
def trees() -> dict[str, ast.Module]:
    """{module: its parsed source}, read once for every test."""
    return {module: ast.parse(path.read_text(), str(path)) for module, path in modules().items()}


def _own(name: str) -> str | None:
    """The module of ours that ``name`` (a module or a name inside one) resolves to, else None."""
    mods = modules()
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


@cache
def imports() -> dict[str, list[tuple[str, str, int]]]:
    """{module: [(imported name as written, module of ours it resolves to or '', line)]}."""
    out = defaultdict(list)
    for module, tree in trees().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            for name in names:
                out[module].append((name, _own(name) or "", node.lineno))
    return out


def _floor(module: str) -> str:
    return next(f for f in FLOORS if module == f or module.startswith(f + "."))


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], 0
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
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
    return found


def test_the_scan_sees_the_whole_tree():
    mods = modules()
    assert len(mods) > 150 and "tasks.identification.calibration" in mods and "fivecal.cli" in mods
    assert ("tasks.machine.kinematics" in {m for _, m, _ in imports()["tasks.identification.pige_identification"]})


def test_cycle_finder_finds_a_known_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    edges = defaultdict(set)
    for module, found in imports().items():
        edges[module] |= {target for _, target, _ in found if target and target != module}
    edges.update({m: edges[m] for m in modules()})
    assert _cycles(edges) == []


def test_every_import_goes_to_the_same_floor_or_below():
    rank = {f: i for i, f in enumerate(FLOORS)}
    upward = [f"{module}:{line} imports {target} ({_floor(target)} is above {_floor(module)})"
              for module, found in imports().items() for _, target, line in found
              if target and rank[_floor(target)] > rank[_floor(module)]]
    assert upward == []


@pytest.mark.parametrize("library", ["prefect", "prefect_dask", "dask", "distributed"])
def test_science_imports_no_workflow_library(library):
    offenders = [f"{module}:{line}" for module, found in imports().items() for name, _, line in found
                 if (name == library or name.startswith(library + ".")) and not module.startswith(PREFECT_AWARE)]
    assert offenders == []


def test_no_private_name_crosses_a_module():
    offenders = []
    for module, tree in trees().items():
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                for a in node.names:
                    source = _own(node.module)
                    if source and source != module and a.name.startswith("_") and not a.name.startswith("__"):
                        offenders.append(f"{module}:{node.lineno} from {node.module} import {a.name}")
                    if _own(f"{node.module}.{a.name}") == f"{node.module}.{a.name}":
                        aliases[a.asname or a.name] = f"{node.module}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if _own(a.name):
                        aliases[a.asname or a.name] = a.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")
                    and aliases[node.value.id] != module):
                offenders.append(f"{module}:{node.lineno} {node.value.id}.{node.attr}")
    assert offenders == []
