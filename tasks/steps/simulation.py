"""Prefect task wrappers of the simulator (the only Prefect-aware module of the simulation).

The simulator is the data source, so nothing here is cached: NO_CACHE, results not persisted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from tasks.simulation.campaign_plan import PLANS
from tasks.simulation.simulate import CampaignTruth, write_campaign_truth, write_images


@task(cache_policy=NO_CACHE, persist_result=False)
def plan_and_write_truth(staging: Path, campaign_id: str, seed: int, size: str, effects: list[str],
                         plan_name: str, effect_modules: list[str] | None = None):
    """Plan the campaign (``plan_name``: a key of :data:`tasks.simulation.campaign_plan.PLANS`), run the true
    machine, write metadata, manifest and truth files (the sources of ``effect_modules`` recorded
    with the truth)."""
    plan = PLANS[plan_name]()
    return write_campaign_truth(staging, campaign_id, seed, size, effects, plan, effect_modules)


@task(cache_policy=NO_CACHE, persist_result=False)
def render_images(staging: Path, machine, poses, truth: CampaignTruth, rows: np.ndarray, seed: int) -> int:
    """Render and write the images of ``rows``; returns how many were written."""
    return write_images(staging, machine, poses, truth, rows, seed)
