"""Where the model fails and watching the error fall, at pose level (no images, no Prefect): the residual
tables, the binned trends that tell structure from noise, the model ladder and the report pages."""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from tasks.analysis.model_ladder import (
    LADDER_COLUMNS,
    add_step,
    append_step,
    effect_specs,
    effects_key,
    ladder_step,
    read_ladder,
    refit_cross_validated_rms,
)
from tasks.analysis.residuals import (
    DOT_RESIDUAL_COLUMNS,
    POSE_RESIDUAL_COLUMNS,
    binned_mean,
    dot_residual_table,
    plates_of,
    pose_residual_table,
    trend_summary,
)
from tasks.core import se3
from tasks.core.units import ARCSEC
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    identify_pige,
    pose_residuals,
    synthetic_measurements,
)
from tasks.lake.schema import TABLES, partition_problems
from tasks.lake.store import partition_path, write_partition
from tasks.machine.camera_model import project_points
from tasks.machine.effects import parse_effect
from tasks.report import ReportData, write_report
from tasks.report.residual_figures import residual_report
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign

COV = np.diag([0.2e-3**2] * 2 + [4e-3**2] + [(70 * ARCSEC) ** 2] * 2 + [(3 * ARCSEC) ** 2])
RATE_UM_PER_HOUR = 20.0
DRIFT = parse_effect(f"thermal_drift:axis=X,driver=time,um_per_hour={RATE_UM_PER_HOUR:g}")
PLAN = CampaignPlan(sweep_positions=10, sweep_repeats=1, pige_poses=90, validation_poses=20, calibration_trials=1,
                    images_per_trial=1)


@pytest.fixture(scope="module")
def frame(machine):
    """Measurements shaped like a small campaign (identity poses), with its calibration views."""
    plan, _ = plan_campaign(machine, PLAN, 5)
    return planned_measurements(plan, COV)


@pytest.fixture(scope="module")
def noise(frame):
    """(N, 4, 4) one draw of pose noise with covariance COV (plate frame), shared by the cases compared."""
    rng = np.random.default_rng(11)
    return se3.exp(rng.normal(size=(len(frame), 6)) @ np.linalg.cholesky(COV).T)


def _noisy(machine, truth, frame, noise) -> Measurements:
    clean = synthetic_measurements(machine, truth, frame)
    return Measurements(clean.table, clean.T @ noise, clean.cov, clean.context)


def _dots(machine, meas: Measurements) -> pd.DataFrame:
    """The exact dot centres every plate shows through its measured pose and the machine's cameras."""
    frames = []
    for cam in np.unique(meas.table.camera):
        idx = np.flatnonzero(meas.table.camera == cam)
        plate, camera = plates_of(machine)[cam], machine.cameras[cam]
        X = plate.dot_centres_mm()  # (K, 3)
        p = np.einsum("nij,kj->nki", meas.T[idx, :3, :3], X) + meas.T[idx, None, :3, 3]  # (n, K, 3)
        uv = project_points(p, camera)  # (n, K, 2)
        rc = np.tile(plate.row_col(), (idx.size, 1))
        frames.append(pd.DataFrame({"image_id": np.repeat(meas.table.image_id.to_numpy()[idx], len(X)), "camera": cam,
                                    "row": rc[:, 0], "col": rc[:, 1], "u_px": uv[..., 0].ravel(),
                                    "v_px": uv[..., 1].ravel()}))
    return pd.concat(frames, ignore_index=True)


# --------------------------------------------------------------------------------------------
# The residual tables
# --------------------------------------------------------------------------------------------


