"""Effects that depend on approach direction, time or temperature reach the tip: in the simulator's
truth (truth-stats, the campaign's and the capture's true tip errors), in the compensation (the
capture's planned context) and in the model ladder; a user effect recorded with the truth is loaded by
the simulator's side without entering the catalogue."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.analysis.model_ladder import LADDER_COLUMNS, TIP_COLUMNS, add_step, compensated_tip_errors
from tasks.campaign.capture_request import capture_times, planned_capture_context
from tasks.machine.context import PoseContext
from tasks.machine.effects import EFFECTS, parse_effect, private_families
from tasks.machine.kinematics import forward, tip_pose_error
from tasks.simulation.campaign_plan import CampaignPlan, plan_context
from tasks.simulation.prototype_errors import load_prototype_errors
from tasks.simulation.simulate import read_truth, write_campaign_truth
from tasks.simulation.truth_stats import effects_change, validation_poses
from tasks.simulation.verification_capture import capture_plan, true_campaign_errors, true_capture_errors

USER_MODULE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "cross_backlash.py"
TINY_PLAN = CampaignPlan(calibration_trials=1, images_per_trial=2, sweep_positions=2, sweep_repeats=2,
                         pige_poses=2, validation_poses=5)
HIDDEN = ("backlash:axis=Z,amount_um=8", "thermal_drift:axis=X,driver=time,um_per_hour=20",
          "cross_backlash:axis=X,along=Y,amount_um=6")


def expected_shift_um(context: PoseContext) -> np.ndarray:
    """‖tip shift‖ (µm) of the HIDDEN effects: ±4 µm along Z by Z's approach, 20 µm/h × t along X,
    ±3 µm along Y by X's approach (base frame; the norm is the same in the workpiece frame)."""
    return np.sqrt((20 * context.time_s / 3600) ** 2 + 3.0**2 * context.approach[:, 0] ** 2
                   + 4.0**2 * context.approach[:, 2] ** 2)


@pytest.fixture(scope="module")
def user_families():
    return private_families([USER_MODULE])


@pytest.mark.parametrize("spec,size", [
    ("backlash:axis=Z,amount_um=8", lambda c: np.full(len(c.time_s), 4.0)),
    ("backlash:axis=X,amount_um=10", lambda c: np.full(len(c.time_s), 5.0)),
    ("thermal_drift:axis=X,driver=time,um_per_hour=20", lambda c: 20 * c.time_s / 3600),
    ("thermal_drift:axis=Y,driver=temperature,um_per_k=10", lambda c: np.abs(10 * (c.temperature_c - 20))),
    ("cross_backlash:axis=X,along=Y,amount_um=6", lambda c: np.full(len(c.time_s), 3.0)),
])
def test_truth_stats_move_by_each_context_effect_in_the_campaign_context(machine, user_families, spec, size):
    """truth-stats' validation poses carry their campaign context: each context-dependent family moves
    every pose's true tip by its size then (the time-driven drift by 20 µm/h × ~1.6 h ≈ 32 µm)."""
    cmds, context = validation_poses(machine, 12, seed=3)
    assert np.all(context.approach != 0) and context.time_s.min() > 5000
    errors = load_prototype_errors()
    errors.effects = [parse_effect(spec, user_families)]
    change = effects_change(machine, cmds, errors, context)
    assert np.allclose(change["position_um"], size(context), rtol=1e-6, atol=1e-6)
    assert change["position_um"].min() > 2.5


@pytest.fixture(scope="module")
def hidden_campaign(tmp_path_factory, user_families):
    """The truth of a tiny campaign (no images) hiding the three HIDDEN context effects, the user's
    family given as a module and then dropped from the catalogue (an analysis that lacks it)."""
    from tasks.machine.effects import load_effect_modules

    folder = tmp_path_factory.mktemp("hidden") / "camp"
    before = dict(EFFECTS)
    load_effect_modules([str(USER_MODULE)], entry_point_group=None)
    try:
        write_campaign_truth(folder, "hidden", 5, "small", list(HIDDEN), TINY_PLAN, [str(USER_MODULE)])
    finally:
        EFFECTS.clear()
        EFFECTS.update(before)
    return folder


def test_a_user_effect_recorded_with_the_truth_loads_without_entering_the_catalogue(hidden_campaign):
    assert "cross_backlash" not in EFFECTS
    assert (hidden_campaign / "truth" / "effect_modules" / "cross_backlash.py").is_file()
    doc, truth = read_truth(hidden_campaign)
    assert doc["effect_modules"] == ["cross_backlash.py"]
    assert [e.spec() for e in truth.effects][2] == "cross_backlash:axis=X,along=Y,amount_um=6"
    assert "cross_backlash" not in EFFECTS  # the analysis side still does not know it
    with pytest.raises(ValueError, match="unknown effect family 'cross_backlash'"):
        parse_effect(HIDDEN[2])


