"""Identification science at pose level (no images, no Prefect): PDGE extraction, the LM of eq. 22
with its identifiability report, compensation and the verification noise floor."""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.analysis.verification import capture_errors, modelled_errors, noise_floor, tool_direction_noise_floor
from tasks.campaign.folder import capture_image_id, validation_id_of
from tasks.core import se3
from tasks.core.units import ARCSEC
from tasks.identification.calibration import calibrate
from tasks.identification.levenberg_marquardt import levenberg_marquardt
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.pdge_extraction import COMPONENT_COLUMNS, extract_pdges
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    identify_pige,
    null_space_sentences,
    synthetic_measurements,
)
from tasks.machine.description import AXIS_ORDER
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward, tip_pose_error
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors
from tasks.vision.poses import COV_COLUMNS, POSE_COLUMNS

COV = np.diag([0.2e-3**2] * 2 + [4e-3**2] + [(70 * ARCSEC) ** 2] * 2 + [(3 * ARCSEC) ** 2])


def _measurements(machine, plan: pd.DataFrame) -> Measurements:
    return planned_measurements(plan, COV)


def _scattered(clean: Measurements, scatter: np.ndarray, seed: int, cov: np.ndarray | None = None) -> Measurements:
    """``clean`` with every pose moved by a plate-frame twist drawn from ``scatter`` (6, 6) (seeded);
    it reports ``cov`` (6, 6; default: clean's own covariances)."""
    rng = np.random.default_rng(seed)
    T = clean.T @ se3.exp(rng.normal(size=(len(clean), 6)) @ np.linalg.cholesky(scatter).T)
    covs = clean.cov if cov is None else np.broadcast_to(cov, clean.cov.shape).copy()
    return Measurements(clean.table, T, covs, clean.context)


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


SMALL = CampaignPlan(sweep_positions=50, sweep_repeats=1, pige_poses=150, validation_poses=30,
                     calibration_trials=1, images_per_trial=1)


def test_noise_free_calibration_reproduces_the_true_tip_poses(machine, errors):
    """The parameter set is complete: from exact poses (PDGEs from the sweeps, then the 20 constant
    parameters over the sweeps and five-axis poses) the model puts the tip where the truth does, on
    held-out poses, and every parameter is identifiable."""
    plan, _ = plan_campaign(machine, SMALL, 5)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    result = calibrate(machine, clean, errors)
    assert result.pige.fit.identifiable.all()
    val = clean.stage("validation", camera="camera1")
    e = tip_pose_error(forward(machine, val.commands, result.model).tool_in_workpiece(),
                       forward(machine, val.commands, errors).tool_in_workpiece())
    # the alternation alone leaves 0.55 µm / 1.6″ (GCV smooths C's εx to 0.9″ RMS off the truth even on
    # exact poses); the joint step, its penalty scaled by the whitening's variance, 0.10 µm / 0.6″ (0.04
    # µm mean). Scaled by the sweep's scatter instead it left 1.6 µm / 8.1″ (docs/calibrate.md, step 3)
    assert e.position_um.max() < 0.3 and e.orientation_arcsec.max() < 1.2, e.describe()
    assert e.position_um.mean() < 0.1


def test_a_pige_the_poses_do_not_excite_is_reported_unidentifiable(machine, errors):
    """With A held at zero in every five-axis pose, A's four PIGEs (zero at home) act nowhere: the SVD
    reports them unidentifiable and they get no value; the rest stay identifiable."""
    plan, _ = plan_campaign(machine, replace(SMALL, max_tilt_deg=0.0), 6)
    assert (plan.loc[plan.stage == "pige", "A"] == 0.0).all()
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    result = calibrate(machine, clean)
    table = result.pige_table().set_index("name")
    a_piges = ["delta_AY", "delta_AZ", "alpha_AZ", "beta_AY"]
    assert not table.loc[a_piges, "identifiable"].any()
    assert table.loc[a_piges, "value"].isna().all()
    assert table.drop(index=a_piges)["identifiable"].all()
    sentences = null_space_sentences(result.pige.specs, result.pige.fit)
    assert sentences and all(any(n in s for n in a_piges) for s in sentences)