def test_true_model_on_exact_poses_leaves_zero_residual_with_every_variable_beside_it(machine, errors, frame):
    exact = synthetic_measurements(machine, errors, frame)
    dots = _dots(machine, exact)
    table = pose_residual_table(machine, errors, exact, dots)
    assert list(table.columns) == list(POSE_RESIDUAL_COLUMNS) == TABLES["residuals"].column_names
    assert "camera_calibration" not in set(table.stage)  # no machine pose: left out
    assert len(table) == (frame.table.stage != "camera_calibration").sum()
    for c in ("dx_um", "dy_um", "dz_um", "cam_dx_um", "cam_dy_um", "cam_dz_um", "position_um"):
        assert np.abs(table[c]).max() < 1e-6, c  # µm
    for c in ("rx_arcsec", "ry_arcsec", "rz_arcsec", "orientation_arcsec", "white_norm"):
        assert np.abs(table[c]).max() < 1e-6, c
    rows = frame.table.set_index("image_id").loc[table.image_id]
    np.testing.assert_array_equal(table.C_deg, rows.C)
    np.testing.assert_array_equal(table.time_s, rows.time_s)
    assert set(np.unique(table[["approach_X", "approach_C"]])) <= {-1, 0, 1}
    assert table.used_in_fit.sum() == (rows.stage.isin(IDENTIFICATION_STAGES)
                                       & (rows.camera == IDENTIFICATION_CAMERA)).sum()
    # the plate's position in the image: the mean of its 49 dots
    first = dots[dots.image_id == table.image_id.iloc[0]]
    assert table.u_mean_px.iloc[0] == pytest.approx(first.u_px.mean()) and table.n_dots.iloc[0] == 49


def test_a_camera_outside_the_fit_is_taken_against_its_chain_completed_by_constant_mounts(machine, errors):
    """Camera 2 takes no part in the constant-parameter fit, so nothing identifies its mount or its plate's.
    Mount errors at both ends move its raw residual by micrometres along the A sweep (a once-per-turn
    pattern, not a constant: centring would leave it); the stored residual completes the chain with them
    and leaves zero, while a drift with time, which no constant mount can imitate, stays whole."""
    plan, _ = plan_campaign(machine, replace(PLAN, sweep_repeats=4, pige_poses=30, validation_poses=5), 5)
    frame = planned_measurements(plan, COV)
    xi_camera = np.array([0.02, -0.015, 0.01, 30 * ARCSEC, -20 * ARCSEC, 45 * ARCSEC])  # mm, rad
    xi_plate = np.array([-0.01, 0.025, 0.005, -40 * ARCSEC, 25 * ARCSEC, 10 * ARCSEC])
    rate = 200.0  # µm/h
    drift = parse_effect(f"thermal_drift:axis=X,driver=time,um_per_hour={rate:g}")
    for truth in (errors, replace(errors, effects=[drift])):
        exact = synthetic_measurements(machine, truth, frame)
        cam2 = (exact.table.camera == "camera2").to_numpy()
        T = exact.T.copy()
        T[cam2] = se3.exp(xi_camera) @ T[cam2] @ se3.exp(xi_plate)
        mounted = Measurements(exact.table, T, exact.cov, exact.context)
        raw = pose_residuals(machine, errors, mounted) * 1e3  # µm, mrad·1e3
        raw_centred = raw[cam2, :3] - raw[cam2, :3].mean(axis=0)
        assert np.abs(raw_centred[:, 0]).max() > 1.5  # µm: what centring alone would leave
        table = pose_residual_table(machine, errors, mounted)
        c2 = table[table.camera == "camera2"]
        camera1 = (table.camera == "camera1").to_numpy()  # the fit's camera: its residual as it is
        np.testing.assert_allclose(table.loc[camera1, ["dx_um", "dy_um", "dz_um"]], raw[~cam2, :3], atol=1e-9)
        assert np.abs(c2[["cam_dx_um", "cam_dy_um"]]).max().max() < 0.01  # µm
        assert np.abs(c2[["rx_arcsec", "ry_arcsec", "rz_arcsec"]]).max().max() < 0.05
        if truth.effects:  # X grows with time and carries camera 2 away from plate b along its line of sight
            growth = rate * c2.time_s / 3600.0
            np.testing.assert_allclose(c2.cam_dz_um, growth - growth.mean(), atol=0.01)
        else:
            assert np.abs(c2.cam_dz_um).max() < 0.01