def test_the_campaign_and_capture_truth_carry_each_image_context(machine, hidden_campaign):
    """The true tip errors of the validation images (before) and of the capture (after) move by the
    hidden effects' size in each image's context: its approach, its time in the plan or the capture's
    schedule (which the analysis side predicts from the manifest's times alone)."""
    manifest = pd.read_csv(hidden_campaign / "manifest.csv")
    val = manifest[manifest["stage"] == "validation"]
    ids = val["image_id"].tolist()
    cmds = val[["X_mm", "Y_mm", "Z_mm", "A_deg", "C_deg"]].to_numpy(float)
    desired = desired_tip_poses(machine, cmds)
    clean = forward(machine, cmds, load_prototype_errors()).tool_in_workpiece()
    from tasks.simulation.simulate import plan_campaign

    plan, _ = plan_campaign(machine, TINY_PLAN, 5)
    ctx = plan_context(plan).take(val.index.to_numpy())
    before = true_campaign_errors(hidden_campaign, ids, cmds, desired)
    shift = np.linalg.norm(before[["dx_um", "dy_um", "dz_um"]].to_numpy() - tip_pose_error(clean, desired)[
        ["dx_um", "dy_um", "dz_um"]].to_numpy(), axis=1)
    assert np.allclose(shift, expected_shift_um(ctx), atol=0.01)  # µm: second order with the other errors

    capture = capture_plan(ids, cmds, "camera1", 0.0, 3.0)  # only its order matters for the approach
    planned_times = capture_times(plan["time_s"].to_numpy(), len(ids))
    after = true_capture_errors(hidden_campaign, ids, cmds, desired)
    cap_ctx = PoseContext(plan_context(capture).approach, planned_times, np.full(len(ids), 20.0))
    shift = np.linalg.norm(after[["dx_um", "dy_um", "dz_um"]].to_numpy() - tip_pose_error(clean, desired)[
        ["dx_um", "dy_um", "dz_um"]].to_numpy(), axis=1)
    assert np.allclose(shift, expected_shift_um(cap_ctx), atol=0.01)
    assert np.all(shift > 4.0)


def test_compensation_in_the_planned_context_removes_the_context_effects(machine, user_families):
    """Compensating with the capture's planned context (approach of the capture's moves, its schedule)
    puts the tip where it should be in the context the simulator then gives the moves; without it, the
    tip misses by the effects' size."""
    cmds, campaign = validation_poses(machine, 6, seed=2)
    model = load_prototype_errors()
    model.effects = [parse_effect(s, user_families) for s in HIDDEN]
    planned = planned_capture_context(cmds, campaign.time_s, campaign.temperature_c)
    desired = desired_tip_poses(machine, cmds)
    with_context = compensate(machine, model, cmds, context=planned).commands
    without = compensate(machine, model, cmds).commands
    sim = capture_plan([f"v{i}" for i in range(len(cmds))], with_context, "camera1", 0.0, 3.0)
    sim_context = PoseContext(plan_context(sim).approach, planned.time_s, planned.temperature_c)
    assert np.array_equal(sim_context.approach, planned.approach)
    reached = tip_pose_error(forward(machine, with_context, model, sim_context).tool_in_workpiece(), desired)
    assert reached["position_um"].max() < 1e-3
    missed = tip_pose_error(forward(machine, without, model, sim_context).tool_in_workpiece(), desired)
    assert np.allclose(missed["position_um"], expected_shift_um(planned), rtol=1e-3)


def test_the_ladder_carries_the_compensated_tip_error():
    verification = pd.DataFrame({"phase": ["before", "after", "after", "after", "after"],
                                 "source": ["vbm", "vbm", "vbm", "truth", "truth"],
                                 "position_um": [50.0, 3.0, 5.0, 2.0, 4.0],
                                 "orientation_arcsec": [100.0, 30.0, 50.0, 20.0, 40.0]})
    tip = compensated_tip_errors(verification)
    assert tip == {"compensated_vbm_position_um": 4.0, "compensated_vbm_orientation_arcsec": 40.0,
                   "compensated_truth_position_um": 3.0, "compensated_truth_orientation_arcsec": 30.0}
    lab = compensated_tip_errors(verification[verification["source"] == "vbm"])
    assert np.isnan(lab["compensated_truth_position_um"])
    # a ladder written before the columns existed takes the new step, its old rows NaN
    old_columns = [c for c in LADDER_COLUMNS if c not in TIP_COLUMNS.values()]
    old = pd.DataFrame([{c: 0 for c in old_columns} | {"effects": "", "created_at": pd.Timestamp.now(tz="UTC")}])
    row = {c: 1 for c in LADDER_COLUMNS} | {"effects": "backlash:axis=Z", **tip,
                                            "created_at": pd.Timestamp.now(tz="UTC")}
    ladder = add_step(old.reindex(columns=list(LADDER_COLUMNS)), row)
    assert list(ladder.columns) == list(LADDER_COLUMNS)
    assert ladder["compensated_vbm_position_um"].tolist()[1] == 4.0
    assert np.isnan(ladder["compensated_vbm_position_um"].iloc[0])