def test_pige_uncertainty_covers_the_error_when_the_pdge_profiles_are_known(machine, errors):
    """eq. 22 with noisy poses and the PDGE profiles of the truth (in the fit's gauge): every PIGE lies
    within 3 standard uncertainties of the truth. (With profiles extracted from noisy sweeps the LM's
    uncertainty misses the profiles' own error: the propagated one carries it, next tests.)"""
    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    noisy = _scattered(clean, COV, 3)
    profiles = extract_pdges(machine, ErrorModel(), clean).profiles
    poses = noisy.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    fit = identify_pige(machine, ErrorModel(pdge=profiles), poses)
    truth = identify_pige(machine, ErrorModel(pdge=profiles), clean.stage(*IDENTIFICATION_STAGES,
                                                                        camera=IDENTIFICATION_CAMERA))
    z = (fit.fit.x - truth.fit.x) / fit.fit.uncertainty
    assert fit.fit.identifiable.all() and np.abs(z).max() < 3.0, z.round(2)
    assert 0.5 < fit.fit.sigma2 < 2.0


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


def _tip_rotation(machine, commands, model, desired):
    """Rotation vectors (N, 3) of the tip at ``commands`` on ``model`` against ``desired`` (arcsec, tip frame)."""
    return modelled_errors(machine, model, desired, commands)[["rx_arcsec", "ry_arcsec", "rz_arcsec"]].to_numpy()


def test_compensation_places_the_tip_and_leaves_only_what_five_axes_cannot_turn(machine):
    """With the true model: the tip lands on the nominal position, and of the orientation error
    exactly the component along the one direction that A and C cannot turn the tool about (normal to
    the tip rotations a turn of A and a turn of C make) stays; the compensation does not spin the
    tool (the singular pose at A ≈ 0 is among these poses)."""
    truth = load_prototype_errors()
    rng = np.random.default_rng(2)
    from tasks.simulation.campaign_plan import five_axis_poses

    cmds = five_axis_poses(machine, 40, CampaignPlan(), rng)
    cmds[0, 3] = 0.2  # next to the singular pose
    comp = compensate(machine, truth, cmds).commands
    desired = desired_tip_poses(machine, cmds)
    before = modelled_errors(machine, truth, desired, cmds)
    after = modelled_errors(machine, truth, desired, comp)
    assert after.position_um.max() < 0.01
    # the direction no A/C turn reaches, from the nominal machine's tip rotations per degree of A and C
    step = 1e-3  # degrees
    turn = [_tip_rotation(machine, cmds + step * np.eye(5)[k], None, desired) / step for k in (3, 4)]
    unturnable = np.cross(*turn)
    unturnable /= np.linalg.norm(unturnable, axis=1, keepdims=True)
    left = np.abs(np.einsum("ij,ij->i", _tip_rotation(machine, cmds, truth, desired), unturnable))
    np.testing.assert_allclose(after.orientation_arcsec, left, rtol=0.01, atol=0.05)
    assert after.orientation_arcsec.mean() < 0.5 * before.orientation_arcsec.mean()
    # near A = 0 what is left is a tilt of the tool (the unturnable direction is across it), not a spin
    assert abs(unturnable[0, 2]) < 0.01
    # the whole rotation angle is at its minimum: no small A/C move (0.36″) reduces it
    for k in (3, 4):
        for d in (-1e-4, 1e-4):  # degrees
            moved = comp.copy()
            moved[:, k] += d
            worse = modelled_errors(machine, truth, desired, moved).orientation_arcsec
            assert (worse >= after.orientation_arcsec - 0.01).all()


