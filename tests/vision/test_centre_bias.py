"""The lens's share of the detector's centre bias (tasks.vision.centre_bias), against rendered truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.render import ImagingConditions, render_plate_image, true_dot_centres
from tasks.vision.centre_bias import rim_centre_bias, unbiased_dots, unbiased_view
from tasks.vision.detection.framework import detect_rrht

CAM1 = CameraModel(3072, 2048, 0.0024, 16.0, 1541.3, 1019.8, (-0.062, 0.115, 0.00012, -0.00018, -0.041),
                   focus_distance_mm=300.0, f_number=8.0)
PLATE_A = DotPlate(7, 7, 11.0, 2.5, dark_dots=True, margin_mm=5.0, name="plate_a")


def rms_px(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(((a - b) ** 2).sum(axis=1))))


def test_without_distortion_the_detectors_perspective_correction_leaves_no_bias():
    """A distortion-free camera: the projected rims are exact ellipses and the plate homography
    exact, so the detector's correction leaves nothing (well under the 0.004 px noise of a centre)."""
    cam = dataclasses.replace(CAM1, distortion=(0.0,) * 5)
    bias = rim_centre_bias(cam, PLATE_A, facing_camera_pose([3.0, -2.0, 300.0], 22.0, 0.0, spin_deg=15.0))
    assert np.abs(bias).max() < 2e-5


@pytest.mark.parametrize("tilt_deg", [10.0, 22.0])
def test_unbiased_centres_of_a_rendered_plate_are_nearer_the_truth(tilt_deg):
    """Plate a at 300 mm in camera 1's focal plane (full size, noise-free, no defocus): the detected
    centres err by 0.0010 px RMS against the projected dot centres (when measured), half of it
    the lens's curvature across each dot, the same in every view at the same place; without
    :func:`rim_centre_bias` (true intrinsics, the view's own PnP pose) 0.00055 px, what a
    distortion-free camera leaves (0.0005 px)."""
    T = facing_camera_pose([3.0, -2.0, 300.0], tilt_deg, 0.0, spin_deg=15.0)
    truth = true_dot_centres(CAM1, PLATE_A, T)
    image = render_plate_image(CAM1, PLATE_A, T, ImagingConditions.ideal(defocus=False), seed=0, noiseless=True)
    det = detect_rrht(image, PLATE_A, expected_rotation_deg=15.0)
    assert det.ok, det.reason
    before, after = rms_px(det.centres, truth), rms_px(unbiased_view(det.centres, CAM1, PLATE_A), truth)
    assert before > 0.0008
    assert after < 0.65 * before


def test_unbiased_dots_corrects_each_image_by_its_own_camera_and_plate():
    """The long dots table: each image's centres move by the bias of its own pose; a dot not found
    stays NaN, an image of a camera without intrinsics is left as it is."""
    poses = [facing_camera_pose([3.0, -2.0, 300.0], 22.0, 0.0, spin_deg=15.0),
             facing_camera_pose([-10.0, 8.0, 290.0], 12.0, -8.0, spin_deg=-30.0)]
    rows = []
    for i, T in enumerate(poses):
        found = np.arange(49) != (3 if i == 0 else -1)  # image 0 misses a dot, which its neighbours' bias sees
        uv = np.where(found[:, None], true_dot_centres(CAM1, PLATE_A, T) + rim_centre_bias(CAM1, PLATE_A, T, found),
                      np.nan)
        rc = PLATE_A.row_col()
        rows.append(pd.DataFrame({"image_id": f"img{i}", "camera": "camera1", "row": rc[:, 0], "col": rc[:, 1],
                                  "u_px": uv[:, 0], "v_px": uv[:, 1]}))
    dots = pd.concat([*rows, rows[1].assign(image_id="other", camera="camera9")], ignore_index=True)
    plate_of = pd.Series("plate_a", index=["img0", "img1", "other"])
    out = unbiased_dots(dots, plate_of, {"camera1": CAM1}, {"plate_a": PLATE_A})
    for i, T in enumerate(poses):
        got = out[out.image_id == f"img{i}"][["u_px", "v_px"]].to_numpy()
        finite = np.isfinite(got).all(axis=1)
        assert finite.sum() == (48 if i == 0 else 49)
        assert np.abs(got[finite] - true_dot_centres(CAM1, PLATE_A, T)[finite]).max() < 2e-5
    np.testing.assert_array_equal(out[out.image_id == "other"][["u_px", "v_px"]].to_numpy(),
                                  dots[dots.image_id == "other"][["u_px", "v_px"]].to_numpy())
