"""The verification capture a lab takes: what fivecal asks for, and the check of what came back.

Verification is a second capture at the compensated commands of the validation poses. For a
simulated campaign the simulator renders it (:mod:`tasks.simulation.verification_capture`). For a lab's
campaign ``fivecal calibrate`` writes the request into ``<campaign>/captures/<capture_id>/``:

* ``campaign.json``: the campaign's metadata under the campaign_id ``<id>-<capture_id>``;
* ``capture_plan.csv``: the images to take, in order (image_id, path, camera, stage, group,
  repeat and the commanded X_mm … C_deg, the compensated commands), ``repeats`` passes over the
  poses (names from :func:`tasks.campaign.folder.capture_image_id`).

The lab's capture software drives the machine through the rows, writes ``images/`` and
``manifest.csv`` (the same rows with timestamp and, optionally, temperature_c) into that folder,
and ``fivecal calibrate`` is run again: it finds the manifest, checks that each image was taken
at the command it was asked for (:func:`check_capture_commands`) and measures it.

No Prefect, no truth: analysis side.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.campaign.folder import MANIFEST_FILE, METADATA_FILE, capture_image_id, image_relpath
from tasks.campaign.ingest import CampaignError, load_manifest
from tasks.core.atomic_io import atomic_write_text
from tasks.machine.context import PoseContext, approach_directions
from tasks.machine.description import COMMAND_COLUMNS

PLAN_FILE = "capture_plan.csv"
CAPTURE_STAGE = "verification"
COMMAND_TOLERANCE = {"X_mm": 1e-3, "Y_mm": 1e-3, "Z_mm": 1e-3, "A_deg": 1 / 3600, "C_deg": 1 / 3600}
"""How far a captured image's command may be from the requested one: 1 µm, 1″ (the manifest's
rounding is 1e-6)."""


def check_repeats(repeats: int) -> int:
    """``repeats`` (images per verification pose) as an int; ValueError when it is below 1."""
    if int(repeats) < 1:
        raise ValueError(f"verification repeats must be at least 1, got {repeats!r}")
    return int(repeats)


def repeats_key(repeats: int) -> list[int]:
    """``repeats`` as a part of a content key (capture folder name, cache key): nothing for one image
    per pose, so that the keys of captures from before repeats existed stay what they were."""
    return [] if int(repeats) == 1 else [int(repeats)]


def capture_rows(image_ids, commands: np.ndarray, camera: str, repeats: int = 1) -> pd.DataFrame:
    """The capture's images in order: ``repeats`` passes over the poses ``image_ids`` at
    ``commands`` (N, 5; mm and deg, AXIS_ORDER). Columns image_id, path, camera, stage, group,
    repeat, X_mm, Y_mm, Z_mm, A_deg, C_deg."""
    repeats = check_repeats(repeats)
    commands = np.asarray(commands, dtype=float)
    names = [capture_image_id(i, r) for r in range(repeats) for i in image_ids]
    rows = pd.DataFrame({"image_id": names, "path": [image_relpath(camera, n) for n in names], "camera": camera,
                         "stage": CAPTURE_STAGE, "group": CAPTURE_STAGE,
                         "repeat": np.repeat(np.arange(repeats), len(commands))})
    for col, values in zip(COMMAND_COLUMNS, np.tile(commands, (repeats, 1)).T, strict=True):
        rows[col] = values
    return rows


CAPTURE_GAP_IMAGES = 60
"""The capture starts this many image intervals after the campaign's last image (the simulator's
schedule, :func:`tasks.simulation.verification_capture.simulate_capture`)."""


def capture_times(campaign_times_s: np.ndarray, n_rows: int) -> np.ndarray:
    """When the capture's ``n_rows`` images are planned (s since the campaign's first image, (n_rows,)):
    one image interval (the median of the campaign's) apart, from :data:`CAPTURE_GAP_IMAGES` + 1
    intervals after the campaign's last image."""
    t = np.sort(np.asarray(campaign_times_s, dtype=float))
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    return t[-1] + (CAPTURE_GAP_IMAGES + 1 + np.arange(n_rows)) * dt


def planned_capture_context(commands: np.ndarray, campaign_time_s: np.ndarray, campaign_temperature_c: np.ndarray,
                            repeats: int = 1) -> PoseContext:
    """The context each of the N poses at ``commands`` (N, 5; mm, deg) will have in the capture of
    :func:`capture_rows`, for compensating them (analysis side, from the campaign's own record):

    - approach: the direction from which each axis arrives when the capture drives through its
      first pass from home (the order of the rows), as a controller's reversal compensation takes it;
    - time_s: the planned times (:func:`capture_times` after the campaign's), averaged over a pose's
      ``repeats`` (the VBM averages its images);
    - temperature_c: the campaign's last recorded temperature, held (a temperature the capture
      will only measure cannot be known before it).

    campaign_time_s, campaign_temperature_c: (M,) s since the first image and °C of every image of
    the campaign (:func:`tasks.identification.measurements.capture_context`). Returns N rows."""
    commands = np.asarray(commands, dtype=float)
    n, repeats = len(commands), check_repeats(repeats)
    times = capture_times(campaign_time_s, n * repeats).reshape(repeats, n).mean(axis=0)
    last = float(np.asarray(campaign_temperature_c, dtype=float)[np.argmax(campaign_time_s)])
    return PoseContext(approach_directions(commands), times, np.full(n, last))


def write_capture_request(campaign_folder: Path, out_folder: Path, rows: pd.DataFrame) -> Path:
    """Write the request for the capture ``rows`` (:func:`capture_rows`) into ``out_folder``:
    campaign.json and capture_plan.csv (atomic writes; a manifest already there is left alone).
    Returns the plan's path."""
    campaign_folder, out_folder = Path(campaign_folder), Path(out_folder)
    metadata = json.loads((campaign_folder / METADATA_FILE).read_text())
    out_folder.mkdir(parents=True, exist_ok=True)
    capture_metadata = {**metadata, "campaign_id": f"{metadata['campaign_id']}-{out_folder.name}"}
    atomic_write_text(out_folder / METADATA_FILE, json.dumps(capture_metadata, indent=1))
    atomic_write_text(out_folder / PLAN_FILE, rows.round(dict.fromkeys(COMMAND_COLUMNS, 6)).to_csv(index=False))
    return out_folder / PLAN_FILE


def has_capture(folder: Path) -> bool:
    """Whether the capture folder holds a manifest (the lab has written its capture)."""
    return (Path(folder) / MANIFEST_FILE).is_file()


def check_capture_commands(folder: Path, rows: pd.DataFrame) -> None:
    """Raise :class:`tasks.campaign.ingest.CampaignError` naming ``<folder>/manifest.csv`` and its rows
    where an image of the request ``rows`` (:func:`capture_rows`) was taken at another command
    than requested (beyond :data:`COMMAND_TOLERANCE`) or at no number. Images the request does not
    name are not checked (the analysis ignores them); a requested image the manifest lacks is not
    an error (the pose is measured by its other repeats, or left out of the after rows)."""
    manifest = load_manifest(folder)
    both = manifest.merge(rows, on="image_id", suffixes=("", "_requested"))
    problems = []
    for col, tol in COMMAND_TOLERANCE.items():
        got = pd.to_numeric(both[col], errors="coerce").to_numpy(dtype=float)
        want = both[f"{col}_requested"].to_numpy(dtype=float)
        with np.errstate(invalid="ignore"):
            bad = ~(np.abs(got - want) <= tol)  # NaN (not a number) counts as bad
        problems += [f"row {r} ({i}): {col} {g!r}, requested {w:.6f}" for r, i, g, w in
                     zip(both["manifest_row"][bad], both["image_id"][bad], both[col][bad], want[bad], strict=True)]
    if problems:
        shown = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        raise CampaignError(f"{Path(folder) / MANIFEST_FILE}: images taken away from the requested compensated "
                            f"commands (tolerance 1 µm, 1″; the request is {PLAN_FILE}): {shown}")