def test_tool_axis_compensation_puts_the_tool_direction_right_where_full_trades_it_for_spin(machine):
    """With the true model, the tool-axis objective leaves no tool-direction error (it turns C
    instead, so the rotation about the tool axis grows), the full objective a smaller whole rotation
    but tens of arcsec of tool direction. Next to the singular pose (A = 0) the tool-axis solution
    turns C by about 19°; at C = −179.9° that leaves C's stroke, and the pose keeps its full
    compensation, saying so."""
    from tasks.simulation.campaign_plan import five_axis_poses

    truth = load_prototype_errors()
    cmds = five_axis_poses(machine, 40, CampaignPlan(), np.random.default_rng(2))
    cmds[0, 3:] = [0.0, -179.9]  # the tool along C, at the end of C's stroke
    desired = desired_tip_poses(machine, cmds)
    full = compensate(machine, truth, cmds)
    tool = compensate(machine, truth, cmds, orientation="tool-axis")
    e_full = modelled_errors(machine, truth, desired, full.commands)
    e_tool = modelled_errors(machine, truth, desired, tool.commands)
    assert set(full.objective) == {"full"}
    assert tool.objective[0].startswith("full (") and set(tool.objective[1:]) == {"tool-axis"}
    np.testing.assert_array_equal(tool.commands[0], full.commands[0])
    assert e_tool.position_um.max() < 0.01 and e_full.position_um.max() < 0.01
    assert e_tool.tool_direction_arcsec[1:].max() < 0.01
    assert e_full.tool_direction_arcsec.mean() > 20.0  # what the full objective gives up for the spin
    assert e_full.orientation_arcsec.mean() < 0.5 * e_tool.orientation_arcsec.mean()
    with pytest.raises(ValueError, match="orientation objective"):
        compensate(machine, truth, cmds, orientation="tool")


def test_noise_floor_propagates_tilt_noise_with_the_tip_lever_arm():
    tip = np.tile(np.eye(4), (1, 1, 1))
    tip[0, :3, 3] = [60.0, 0.0, 0.0]
    cov = np.diag([0.0] * 4 + [1e-4**2, 0.0])[None]  # only a tilt about y: 1e-4 rad
    pos, ori = noise_floor(tip, cov)
    assert pos[0] == pytest.approx(60.0 * 1e-4 * 1e3)  # µm
    assert ori[0] == pytest.approx(1e-4 / ARCSEC)
    assert tool_direction_noise_floor(tip, cov)[0] == pytest.approx(1e-4 / ARCSEC)  # a tilt across the tool
    spin = np.diag([0.0] * 5 + [1e-4**2])[None]  # only a turn about the tool axis (tip z)
    assert tool_direction_noise_floor(tip, spin)[0] == pytest.approx(0.0, abs=1e-9)


def _capture_rows(image_ids: list[str], T: np.ndarray, cov: np.ndarray, status: list[str]) -> pd.DataFrame:
    """A capture's poses table: image_id, status, T00…T23 and cov00…cov55 (NaN where not ok)."""
    T = np.where(np.array(status)[:, None, None] == "ok", T, np.nan)
    return pd.DataFrame({"image_id": image_ids, "status": status,
                         **dict(zip(POSE_COLUMNS, T[:, :3, :].reshape(len(T), 12).T, strict=True)),
                         **dict(zip(COV_COLUMNS, cov.reshape(len(cov), 36).T, strict=True))})


def test_capture_image_names_map_back_to_their_validation_pose():
    assert [capture_image_id("img7", k) for k in (0, 1, 12)] == ["img7_v", "img7_v1", "img7_v12"]
    assert [validation_id_of(n) for n in ("img7_v", "img7_v1", "img7_v12", "a_v_v2")] == ["img7"] * 3 + ["a_v"]
    assert [validation_id_of(n) for n in ("img7", "img7_v0", "img7_vx", "_v")] == [None] * 4


