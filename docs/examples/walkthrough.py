"""The figures of docs/walkthrough.md: a campaign that hides an effect the model lacks, calibrated, diagnosed,
refitted with the diagnosis' spec, beside the same campaign without the effect.

Two levels, one table:

- ``poses`` (default; seconds, no images, no Prefect): the plan's exact poses under the prototype's true
  errors plus pose noise of the size the small images give (the demo campaign's median pose standard
  deviations, as docs/examples/context_at_tip_poses.py), the science functions called directly. This is
  what the test (tests/analysis/test_walkthrough.py) runs on the small plan.
- ``images WORKDIR``: the walk-through's commands themselves (``fivecal simulate`` of both campaigns,
  ``fivecal diagnose``, ``fivecal diagnose --add-effect`` with the printed spec (the refit, then its
  diagnosis), ``fivecal diagnose`` of the campaign without the effect), then the figures read back from
  the results lake under WORKDIR. A campaign already simulated there is reused, and Prefect's cache
  serves what has not changed.

Printed per model: the fit's σ² (train RMS², whitened), the model ladder's cross-validated RMS (refit per
fold of five-axis poses, whitened; 1 at the noise level), the validation tip discrepancy (µm, arcsec) and
the mean true tip error after compensating the validation poses with that model (µm, arcsec) and, on
images, after the dispensing test's tip fit folded into that compensation (µm); and the diagnosis'
first-ranked candidate with its share of the residual and whether it was accepted.

    python docs/examples/walkthrough.py                                  # poses, small plan, seed 7
    python docs/examples/walkthrough.py --plan default --seed 7          # poses, the demo's plan
    python docs/examples/walkthrough.py images WORKDIR --plan default --seed 7   # the image campaigns
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.analysis.diagnosis import diagnose
from tasks.analysis.model_ladder import ladder_step, refit_cross_validated_rms
from tasks.analysis.verification import tip_errors_with_tool_direction
from tasks.campaign.capture_request import CAPTURE_GAP_IMAGES, planned_capture_context
from tasks.core import se3
from tasks.core.units import ARCSEC
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.pige_identification import synthetic_measurements
from tasks.machine.description import load_machine
from tasks.machine.effects import parse_effect
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.campaign_plan import PLANS, plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors
from tasks.simulation.verification_capture import capture_plan

HIDDEN = "backlash:axis=X,amount_um=10"
POSE_COV = np.diag([0.21e-3**2] * 2 + [1.7e-3**2] + [(14.7 * ARCSEC) ** 2] * 2 + [(1.15 * ARCSEC) ** 2])
"""Per-pose covariance of the plate pose's tangent vector (mm², rad²: x, y across camera 1's axis, z along it,
the two tilts, the rotation about the axis): 0.21 µm, 0.21 µm, 1.7 µm, 14.7″, 14.7″, 1.15″."""
COLUMNS = ["campaign", "model", "sigma2", "cv_rms", "bic", "validation_position_um", "validation_orientation_arcsec",
           "noise_floor_position_um", "true_tip_after_um", "true_tip_after_arcsec", "vbm_tip_after_um",
           "true_tip_after_dispensing_um"]


@dataclass
class Story:
    """ladder: one row per (campaign, model) with :data:`COLUMNS`. diagnosis: the hidden-effect campaign's
    diagnosis table of the base model (rank order); after: the same of the refit with the added effect;
    clean_diagnosis: the campaign without the effect's. added: the spec the
    hidden-effect campaign was refitted with (:func:`added_spec`). trends (images only): camera 1's
    significant residual trend panels (the ``residual_trends`` table) per "hidden", "after", "clean".
    effect_rows (images only): the refit's ``pige`` rows of kind "effect" (value, propagated uncertainty
    and its parts, truth in the fit's gauge)."""

    ladder: pd.DataFrame
    diagnosis: pd.DataFrame
    after: pd.DataFrame
    clean_diagnosis: pd.DataFrame
    added: str
    trends: dict[str, pd.DataFrame] = field(default_factory=dict)
    effect_rows: pd.DataFrame = field(default_factory=pd.DataFrame)


def noisy(meas: Measurements, seed: int) -> Measurements:
    """``meas`` with pose noise drawn from :data:`POSE_COV` (seeded)."""
    noise = np.random.default_rng(seed).normal(size=(len(meas), 6)) @ np.linalg.cholesky(POSE_COV).T
    return Measurements(meas.table, meas.T @ se3.exp(noise), meas.cov, meas.context)


