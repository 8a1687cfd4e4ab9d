"""User effect families: load the modules that register them.

A user writes an :class:`tasks.effects.Effect` subclass decorated with :func:`tasks.effects.register`
in a module of their own (docs/user-effects.md). Importing the module registers the family; from then
on it parses, simulates, takes part in ``diagnose`` as a candidate and is fitted by ``calibrate``
like a built-in one. Modules are named by dotted path (``mypkg.myeffects``, importable from
``sys.path``) or by file (``path/to/myeffects.py``), or advertised by an installed package under
the entry-point group ``fivecal.effects``.

SYNOPSIS
    >>> load_effect_modules(["mypkg.myeffects"])      # e.g. from --effect-module mypkg.myeffects
    ['straightness_bow']
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Iterable
from importlib.metadata import entry_points
from pathlib import Path

from tasks.effects import EFFECTS

ENTRY_POINT_GROUP = "fivecal.effects"


def _import(name: str):
    path = Path(name)
    if name.endswith(".py"):
        if not path.is_file():
            raise ValueError(f"effect module file {name!r} does not exist")
        module_name = f"fivecal_user_effects_{path.stem}"
        spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)
        return module
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as err:
        raise ValueError(f"effect module {name!r} cannot be imported ({err}); give a dotted path on "
                         "sys.path (e.g. mypkg.myeffects) or a .py file") from err


def load_effect_modules(modules: Iterable[str] = (), entry_point_group: str | None = ENTRY_POINT_GROUP) -> list[str]:
    """Import ``modules`` (dotted paths or .py files) and every entry point of ``entry_point_group``
    (None: none), so that their ``@register`` decorators run. Returns the families they added, sorted
    (a module imported before adds nothing new)."""
    before = set(EFFECTS)
    for name in modules:
        _import(str(name))
    if entry_point_group:
        for ep in entry_points(group=entry_point_group):
            ep.load()
    return sorted(set(EFFECTS) - before)
