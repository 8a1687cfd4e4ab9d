"""The campaign folder: the input contract a lab's capture software writes.

Layout (documented for other software in docs/campaign-format.md)::

    <campaign>/
      campaign.json      metadata: format version, campaign_id, machine geometry, cameras
                         (nominal sensor and lens), plates, which camera views which plate
      manifest.csv       one row per image (MANIFEST_COLUMNS)
      images/<camera>/<image_id>.png
      truth/             simulated campaigns only; no analysis stage reads it

Writes are atomic and durable: files go to a temporary name, are fsync'd and renamed into place;
they follow the umask like any file the user creates.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd

from tasks.core.atomic_io import atomic_write_text

FORMAT_VERSION = 1
METADATA_FILE = "campaign.json"
MANIFEST_FILE = "manifest.csv"
TRUTH_DIR = "truth"
MANIFEST_COLUMNS = (
    "image_id", "path", "camera", "stage", "group", "repeat",
    "X_mm", "Y_mm", "Z_mm", "A_deg", "C_deg", "timestamp", "temperature_c",
)
# The manifest's stage vocabulary (docs/campaign-format.md) and each stage's groups: any
# non-empty name (a calibration trial), one of the axes (the axis a PDGE sweep moves), or the
# stage's own name (None).
MANIFEST_STAGES: dict[str, tuple[str, ...] | str | None] = {
    "camera_calibration": "any", "pdge": ("X", "Y", "Z", "A", "C"), "pige": None, "validation": None,
    "verification": None,
}


def write_metadata(folder: Path, metadata: dict) -> None:
    atomic_write_text(Path(folder) / METADATA_FILE, json.dumps(metadata, indent=1))


def write_manifest(folder: Path, manifest: pd.DataFrame) -> None:
    missing = [c for c in MANIFEST_COLUMNS if c not in manifest.columns]
    if missing:
        raise ValueError(f"manifest lacks columns {missing}")
    atomic_write_text(Path(folder) / MANIFEST_FILE, manifest[list(MANIFEST_COLUMNS)].to_csv(index=False))


def image_relpath(camera: str, image_id: str) -> str:
    return f"images/{camera}/{image_id}.png"


CAPTURE_SUFFIX = "_v"


def capture_image_id(validation_id: str, repeat: int = 0) -> str:
    """The follow-up capture's name for repeat ``repeat`` of validation pose ``validation_id``:
    ``<id>_v`` for the first image, ``<id>_v<k>`` for repeat k ≥ 1 (docs/campaign-format.md)."""
    return f"{validation_id}{CAPTURE_SUFFIX}" + (str(repeat) if repeat else "")


def validation_id_of(capture_id: str) -> str | None:
    """The validation pose a capture image re-measures (the inverse of :func:`capture_image_id`);
    None for a name that does not follow it."""
    m = re.fullmatch(rf"(.+){CAPTURE_SUFFIX}(\d*)", capture_id)
    return None if m is None or m.group(2).startswith("0") else m.group(1)
