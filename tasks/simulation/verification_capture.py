"""The second capture of verification, played by the simulator.

In a lab the capture software drives the machine to the compensated commands and photographs
the plate again. For a simulated campaign the simulator plays the machine: it reads the
campaign's truth (this module is simulator side, like :mod:`tasks.simulation.simulate`), renders the images
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

from tasks.analysis.verification import modelled_errors
from tasks.campaign.capture_request import CAPTURE_GAP_IMAGES, capture_rows
from tasks.campaign.folder import TRUTH_DIR, write_manifest, write_metadata
from tasks.core.atomic_io import staged_folder
from tasks.machine.description import AXIS_ORDER, COMMAND_COLUMNS, load_machine
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign, plan_context, temperature_at
from tasks.simulation.simulate import EFFECT_MODULES_DIR, manifest_from_plan, read_truth, simulate_truth, write_images


def is_simulated(campaign_folder: Path) -> bool:
    return (Path(campaign_folder) / TRUTH_DIR / "truth.json").exists()


def capture_plan(image_ids, commands: np.ndarray, camera: str, start_s: float,
                 seconds_per_image: float, repeats: int = 1) -> pd.DataFrame:
    """Plan rows for a capture at ``commands`` (N, 5), after the campaign (time from ``start_s``):
    the rows a lab would be asked for (:func:`tasks.campaign.capture_request.capture_rows`, ``repeats``
    passes over all the poses in turn, so that each repeat sees the machine at another time and
    temperature), with the axes as AXIS_ORDER columns, time_s and temperature_c."""
    rows = capture_rows(image_ids, commands, camera, repeats)
    df = rows.drop(columns=["path", *COMMAND_COLUMNS]).assign(
        **{axis: rows[col] for axis, col in zip(AXIS_ORDER, COMMAND_COLUMNS, strict=True)})
    df["time_s"] = start_s + np.arange(len(df)) * seconds_per_image
    df["temperature_c"] = temperature_at(df["time_s"].to_numpy())
    return df


def _capture_plan_of(campaign_folder: Path, doc: dict, image_ids, commands: np.ndarray, camera: str,
                     repeats: int) -> pd.DataFrame:
    """:func:`capture_plan` on the campaign's schedule: :data:`CAPTURE_GAP_IMAGES` + 1 image intervals
    after its last image (pauses between passes included), at its image interval."""
    seconds = float(doc["plan"].get("seconds_per_image", 3.0))
    stamps = pd.to_datetime(pd.read_csv(Path(campaign_folder) / "manifest.csv")["timestamp"], utc=True)
    last_s = (stamps.max() - stamps.min()).total_seconds()
    return capture_plan(image_ids, commands, camera, last_s + (CAPTURE_GAP_IMAGES + 1) * seconds, seconds, repeats)


def simulate_capture(campaign_folder: Path, out_folder: Path, image_ids, commands: np.ndarray,
                     camera: str = "camera1", repeats: int = 1) -> Path:
    """Render the capture at ``commands`` (N, 5), ``repeats`` images per pose (:func:`capture_plan`),
    into ``out_folder`` (replaced whole); returns it."""
    campaign_folder, out_folder = Path(campaign_folder), Path(out_folder)
    doc, errors = read_truth(campaign_folder)
    metadata = json.loads((campaign_folder / "campaign.json").read_text())
    plan = _capture_plan_of(campaign_folder, doc, image_ids, commands, camera, repeats)
    machine = load_machine("prototype")
    truth = simulate_truth(machine, errors, plan, {}, doc["size"])
    with staged_folder(out_folder) as staging:
        write_metadata(staging, {**metadata, "campaign_id": f"{metadata['campaign_id']}-{out_folder.name}"})
        write_manifest(staging, manifest_from_plan(plan))
        (staging / TRUTH_DIR).mkdir()
        (staging / TRUTH_DIR / "truth.json").write_text(json.dumps({**doc, "note": "verification capture"}))
        modules = campaign_folder / TRUTH_DIR / EFFECT_MODULES_DIR
        if modules.is_dir():
            shutil.copytree(modules, staging / TRUTH_DIR / EFFECT_MODULES_DIR)
        write_images(staging, machine, plan, truth, range(len(plan)), int(doc["seed"]) * 7919 + 1)
    return out_folder


def true_capture_errors(campaign_folder: Path, image_ids, commands: np.ndarray, desired: np.ndarray,
                        camera: str = "camera1", repeats: int = 1) -> pd.DataFrame:
    """The true tip errors of the capture that :func:`simulate_capture` renders at ``commands`` (N, 5)
    against ``desired`` (N, 4, 4): each image with its context (approach from the capture's moves,
    time and temperature of its schedule), a pose's row the mean of its ``repeats`` images (columns
    of :func:`tasks.analysis.verification.modelled_errors`, µm and arcsec, workpiece frame)."""
    doc, errors = read_truth(campaign_folder)
    plan = _capture_plan_of(campaign_folder, doc, image_ids, commands, camera, repeats)
    n = len(commands)
    rows = modelled_errors(load_machine("prototype"), errors, np.tile(desired, (repeats, 1, 1)),
                           plan[list(AXIS_ORDER)].to_numpy(dtype=float), plan_context(plan))
    return rows.groupby(np.tile(np.arange(n), repeats)).mean().reset_index(drop=True)


def true_campaign_errors(campaign_folder: Path, image_ids, commands: np.ndarray, desired: np.ndarray
                         ) -> pd.DataFrame:
    """The true tip errors of the campaign's images ``image_ids`` at their ``commands`` (N, 5; e.g. the
    validation poses, before compensation) against ``desired`` (N, 4, 4), each in the context the
    simulator gave it (the campaign's plan: approach, time, temperature); columns of
    :func:`tasks.analysis.verification.modelled_errors`."""
    doc, errors = read_truth(campaign_folder)
    machine = load_machine("prototype")
    plan, _ = plan_campaign(machine, CampaignPlan(**doc["plan"]), int(doc["seed"]))
    row = pd.Series(np.arange(len(plan)), index=plan["image_id"]).loc[list(image_ids)].to_numpy()
    return modelled_errors(machine, errors, desired, commands, plan_context(plan).take(row))