def test_a_verification_capture_averages_the_repeats_of_each_pose(machine, errors):
    """Two repeats of a pose moved by ±δ (plate frame) measure it exactly, with half one image's
    covariance (its noise floor / √2); a failed repeat is left out of the mean, a pose with no ok
    image is dropped, and an image of no validation pose is ignored."""
    commands = _measurements(machine, plan_campaign(machine, SMALL, 5)[0]).stage("validation").commands[:3]
    desired = desired_tip_poses(machine, commands)
    cam_tip = forward(machine, commands, errors).relative(machine.tip, "camera1")
    exact = cam_tip @ se3.inverse(desired)  # the plate poses that put the tip where it is desired
    delta = np.array([2e-3, -1e-3, 5e-3, 20 * ARCSEC, -30 * ARCSEC, 5 * ARCSEC])
    plus, minus = se3.exp(delta), se3.exp(-delta)
    ids = ["p0", "p1", "p2"]
    names = ["p0_v", "p0_v1", "p1_v", "p1_v1", "p2_v", "stray"]
    T = np.stack([exact[0] @ plus, exact[0] @ minus, exact[1] @ plus, exact[1], exact[2], exact[2]])
    status = ["ok", "ok", "ok", "pnp_failed", "pnp_failed", "ok"]
    capture = _capture_rows(names, T, np.broadcast_to(COV, (6, 6, 6)), status)

    kept, e = capture_errors(machine, errors, desired, commands, ids, capture, "camera1")
    assert kept == ["p0", "p1"] and e["repeats"].tolist() == [2, 1]
    assert e["position_um"].iloc[0] < 1e-6 and e["orientation_arcsec"].iloc[0] < 1e-6
    one = capture_errors(machine, errors, desired, commands, ids, capture.iloc[[2]], "camera1")[1]
    assert e["position_um"].iloc[1] == pytest.approx(one["position_um"].iloc[0], rel=1e-12)
    assert one["position_um"].iloc[0] > 5.0  # δ moves the tip by micrometres: the mean above is not trivial
    measured = np.stack([exact[0], exact[1] @ plus])  # the mean plate pose of each kept pose
    single_floor = noise_floor(se3.inverse(measured) @ cam_tip[:2], np.broadcast_to(COV, (2, 6, 6)))[0]
    np.testing.assert_allclose(e["noise_floor_position_um"], single_floor / np.sqrt([2.0, 1.0]), rtol=1e-9)


def test_expected_tip_errors_are_the_tip_changes_the_model_uncertainty_makes(machine, errors):
    """One camera re-fit and no noise draws: the expected errors are exactly how far that model moves
    the tip from the identified one, by the verification's own measures (position, whole rotation,
    tool direction); a re-fit that only spins the tip about the tool axis leaves the tool direction."""
    from tasks.analysis.verification import tip_errors_with_tool_direction
    from tasks.identification.uncertainty import PropagatedUncertainty, expected_tip_errors

    commands = _measurements(machine, plan_campaign(machine, SMALL, 5)[0]).stage("validation").commands
    moved = replace(errors, pige={**errors.pige, "beta_AY": errors.pige["beta_AY"] + 20 * ARCSEC,
                                  "alpha_CX": errors.pige["alpha_CX"] - 15 * ARCSEC,
                                  "delta_CY": errors.pige["delta_CY"] + 3e-3})

    def expected(model):
        prop = PropagatedUncertainty(names=[], fit=np.zeros(0), camera=np.zeros(0), by_camera={}, noise=np.zeros(0),
                                     camera_models=[model], noise_models=[])
        return expected_tip_errors(machine, errors, prop, commands)

    pos, ori, tool = expected(moved)
    exact = tip_errors_with_tool_direction(forward(machine, commands, moved).tool_in_workpiece(),
                                           forward(machine, commands, errors).tool_in_workpiece())
    np.testing.assert_allclose(pos, exact.position_um, rtol=1e-6)
    np.testing.assert_allclose(ori, exact.orientation_arcsec, rtol=1e-4)
    np.testing.assert_allclose(tool, exact.tool_direction_arcsec, rtol=1e-3, atol=1e-3)
    assert tool.mean() > 5.0 and (tool <= ori + 1e-9).all()

    # a tip mounting error about its own z, the tool axis: a spin only
    tip = np.asarray(errors.attachment_offsets.get("tip", np.zeros(6)), dtype=float)
    spun = replace(errors, attachment_offsets={**errors.attachment_offsets,
                                               "tip": tip + np.array([0, 0, 0, 0, 0, 30 * ARCSEC])})
    _, ori_spun, tool_spun = expected(spun)
    assert ori_spun == pytest.approx(np.full(len(commands), 30.0), rel=1e-3)
    assert tool_spun.max() < 1e-3


