"""A house rule of the compiled kernels: each one depends only on its own file.

numba's disk cache (``cache=True``) is keyed on the kernel's own source file. A kernel that calls a
compiled function, or reads a constant, defined in another file keeps the compiled copy of that code
after the other file changes (numba's documented limitation, numba/numba#1833), so a checkout
that has run before would compute with the old code. Kernels therefore take such values as
arguments, and call only kernels of their own file.
"""

from __future__ import annotations

import ast
import importlib
import types
from pathlib import Path

import pytest
from numba.core.registry import CPUDispatcher

ROOT = Path(__file__).resolve().parents[1]
KERNEL_MODULES = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts)
                        for p in (ROOT / "tasks").rglob("*.py") if "@njit" in p.read_text())


def _names_read(code: types.CodeType) -> set[str]:
    """Global and attribute names read by a function's code and the code nested in it."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _names_read(const)
    return names


def _defined_in(module: types.ModuleType) -> set[str]:
    """The names a module's own source binds at its top level (assignments, functions, classes)."""
    tree = ast.parse(Path(module.__file__).read_text())
    names = set()
    for node in tree.body:
        if isinstance(node, ast.Assign):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
    return names


def test_there_are_kernel_modules_to_check():
    assert "tasks.vision.detection.rrht" in KERNEL_MODULES and len(KERNEL_MODULES) >= 9


@pytest.mark.parametrize("module_name", KERNEL_MODULES)
def test_a_cached_kernel_reads_no_compiled_function_or_constant_of_another_file(module_name):
    module = importlib.import_module(module_name)
    own = _defined_in(module)
    foreign = []
    for name, kernel in vars(module).items():
        if not (isinstance(kernel, CPUDispatcher) and kernel.py_func.__module__ == module_name):
            continue
        for read in sorted(_names_read(kernel.py_func.__code__)):
            value = kernel.py_func.__globals__.get(read)
            if value is None or isinstance(value, types.ModuleType):
                continue  # a builtin, an attribute name, or a module (numpy, math)
            if read not in own:
                foreign.append(f"{name} reads {read}")
    assert not foreign, f"{module_name}: {foreign}"
