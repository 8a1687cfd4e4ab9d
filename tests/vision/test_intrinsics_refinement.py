"""Tests of the intrinsics refined on the machine's own images (tasks/vision/intrinsics_refinement.py).

Pose level (no images): camera 1 of ``load_machine("prototype")``, true projected dot centres and
seeded Gaussian pixel noise σ = 0.03 px per coordinate. About 10 s.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from tasks.core import se3
from tasks.machine.description import load_machine
from tasks.simulation.camera_calibration_trials import simulated_trials
from tasks.simulation.campaign_plan import CampaignPlan
from tasks.simulation.render import true_dot_centres
from tasks.vision.camera_calibration import calibrate_trial, machine_views, nominal_camera
from tasks.vision.intrinsics_refinement import refine_intrinsics
from tasks.vision.intrinsics_uncertainty import intrinsics_vector
from tasks.vision.poses import estimate_pose

SIGMA = 0.03  # px per coordinate
SWEEP_MM = np.arange(-25.0, 26.0, 5.0)  # where the X sweep puts plate a (camera frame x, mm)


def _nominal(machine):
    c = machine.cameras["camera1"]
    return nominal_camera({"width_px": c.width_px, "height_px": c.height_px, "pixel_size_mm": c.pixel_size_mm,
                           "focal_length_mm": c.focal_length_mm, "focus_distance_mm": c.focus_distance_mm}, "camera1")


def _fixture_views(machine, trials: int, seed: int, sigma: float = SIGMA):
    plan = CampaignPlan(calibration_trials=trials, images_per_trial=15)
    views = simulated_trials("camera1", sigma, seed, plan=plan, machine=machine)
    return [(o, m) for objs, imgs, _ in views.values() for o, m in zip(objs, imgs, strict=True)]


def _plate_a_at(x_mm: float) -> np.ndarray:
    """Plate a square to camera 1's axis at its focus distance, moved x_mm across the field."""
    return se3.from_rotation_translation(se3.rot_x(np.array([np.pi]))[0], np.array([x_mm, 0.0, 300.0]))


def _sweep_views(machine, repeats: int, rng, sigma: float = SIGMA):
    cam, plate = machine.cameras["camera1"], machine.plates["plate_a"]
    return [(plate.dot_centres_mm(), true_dot_centres(cam, plate, _plate_a_at(x)) + rng.normal(0, sigma, (49, 2)))
            for x in SWEEP_MM for _ in range(repeats)]


