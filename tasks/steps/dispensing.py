"""Prefect tasks of the dispensing test. Cache keys: the inputs' content plus DISPENSE_CODE_VERSION
(bump it when the science of tasks/dispensing changes)."""

from __future__ import annotations

import hashlib
from dataclasses import asdict
from pathlib import Path

import pandas as pd
from prefect import task

from tasks.dispensing.capture import simulate_dispense_capture
from tasks.dispensing.inspection import InspectionConfig
from tasks.dispensing.measure import inspect_capture, load_capture_manifest
from tasks.dispensing.workpiece import Workpiece
from tasks.vision.pipeline import content_key

DISPENSE_CODE_VERSION = "dispense-4"


def _images_digest(folder: Path, manifest: pd.DataFrame) -> str:
    h = hashlib.sha256()
    for path in manifest["path"]:
        p = Path(folder) / path
        h.update(p.read_bytes() if p.is_file() else b"missing")
    return h.hexdigest()


@task(name="simulate-dispense-capture", persist_result=True,
      cache_key_fn=lambda c, p: "dispense-capture-" + content_key(
          DISPENSE_CODE_VERSION, str(p["campaign_folder"]), str(p["out_folder"]), p["rows"].round(9),
          p["workpiece"].to_dict(), p["seed"]))
def dispense_capture_task(campaign_folder: Path, out_folder: Path, rows: pd.DataFrame, workpiece: Workpiece,
                          seed: int) -> str:
    """The simulator dispenses the workpiece at the rows' commands and images every ring."""
    return str(simulate_dispense_capture(campaign_folder, out_folder, rows, workpiece, seed))


@task(name="inspect-dispense-capture", persist_result=True,
      cache_key_fn=lambda c, p: "dispense-inspect-" + content_key(
          DISPENSE_CODE_VERSION, load_capture_manifest(p["folder"]),
          _images_digest(p["folder"], load_capture_manifest(p["folder"])), asdict(p["config"])))
def inspect_task(folder: Path, config: InspectionConfig) -> pd.DataFrame:
    """§4.3 inspection of every ring image of a capture folder (tasks.dispensing.measure)."""
    return inspect_capture(folder, load_capture_manifest(folder), config)