def test_the_smoother_chooses_scipys_roughness_and_gives_its_fit():
    """tasks.identification.smoothing evaluates GCV in closed form; the λ and the fitted values are
    scipy's make_smoothing_spline's (its GCV) to the tolerance of the λ search."""
    from scipy.interpolate import make_smoothing_spline

    from tasks.identification.smoothing import smooth

    rng = np.random.default_rng(1)
    for n in (5, 11, 50):
        x = np.sort(rng.uniform(-3, 3, n))
        w = rng.uniform(0.5, 2.0, n)
        Y = np.column_stack([np.sin(x) + 0.1 * rng.standard_normal(n) for _ in range(3)]) * 1e-3
        ours, lam = smooth(x, Y, w)
        ref = np.column_stack([make_smoothing_spline(x, Y[:, k], w=w / w.mean())(x) for k in range(3)])
        assert np.abs(ours - ref).max() <= 1e-5 * np.abs(ref).max(), n
        held, _ = smooth(x, 2.0 * Y, w, lam)  # λ held: a linear smoother
        np.testing.assert_allclose(held, 2.0 * ours, rtol=1e-12, atol=1e-15)


def test_with_repeats_the_smoother_takes_the_smoothest_fit_the_noise_explains():
    """scipy's bound λ < n is in the axis' units: a 50-position sweep at 1 mm steps keeps at least 7.6
    effective degrees of freedom, and GCV's flat curve there picks more by chance. Given the noise of
    a position's mean (from repeats), the smoother takes the smoothest fit down to 3 degrees of
    freedom whose residuals the noise explains (χ², 95 %). On 40 draws of white noise (σ = 1) about
    a smooth profile (2 sin(x / 25 mm)) the fit is closer to the truth than GCV's (RMS 0.23 against
    0.38 measured, never worse on a draw); without the noise the choice is GCV's."""
    from tasks.identification.smoothing import MIN_DEGREES_OF_FREEDOM, SplineBasis, smooth

    rng = np.random.default_rng(3)
    x = np.arange(50.0) - 25.0
    truth = 2.0 * np.sin(x / 25.0)
    basis = SplineBasis.of(x, np.ones(50))
    assert basis.degrees_of_freedom(50.0) > 7.5
    with_noise, gcv_only, dof = [], [], []
    for _ in range(40):
        y = truth + rng.standard_normal(50)
        fitted, lam = smooth(x, y[:, None], np.ones(50), noise_var=np.ones(1))
        plain, lam_gcv = smooth(x, y[:, None], np.ones(50))
        assert lam_gcv[0] == pytest.approx(basis.gcv_roughness(y), rel=1e-12)
        assert lam[0] >= lam_gcv[0]
        with_noise.append(np.sqrt(np.mean((fitted[:, 0] - truth) ** 2)))
        gcv_only.append(np.sqrt(np.mean((plain[:, 0] - truth) ** 2)))
        dof.append(basis.degrees_of_freedom(float(lam[0])))
    assert np.sqrt(np.mean(np.square(with_noise))) < 0.7 * np.sqrt(np.mean(np.square(gcv_only)))
    assert np.median(dof) == pytest.approx(MIN_DEGREES_OF_FREEDOM, abs=0.5)
    assert min(dof) >= MIN_DEGREES_OF_FREEDOM - 1e-3


