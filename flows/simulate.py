"""Simulate a measurement campaign: the virtual machine plays every planned pose and the
cameras' images are rendered in parallel into a new campaign folder."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
from prefect import flow, get_run_logger

from flows.runners import image_task_runner
from tasks.machine.effects import load_effect_modules
from tasks.steps.simulation import plan_and_write_truth, render_images

BATCH_SIZE = 25


@flow(name="simulate-campaign", task_runner=image_task_runner())
def simulate_campaign(out: str, seed: int = 0, size: str = "full", effects: list[str] | None = None,
                      plan: str = "default", overwrite: bool = False,
                      effect_modules: list[str] | None = None) -> str:
    """Write a simulated campaign to ``out``. The folder appears only when complete.

    plan: a key of :data:`tasks.simulation.campaign_plan.PLANS` (default, small, context).

    effect_modules: user modules defining families of ``effects`` (dotted paths or ``.py`` files);
    they are imported here and their source is recorded with the truth, so that the simulator's side
    of later runs (the verification capture) has them and the analysis side does not.

    The rendering batches go to the flow's task runner (``simulate_campaign.with_options(task_runner=
    flows.runners.image_task_runner(...))`` for Dask); its workers must see ``out``'s parent folder.
    """
    logger = get_run_logger()
    load_effect_modules(effect_modules or [], entry_point_group=None)
    out_path = Path(out).resolve()
    if out_path.exists() and not overwrite:
        raise FileExistsError(f"{out_path} already exists; choose another folder or pass --overwrite")
    staging = out_path.with_name(f".{out_path.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    machine, poses, truth = plan_and_write_truth(staging, out_path.name, seed, size, list(effects or []),
                                                 plan, list(effect_modules or []))
    batches = np.array_split(np.arange(len(poses)), max(1, int(np.ceil(len(poses) / BATCH_SIZE))))
    logger.info(f"rendering {len(poses)} images ({size}) in {len(batches)} batches")
    futures = [render_images.submit(staging, machine, poses, truth, rows, seed) for rows in batches]
    done = 0
    for f in futures:
        done += f.result()
        logger.info(f"rendered {done}/{len(poses)} images")
    if out_path.exists():
        shutil.rmtree(out_path)
    os.replace(staging, out_path)
    logger.info(f"campaign written to {out_path}")
    return str(out_path)