def test_whitened_residual_is_the_fit_whitening_first_component_the_plain_z_score(machine, errors, frame, noise):
    noisy = _noisy(machine, errors, frame, noise)
    table = pose_residual_table(machine, errors, noisy)
    sd = np.sqrt(COV[0, 0] + 1e-4**2) * 1e3  # µm, with the fit's 0.1 µm floor
    np.testing.assert_allclose(table.white_dx, table.dx_um / sd, rtol=1e-9)
    white = table[["white_dx", "white_dy", "white_dz", "white_rx", "white_ry", "white_rz"]].to_numpy()
    np.testing.assert_allclose(table.white_norm, np.linalg.norm(white, axis=1))
    # noise at its covariance: whitened components of unit variance (within the floor's shrinkage)
    assert 0.8 < white.std() < 1.05


def test_a_tool_drift_along_X_is_one_camera_frame_component_whatever_C(machine, errors, frame):
    """The reason for the cam_* columns: the thermal growth of X moves camera 1 along machine X, so the
    plate appears moved by −growth along camera x at every pose, while in the plate frame (which turns
    with C) the same error is spread over dx and dy and averages out over the five-axis poses."""
    exact = synthetic_measurements(machine, replace(errors, effects=[DRIFT]), frame)
    table = pose_residual_table(machine, errors, exact)
    cam1 = table[table.camera == "camera1"]
    growth = RATE_UM_PER_HOUR * cam1.time_s / 3600.0  # µm
    np.testing.assert_allclose(cam1.cam_dx_um, -growth, atol=2e-3)
    assert np.abs(cam1[["cam_dy_um", "cam_dz_um"]]).max().max() < 2e-3
    five_axis = cam1.stage == "pige"
    assert abs(cam1.dx_um[five_axis].mean()) < 0.3 * abs(cam1.cam_dx_um[five_axis].mean())


def test_dot_residual_is_detected_minus_projected_through_the_measured_pose(machine, errors, frame):
    exact = synthetic_measurements(machine, errors, frame)
    dots = _dots(machine, exact)
    dots.loc[dots.camera == "camera1", "u_px"] += 0.3  # a detector bias of 0.3 px along u
    dots.loc[0, "v_px"] = np.nan  # a dot not found
    stray = dots.iloc[:1].assign(image_id="not-measured")
    table = dot_residual_table(pd.concat([dots, stray], ignore_index=True), exact, machine.cameras,
                               plates_of(machine))
    assert list(table.columns) == list(DOT_RESIDUAL_COLUMNS) == TABLES["dot_residuals"].column_names
    assert len(table) == len(dots) - 1 and "not-measured" not in set(table.image_id)
    cam1 = table.camera == "camera1"
    np.testing.assert_allclose(table.du_px[cam1], 0.3, atol=1e-6)
    np.testing.assert_allclose(table.du_px[~cam1], 0.0, atol=1e-6)
    np.testing.assert_allclose(table.dv_px, 0.0, atol=1e-6)
    assert set(table.stage) == set(frame.table.stage)  # calibration views too: they have a measured pose


def test_new_tables_are_in_the_registry_and_written_files_match_it(machine, errors, frame, noise, tmp_path):
    assert {"residuals", "dot_residuals", "model_ladder"} <= set(TABLES)
    noisy = _noisy(machine, errors, frame, noise)
    dots = _dots(machine, noisy)
    ladder = add_step(pd.DataFrame(columns=list(LADDER_COLUMNS)), _row([]))
    for name, df in (("residuals", pose_residual_table(machine, errors, noisy, dots)),
                     ("dot_residuals", dot_residual_table(dots, noisy, machine.cameras, plates_of(machine))),
                     ("model_ladder", ladder)):
        path = write_partition(name, "c1", df, {"fivecal_version": "test"}, tmp_path)
        assert partition_problems(name, path) == [], name


# --------------------------------------------------------------------------------------------
# Trends: structure against noise
# --------------------------------------------------------------------------------------------