def _focal_like_sensitivity(meas: Measurements, camera: str) -> np.ndarray:
    """(N, 6, 8) with one 'intrinsic' that moves each pose of ``camera`` along its line of sight by
    its distance per unit (a relative focal-length error), the other seven doing nothing."""
    S = np.zeros((len(meas), 6, 8))
    rows = (meas.table.camera == camera).to_numpy()
    R, t = meas.T[rows, :3, :3], meas.T[rows, :3, 3]
    S[rows, :3, 0] = np.einsum("nji,nj->ni", R, t)  # plate frame: Rᵀ (the camera-frame shift t·ε)
    return S


def test_propagated_uncertainty_covers_pdge_noise_and_matches_a_full_refit_for_the_camera(machine, errors):
    """With PDGE profiles extracted from the same noisy sweeps, the LM's covariance misses the profiles'
    error; the bootstrap through extraction and fit covers it (every parameter within 3u of the truth).
    The camera part, a linearised alternation, agrees with re-running the whole calibration on poses
    moved by a 100 ppm focal-length error."""
    from tasks.identification.uncertainty import propagate_uncertainty

    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    noisy = _scattered(clean, COV, 3)
    result = calibrate(machine, noisy, errors)
    S = _focal_like_sensitivity(noisy, "camera1")
    cov = np.zeros((8, 8))
    cov[0, 0] = 100e-6**2
    prop = propagate_uncertainty(machine, result, noisy, S, {"camera1": cov}, draws=16)

    table = result.pige_table(prop)
    z = ((table.value - table.truth).abs() / table.uncertainty).to_numpy()
    assert np.all(z < 3.0), table.assign(z=z)[["name", "value", "truth", "uncertainty", "uncertainty_fit"]]
    assert (prop.noise > prop.fit).sum() >= 5  # the profiles' noise is real and the LM does not see it

    moved = Measurements(noisy.table, noisy.T @ se3.exp(S[:, :, 0] * 100e-6), noisy.cov, noisy.context)
    full = np.abs(calibrate(machine, moved).pige.fit.x - result.pige.fit.x)
    big = full > 0.1 * full.max()
    np.testing.assert_allclose(prop.by_camera["camera1"][big], full[big], rtol=0.2)


def test_propagated_noise_is_scaled_by_the_birge_ratio_when_pose_covariances_understate_the_scatter(machine, errors):
    """Poses drawn with covariance COV but reporting COV/4: the fit sees σ² ≈ 3.3 (4 on the tilts and
    the depth, 2 on the lateral position, where the 0.1 µm floor is half the claimed variance; 0.94
    with the honest covariance), and the bootstrap draws √σ² times the reported covariance, so the
    noise part matches the one propagated with the honest covariance (within the 16 draws' ±18 %
    each) and every parameter stays within 3u. (With σ² counting only the 20 constants, not the
    degrees of freedom the profiles take, it read 2.9 and βAY fell at 3.03u.)"""
    from tasks.identification.uncertainty import propagate_uncertainty

    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    honest = _scattered(clean, COV, 3)
    understated = Measurements(honest.table, honest.T, honest.cov / 4.0, honest.context)
    props, results = {}, {}
    for name, meas in (("honest", honest), ("understated", understated)):
        results[name] = calibrate(machine, meas, errors)
        props[name] = propagate_uncertainty(machine, results[name], meas, draws=16)
    assert 3.0 < results["understated"].pige.fit.sigma2 / results["honest"].pige.fit.sigma2 < 5.0
    ratio = props["understated"].noise / props["honest"].noise
    assert 0.6 < np.median(ratio) < 1.4, ratio
    table = results["understated"].pige_table(props["understated"])
    z = ((table.value - table.truth).abs() / table.uncertainty).to_numpy()
    assert np.all(z < 3.0), table.assign(z=z)[["name", "value", "truth", "uncertainty", "uncertainty_fit"]]