def _tilt_error_arcsec(machine, camera) -> np.ndarray:
    """The tilt about y (″) that PnP with ``camera`` reads from exact dots of plate a along the
    sweep, less the one it reads at the centre: what an intrinsics error puts into X's εy."""
    cam, plate = machine.cameras["camera1"], machine.plates["plate_a"]
    tilt = []
    for x in SWEEP_MM:
        T = _plate_a_at(x)
        pose = estimate_pose(plate.dot_centres_mm(), true_dot_centres(cam, plate, T), camera)
        tilt.append(np.degrees(se3.log(se3.inverse(T) @ pose.T_cam_plate)[4]) * 3600)
    tilt = np.array(tilt)
    return tilt - tilt[len(tilt) // 2]


def test_refinement_reaches_opencvs_joint_fit(machine):
    """On the same views (45 fixture views, k3 held) the variable-projection Gauss–Newton, started
    off the optimum (focal length 0.5 % long, principal point 3 px off, k1 + 0.02), ends where
    OpenCV's joint fit ends, with the same standard deviations and RMS."""
    views = _fixture_views(machine, 3, seed=1)
    nominal = _nominal(machine)
    opencv = calibrate_trial([v[0] for v in views], [v[1] for v in views], (nominal.width_px, nominal.height_px),
                             nominal, fix_aspect_ratio=True, fix_k3=True)
    best = opencv.camera_model(nominal)
    start = replace(best, focal_length_mm=best.focal_length_mm * 1.005, cx_px=best.cx_px + 3.0,
                    distortion=(best.distortion[0] + 0.02, *best.distortion[1:]))
    refined = refine_intrinsics(views, start, fix_k3=True)
    assert refined.ok and refined.n_images == 45
    sd = opencv.std_intrinsics
    np.testing.assert_array_less(np.abs(refined.intrinsics - opencv.intrinsics)[:8], 0.01 * sd[:8])
    assert refined.dist_coeffs[4] == 0.0
    np.testing.assert_allclose(refined.std_intrinsics[:8], sd[:8], rtol=0.02)
    assert refined.rms_px == pytest.approx(opencv.rms_px, rel=1e-4)


def test_the_machines_views_pin_the_distortion_where_it_puts_the_plate(machine):
    """Fixture views alone (45, k3 held) leave a tilt trend along the X sweep (the error of k1, k2
    at the field's edges); adding plate a's square-on views of the sweep (11 positions × 20
    repeats, free poses) shrinks it. Measured over noise seeds 1–4: RMS of the trend 1.2, 3.7, 2.6,
    2.7″ (fixture views) → 1.0, 0.4, 1.4, 0.7″ (with the sweep's views)."""
    nominal = _nominal(machine)
    before, after = [], []
    for seed in (1, 2, 3, 4):
        views = _fixture_views(machine, 3, seed)
        fit = calibrate_trial([v[0] for v in views], [v[1] for v in views], (nominal.width_px, nominal.height_px),
                              nominal, fix_aspect_ratio=True, fix_k3=True).camera_model(nominal)
        refined = refine_intrinsics(views + _sweep_views(machine, 20, np.random.default_rng(seed)), fit, fix_k3=True)
        before.append(np.sqrt(np.mean(_tilt_error_arcsec(machine, fit) ** 2)))
        after.append(np.sqrt(np.mean(_tilt_error_arcsec(machine, refined.camera_model(fit)) ** 2)))
    assert np.sqrt(np.mean(np.square(after))) < 0.5 * np.sqrt(np.mean(np.square(before)))
    assert max(after) < 1.6


def test_exact_views_refine_to_the_truth(machine):
    """Noise-free fixture and sweep views, k3 free, started 0.3 % long, 1 px off and k1 + 0.01:
    the refinement lands on the true intrinsics."""
    truth = machine.cameras["camera1"]
    views = (_fixture_views(machine, 2, seed=4, sigma=0.0)
             + _sweep_views(machine, 1, np.random.default_rng(0), sigma=0.0))
    start = replace(truth, focal_length_mm=truth.focal_length_mm * 1.003, cx_px=truth.cx_px + 1.0,
                    distortion=(truth.distortion[0] + 0.01, *truth.distortion[1:]))
    refined = refine_intrinsics(views, start)
    assert refined.ok
    np.testing.assert_allclose(intrinsics_vector(refined.camera_model(truth)), intrinsics_vector(truth),
                               rtol=0, atol=1e-6)


def test_machine_views_take_the_named_sweeps_and_five_axis_poses_of_the_measured_plate(tiny_campaign):
    """From the long dots table: the camera's images in the X and Y sweeps and the five-axis poses,
    not in its calibration views, other sweeps or validation poses."""
    dots = pd.read_parquet(tiny_campaign / "truth" / "dots.parquet")
    manifest = pd.read_csv(tiny_campaign / "manifest.csv")
    plate = load_machine("prototype").plates["plate_a"]
    views = machine_views(dots, manifest, "camera1", plate, ("X", "Y"))
    mine = manifest[(manifest.camera == "camera1") & ((manifest.stage == "pige")
                                                      | ((manifest.stage == "pdge") & manifest.group.isin(["X", "Y"])))]
    assert set(manifest.stage) > {"pige", "pdge", "validation"} and set(manifest.group) > {"X", "Y", "Z"}
    assert len(views) == len(mine) > 0
    assert all(o.shape == (49, 3) and m.shape == (49, 2) for o, m in views)
    assert all(np.array_equal(o, plate.dot_centres_mm()) for o, _ in views)
    found = sum(int(np.isfinite(m).all(axis=1).sum()) for _, m in views)
    assert found == int(dots.image_id.isin(mine.image_id).sum())
