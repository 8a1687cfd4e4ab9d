"""Pose-level companion of docs/examples/context_walkthrough.sh (docs/effects.md, "Measured at the tip"): the
same loop on the same plan (``CampaignPlan.context()``: 206 images in two passes an hour apart), exact poses plus
pose noise of the size the small images give (the demo campaign's median pose standard deviations:
0.21 µm across, 1.7 µm along camera 1's axis, 14.7″ of tilt, 1.15″ about the axis), no images.

Per seed (the plan's and the noise's) and hidden effect (none; 20 µm/h time-driven thermal drift on X;
8 µm backlash on Z; the user family docs/examples/cross_backlash.py, 8 µm along Y by X's approach):
calibrate, diagnose (the user's family first unknown, then registered), refit with the diagnosis' spec
(the accepted one or, with none accepted, its best candidate), and for both models compensate the
validation poses in the capture's planned context and play
the capture: the true tip error (each capture image in its context) and the VBM's (the capture's plate
poses with pose noise), and how far the true compensated tip sits from the clean campaign's (same
seed and validation poses, mean of the per-pose distance). Prints one row per (seed, hidden effect, model).

    python docs/examples/context_at_tip_poses.py 10 67 161
    python docs/examples/context_at_tip_poses.py --plan small 10 67  # another plan of campaign_plan.PLANS
"""

import sys
from dataclasses import replace

import numpy as np
import pandas as pd

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.analysis.diagnosis import diagnose
from tasks.analysis.verification import tip_errors_with_tool_direction, vbm_errors
from tasks.campaign.capture_request import CAPTURE_GAP_IMAGES, planned_capture_context
from tasks.core import se3
from tasks.core.units import ARCSEC
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.pige_identification import synthetic_measurements
from tasks.machine.description import load_machine
from tasks.machine.effects import EFFECTS, load_effect_modules, parse_effect, private_families
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.campaign_plan import PLANS, plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors
from tasks.simulation.verification_capture import capture_plan

COV = np.diag([0.21e-3**2] * 2 + [1.7e-3**2] + [(14.7 * ARCSEC) ** 2] * 2 + [(1.15 * ARCSEC) ** 2])
MODULE = "docs/examples/cross_backlash.py"
HIDDEN = {"none": None, "drift": "thermal_drift:axis=X,driver=time,um_per_hour=20",
          "backlash": "backlash:axis=Z,amount_um=8", "user": "cross_backlash:axis=X,along=Y,amount_um=8"}


def noisy(meas: Measurements, seed: int) -> Measurements:
    noise = np.random.default_rng(seed).normal(size=(len(meas), 6)) @ np.linalg.cholesky(COV).T
    return Measurements(meas.table, meas.T @ se3.exp(noise), meas.cov, meas.context)


def tip_after(machine, truth, model, plan, frame, seed):
    """True tip position error vectors (N, 3) µm and the mean VBM tip position error (µm) after
    compensating the validation poses with ``model``."""
    val = frame.stage("validation", camera="camera1")
    ids, cmds = val.table.image_id.tolist(), val.commands
    planned = planned_capture_context(cmds, plan["time_s"].to_numpy(), plan["temperature_c"].to_numpy())
    comp = compensate(machine, model, cmds, context=planned).commands
    desired = desired_tip_poses(machine, cmds)
    seconds = PLAN.seconds_per_image
    capture = capture_plan(ids, comp, "camera1", plan["time_s"].max() + (CAPTURE_GAP_IMAGES + 1) * seconds, seconds)
    cap_frame = planned_measurements(capture.assign(stage="validation"), COV)
    true_tip = forward(machine, comp, truth, cap_frame.context).tool_in_workpiece()
    measured = noisy(synthetic_measurements(machine, truth, cap_frame), seed + 1000)
    vbm = vbm_errors(machine, model, desired, comp, measured.T, measured.cov, "camera1")
    true_err = tip_errors_with_tool_direction(true_tip, desired)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    return true_err, vbm["position_um"].mean()


def main(seeds):
    machine = load_machine("prototype")
    user = private_families([MODULE])
    rows = []
    for seed in seeds:
        plan, _ = plan_campaign(machine, PLAN, seed)
        frame = planned_measurements(plan, COV)
        clean_err = None
        for name, spec in HIDDEN.items():
            truth = replace(load_prototype_errors(), effects=[parse_effect(spec, user)] if spec else [])
            meas = noisy(synthetic_measurements(machine, truth, frame), seed)
            base = calibrate(machine, meas)
            d = diagnose(machine, meas, base, max_effects=1)
            note = d.best or f"none accepted; top {d.table.iloc[0].spec}"
            if name == "user":
                before = dict(EFFECTS)
                load_effect_modules([MODULE], entry_point_group=None)
                d = diagnose(machine, meas, base, max_effects=1)
                note = f"without the module: {note}; with it: {d.best}"
            # the accepted spec, or with none accepted the best candidate (as context_walkthrough.sh)
            spec_added = d.best or (d.table.iloc[0].spec if name != "none" else None)
            models = [("base", base.model)]
            if spec_added:
                models.append((spec_added, calibrate(machine, meas, base=ErrorModel(effects=[parse_effect(spec_added)]))
                               .model))
            if name == "user":
                EFFECTS.clear()
                EFFECTS.update(before)
            for label, model in models:
                true_err, vbm_um = tip_after(machine, truth, model, plan, frame, seed)
                clean_err = true_err if clean_err is None else clean_err
                rows.append({"seed": seed, "hidden": name, "model": label,
                             "after_truth_um": np.linalg.norm(true_err, axis=1).mean(), "after_vbm_um": vbm_um,
                             # how far the true compensated tip sits from the clean campaign's, pose by pose
                             "shift_from_clean_um": np.linalg.norm(true_err - clean_err, axis=1).mean(),
                             "diagnosis": note if label == "base" else ""})
                print(rows[-1], flush=True)
    out = pd.DataFrame(rows)
    clean = out[out.hidden == "none"].set_index("seed")
    for q in ("after_truth_um", "after_vbm_um"):
        out[f"{q}/clean"] = out[q] / out["seed"].map(clean[q])
    pd.set_option("display.width", 250, "display.max_colwidth", 120)
    print(out.round(3).to_string(index=False))


if __name__ == "__main__":
    args = sys.argv[1:]
    name = args[args.index("--plan") + 1] if "--plan" in args else "context"
    PLAN = PLANS[name]()
    main([int(a) for a in args if a.isdigit()] or [10, 67, 161])
