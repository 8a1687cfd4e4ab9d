"""Prefect task wrappers of the simulator (the only Prefect-aware module of the simulation).

The simulator is the data source, so nothing here is cached: NO_CACHE, results not persisted.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

import fivecal
from tasks.campaign_io import (
    TRUTH_DIR,
    atomic_write_bytes,
    atomic_write_parquet,
    atomic_write_text,
    write_manifest,
    write_metadata,
)
from tasks.campaign_plan import CampaignPlan, plan_campaign
from tasks.effects import parse_effect
from tasks.machine import load_machine
from tasks.prototype_errors import load_prototype_errors
from tasks.simulate import (
    SIZES,
    CampaignTruth,
    encode_png,
    manifest_from_plan,
    render_image,
    simulate_truth,
    truth_tables,
)


def campaign_metadata(machine, campaign_id: str, size: str) -> dict:
    """campaign.json content: geometry and *nominal* camera data only (no true intrinsics)."""
    src = machine.source
    cams = {}
    for name, cam in machine.cameras.items():
        c = cam.scaled(SIZES[size])
        cams[name] = {"width_px": c.width_px, "height_px": c.height_px, "pixel_size_mm": c.pixel_size_mm,
                      "focal_length_mm": src["cameras"][name]["focal_length_mm"],
                      "focus_distance_mm": c.focus_distance_mm}
    machine_geometry = {k: src[k] for k in ("name", "axes", "tool_chain", "workpiece_chain", "attachments",
                                             "tip", "workpiece", "views", "plates", "notes")}
    return {"format_version": 1, "campaign_id": campaign_id, "simulated": True,
            "fivecal_version": fivecal.__version__, "machine": machine_geometry,
            "cameras": cams, "plates": src["plates"], "views": src["views"]}


@task(cache_policy=NO_CACHE, persist_result=False)
def plan_and_write_truth(staging: Path, campaign_id: str, seed: int, size: str, effects: list[str],
                         small_plan: bool):
    """Plan the campaign, run the true machine, write metadata, manifest and truth files."""
    machine = load_machine("prototype")
    errors = load_prototype_errors()
    errors.effects = [parse_effect(s) for s in effects]
    plan = CampaignPlan.small() if small_plan else CampaignPlan()
    poses, fixture = plan_campaign(machine, plan, seed)
    truth = simulate_truth(machine, errors, poses, fixture, size)
    write_metadata(staging, campaign_metadata(machine, campaign_id, size))
    write_manifest(staging, manifest_from_plan(poses))
    images, dots = truth_tables(poses, truth, machine)
    provenance = {"fivecal_version": fivecal.__version__, "seed": seed, "size": size}
    atomic_write_parquet(staging / TRUTH_DIR / "images.parquet", images, provenance)
    atomic_write_parquet(staging / TRUTH_DIR / "dots.parquet", dots, provenance)
    truth_doc = {"seed": seed, "size": size, "plan": plan.__dict__, "effects": effects,
                 "error_model": errors.to_dict(),
                 "cameras": {n: c.to_dict() for n, c in truth.cameras.items()},
                 "note": "Ground truth of a simulated campaign. No analysis stage reads this folder."}
    atomic_write_text(staging / TRUTH_DIR / "truth.json", json.dumps(truth_doc, indent=1))
    return machine, poses, truth


@task(cache_policy=NO_CACHE, persist_result=False)
def render_images(staging: Path, machine, poses, truth: CampaignTruth, rows: np.ndarray, seed: int) -> int:
    """Render and write the images of ``rows``; returns how many were written."""
    for i in rows:
        camera, image_id = poses["camera"].iloc[i], poses["image_id"].iloc[i]
        png = encode_png(render_image(machine, truth, camera, int(i), seed))
        atomic_write_bytes(staging / "images" / camera / f"{image_id}.png", png)
    return len(rows)