def test_propagated_noise_draws_from_the_error_model_the_fit_weights_by(machine, errors):
    """The fit whitens by C + C_floor (0.1 µm, 1″): no image is believed better than that. Poses
    measured as at full size (lateral 0.04 µm, depth 0.6 µm, tilt 7″) that also carry 0.1 µm of
    lateral error their covariance does not claim: the bootstrap must draw from the same
    C + C_floor, so its noise part matches the joint fit's σ²-scaled one for the laterally fixed
    parameters (Z.ez0, gamma_YX), where drawing from C alone gives a third to a half of it, and every
    parameter stays within 3u of the truth."""
    from tasks.identification.uncertainty import propagate_uncertainty

    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    claimed = np.diag([0.04e-3**2] * 2 + [0.6e-3**2] + [(7 * ARCSEC) ** 2] * 2 + [(0.4 * ARCSEC) ** 2])
    scatter = claimed + np.diag([0.1e-3**2] * 2 + [0.0] * 4)
    meas = _scattered(clean, scatter, 5, cov=claimed)
    result = calibrate(machine, meas, errors)
    prop = propagate_uncertainty(machine, result, meas, draws=16)
    ratio = dict(zip(prop.names, prop.noise / prop.fit, strict=True))
    # measured 1.00, 1.30; drawn from C alone 0.37, 0.49. The fit's σ² counts the degrees of freedom the
    # profiles take, so the fit part is unbiased and the expected ratio is 1, ±18 % over 16 draws
    assert ratio["Z.ez0"] > 0.7 and ratio["gamma_YX"] > 0.7, ratio
    table = result.pige_table(prop)
    z = ((table.value - table.truth).abs() / table.uncertainty).to_numpy()
    assert np.all(z < 3.0), table.assign(z=z)[["name", "value", "truth", "uncertainty", "uncertainty_fit"]]


def test_noise_refits_are_the_joint_step_on_moved_poses_with_the_penalty_set_again(machine, errors, monkeypatch):
    """The bootstrap's noise re-fits must move like the calibration itself. The calibration ends with
    the joint step, whose penalty GCV sets from whatever sweeps it gets (its roughness jumps between
    draws by orders of magnitude where GCV's curve is flat: log10 λ of A's δz +4.8 on one draw, −4.8
    on the next). Given the same penalty, the linearised re-fit from the first solution lands within
    0.5u of a full re-calibration of independently re-drawn poses (measured 0.29u): the rest of the
    estimator is linear over the noise. And propagate_uncertainty's noise draws set the penalty again
    from their own sweeps (one extraction each), its reference re-fit holds it."""
    from tasks.identification import uncertainty
    from tasks.identification.joint_fit import JointStep
    from tasks.identification.uncertainty import propagate_uncertainty

    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    first, other = _scattered(clean, COV, 3), _scattered(clean, COV, 11)
    result, full = calibrate(machine, first), calibrate(machine, other)
    f = result.pige.fit
    step = JointStep.build(machine, result.pige.specs, result.model, f.x, f.jacobian, f.null_space,
                           result.pdge.smoothing, first)
    x, _ = step.with_penalty(full.pdge.smoothing).solve(other)
    assert np.max(np.abs(x - full.pige.fit.x) / f.uncertainty) < 0.5

    chosen = []

    def spy(*args, smoothing=None, **kwargs):
        chosen.append(smoothing is None)
        return extract_pdges(*args, smoothing=smoothing, **kwargs)

    monkeypatch.setattr(uncertainty, "extract_pdges", spy)
    propagate_uncertainty(machine, result, first, draws=2, workers=1)
    assert chosen == [True, True]  # the reference re-fit holds the penalty, each draw sets it again


