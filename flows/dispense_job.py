"""The dispensing job (the automated-dispensing paper), after ``calibrate``: trays of boards glued.

For every tray image: locate the boards and their dispensing areas (tasks.dispense_job.locate), map
the accepted areas to the machine (phases ``compensated``: camera 1's calibrated model, the identified
machine model and compensated commands; ``nominal``: the nominal machine, no compensation; ``planar``:
the paper's affine hand–eye map), plan each bead and the tour over the boards, write the dispensing
program (CSV), and for a simulated tray let the true machine run it, image the beads and inspect them.
A tray that fails (unreadable, no board, larger than the travel) is recorded and the others go on; a
rejected board is a row with its reason and the tray goes on without it.

Writes the ``dispense_areas``, ``dispense_paths`` and ``dispense_beads`` tables (partition: the
calibrated campaign) and ``<reports>/<campaign_id>/<run>/dispense-job/`` (report.md, programs,
images of the dispensed trays), published whole: a failed run leaves no half-written folder.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger

from flows.lake_calibration import calibration_from_lake
from tasks.core.version import FIVECAL_VERSION
from tasks.dispense_job.area_acceptance import AcceptanceRules
from tasks.dispense_job.bead_path import bead_path
from tasks.dispense_job.tour_exact import plan_tour
from tasks.dispense_job.travel_time import travel_time_s
from tasks.dispense_job.tray_io import read_tray
from tasks.dispense_job.tray_job import PHASES, Calibration, Planners
from tasks.dispensing.tip import with_tool_offset
from tasks.lake.store import read_provenance, write_partitions
from tasks.report.dispense_job import write_dispense_job_report
from tasks.steps.dispense_job import JOB_CODE_VERSION, dispense_tray_task, locate_task

CAMERA = "camera1"


def load_calibration(campaign: Path, root: Path | None, effect_modules: list[str] | None = None) -> Calibration:
    """The calibrated machine of a campaign from the lake (calibrate's cached identification), with
    the dispensing test's tip offset folded in when it was run; its truth when simulated.
    effect_modules: the user modules defining the effect families the calibration added (default:
    the ones it recorded)."""
    lake = calibration_from_lake(campaign, root, effect_modules)  # calibrate's identification, cached
    campaign_id, machine, model, truth = lake.campaign_id, lake.machine, lake.model, lake.truth
    notes = [f"identified model of campaign {campaign_id}"]
    try:
        tip = read_provenance("dispense_inspection", campaign_id, root).get("tip_offset_um")
    except (FileNotFoundError, OSError):
        tip = None
    if tip is not None:
        model = with_tool_offset(model, tip)
        notes.append("with the dispensing test's tip offset (" + ", ".join(f"{v:+.2f}" for v in tip) + " µm)")
    else:
        notes.append("without a tip offset (fivecal dispense-test not run)")
    return Calibration(campaign_id, machine, model, lake.full_resolution_camera(CAMERA), truth, tuple(notes))


@flow(name="dispense-job")
def dispense_job(images: list[str], campaign: str, results_root: str | None = None, reports_root: str = "reports",
                 run: str | None = None, phases: tuple[str, ...] | None = None, seed: int = 0,
                 effect_modules: list[str] | None = None) -> dict[str, Any]:
    """Run the job on tray images with the calibration of ``campaign``; returns a summary (per tray:
    boards found and accepted, or why it failed; the tables and the report). ``phases``: default all
    three for simulated trays, ``compensated`` alone otherwise. ``effect_modules``: as
    ``fivecal dispense-job --effect-module`` (load_calibration)."""
    logger = get_run_logger()
    root = None if results_root is None else Path(results_root)
    cal = load_calibration(Path(campaign).resolve(), root, effect_modules)
    planners = Planners(plan_tour, travel_time_s, bead_path)
    rules = AcceptanceRules()
    run = run or datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    out_dir = Path(reports_root) / cal.campaign_id / run / "dispense-job"
    programs, dispensed = {}, {}
    results, failures, summary = [], [], {"campaign_id": cal.campaign_id, "trays": {}, "tables": {}}
    for image in images:
        try:
            tray = read_tray(Path(image))
            want = phases or (PHASES if tray.simulated and cal.truth is not None else ("compensated",))
            located = locate_task.submit(str(image), tray.mm_per_px, rules).result()
            res = dispense_tray_task.submit(str(image), located, cal, planners, tuple(want), seed).result()
        except ValueError as e:
            logger.warning(f"tray skipped: {e}")
            failures.append(str(e))
            summary["trays"][Path(image).stem] = {"error": str(e)}
            continue
        results.append(res)
        first = res.areas[res.areas.phase == res.areas.phase.iloc[0]]
        missed = first.reason == "not found"  # true boards of a simulated tray that were not found
        summary["trays"][tray.tray_id] = {"boards": int((~missed).sum()), "accepted": int(first.ok.sum()),
                                          "rejected": first.loc[~first.ok & ~missed, "reason"].tolist()}
        if first.recognised.notna().any():
            summary["trays"][tray.tray_id] |= {"recognised": int(first.recognised.sum()), "true_boards":
                                               int((first.true_defect != "unmatched").sum())}
        programs |= {f"program-{tray.tray_id}-{phase}": program for phase, program in res.programs.items()}
        dispensed |= {f"dispensed-{tray.tray_id}-{phase}": rgb for phase, rgb in res.dispensed.items()}
    areas = pd.concat([r.areas for r in results], ignore_index=True) if results else pd.DataFrame()
    paths = pd.concat([r.paths for r in results], ignore_index=True) if results else pd.DataFrame()
    beads = pd.concat([r.beads for r in results if not r.beads.empty], ignore_index=True) \
        if any(not r.beads.empty for r in results) else pd.DataFrame()
    if not results:
        raise ValueError("no tray could be dispensed: " + "; ".join(failures))
    provenance = {"fivecal_version": FIVECAL_VERSION, "campaign": str(campaign), "job_code": JOB_CODE_VERSION,
                  "images": [str(i) for i in images], "calibration": list(cal.notes), "failures": failures,
                  "effect_modules": list(effect_modules or [])}
    tables = {"dispense_areas": areas, "dispense_paths": paths}
    if not beads.empty:
        tables["dispense_beads"] = beads
    summary["tables"] = {k: str(v) for k, v in write_partitions(tables, cal.campaign_id, provenance, root).items()}
    header = (f"Calibration: {'; '.join(cal.notes)}. Trays: {len(results)} dispensed, {len(failures)} failed.")
    summary["report"] = str(write_dispense_job_report(out_dir, header, areas, paths, beads, failures,
                                                               programs, dispensed))
    summary["areas"], summary["paths"], summary["beads"] = areas, paths, beads
    return summary
