"""Which code wrote a result: fivecal's version number and a fingerprint of its source."""

from __future__ import annotations

import hashlib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

try:
    FIVECAL_VERSION = version("fivecal")
except PackageNotFoundError:  # running from a source tree without installation
    FIVECAL_VERSION = "0.0.0+source"

CODE_PACKAGES = ("fivecal", "flows", "tasks")
SOURCE_ROOT = Path(__file__).resolve().parents[2]


def code_fingerprint(packages: dict[str, Path] | None = None) -> str:
    """sha256 of fivecal's own code and data files: every .py and .json file of the fivecal, flows
    and tasks packages (machine descriptions included; ``packages``: {name: folder} instead),
    relative path and content, in path order. fivecal's version number does not change while the
    code is edited; this does."""
    if packages is None:
        packages = {name: SOURCE_ROOT / name for name in CODE_PACKAGES}
    h = hashlib.sha256()
    for name, base in sorted(packages.items()):
        for f in sorted(Path(base).rglob("*")):
            if f.suffix not in (".py", ".json") or "__pycache__" in f.parts:
                continue
            h.update(f"{name}/{f.relative_to(base).as_posix()}\n".encode())
            h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()