def test_the_joint_step_takes_a_profile_the_sweep_measures_through_a_lever_arm_from_the_five_axis_poses(
        machine, errors):
    """Camera 2 sees plate b 150 mm along the A axis from A's frame: its tilt noise (70″ per image)
    becomes about 50 µm of noise per image in A's translation profile. Held fixed, such a profile
    pulled the constants by tens of u (δAY −105 µm, σ² 14 with noise on the A sweep alone; 13 with
    noise on every pose, this draw); estimated jointly with the five-axis poses, which see plate a
    next to A's frame, the profile's translations are within 3 µm of the truth (13.9 µm before), σ²
    is at the noise level and every constant within 3 of its stated uncertainties."""
    plan, _ = plan_campaign(machine, SMALL, 5)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    result = calibrate(machine, _scattered(clean, COV, 100), errors)
    a = result.pdge.table[result.pdge.table.axis == "A"]
    off = {c: np.sqrt(np.mean((a[f"fit_{c}"] - a[f"truth_{c}"]) ** 2)) for c in COMPONENT_COLUMNS}
    assert max(off[c] for c in COMPONENT_COLUMNS[:3]) < 3.0 and max(off[c] for c in COMPONENT_COLUMNS[3:]) < 5.0, off
    fit = result.pige.fit
    assert 0.5 < fit.sigma2 < 2.0
    z = (fit.x - result.truth_pige.fit.x) / fit.uncertainty
    assert fit.identifiable.all() and np.abs(z).max() < 3.0, z.round(2)


def test_the_tool_frame_offset_covariance_predicts_the_tip_offset_a_camera_error_leaves(machine, errors):
    """Against the simulator's truth: exact poses, then every camera-1 pose moved by a focal-length
    error of 2σ (200 ppm against a stated 100 ppm). The stated covariance of the constant tool-frame
    tip offset (camera part of the propagation, rank one here) predicts the offset the moved
    calibration leaves after compensation against the truth: its direction, its size (2σ) and
    cᵀΣ⁺c ≈ 4, the χ² the bench/tip_uncertainty.py check reads over seeds."""
    from tasks.identification.uncertainty import (
        expected_tip_errors,
        propagate_uncertainty,
        tool_frame_offset_covariance,
    )

    plan, _ = plan_campaign(machine, SMALL, 7)
    clean = synthetic_measurements(machine, errors, _measurements(machine, plan))
    result = calibrate(machine, clean, errors)
    S = _focal_like_sensitivity(clean, "camera1")
    cov = np.zeros((8, 8))
    cov[0, 0] = 100e-6**2
    prop = propagate_uncertainty(machine, result, clean, S, {"camera1": cov}, draws=0)
    commands = clean.stage("validation").commands
    R = desired_tip_poses(machine, commands)[:, :3, :3]
    sigma = tool_frame_offset_covariance(machine, result.model, prop, commands, R)

    moved = Measurements(clean.table, clean.T @ se3.exp(S[:, :, 0] * 200e-6), clean.cov, clean.context)
    model = calibrate(machine, moved).model
    d = (forward(machine, commands, errors).tool_in_workpiece()[:, :3, 3]
         - forward(machine, commands, model).tool_in_workpiece()[:, :3, 3]) / 1e-3  # µm
    offset = np.einsum("nji,nj->ni", R, d).mean(axis=0)

    w, V = np.linalg.eigh(sigma)
    assert w[-1] > 1e3 * w[-2] and np.sqrt(w[-1]) > 5.0  # one direction, microns per 100 ppm
    assert abs(offset @ V[:, -1]) / np.linalg.norm(offset) > 0.999
    assert np.linalg.norm(offset) == pytest.approx(2 * np.sqrt(w[-1]), rel=0.02)  # measured: 60.00 against 59.98 µm
    assert offset @ np.linalg.pinv(sigma) @ offset == pytest.approx(4.0, rel=0.04)
    # the per-pose model uncertainty is this vector's size where the offset is all there is
    u = expected_tip_errors(machine, result.model, prop, commands)[0]
    assert u.mean() == pytest.approx(np.sqrt(np.trace(sigma)), rel=0.01)