def true_tip_after(machine, truth: ErrorModel, model: ErrorModel, plan: pd.DataFrame, frame: Measurements,
                   seconds_per_image: float) -> tuple[float, float]:
    """Mean true tip position (µm) and orientation (arcsec) error of the validation poses compensated
    with ``model`` (in the context the capture will give them) and driven on ``truth`` in the capture's
    context, as the verification capture plays them."""
    val = frame.stage("validation", camera="camera1")
    cmds = val.commands
    planned = planned_capture_context(cmds, plan["time_s"].to_numpy(), plan["temperature_c"].to_numpy())
    comp = compensate(machine, model, cmds, context=planned).commands
    start = plan["time_s"].max() + (CAPTURE_GAP_IMAGES + 1) * seconds_per_image
    capture = capture_plan(val.table.image_id.tolist(), comp, "camera1", start, seconds_per_image)
    played = planned_measurements(capture.assign(stage="validation"), POSE_COV)
    err = tip_errors_with_tool_direction(forward(machine, comp, truth, played.context).tool_in_workpiece(),
                                         desired_tip_poses(machine, cmds))
    return float(err["position_um"].mean()), float(err["orientation_arcsec"].mean())


def ladder_row(machine, campaign: str, label: str, result, meas: Measurements, tip: tuple[float, float]) -> dict:
    """One row of :data:`COLUMNS` for a calibration ``result`` of ``meas``: the model ladder's figures
    (:func:`tasks.analysis.model_ladder.ladder_step`, its cross-validated RMS refitted per fold) and ``tip``, the
    (µm, arcsec) of :func:`true_tip_after`."""
    step = ladder_step(machine, result.model, result.pige.fit, meas,
                       cv_rms=refit_cross_validated_rms(machine, result.model, result.pige.specs, meas))
    return {"campaign": campaign, "model": label, "sigma2": step["train_rms"] ** 2, "cv_rms": step["cv_rms"],
            "bic": step["bic"], "validation_position_um": step["validation_position_um"],
            "validation_orientation_arcsec": step["validation_orientation_arcsec"],
            "noise_floor_position_um": step["noise_floor_position_um"],
            "true_tip_after_um": tip[0], "true_tip_after_arcsec": tip[1], "vbm_tip_after_um": float("nan"),
            "true_tip_after_dispensing_um": float("nan")}


def added_spec(accepted: str | None, table: pd.DataFrame) -> str:
    """The spec the walk-through adds: the one the diagnosis accepted or, with none accepted, its
    first-ranked candidate (as docs/examples/context_walkthrough.sh does)."""
    return accepted or str(table.iloc[0].spec)


def pose_story(plan_name: str = "small", seed: int = 7, hidden: str = HIDDEN) -> Story:
    """The walk-through at pose level: the campaign of ``plan_name`` and ``seed`` with ``hidden`` and
    without it (same plan, same noise draw), calibrated and diagnosed; the first refitted with
    :func:`added_spec` and the refit diagnosed again."""
    machine = load_machine("prototype")
    plan_spec = PLANS[plan_name]()
    plan, _ = plan_campaign(machine, plan_spec, seed)
    frame = planned_measurements(plan, POSE_COV)
    rows, tables = [], {}
    for campaign, effects in (("hidden", [parse_effect(hidden)]), ("clean", [])):
        truth = replace(load_prototype_errors(), effects=effects)
        meas = noisy(synthetic_measurements(machine, truth, frame), seed)
        base = calibrate(machine, meas)
        d = diagnose(machine, meas, base, max_effects=1)
        tables[campaign] = d.table
        fits = [("base", base)]
        if campaign == "hidden":
            added = added_spec(d.best, d.table)
            fits.append((f"+ {added}", calibrate(machine, meas, base=ErrorModel(effects=[parse_effect(added)]))))
            tables["after"] = diagnose(machine, meas, fits[-1][1], max_effects=1).table
        for label, result in fits:
            tip = true_tip_after(machine, truth, result.model, plan, frame, plan_spec.seconds_per_image)
            rows.append(ladder_row(machine, campaign, label, result, meas, tip))
    return Story(pd.DataFrame(rows, columns=COLUMNS), tables["hidden"], tables["after"], tables["clean"], added)


def _fivecal(*args: str) -> str:
    """Run one fivecal command (this interpreter's environment); its output, echoed; raise on failure."""
    cmd = [str(Path(sys.executable).with_name("fivecal")), *args]
    print("$", " ".join(cmd), flush=True)
    out = subprocess.run(cmd, capture_output=True, text=True)
    print(out.stdout[-4000:], out.stderr[-2000:] if out.returncode else "", sep="", flush=True)
    if out.returncode:
        raise SystemExit(f"error: {' '.join(args[:2])} exited {out.returncode}")
    return out.stdout