def test_binned_mean_band_is_the_bonferroni_t_interval():
    x = np.repeat([0.0, 1.0, 2.0], 5)
    y = np.array([1, 2, 3, 4, 5, 0, 0, 0, 0, 0.5, -1, 1, -1, 1, 0], dtype=float)
    b = binned_mean(x, y, categorical=True)
    assert b.n.tolist() == [5, 5, 5] and b["mean"].tolist() == pytest.approx([3.0, 0.1, 0.0])
    t = stats.t.ppf(1 - 0.05 / 6, 4)  # three bins: 95 % for the whole band
    assert b.half_width[0] == pytest.approx(t * np.std(y[:5], ddof=1) / np.sqrt(5))
    assert b.excludes_zero.tolist() == [True, False, False]
    pointwise = binned_mean(x, y, categorical=True, simultaneous=False)
    assert pointwise.half_width[0] == pytest.approx(stats.t.ppf(0.975, 4) * np.std(y[:5], ddof=1) / np.sqrt(5))
    q = binned_mean(np.arange(100.0), np.ones(100), n_bins=4)
    assert q.n.tolist() == [25, 25, 25, 25] and q.x_lo.tolist() == [0, 25, 50, 75]


def test_hidden_drift_shows_against_time_beyond_the_band_and_no_effect_stays_inside_it(machine, errors, frame,
                                                                                       noise):
    """The model lacks the thermal drift of X; the same poses and noise with and without the drift. With
    it, camera 1's x residual falls with time at the drift rate and its band leaves zero; without it, no
    bin's (simultaneous 95 %) band leaves zero."""
    with_drift = pose_residual_table(machine, errors, _noisy(machine, replace(errors, effects=[DRIFT]), frame, noise))
    without = pose_residual_table(machine, errors, _noisy(machine, errors, frame, noise))
    cam1 = with_drift.camera == "camera1"
    b = binned_mean(with_drift.time_s[cam1], with_drift.cam_dx_um[cam1])
    assert b.excludes_zero.iloc[-1] and b.excludes_zero.sum() >= 3
    slope = np.polyfit(b.x / 3600.0, b["mean"], 1)[0]  # µm per hour
    assert slope == pytest.approx(-RATE_UM_PER_HOUR, rel=0.2)
    quiet = binned_mean(without.time_s[cam1], without.cam_dx_um[cam1])
    assert not quiet.excludes_zero.any() and len(quiet) == len(b)
    s = trend_summary(with_drift).set_index(["camera", "variable", "component"])
    q = trend_summary(without).set_index(["camera", "variable", "component"])
    assert s.loc[("camera1", "time_s", "cam_dx_um"), "significant"]
    assert not q.loc[("camera1", "time_s", "cam_dx_um"), "significant"]
    assert q.loc[("camera1", "time_s", "cam_dx_um"), "p_value"] > 0.01 > s.loc[("camera1", "time_s", "cam_dx_um"),
                                                                               "p_value"]


# --------------------------------------------------------------------------------------------
# The model ladder
# --------------------------------------------------------------------------------------------


def _row(effects: list, cv: float = 1.0) -> dict:
    return {"effects": effects_key(effects), "effect_specs": effect_specs(effects), "n_params": 20,
            "n_residuals": 600, "train_rms": 1.0, "cv_rms": cv,
            "validation_rms": cv, "validation_position_um": 3.0, "validation_orientation_arcsec": 10.0,
            "n_validation": 20, "noise_floor_position_um": 2.0, "noise_floor_orientation_arcsec": 9.0, "bic": -5.0,
            "created_at": pd.Timestamp("2026-01-01", tz="UTC")}


