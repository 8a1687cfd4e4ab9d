"""A plate partly out of the image, measured on the dots inside it (tasks/vision/detection/partial_view).

Full-size renders (tasks.simulation.render: distortion, defocus, vignetting, noise) of a 66 mm plate that
a 50 mm sweep carries partly out of camera 1's field, checked against the renderer's true dot
centres and the true pose; the prior is the true projection moved as a nominal model would be
off (a fraction of the pitch). Every image is seeded: the file is deterministic.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tasks.core.se3 import log
from tasks.core.units import RAD_TO_ARCSEC
from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.render import ImagingConditions, render_plate_image, true_dot_centres
from tasks.vision.detection import detect_grid
from tasks.vision.detection.framework import cut_by_border
from tasks.vision.detection.partial_view import MIN_FRACTION
from tasks.vision.poses import estimate_pose

DIST = (-0.062, 0.115, 0.00012, -0.00018, -0.041)
CAM1 = CameraModel(3072, 2048, 0.0024, 16.0, 1541.3, 1019.8, DIST, focus_distance_mm=300.0, f_number=8.0)
PLATE = DotPlate(7, 7, 11.0, 2.5, dark_dots=True, margin_mm=5.0, name="a")
PITCH_PX = 11.0 * CAM1.fx_px / 300.0


def prior_off_by(truth: np.ndarray, shift_px=(0.0, 0.0), turn_deg: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """The true centres moved as a nominal model's prediction would be: turned by ``turn_deg`` and
    scaled about their mean, then shifted (px)."""
    c = truth.mean(axis=0)
    a = np.radians(turn_deg)
    rot = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return (truth - c) @ rot.T + c + np.asarray(shift_px)


def whole_in_image(truth: np.ndarray, margin_px: float) -> np.ndarray:
    u, v = truth[:, 0], truth[:, 1]
    w, h = CAM1.width_px, CAM1.height_px
    return (u >= margin_px) & (u <= w - 1 - margin_px) & (v >= margin_px) & (v <= h - 1 - margin_px)


# (name, T_cam_plate): the Y sweep's end (two rows out) and the C sweep at 45° (corners out)
VIEWS = [
    ("two rows below the image", facing_camera_pose([2.0, 25.0, 300.0], 0.3, -0.2, spin_deg=0.0)),
    ("turned 45°, corners out", facing_camera_pose([1.0, -3.0, 300.0], 0.5, 0.4, spin_deg=45.0)),
    ("tilted 20°, a column out", facing_camera_pose([-45.0, 2.0, 295.0], 0.0, 20.0, spin_deg=-8.0)),
]


@pytest.mark.parametrize(("name", "T"), VIEWS, ids=[v[0] for v in VIEWS])
def test_a_plate_partly_out_of_view_is_measured_on_the_dots_inside_it(name, T):
    img = render_plate_image(CAM1, PLATE, T, ImagingConditions(), seed=11)
    truth = true_dot_centres(CAM1, PLATE, T)
    prior = prior_off_by(truth, shift_px=(0.12 * PITCH_PX, -0.08 * PITCH_PX), turn_deg=0.6, scale=1.01)
    det = detect_grid(img, PLATE, "rrht", expected_rotation_deg=None, expected_centres_px=prior)
    assert det.ok, det.reason
    found = det.found
    n = PLATE.rows * PLATE.cols
    assert MIN_FRACTION * n <= found.sum() < n
    # every dot well inside is measured; none whose rim rays the border would cut
    assert np.all(found[whole_in_image(truth, 0.5 * PITCH_PX)])
    radius_px = 1.25 * CAM1.fx_px / T[2, 3]
    assert not np.any(found & cut_by_border(truth, np.full(n, radius_px), 11.0 / 2.5 - 1.0, img.shape))
    err = np.linalg.norm(det.centres[found] - truth[found], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.05
    # the pose from the partial view agrees with the truth within its stated uncertainty
    pose = estimate_pose(PLATE.dot_centres_mm(), det.centres, CAM1)
    assert pose.ok and pose.n_points == found.sum()
    delta = log(np.linalg.inv(T) @ pose.T_cam_plate)  # body-frame (v mm, ω rad)
    z = delta / np.sqrt(np.diag(pose.covariance))
    assert np.all(np.abs(z) < 5.0), (z, delta[3:] * RAD_TO_ARCSEC)


def test_without_the_prior_a_partial_view_is_rejected():
    T = VIEWS[0][1]
    img = render_plate_image(CAM1, PLATE, T, ImagingConditions(), seed=11)
    det = detect_grid(img, PLATE, "rrht")
    assert not det.ok
    assert "partial view" in det.reason


def test_a_dot_hidden_inside_the_image_fails_the_view_and_is_named():
    T = VIEWS[0][1]
    img = render_plate_image(CAM1, PLATE, T, ImagingConditions(), seed=11)
    truth = true_dot_centres(CAM1, PLATE, T)
    k = 3 * PLATE.cols + 2  # row 3, col 2: well inside the image
    u, v = np.round(truth[k]).astype(int)
    background = int(np.median(img[v - 60 : v + 60, u + 45 : u + 60]))
    cv2.circle(img, (int(u), int(v)), 40, background, -1)
    det = detect_grid(img, PLATE, "rrht", expected_centres_px=truth)
    assert not det.ok
    assert "missing dots" in det.reason and "row 3 col 2" in det.reason


def test_a_prior_half_a_pitch_off_fails_instead_of_mislabelling():
    T = VIEWS[0][1]
    img = render_plate_image(CAM1, PLATE, T, ImagingConditions(), seed=11)
    truth = true_dot_centres(CAM1, PLATE, T)
    det = detect_grid(img, PLATE, "rrht", expected_centres_px=prior_off_by(truth, shift_px=(0.5 * PITCH_PX, 0.0)))
    assert not det.ok
    assert "partial view" in det.reason


def test_a_prior_one_pitch_off_is_caught_by_the_dots_it_says_are_missing():
    """Shifted by a whole row, the prior labels the visible rows one row off; it then puts a row
    it calls visible where the image has none, and the view fails rather than mislabel."""
    T = VIEWS[0][1]
    img = render_plate_image(CAM1, PLATE, T, ImagingConditions(), seed=11)
    truth = true_dot_centres(CAM1, PLATE, T)
    det = detect_grid(img, PLATE, "rrht", expected_centres_px=prior_off_by(truth, shift_px=(0.0, -PITCH_PX)))
    assert not det.ok
    assert "missing dots" in det.reason


def test_too_little_of_the_plate_in_view_fails():
    T = facing_camera_pose([0.0, 50.0, 300.0], spin_deg=0.0)  # three rows of seven in the image
    img = render_plate_image(CAM1, PLATE, T, ImagingConditions(), seed=11)
    det = detect_grid(img, PLATE, "rrht", expected_centres_px=true_dot_centres(CAM1, PLATE, T))
    assert not det.ok
    assert "partial view" in det.reason and "fewer than 50%" in det.reason
