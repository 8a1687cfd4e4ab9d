"""The second capture of verification, played by the simulator.

In a lab the capture software drives the machine to the compensated commands and photographs
the plate again. For a simulated campaign the simulator plays the machine: it reads the
campaign's truth (this module is simulator side, like :mod:`tasks.simulate`), renders the images
at the compensated commands and writes them as a campaign folder of their own
(``<campaign>/captures/<capture_id>/``: campaign.json, manifest.csv, images/, truth/). The
analysis only reads that folder's manifest and images.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.campaign_io import COMMAND_COLUMNS, TRUTH_DIR, write_manifest, write_metadata
from tasks.campaign_plan import temperature_at
from tasks.capture_request import capture_rows
from tasks.error_model import ErrorModel
from tasks.machine import AXIS_ORDER, load_machine
from tasks.simulate import manifest_from_plan, simulate_truth, write_images


def is_simulated(campaign_folder: Path) -> bool:
    return (Path(campaign_folder) / TRUTH_DIR / "truth.json").exists()


def capture_plan(image_ids, commands: np.ndarray, camera: str, start_s: float,
                 seconds_per_image: float, repeats: int = 1) -> pd.DataFrame:
    """Plan rows for a capture at ``commands`` (N, 5), after the campaign (time from ``start_s``):
    the rows a lab would be asked for (:func:`tasks.capture_request.capture_rows`, ``repeats``
    passes over all the poses in turn, so that each repeat sees the machine at another time and
    temperature), with the axes as AXIS_ORDER columns, time_s and temperature_c."""
    rows = capture_rows(image_ids, commands, camera, repeats)
    df = rows.drop(columns=["path", *COMMAND_COLUMNS]).assign(
        **{axis: rows[col] for axis, col in zip(AXIS_ORDER, COMMAND_COLUMNS, strict=True)})
    df["time_s"] = start_s + np.arange(len(df)) * seconds_per_image
    df["temperature_c"] = temperature_at(df["time_s"].to_numpy())
    return df


def simulate_capture(campaign_folder: Path, out_folder: Path, image_ids, commands: np.ndarray,
                     camera: str = "camera1", repeats: int = 1) -> Path:
    """Render the capture at ``commands`` (N, 5), ``repeats`` images per pose (:func:`capture_plan`),
    into ``out_folder`` (replaced whole); returns it."""
    campaign_folder, out_folder = Path(campaign_folder), Path(out_folder)
    doc = json.loads((campaign_folder / TRUTH_DIR / "truth.json").read_text())
    metadata = json.loads((campaign_folder / "campaign.json").read_text())
    seconds = float(doc["plan"].get("seconds_per_image", 3.0))
    manifest = pd.read_csv(campaign_folder / "manifest.csv")
    plan = capture_plan(image_ids, commands, camera, (len(manifest) + 60) * seconds, seconds, repeats)
    machine = load_machine("prototype")
    errors = ErrorModel.from_dict(doc["error_model"])
    truth = simulate_truth(machine, errors, plan, {}, doc["size"])
    staging = out_folder.with_name(out_folder.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    write_metadata(staging, {**metadata, "campaign_id": f"{metadata['campaign_id']}-{out_folder.name}"})
    write_manifest(staging, manifest_from_plan(plan))
    (staging / TRUTH_DIR).mkdir()
    (staging / TRUTH_DIR / "truth.json").write_text(json.dumps({**doc, "note": "verification capture"}))
    write_images(staging, machine, plan, truth, range(len(plan)), int(doc["seed"]) * 7919 + 1)
    shutil.rmtree(out_folder, ignore_errors=True)
    staging.rename(out_folder)
    return out_folder
