"""Prefect tasks of the dispensing job. Cache keys: the image's content, the rules and
JOB_CODE_VERSION (bump it when the location's science changes)."""

from __future__ import annotations

import hashlib
from dataclasses import asdict
from pathlib import Path

from prefect import task

from tasks.dispense_job.area_acceptance import AcceptanceRules
from tasks.dispense_job.locate import Located, locate
from tasks.dispense_job.tray_io import read_tray
from tasks.dispense_job.tray_job import Calibration, Planners, TrayResult, run_tray
from tasks.vision.pipeline import content_key

JOB_CODE_VERSION = "dispense-job-2"


def _image_digest(path: str) -> str:
    p = Path(path)
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "missing"


@task(name="locate-dispensing-areas", persist_result=True,
      cache_key_fn=lambda c, p: "dispense-job-locate-" + content_key(
          JOB_CODE_VERSION, _image_digest(p["image"]), p["mm_per_px"], asdict(p["rules"])))
def locate_task(image: str, mm_per_px: float, rules: AcceptanceRules) -> Located:
    """The boards and dispensing areas of one tray image (tasks.dispense_job.locate)."""
    return locate(read_tray(Path(image)).read_rgb(), rules, mm_per_px)


@task(name="dispense-tray")
def dispense_tray_task(image: str, located: Located, calibration: Calibration, planners: Planners, phases: tuple,
                       seed: int) -> TrayResult:
    """Map, plan, program and (simulated trays) execute and inspect one tray (tasks.dispense_job.tray_job)."""
    return run_tray(read_tray(Path(image)), located, calibration, planners, phases, seed=seed)