CAMPAIGN_COV = np.diag([0.21e-3**2] * 2 + [1.7e-3**2] + [(14.7 / 206265) ** 2] * 2 + [(1.15 / 206265) ** 2])
"""Pose noise of the size the small images give (the demo campaign's median pose standard deviations)."""


@pytest.fixture(scope="module")
def context_campaign(machine):
    """The context plan (seed 10) at pose level: its plan, measurement frame and clean calibration."""
    from tasks.identification.calibration import calibrate
    from tasks.identification.measurements import planned_measurements
    from tasks.simulation.campaign_plan import plan_campaign

    plan, _ = plan_campaign(machine, CampaignPlan.context(), 10)
    frame = planned_measurements(plan, CAMPAIGN_COV)
    clean = _noisy_poses(machine, frame, [])
    return plan, frame, calibrate(machine, clean).model


def _noisy_poses(machine, frame, effects):
    from tasks.core import se3
    from tasks.identification.measurements import Measurements
    from tasks.identification.pige_identification import synthetic_measurements

    truth = load_prototype_errors()
    truth.effects = list(effects)
    exact = synthetic_measurements(machine, truth, frame)
    noise = np.random.default_rng(10).normal(size=(len(exact), 6)) @ np.linalg.cholesky(CAMPAIGN_COV).T
    return Measurements(exact.table, exact.T @ se3.exp(noise), exact.cov, exact.context)


def _true_tip_after(machine, plan, truth, model) -> float:
    """Mean true tip position error (µm) of the validation poses compensated with ``model`` in the
    capture's planned context, each capture image in the context the simulator gives it."""
    from tasks.campaign.capture_request import CAPTURE_GAP_IMAGES

    val = plan[plan.stage == "validation"]
    cmds = val[["X", "Y", "Z", "A", "C"]].to_numpy()
    planned = planned_capture_context(cmds, plan.time_s.to_numpy(), plan.temperature_c.to_numpy())
    comp = compensate(machine, model, cmds, context=planned).commands
    capture = capture_plan(val.image_id.tolist(), comp, "camera1",
                           plan.time_s.max() + (CAPTURE_GAP_IMAGES + 1) * 3.0, 3.0)
    reached = forward(machine, comp, truth, plan_context(capture)).tool_in_workpiece()
    return float(tip_pose_error(reached, desired_tip_poses(machine, cmds))["position_um"].mean())


@pytest.mark.parametrize("hidden,family,size", [
    ("thermal_drift:axis=X,driver=time,um_per_hour=20", "thermal_drift", ("um_per_hour", 20.0)),
    ("backlash:axis=Z,amount_um=8", "backlash", ("amount_um", 8.0)),
])
def test_on_the_context_plan_the_diagnosis_accepts_the_hidden_effect_and_adding_it_restores_the_tip(
        machine, context_campaign, hidden, family, size):
    """A campaign of the context plan with a hidden time drift or backlash (pose level, image-sized
    pose noise): the diagnosis accepts the family at its size (5 %), and the model with it, fitted and
    ended with the joint step, compensates the true tip to within 1.2× of the clean campaign's, where
    the model without it is off by the effect."""
    from tasks.analysis.diagnosis import diagnose
    from tasks.identification.calibration import calibrate
    from tasks.machine.error_model import ErrorModel

    plan, frame, clean_model = context_campaign
    effect = parse_effect(hidden)
    meas = _noisy_poses(machine, frame, [effect])
    base = calibrate(machine, meas)
    d = diagnose(machine, meas, base, max_effects=1)
    assert d.best is not None, d.sentences[0]
    found = parse_effect(d.best)
    assert found.family == family and found[size[0]] == pytest.approx(size[1], rel=0.05)
    truth = load_prototype_errors()
    truth.effects = [effect]
    clean_tip = _true_tip_after(machine, plan, load_prototype_errors(), clean_model)
    without = _true_tip_after(machine, plan, truth, base.model)
    with_it = _true_tip_after(machine, plan, truth, calibrate(machine, meas, base=ErrorModel(effects=[found])).model)
    assert with_it < 1.2 * clean_tip < without, (clean_tip, without, with_it)
