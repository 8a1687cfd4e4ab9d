"""Tests of plate pose estimation and its covariance (tasks/vision/poses.py).

Pose level: true fixture poses from the default campaign plan, true intrinsics, true projected
dot centres + seeded Gaussian noise σ = 0.03 px. The covariance must be *calibrated*: over
200 noisy draws per pose the empirical standard deviation of δ = log(T_true⁻¹ T_est) (eq. 20)
must be 0.8–1.25 × the predicted one. One end-to-end check on full-size rendered images with
the RRHT detector. Deterministic; a few seconds.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from tasks.core import se3
from tasks.core.units import RAD_TO_ARCSEC
from tasks.machine.description import load_machine
from tasks.machine.kinematics import pose_error
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign
from tasks.simulation.render import ImagingConditions, render_plate_image, true_dot_centres
from tasks.vision.poses import (
    COV_COLUMNS,
    POSE_COLUMNS,
    STD_COLUMNS,
    covariance_in_camera_frame,
    covariances_from_table,
    estimate_pose,
    estimate_poses,
    pose_jacobian,
    poses_from_table,
)

SIGMA = 0.03
N_DRAWS = 200


@pytest.fixture(scope="module")
def setup():
    machine = load_machine("prototype")
    poses, fixture = plan_campaign(machine, CampaignPlan(), 0)
    return machine, poses, fixture


def views(setup, camera: str, n: int, start: int = 0):
    machine, poses, fixture = setup
    rows = np.flatnonzero((poses["camera"] == camera) & (poses["stage"] == "camera_calibration"))[start:start + n]
    cam, plate = machine.cameras[camera], machine.plates[machine.views[camera]]
    return cam, plate, [(str(poses["image_id"].iloc[i]), fixture[int(i)]) for i in rows]


@pytest.mark.parametrize("camera", ["camera1", "camera2"])
def test_jacobian_matches_finite_differences(setup, camera):
    cam, plate, vs = views(setup, camera, 1, 3)
    T = vs[0][1]
    obj = plate.dot_centres_mm()
    J = pose_jacobian(obj, T, cam).reshape(-1, 6)
    h = 1e-6
    for j in range(6):
        d = np.zeros(6)
        d[j] = h
        num = (true_dot_centres(cam, plate, T @ se3.exp(d)) - true_dot_centres(cam, plate, T @ se3.exp(-d))) / (2 * h)
        np.testing.assert_allclose(J[:, j], num.ravel(), rtol=1e-6, atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize("camera", ["camera1", "camera2"])
def test_noise_free_pose_is_exact(setup, camera):
    cam, plate, vs = views(setup, camera, 3)
    for _, T in vs:
        r = estimate_pose(plate.dot_centres_mm(), true_dot_centres(cam, plate, T), cam)
        assert r.ok and r.n_points == 49 and r.message == ""
        e = pose_error(r.T_cam_plate[None], T[None])[0]
        assert np.abs(e[:3]).max() < 1e-8 and np.abs(e[3:]).max() < 1e-10
        assert r.rms_px < 1e-6


@pytest.mark.parametrize("camera", ["camera1", "camera2"])
def test_covariance_is_calibrated_monte_carlo(setup, camera):
    """200 draws × 2 poses per camera: ratio empirical / predicted std in [0.8, 1.25] for all six
    components (measured 0.99–1.06); |δ_i| > 3σ_i in ≤ 1 % of components; mean Mahalanobis
    distance ≈ 6 (χ²₆; slightly above with σ estimated from 92 degrees of freedom)."""
    cam, plate, vs = views(setup, camera, 2, 5)
    obj = plate.dot_centres_mm()
    rng = np.random.default_rng([7, int(camera[-1])])
    for _, T in vs:
        clean = true_dot_centres(cam, plate, T)
        deltas, covs, deltas_cam = [], [], []
        for _ in range(N_DRAWS):
            r = estimate_pose(obj, clean + rng.normal(0.0, SIGMA, clean.shape), cam)
            assert r.ok
            deltas.append(pose_error(r.T_cam_plate[None], T[None])[0])
            deltas_cam.append(se3.log(r.T_cam_plate @ se3.inverse(T)))
            covs.append(r.covariance)
        d, c, dc = np.array(deltas), np.array(covs), np.array(deltas_cam)
        predicted = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0))
        ratio = d.std(axis=0) / predicted
        assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
        z = d / np.sqrt(np.diagonal(c, axis1=1, axis2=2))
        assert np.mean(np.abs(z) > 3) <= 0.01
        maha = np.einsum("ni,nij,nj->n", d, np.linalg.inv(c), d)
        assert 5.0 < maha.mean() < 7.5
        # the same uncertainty as a left perturbation in the camera frame
        cc = np.mean([covariance_in_camera_frame(T, ci) for ci in c], axis=0)
        ratio_cam = dc.std(axis=0) / np.sqrt(np.diag(cc))
        assert np.all((ratio_cam > 0.8) & (ratio_cam < 1.25)), ratio_cam


def test_given_sigma_scales_the_covariance(setup):
    cam, plate, vs = views(setup, "camera1", 1)
    T = vs[0][1]
    uv = true_dot_centres(cam, plate, T) + np.random.default_rng(3).normal(0, SIGMA, (49, 2))
    a = estimate_pose(plate.dot_centres_mm(), uv, cam, sigma_px=0.03)
    b = estimate_pose(plate.dot_centres_mm(), uv, cam, sigma_px=0.06)
    np.testing.assert_allclose(b.covariance, 4 * a.covariance)
    assert a.sigma_px == 0.03 and a.rms_px == b.rms_px
    s = a.std_mm_arcsec
    np.testing.assert_allclose(s[3:], np.sqrt(np.diag(a.covariance))[3:] * RAD_TO_ARCSEC)
    # camera 1 at 300 mm, plate frame: a few µm (mostly along the optical axis), ~16″ tilt, ~4″ spin
    assert np.all(s[:3] < 0.01) and np.all(s[3:5] < 30) and s[5] < 10


def test_partial_and_failed_images_get_a_status(setup):
    cam, plate, vs = views(setup, "camera2", 1)
    T = vs[0][1]
    obj = plate.dot_centres_mm()
    uv = true_dot_centres(cam, plate, T)
    part = uv.copy()
    part[:30] = np.nan
    r = estimate_pose(obj, part, cam)
    assert r.ok and r.n_points == 19 and "30 of 49" in r.message
    assert np.isnan(r.residuals_px[:30]).all() and np.isfinite(r.residuals_px[30:]).all()
    assert np.abs(pose_error(r.T_cam_plate[None], T[None])[0]).max() < 1e-8

    few = uv.copy()
    few[5:] = np.nan
    r = estimate_pose(obj, few, cam)
    assert r.status == "too_few_points" and not r.ok and np.isnan(r.T_cam_plate).all()
    assert estimate_pose(obj, np.full((49, 2), np.nan), cam).status == "too_few_points"
    assert estimate_pose(obj, uv[:10], cam).status == "bad_input"


def dots_table(ids_poses, cam_name, cam, plate, rng=None):
    rc = plate.row_col()
    parts = []
    for image_id, T in ids_poses:
        uv = true_dot_centres(cam, plate, T)
        if rng is not None:
            uv = uv + rng.normal(0, SIGMA, uv.shape)
        parts.append(pd.DataFrame({"image_id": image_id, "camera": cam_name, "row": rc[:, 0], "col": rc[:, 1],
                                   "u_px": uv[:, 0], "v_px": uv[:, 1]}))
    return pd.concat(parts, ignore_index=True)


def test_estimate_poses_table(setup):
    """Many images from a long dots table (the truth/dots.parquet layout), both cameras, one
    image with no dots found and one with an unknown camera: statuses, not exceptions."""
    machine = setup[0]
    rng = np.random.default_rng(11)
    tables, truth = [], {}
    for name in ("camera1", "camera2"):
        cam, plate, vs = views(setup, name, 10)
        tables.append(dots_table(vs, name, cam, plate, rng))
        truth.update(dict(vs))
    dots = pd.concat(tables, ignore_index=True)
    lost = dots["image_id"].iloc[0]
    dots.loc[dots["image_id"] == lost, ["u_px", "v_px"]] = np.nan
    odd = dots["image_id"].iloc[-1]
    dots.loc[dots["image_id"] == odd, "camera"] = "camera9"
    plates = {c: machine.plates[p] for c, p in machine.views.items()}
    out = estimate_poses(dots.sample(frac=1.0, random_state=1), machine.cameras, plates)
    assert len(out) == 20 and set(out["image_id"]) == set(truth)
    assert [*POSE_COLUMNS, *STD_COLUMNS, *COV_COLUMNS] <= list(out.columns)
    out = out.set_index("image_id")
    assert out.loc[lost, "status"] == "too_few_points"
    assert out.loc[odd, "status"] == "bad_input" and "camera9" in out.loc[odd, "message"]
    ok = out[out["status"] == "ok"]
    assert len(ok) == 18 and (ok["n_points"] == 49).all()
    T = poses_from_table(ok.reset_index())
    C = covariances_from_table(ok.reset_index())
    T_true = np.array([truth[i] for i in ok.index])
    d = pose_error(T, T_true)
    z = d / np.sqrt(np.diagonal(C, axis1=1, axis2=2))
    assert np.abs(z).max() < 4.5
    assert np.allclose(ok["rms_px"], math.sqrt(2) * SIGMA, rtol=0.25)
    np.testing.assert_allclose(ok["std_wz_arcsec"], np.sqrt(C[:, 5, 5]) * RAD_TO_ARCSEC)


def test_missing_columns_raise(setup):
    cam, plate, _ = views(setup, "camera1", 1)
    with pytest.raises(ValueError, match="camera"):
        estimate_poses(pd.DataFrame({"image_id": [], "row": [], "col": [], "u_px": [], "v_px": []}),
                       {"camera1": cam}, plate)


def test_end_to_end_rendered_images(setup):
    """Full-size rendered images (3 per camera), RRHT detector centres, true intrinsics: poses within
    10 µm and 15″ of the truth per component (measured ≤ 3.2 µm, ≤ 8″). The detector's small
    systematic errors are correlated over the dots, which the white-noise covariance does not
    model: for camera 2 the error reaches several reported σ (see docs/camera-calibration.md)."""
    from tasks.vision.detection import detect_grid

    machine = setup[0]
    for name in ("camera1", "camera2"):
        cam, plate, vs = views(setup, name, 3)
        for k, (image_id, T) in enumerate(vs):
            truth = true_dot_centres(cam, plate, T)
            d = truth[1] - truth[0]
            img = render_plate_image(cam, plate, T, ImagingConditions(), seed=100 + k)
            det = detect_grid(img, plate, "rrht", expected_rotation_deg=math.degrees(math.atan2(-d[1], d[0])))
            assert det.ok, det.reason
            r = estimate_pose(plate.dot_centres_mm(), det.centres, cam)
            assert r.ok and r.rms_px < 0.03, (image_id, r.rms_px)
            e = pose_error(r.T_cam_plate[None], T[None])[0]
            assert np.abs(e[:3]).max() < 0.01, (image_id, e)
            assert np.abs(e[3:]).max() * RAD_TO_ARCSEC < 15.0, (image_id, e)
    assert machine.views["camera2"] == "plate_b"
