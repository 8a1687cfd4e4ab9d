"""Identification science at pose level (no images, no Prefect): PDGE extraction, the LM of eq. 22
with its identifiability report, compensation and the verification noise floor."""

import numpy as np
import pandas as pd
import pytest

from tasks.campaign_plan import CampaignPlan, plan_campaign
from tasks.compensation import compensate, desired_tip_poses
from tasks.context import PoseContext
from tasks.error_model import ARCSEC, UM, ErrorModel
from tasks.identification.levenberg_marquardt import levenberg_marquardt
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import apply_parameters, default_parameters
from tasks.identification.pdge_extraction import COMPONENT_COLUMNS, extract_pdges
from tasks.identification.pige_identification import identify_pige, synthetic_measurements
from tasks.kinematics import forward
from tasks.machine import AXIS_ORDER
from tasks.prototype_errors import load_prototype_errors
from tasks.verification import noise_floor


def _measurements(machine, plan: pd.DataFrame) -> Measurements:
    machine_rows = plan[plan.stage != "camera_calibration"].reset_index(drop=True)
    n = len(machine_rows)
    cov = np.tile(np.diag([0.2e-3**2] * 2 + [4e-3**2] + [(70 * ARCSEC) ** 2] * 2 + [(3 * ARCSEC) ** 2]), (n, 1, 1))
    like = Measurements(machine_rows, np.tile(np.eye(4), (n, 1, 1)), cov, PoseContext.neutral(n))
    return like


def test_pdge_extraction_recovers_the_true_profiles_from_noise_free_sweeps(machine):
    """eqs. 13-19: with exact poses, the extracted (home-referred) PDGEs equal the truth in the same gauge."""
    plan, _ = plan_campaign(machine, CampaignPlan(sweep_positions=30, sweep_repeats=1, pige_poses=4,
                                                  validation_poses=2, calibration_trials=1, images_per_trial=1), 3)
    truth = load_prototype_errors()
    meas = synthetic_measurements(machine, truth, _measurements(machine, plan))
    result = extract_pdges(machine, ErrorModel(pige=truth.pige), meas, truth)
    t = result.table
    assert set(t.axis) == set(AXIS_ORDER)
    for col in COMPONENT_COLUMNS:
        err = np.abs(t[col] - t[f"truth_{col}"])
        scale = 0.05 if col.endswith("um") else 2.0  # µm, arcsec: second-order terms (C turns ±180° with 50″ PIGEs)
        assert err.max() < scale, (col, err.max())


def test_lm_recovers_parameters_and_names_the_direction_it_cannot_fix(machine):
    """eq. 22 on exact poses: identifiable parameters come back; gamma_YX and beta_AY (a rigid turn of the
    tool chain against the workpiece chain about z: they move every pose alike) are reported together."""
    plan, _ = plan_campaign(machine, CampaignPlan(sweep_positions=2, sweep_repeats=1, pige_poses=120,
                                                  validation_poses=2, calibration_trials=1, images_per_trial=1), 5)
    specs = default_parameters()
    rng = np.random.default_rng(0)
    true_x = np.array([rng.normal(0, 20) * s.scale for s in specs])
    truth = apply_parameters(ErrorModel(), specs, true_x)
    meas = synthetic_measurements(machine, truth, _measurements(machine, plan)).stage("pige")
    fit = identify_pige(machine, ErrorModel(), meas, specs)
    names = [s.name for s in specs]
    assert not fit.fit.identifiable[names.index("gamma_YX")] and not fit.fit.identifiable[names.index("beta_AY")]
    ok = fit.fit.identifiable
    assert ok.sum() >= 5
    np.testing.assert_allclose(fit.fit.x[ok] / [s.scale for s, k in zip(specs, ok, strict=True) if k],
                               true_x[ok] / [s.scale for s, k in zip(specs, ok, strict=True) if k], atol=0.5)
    # atol of ~20 µm/″: small loadings (< 0.1) on the unexcited directions, which stay at zero, bias them slightly
    # the fitted model reproduces every measured pose even though the split along null directions is arbitrary
    res = forward(machine, meas.commands, fit.model).camera_view("camera1")
    assert np.abs(res[:, :3, 3] - meas.T[:, :3, 3]).max() < 5e-5  # mm: 0.05 µm


def test_lm_reports_uncertainty_that_matches_the_scatter_of_noisy_refits():
    """Linear model y = a x + b with unit noise: the reported standard uncertainty equals the textbook one."""
    rng = np.random.default_rng(1)
    x = np.linspace(-1, 1, 200)
    y = 3.0 * x + 0.5 + rng.normal(size=x.size)
    fit = levenberg_marquardt(lambda p: p[0] * x + p[1] - y, np.zeros(2), np.array([1e-3, 1e-3]),
                              max_uncertainty=1e9)
    np.testing.assert_allclose(fit.x, np.polyfit(x, y, 1), atol=1e-8)
    sd = np.sqrt(fit.sigma2 / np.sum((x - x.mean()) ** 2))
    assert fit.uncertainty[0] == pytest.approx(sd, rel=1e-6)


def test_compensation_puts_the_identified_machine_on_the_nominal_tip_poses(machine):
    truth = load_prototype_errors()
    rng = np.random.default_rng(2)
    from tasks.campaign_plan import five_axis_poses

    cmds = five_axis_poses(machine, 20, CampaignPlan(), rng)
    comp = compensate(machine, truth, cmds)
    reached = forward(machine, comp, truth).tool_in_workpiece()
    desired = desired_tip_poses(machine, cmds)
    assert np.abs(reached[:, :3, 3] - desired[:, :3, 3]).max() < 1e-6 * 1e3 * UM
    assert np.abs(reached[:, :3, 2] - desired[:, :3, 2]).max() < 1e-8


def test_noise_floor_propagates_tilt_noise_with_the_tip_lever_arm():
    tip = np.tile(np.eye(4), (1, 1, 1))
    tip[0, :3, 3] = [60.0, 0.0, 0.0]
    cov = np.diag([0.0] * 4 + [1e-4**2, 0.0])[None]  # only a tilt about y: 1e-4 rad
    pos, ori = noise_floor(tip, cov)
    assert pos[0] == pytest.approx(60.0 * 1e-4 * 1e3)  # µm
    assert ori[0] == pytest.approx(1e-4 / ARCSEC)