def test_ladder_appends_steps_and_replaces_the_step_with_the_same_effects(tmp_path):
    refitted = parse_effect("thermal_drift:axis=X,driver=time,um_per_hour=19.2")  # the drift, refitted
    append_step("c1", _row([], cv=3.0), {"fivecal_version": "test"}, tmp_path)
    append_step("c1", _row([DRIFT], cv=1.1), {"fivecal_version": "test"}, tmp_path)
    append_step("c1", _row([], cv=2.5), {"fivecal_version": "test"}, tmp_path)  # the base model refitted
    ladder = append_step("c1", _row([refitted], cv=1.05), {"fivecal_version": "test"}, tmp_path)  # other amplitude
    back = read_ladder("c1", tmp_path)
    assert back.step.tolist() == [0, 1]
    assert back.effects.tolist() == ["", "thermal_drift:axis=X,driver=time,reference_c=20"]
    assert back.effect_specs.tolist() == ["", refitted.spec()] and "um_per_hour=19.2" in refitted.spec()
    assert back.cv_rms.tolist() == [2.5, 1.05]
    assert ladder.step.tolist() == back.step.tolist()
    assert partition_problems("model_ladder", partition_path("model_ladder", "c1", tmp_path) / "part-0.parquet") == []
    assert read_ladder("other", tmp_path).empty  # other campaigns untouched / absent


def test_ladder_falls_to_the_noise_floor_when_the_hidden_effect_is_added(machine, errors, frame, noise, tmp_path):
    """Poses of a machine with a thermal drift of X. Step 0 refits the constants of a model without the drift:
    the fit and the held-out poses are far above the noise level. Step 1 adds the drift: train and
    cross-validated RMS come down to about 1 and the validation error to its noise floor."""
    meas = _noisy(machine, replace(errors, effects=[DRIFT]), frame, noise)
    poses = meas.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    rows = []
    for model in (errors, replace(errors, effects=[DRIFT])):
        fit = identify_pige(machine, model, poses)
        cv = refit_cross_validated_rms(machine, fit.model, fit.specs, meas, folds=3)
        rows.append(ladder_step(machine, fit.model, fit.fit, meas, cv_rms=cv))
        ladder = append_step("c1", rows[-1], {"fivecal_version": "test"}, tmp_path)
    before, after = rows
    assert ladder.effect_specs.tolist() == ["", DRIFT.spec()]
    assert after["train_rms"] < before["train_rms"] and after["bic"] < before["bic"]
    assert before["cv_rms"] > 1.4 * after["cv_rms"] and 0.8 < after["cv_rms"] < 1.2
    assert before["validation_rms"] > 1.4 * after["validation_rms"] and 0.8 < after["validation_rms"] < 1.2
    # the tip comparison is dominated by each pose's tilt noise times the lever arm: at its floor either way
    assert after["validation_position_um"] == pytest.approx(after["noise_floor_position_um"], rel=0.3)
    assert before["validation_position_um"] >= after["validation_position_um"]
    assert after["validation_orientation_arcsec"] == pytest.approx(after["noise_floor_orientation_arcsec"], rel=0.3)
    assert after["n_validation"] == 20 and after["n_params"] == len(fit.specs)


# --------------------------------------------------------------------------------------------
# Report pages
# --------------------------------------------------------------------------------------------


