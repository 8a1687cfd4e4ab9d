"""The model uncertainty of the tip after the dispensing test's tip fit, at pose level (no images, no
Prefect), against the simulator's truth."""

from dataclasses import replace

import numpy as np
import pytest

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.analysis.verification import modelled_errors
from tasks.core import se3
from tasks.dispensing.tip import fit_tip_offset, landing_points
from tasks.dispensing.tip_uncertainty import after_tip_uncertainty
from tasks.dispensing.workpiece import Workpiece, ring_layout
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.pige_identification import synthetic_measurements
from tasks.identification.uncertainty import PropagatedUncertainty, propagate_uncertainty
from tasks.machine.effects import ToolOffset
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign

COV = np.diag([0.2e-3**2] * 2 + [4e-3**2] + [(70 * np.pi / 648000) ** 2] * 2 + [(3 * np.pi / 648000) ** 2])
SMALL = CampaignPlan(sweep_positions=50, sweep_repeats=1, pige_poses=150, validation_poses=30,
                     calibration_trials=1, images_per_trial=1)


def _dispensed(machine, model, five_axis_commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(commands (2R, 5), ring centres (2R, 2)) of the flow's two workpieces over the five-axis poses'
    range: the first dispensed nominally, the second compensated by ``model``."""
    ranges = np.column_stack([five_axis_commands.min(axis=0), five_axis_commands.max(axis=0)])
    first, second = (ring_layout(machine, Workpiece(), ranges, seed) for seed in (1, 2))
    commands = np.vstack([first.commands, compensate(machine, model, second.commands).commands])
    return commands, np.vstack([first.centres, second.centres])


def _focal_like_sensitivity(meas: Measurements, camera: str) -> np.ndarray:
    """(N, 6, 1): one 'intrinsic' that moves each pose of ``camera`` along its line of sight by its
    distance per unit (a relative focal-length error)."""
    S = np.zeros((len(meas), 6, 1))
    rows = (meas.table.camera == camera).to_numpy()
    S[rows, :3, 0] = np.einsum("nji,nj->ni", meas.T[rows, :3, :3], meas.T[rows, :3, 3])
    return S


def test_after_tip_uncertainty_predicts_what_a_camera_error_leaves_after_the_tip_fit(machine, errors):
    """Exact poses, every camera-1 pose moved by a focal-length error of 2σ (200 ppm against a
    stated 100 ppm), calibrated, compensated, its tip fitted from exact dots on the flow's two
    workpieces and folded in. The propagation (about that calibration) is rank one here, so the true
    error after the tip fit must be twice the stated uncertainty at every pose. Almost all of it (10.9 of 11.0 µm) is a
    constant along the tool axis: what the dispensing poses (seen through sin A, beside the sin A
    term) make of the model's error, not its constant over the validation poses. The pose-varying
    part at the validation poses alone would state 0.33 µm per σ where 5.5 µm is right: the cross
    terms through the fit must be right."""
    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, planned_measurements(plan, COV))
    S = _focal_like_sensitivity(clean, "camera1")
    moved = Measurements(clean.table, clean.T @ se3.exp(S[:, :, 0] * 200e-6), clean.cov, clean.context)
    result = calibrate(machine, moved)
    model = result.model
    # propagated about the moved calibration: the truth lies 2σ away along the one direction
    prop = propagate_uncertainty(machine, result, moved, _focal_like_sensitivity(moved, "camera1"),
                                 {"camera1": np.array([[100e-6**2]])}, draws=0)

    commands, rings = _dispensed(machine, model, clean.stage("pige").commands)
    fit = fit_tip_offset(machine, model, commands, rings, landing_points(machine, errors, commands) - rings)
    val = clean.stage("validation", camera="camera1").commands
    after_tip = compensate(machine, fit.model, val).commands
    true = modelled_errors(machine, errors, desired_tip_poses(machine, val), after_tip)["position_um"].to_numpy()
    # the dots are exact: the fit's dot-noise term is the next test's
    stated = after_tip_uncertainty(machine, model, prop, commands, np.zeros((3, 3)), after_tip)
    u = stated.norms()[0]
    assert true.mean() > 5.0  # measured 10.97 µm; after compensation alone 60 µm
    np.testing.assert_allclose(true / u, 2.0, rtol=0.05)  # measured 1.98–2.01
    c = np.linalg.eigvalsh(stated.constant_covariance_um2)
    assert np.sqrt(c[-1]) == pytest.approx(true.mean() / 2, rel=0.05)  # the constant is most of it


def test_after_tip_uncertainty_states_the_dot_noise_the_fit_leaves(machine, errors):
    """No model error but the tip's: the truth is the identified model with a tool offset, the dots
    carry 1.2 µm of noise per axis (the image panel's measured − true). Over 40 draws of the dots,
    the mean squared true tip error at the validation poses compensated with each fit is the
    stated u² (pooled over the draws: χ² on 120 degrees of freedom, ±13 %)."""
    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = planned_measurements(plan, COV)
    val_commands = clean.stage("validation", camera="camera1").commands[:10]
    truth = replace(errors, effects=[ToolOffset(dx_um=1.9, dy_um=-2.1, dz_um=10.8)])
    commands, rings = _dispensed(machine, errors, clean.stage("pige").commands)
    desired = desired_tip_poses(machine, val_commands)
    nothing = PropagatedUncertainty([], np.zeros(0), np.zeros(0), {}, np.zeros(0), [], [])
    exact = landing_points(machine, truth, commands) - rings
    rng = np.random.default_rng(5)
    e2, u2 = [], []
    for _ in range(40):
        fit = fit_tip_offset(machine, errors, commands, rings, exact + rng.normal(0, 1.2e-3, exact.shape))
        after_tip = compensate(machine, fit.model, val_commands).commands
        e2.append(modelled_errors(machine, truth, desired, after_tip)["position_um"].to_numpy() ** 2)
        u2.append(after_tip_uncertainty(machine, errors, nothing, commands, fit.covariance_um2,
                                        after_tip).norms()[0] ** 2)
    ratio = np.mean(e2) / np.mean(u2)
    assert 0.7 < ratio < 1.4, ratio  # measured 0.90