def image_story(workdir: Path, plan_name: str = "default", seed: int = 7, hidden: str = HIDDEN) -> Story:
    """The walk-through's commands on image campaigns under ``workdir`` (campaigns/, results/, reports/),
    then its figures read from the lake. A campaign already simulated there is reused."""
    from tasks.lake.store import read_table

    camps, results, reports = workdir / "campaigns", workdir / "results", workdir / "reports"
    lake = ["--results", str(results), "--reports", str(reports)]
    for name, effect in (("walk-hidden", ["--effect", hidden]), ("walk-clean", [])):
        if not (camps / name / "manifest.csv").exists():
            _fivecal("simulate", str(camps / name), "--size", "small", "--seed", str(seed), "--plan", plan_name,
                     *effect)
    def diagnosis_of(cid: str) -> pd.DataFrame:  # each calibrate run replaces the campaign's partition
        diag = read_table("diagnosis", results)
        return diag[diag.campaign_id == cid].sort_values("rank")

    def trends_of(cid: str) -> pd.DataFrame:
        t = read_table("residual_trends", results)
        t = t[(t.campaign_id == cid) & (t.camera == "camera1") & t.significant]
        return t.sort_values("p_value")[["variable", "component", "span", "p_value"]]

    def dispensing_test(name: str, *effect: str) -> float:
        """``fivecal dispense-test`` of the campaign's latest calibration: the mean true tip error (µm) of
        the held-out poses compensated with the tip fit folded in."""
        _fivecal("dispense-test", str(camps / name), *effect, *lake)
        v = read_table("verification", results, campaign_id=name)
        return float(v[(v.phase == "after_tip") & (v.source == "truth")].position_um.mean())

    out = _fivecal("diagnose", str(camps / "walk-hidden"), *lake)
    base, trends = diagnosis_of("walk-hidden"), {"hidden": trends_of("walk-hidden")}
    dispensed = {("hidden", "base"): dispensing_test("walk-hidden")}
    found = re.search(r"^next: fivecal calibrate .* --add-effect '(.*)'$", out, re.M)
    added = added_spec(found.group(1) if found else None, base)
    _fivecal("diagnose", str(camps / "walk-hidden"), "--add-effect", added, *lake)
    after, trends["after"] = diagnosis_of("walk-hidden"), trends_of("walk-hidden")
    dispensed["hidden", "added"] = dispensing_test("walk-hidden")
    pige = read_table("pige", results, campaign_id="walk-hidden")
    effect_rows = pige[pige.kind == "effect"][["name", "value", "uncertainty", "uncertainty_fit", "uncertainty_noise",
                                               "uncertainty_camera", "truth", "note"]]
    _fivecal("diagnose", str(camps / "walk-clean"), *lake)
    trends["clean"] = trends_of("walk-clean")
    dispensed["clean", "base"] = dispensing_test("walk-clean")
    ladder = read_table("model_ladder", results)
    rows = []
    for campaign, cid in (("hidden", "walk-hidden"), ("clean", "walk-clean")):
        for _, s in ladder[ladder.campaign_id == cid].sort_values("step").iterrows():
            rows.append({"campaign": campaign, "model": f"+ {s.effect_specs}" if s.effect_specs else "base",
                         "sigma2": s.train_rms**2, "cv_rms": s.cv_rms, "bic": s.bic,
                         "validation_position_um": s.validation_position_um,
                         "validation_orientation_arcsec": s.validation_orientation_arcsec,
                         "noise_floor_position_um": s.noise_floor_position_um,
                         "true_tip_after_um": s.compensated_truth_position_um,
                         "true_tip_after_arcsec": s.compensated_truth_orientation_arcsec,
                         "vbm_tip_after_um": s.compensated_vbm_position_um,
                         "true_tip_after_dispensing_um": dispensed.get(
                             (campaign, "added" if s.effect_specs else "base"), float("nan"))})
    return Story(pd.DataFrame(rows, columns=COLUMNS), base, after, diagnosis_of("walk-clean"), added, trends,
                 effect_rows)


def print_story(story: Story, hidden: str) -> None:
    pd.set_option("display.width", 250, "display.max_colwidth", 100)
    print(f"hidden effect: {hidden}")
    print("diagnosis of the hidden-effect campaign (base model), top 3:")
    cols = ["rank", "spec", "explained", "p_value", "delta_bic", "cv_rms", "accepted"]
    print(story.diagnosis[cols].head(3).to_string(index=False))
    accepted = bool(story.diagnosis.iloc[0].accepted)
    print(f"added: {story.added} ({'accepted' if accepted else 'not accepted: the first-ranked candidate'})")
    print("diagnosis after adding it, top 1:")
    print(story.after[cols].head(1).to_string(index=False))
    print("diagnosis of the campaign without the effect, top 1:")
    print(story.clean_diagnosis[cols].head(1).to_string(index=False))
    if len(story.effect_rows):
        print("the added effect's pige rows:")
        print(story.effect_rows.to_string(index=False))
    for name, t in story.trends.items():
        print(f"camera1 residual trend panels flagged ({name}): {len(t)}; the first 6 by p:")
        print(t.head(6).round(4).to_string(index=False))
    print(story.ladder.round(3).to_string(index=False))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("level", nargs="?", default="poses", choices=["poses", "images"])
    ap.add_argument("workdir", nargs="?", type=Path, help="images: folder for campaigns, results, reports")
    ap.add_argument("--plan", default=None, choices=sorted(PLANS), help="poses: small; images: default")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--effect", default=HIDDEN, help="the hidden effect's spec")
    a = ap.parse_args(argv)
    if a.level == "images":
        if a.workdir is None:
            ap.error("images needs WORKDIR")
        story = image_story(a.workdir, a.plan or "default", a.seed, a.effect)
    else:
        story = pose_story(a.plan or "small", a.seed, a.effect)
    print_story(story, a.effect)


if __name__ == "__main__":
    main()