def test_report_pages_render_to_png_and_into_the_report(machine, errors, frame, noise, tmp_path):
    meas = _noisy(machine, replace(errors, effects=[DRIFT]), frame, noise)
    dots = _dots(machine, meas)
    residuals = pose_residual_table(machine, errors, meas, dots)
    dot_res = dot_residual_table(dots, meas, machine.cameras, plates_of(machine))
    dot_res["du_px"] += 0.02 * (dot_res.u_px - 1536) / 1536  # a radial-ish pattern to draw
    ladder = add_step(add_step(pd.DataFrame(columns=list(LADDER_COLUMNS)), _row([], 3.0)), _row([DRIFT]))
    sections, figures = residual_report(residuals, dot_res, ladder, cameras=machine.cameras)
    titles = [t for t, _ in sections]
    assert titles == ["Residuals — where the model fails", "Reprojection residuals over the image",
                      "Model ladder — watch the error fall"]
    stems = [s for s, _ in figures]
    assert {"residual_trends_camera1", "residual_approach_camera1", "residual_field_camera1", "model_ladder"} <= set(
        stems)
    text = dict(sections)["Residuals — where the model fails"]
    assert "| camera1 | time_s | cam_dx_um |" in text  # the drift is listed among the significant trends
    empty = pd.DataFrame
    paths = write_report(tmp_path / "report", ReportData(
        campaign_id="c1", run="r1", pdge=empty(columns=["axis", "position", "dx_um", "dy_um", "dz_um", "ex_arcsec",
                                                        "ey_arcsec", "ez_arcsec"]),
        pige=empty(columns=["name", "value", "uncertainty", "identifiable"]),
        verification=empty(columns=["pose", "phase", "source", "position_um", "orientation_arcsec"]),
        extra_sections=sections, extra_figures=figures))
    for stem in stems:
        png = (paths["figures"] / f"{stem}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000, stem
    html = paths["html"].read_text()
    assert "Model ladder — watch the error fall" in html and html.count("data:image/png;base64,") == len(figures)


# --------------------------------------------------------------------------------------------
# Trend tests (residual_trends)
# --------------------------------------------------------------------------------------------


def _noise_table(rng, n: int = 400) -> pd.DataFrame:
    """A residuals-like table of one camera: uniform variables, Gaussian components (µm, arcsec)."""
    from tasks.analysis.residuals import CAMERA_COMPONENTS

    t = pd.DataFrame({"camera": "camera1", "X_mm": rng.uniform(-5, 5, n), "time_s": np.arange(n) * 3.0,
                      "approach_X": rng.choice([-1, 1], n)})
    for c in CAMERA_COMPONENTS:
        t[c] = rng.normal(0.0, 2.0, n)
    return t


def test_trend_tests_flag_the_nominal_share_of_pure_noise_and_ignore_a_constant_offset():
    """Pure noise: about 5 % of the panels are flagged at the 5 % level (600 panels: 2.5–8 %). A constant
    offset of a component is no trend: flagged no more often. A linear trend of 4 µm over X is."""
    from tasks.analysis.residual_trends import trend_tests

    rng = np.random.default_rng(4)
    tables = [_noise_table(rng) for _ in range(34)]
    flags = pd.concat([trend_tests(t, variables=("X_mm", "time_s", "approach_X")) for t in tables])
    assert 0.025 < flags.significant.mean() < 0.08, flags.significant.mean()
    assert len(flags) == 34 * 3 * 6 and set(flags.columns) == {"camera", "variable", "component", "bins", "span",
                                                              "statistic", "p_value", "significant"}
    offset = [t.assign(cam_rx_arcsec=t.cam_rx_arcsec - 12.0) for t in tables]
    rx = pd.concat([trend_tests(t, variables=("X_mm",)) for t in offset]).query("component == 'cam_rx_arcsec'")
    assert rx.significant.mean() < 0.15
    trend = tables[0].assign(cam_dx_um=tables[0].cam_dx_um + 0.4 * tables[0].X_mm)
    row = trend_tests(trend, variables=("X_mm",)).set_index("component").loc["cam_dx_um"]
    assert row.significant and row.p_value < 1e-4 and row.span > 3.0


def test_a_trend_the_models_own_uncertainty_explains_is_not_flagged():
    """A wave over X that the identified model's uncertainty could make (a shared deviation of that shape
    at its size) is within the test's allowance; without that allowance it is flagged."""
    from tasks.analysis.residual_trends import trend_tests
    from tasks.analysis.residuals import CAMERA_COMPONENTS

    rng = np.random.default_rng(5)
    t = _noise_table(rng, 600)
    wave = 1.0 * np.sin(t.X_mm.to_numpy())
    t["cam_dz_um"] += wave
    shared = np.zeros((1, len(t), len(CAMERA_COMPONENTS)))
    shared[0, :, CAMERA_COMPONENTS.index("cam_dz_um")] = wave  # the model could be off by this, at 1σ
    without = trend_tests(t, variables=("X_mm",)).set_index("component").loc["cam_dz_um"]
    with_shared = trend_tests(t, shared, variables=("X_mm",)).set_index("component").loc["cam_dz_um"]
    assert without.significant and not with_shared.significant, (without.p_value, with_shared.p_value)
