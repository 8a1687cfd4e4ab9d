"""Tests of dot-grid detection (tasks/vision/detection): accuracy against renderer truth, ordering,
polarity, clutter, rejection of bad views, baselines, and the maths underneath.

Images come from ``tasks.simulation.render`` (realistic: distortion, defocus, vignetting, gradient, noise) at
full size (3072×2048) for accuracy claims and at the 4× binned size (768×512) elsewhere; the
clutter and defect tests use ``tasks.vision.detection.synthetic`` (homography-only, with clutter).
Every image is seeded: the file is deterministic.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.detector_stress import errors_up_to_symmetry
from tasks.simulation.render import ImagingConditions, render_plate_image, true_dot_centres
from tasks.vision.detection import DETECTORS, GridDetection, detect_grid
from tasks.vision.detection.chaincode import filter_edges
from tasks.vision.detection.conics import ellipse_params, fit_conic_lsq, ransac_ellipse, ransac_samples
from tasks.vision.detection.edge_fit import EdgeFitParams
from tasks.vision.detection.framework import FrameworkParams, detect_rrht
from tasks.vision.detection.grid import build_lattice, order_grid, reduce_lattice
from tasks.vision.detection.perspective import centre_bias, correct_bias
from tasks.vision.detection.subpixel import SubpixelParams
from tasks.vision.detection.synthetic import (
    SyntheticConditions,
    apply_homography,
    design_camera,
    facing_pose,
    plate_homography,
    render_synthetic,
)

DIST = (-0.062, 0.115, 0.00012, -0.00018, -0.041)
CAM1 = CameraModel(3072, 2048, 0.0024, 16.0, 1541.3, 1019.8, DIST, focus_distance_mm=300.0, f_number=8.0)
CAM2 = CameraModel(3072, 2048, 0.0024, 16.0, 1529.6, 1027.1, DIST, focus_distance_mm=80.0, f_number=8.0)
PLATE_A = DotPlate(7, 7, 5.0, 2.5, dark_dots=True, margin_mm=5.0, name="a")
PLATE_B = DotPlate(7, 7, 2.0, 1.0, dark_dots=True, margin_mm=2.0, name="b")


def pose(t, tilt_x=0.0, tilt_y=0.0, angle_deg=0.0) -> np.ndarray:
    """T_cam_plate: printed face towards the camera, plate +X at ``angle_deg`` ccw on screen."""
    return facing_camera_pose(t, tilt_x, tilt_y, spin_deg=angle_deg)


def rms_px(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(((a - b) ** 2).sum(axis=1).mean()))


def small(camera: CameraModel) -> CameraModel:
    return camera.scaled(4)


# --------------------------------------------------------------------------------------------
# Accuracy against renderer truth (full size)
# --------------------------------------------------------------------------------------------

FULL_CASES = [
    ("camera 1, plate a, near frontal", CAM1, PLATE_A, pose([3.0, -2.0, 300.0], 0.4, 0.3, -5.0), -5.0),
    ("camera 1, plate a, tilted 25°", CAM1, PLATE_A, pose([10.0, 5.0, 290.0], 20.0, -15.0, 40.0), 40.0),
    ("camera 2, plate b, tilted and defocused", CAM2, PLATE_B, pose([1.0, 1.0, 82.0], 25.0, 10.0, -120.0),
     -120.0),
]


@pytest.mark.parametrize(("name", "camera", "plate", "T", "angle"), FULL_CASES, ids=[c[0] for c in FULL_CASES])
def test_rrht_centres_within_0_05_px_rms_on_realistic_full_size_images(name, camera, plate, T, angle):
    img = render_plate_image(camera, plate, T, ImagingConditions(), seed=7)
    truth = true_dot_centres(camera, plate, T)
    det = detect_grid(img, plate, "rrht", expected_rotation_deg=angle)
    assert det.ok, det.reason
    assert det.centres.shape == (49, 2)
    assert rms_px(det.centres, truth) <= 0.05
    assert np.all(det.support_ratio > 0.9)
    assert np.all(det.residual_rms_px < 0.3)
    assert abs((det.rotation_deg - angle + 180) % 360 - 180) < 5.0


def test_perspective_bias_correction_reduces_error_on_a_tilted_plate():
    T = pose([1.0, 1.0, 82.0], 25.0, 10.0, -120.0)
    cam = dataclasses.replace(CAM2, focus_distance_mm=82.0)
    img = render_plate_image(cam, PLATE_B, T, ImagingConditions(), seed=3)
    truth = true_dot_centres(cam, PLATE_B, T)
    with_corr = detect_rrht(img, PLATE_B, expected_rotation_deg=-120.0)
    without = detect_rrht(img, PLATE_B, expected_rotation_deg=-120.0, correct_perspective=False)
    assert with_corr.ok and without.ok
    e_with, e_without = rms_px(with_corr.centres, truth), rms_px(without.centres, truth)
    assert e_without > 0.05  # the bias is real: ~0.1 px for 83 px dots tilted 27°
    assert e_with < 0.3 * e_without
    # the raw ellipse centres are kept alongside
    assert rms_px(with_corr.ellipse_centres, truth) == pytest.approx(e_without, rel=0.05)


def test_rrht_beats_findcirclesgrid_on_a_tilted_plate():
    T = FULL_CASES[1][3]
    img = render_plate_image(CAM1, PLATE_A, T, ImagingConditions(), seed=11)
    truth = true_dot_centres(CAM1, PLATE_A, T)
    rr = detect_grid(img, PLATE_A, "rrht", expected_rotation_deg=40.0)
    bb = detect_grid(img, PLATE_A, "blob", expected_rotation_deg=40.0)
    assert rr.ok and bb.ok
    assert rms_px(rr.centres, truth) < 0.5 * rms_px(bb.centres, truth)


# --------------------------------------------------------------------------------------------
# Ordering: rotation, symmetry, non-square grids, polarity (reduced size, 768×512)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("angle", [0.0, 23.0, 90.0, 137.0, 180.0, -71.0, -150.0])
def test_any_in_plane_rotation_is_ordered_like_the_plate_with_a_prior(angle):
    cam = small(CAM1)
    T = pose([2.0, -1.0, 280.0], 8.0, -5.0, angle)
    img = render_plate_image(cam, PLATE_A, T, ImagingConditions(), seed=int(angle) % 97)
    truth = true_dot_centres(cam, PLATE_A, T)
    det = detect_grid(img, PLATE_A, "rrht", expected_rotation_deg=angle + 30.0)  # prior 30° off
    assert det.ok, det.reason
    assert np.max(np.linalg.norm(det.centres - truth, axis=1)) < 0.1
    assert abs((det.rotation_deg - angle + 180) % 360 - 180) < 5.0
    assert not det.orientation_ambiguous


def test_square_grid_90_degree_ambiguity_is_resolved_by_the_prior_and_flagged_without():
    cam = small(CAM1)
    T = pose([0.0, 0.0, 280.0], 0.0, 0.0, 90.0)
    img = render_plate_image(cam, PLATE_A, T, ImagingConditions(), seed=5)
    truth = true_dot_centres(cam, PLATE_A, T)
    no_prior = detect_grid(img, PLATE_A, "rrht")
    assert no_prior.ok and no_prior.orientation_ambiguous
    assert abs(no_prior.rotation_deg) < 45.0  # convention: the orientation closest to 0°
    assert np.max(np.linalg.norm(no_prior.centres - truth, axis=1)) > 10.0  # a different corner first
    # same dots, permuted: the unordered sets agree
    d = np.linalg.norm(no_prior.centres[:, None] - truth[None], axis=2)
    assert np.all(d.min(axis=1) < 0.1)
    with_prior = detect_grid(img, PLATE_A, "rrht", expected_rotation_deg=80.0)
    assert with_prior.ok and not with_prior.orientation_ambiguous
    assert np.max(np.linalg.norm(with_prior.centres - truth, axis=1)) < 0.1


def test_non_square_grid_and_other_pitch_and_diameter():
    plate = DotPlate(5, 8, 3.0, 1.2, dark_dots=True, margin_mm=3.0, name="5x8")
    cam = small(CAM1)
    T = pose([1.0, 2.0, 200.0], 10.0, 12.0, 165.0)
    img = render_plate_image(cam, plate, T, ImagingConditions(), seed=2)
    truth = true_dot_centres(cam, plate, T)
    det = detect_grid(img, plate, "rrht", expected_rotation_deg=170.0)
    assert det.ok, det.reason
    assert det.centres.shape == (40, 2)
    assert np.max(np.linalg.norm(det.centres - truth, axis=1)) < 0.15
    # without the prior, the 180° symmetry of a rectangle is flagged
    det0 = detect_grid(img, plate, "rrht")
    assert det0.ok and det0.orientation_ambiguous


def test_a_rectangular_lattice_is_never_labelled_a_quarter_turn_off():
    """7×7 dots 9 mm apart along a row and 6 mm between rows (the prototype's plate a): the
    detector finds them under tilt and turned by 80°, and even without a rotation prior it only
    hesitates between the two labellings a half turn apart, never the quarter turns that would
    swap the long and short spacings (they fit a square lattice equally well)."""
    plate = DotPlate(7, 7, 9.0, 2.5, dark_dots=True, margin_mm=5.0, name="a-rect", row_pitch_mm=6.0)
    cam = small(CAM1)
    T = pose([2.0, -1.0, 300.0], 12.0, -8.0, 80.0)
    img = render_plate_image(cam, plate, T, ImagingConditions(), seed=5)
    truth = true_dot_centres(cam, plate, T)
    det = detect_grid(img, plate, "rrht", expected_rotation_deg=85.0)
    assert det.ok and not det.orientation_ambiguous, det.reason
    assert np.max(np.linalg.norm(det.centres - truth, axis=1)) < 0.1
    det0 = detect_grid(img, plate, "rrht")
    assert det0.ok and det0.orientation_ambiguous
    half_turn = truth[::-1]  # row-major order reversed: the same lattice labelled from the far corner
    off = min(np.max(np.linalg.norm(det0.centres - t, axis=1)) for t in (truth, half_turn))
    assert off < 0.1


def test_a_lattice_through_strong_barrel_distortion_is_grown_whole():
    """A 4 × 3 grid off the axis of a fisheye lens (k1 −0.35, k2 0.1, f 170 px, as the fisheye
    stress case): the step from a dot to its neighbour on the squeezed side is much shorter than
    to the other side, so that one step per axis carried from dot to dot missed (6 of the 12
    found); growth keeps a step per direction."""
    f, k1, k2, pitch = 170.0, -0.35, 0.1, 60.0
    r, c = np.meshgrid(np.arange(4), np.arange(3), indexing="ij")
    und = np.stack([c.ravel() * pitch - pitch + 60.0, r.ravel() * pitch - 1.5 * pitch + 75.0], axis=1) / f
    r2 = (und ** 2).sum(axis=1)
    scale = 1 + k1 * r2 + k2 * r2 ** 2
    pts = np.array([160.0, 180.0]) + f * und * scale[:, None]
    sizes = 0.4 * pitch * scale  # dots shrink with the local magnification
    mn, assigned = build_lattice(pts, sizes, 2.5)
    assert assigned.all()
    box = reduce_lattice(mn)
    box -= box.min(axis=0)
    assert sorted(box[:, 0].tolist()) == sorted(r.ravel().tolist())  # 4 rows of 3 …
    assert sorted(box[:, 1].tolist()) == sorted(c.ravel().tolist())  # … each a row of the plate
    assert len({tuple(m) for m in box}) == 12


def test_light_dots_on_a_dark_plate():
    plate = dataclasses.replace(PLATE_A, dark_dots=False, name="a-light")
    cam = small(CAM1)
    T = pose([0.0, 3.0, 290.0], -6.0, 9.0, 12.0)
    img = render_plate_image(cam, plate, T, ImagingConditions(), seed=4)
    truth = true_dot_centres(cam, plate, T)
    det = detect_grid(img, plate, "rrht", expected_rotation_deg=12.0)
    assert det.ok, det.reason
    assert np.max(np.linalg.norm(det.centres - truth, axis=1)) < 0.1
    # asking for dark dots on this image finds no grid, and says so
    wrong = detect_grid(img, PLATE_A, "rrht")
    assert not wrong.ok and wrong.reason


def test_scale_hint_gives_the_same_centres():
    cam = small(CAM2)
    T = pose([0.5, -0.5, 80.0], 5.0, 5.0, 20.0)
    img = render_plate_image(cam, PLATE_B, T, ImagingConditions(), seed=8)
    a = detect_grid(img, PLATE_B, "rrht", expected_rotation_deg=20.0)
    b = detect_grid(img, PLATE_B, "rrht", expected_rotation_deg=20.0, px_per_mm_hint=cam.fx_px / 80.0)
    assert a.ok and b.ok
    assert np.max(np.linalg.norm(a.centres - b.centres, axis=1)) < 0.05


# --------------------------------------------------------------------------------------------
# Clutter and rejected views (synthetic images)
# --------------------------------------------------------------------------------------------


def synthetic(plate, distance=140.0, angle=15.0, tilt=(10.0, -8.0), offset=(0.0, 0.0), clutter=0, seed=0,
              factor=4):
    cam = design_camera(factor)
    r, t = facing_pose(distance, angle, tilt[0], tilt[1], offset)
    h = plate_homography(cam, r, t)
    cond = SyntheticConditions(blur_sigma_px=0.8, noise_sigma=2.0, clutter=clutter)
    img, truth = render_synthetic(plate, h, (cam.height_px, cam.width_px), cond, seed=seed)
    return img, truth, h


PLATE_S = DotPlate(7, 7, 4.0, 2.5, dark_dots=True, margin_mm=3.0, name="s")


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_clutter_around_the_plate_does_not_break_detection(seed):
    img, truth, _ = synthetic(PLATE_S, clutter=30, seed=seed, angle=20.0 * seed)
    det = detect_grid(img, PLATE_S, "rrht", expected_rotation_deg=20.0 * seed)
    assert det.ok, det.reason
    assert rms_px(det.centres, truth) < 0.03


def test_plate_half_out_of_view_is_rejected_with_a_reason():
    img, _, _ = synthetic(PLATE_S, offset=(24.0, 0.0))
    det = detect_grid(img, PLATE_S, "rrht")
    assert not det.ok
    assert "partial view" in det.reason
    assert np.isnan(det.centres).all()


def test_a_missing_dot_is_rejected_with_a_reason():
    img, truth, _ = synthetic(PLATE_S, seed=4)
    c = np.round(truth[24]).astype(int)
    cv2.circle(img, (int(c[0]), int(c[1])), 14, int(np.median(img[c[1] - 20 : c[1] + 20, c[0] + 14])), -1)
    det = detect_grid(img, PLATE_S, "rrht")
    assert not det.ok
    assert "missing" in det.reason


def test_extra_dots_are_rejected_with_a_reason():
    bigger = dataclasses.replace(PLATE_S, cols=8)
    img, _, _ = synthetic(bigger, seed=5, distance=160.0)
    det = detect_grid(img, PLATE_S, "rrht")
    assert not det.ok
    assert "extra dots" in det.reason


@pytest.mark.parametrize("detector", sorted(DETECTORS))
@pytest.mark.parametrize("kind", ["blank", "saturated", "noise", "gradient"])
def test_featureless_images_fail_cleanly(detector, kind):
    rng = np.random.default_rng(0)
    img = {
        "blank": np.zeros((512, 768), np.uint8),
        "saturated": np.full((512, 768), 255, np.uint8),
        "noise": rng.integers(0, 256, (512, 768), dtype=np.uint8),
        "gradient": np.tile(np.linspace(0, 255, 768).astype(np.uint8), (512, 1)),
    }[kind]
    det = detect_grid(img, PLATE_A, detector)
    assert isinstance(det, GridDetection)
    assert not det.ok and det.reason
    assert det.centres.shape == (49, 2)


def test_bad_inputs_raise_value_error():
    with pytest.raises(ValueError, match="uint8"):
        detect_grid(np.zeros((100, 100), np.float32), PLATE_A)
    with pytest.raises(ValueError, match="2-D"):
        detect_grid(np.zeros((100, 100, 3), np.uint8), PLATE_A)
    with pytest.raises(ValueError, match="unknown detector"):
        detect_grid(np.zeros((100, 100), np.uint8), PLATE_A, "nope")


# --------------------------------------------------------------------------------------------
# Baselines share the output type and the ordering
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("detector", "tol_px"), [("blob", 0.3), ("hough", 2.0)])
def test_baselines_find_and_order_the_grid(detector, tol_px):
    cam = small(CAM1)
    T = pose([0.0, 0.0, 280.0], 3.0, -4.0, 63.0)
    img = render_plate_image(cam, PLATE_A, T, ImagingConditions(), seed=9)
    truth = true_dot_centres(cam, PLATE_A, T)
    det = detect_grid(img, PLATE_A, detector, expected_rotation_deg=60.0)
    assert det.ok, det.reason
    assert det.detector == detector
    assert np.max(np.linalg.norm(det.centres - truth, axis=1)) < tol_px
    assert abs(det.rotation_deg - 63.0) < 5.0


# --------------------------------------------------------------------------------------------
# The maths underneath
# --------------------------------------------------------------------------------------------


def test_batched_ellipse_fit_recovers_known_ellipses_and_ransac_drops_outliers():
    rng = np.random.default_rng(1)
    k, n = 5, 120
    centre = rng.uniform(-3, 3, (k, 2))
    a, b, th = rng.uniform(20, 40, k), rng.uniform(10, 20, k), rng.uniform(0, np.pi, k)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    x = centre[:, 0:1] + a[:, None] * np.cos(t) * np.cos(th)[:, None] - b[:, None] * np.sin(t) * np.sin(th)[:, None]
    y = centre[:, 1:2] + a[:, None] * np.cos(t) * np.sin(th)[:, None] + b[:, None] * np.sin(t) * np.cos(th)[:, None]
    x = x + rng.normal(0, 0.05, x.shape)
    y = y + rng.normal(0, 0.05, y.shape)
    # outliers: a run of rim points pushed 30 % further out (clutter touching the rim)
    x[:, :15] = centre[:, 0:1] + 1.3 * (x[:, :15] - centre[:, 0:1])
    y[:, :15] = centre[:, 1:2] + 1.3 * (y[:, :15] - centre[:, 1:2])
    scale = np.full(k, 30.0)
    origin = np.zeros((k, 2))
    inl = ransac_ellipse(x / 30, y / 30, np.ones((k, n), bool), np.full(k, 0.5 / 30), ransac_samples(k, n, 32, rng))
    assert not inl[:, :15].any() and inl[:, 15:].mean() > 0.95
    conic = fit_conic_lsq(x / 30, y / 30, inl.astype(float))
    c, axes, _ = ellipse_params(conic, origin, scale)
    assert np.allclose(c, centre, atol=0.03)
    assert np.allclose(axes, np.stack([a, b], 1), atol=0.05)


def test_centre_bias_matches_the_projected_circle():
    cam = design_camera(1)
    r, t = facing_pose(90.0, 10.0, 30.0, 20.0)
    h = plate_homography(cam, r, t)
    xy = np.array([[0.0, 0.0], [6.0, -4.0]])
    radius = 1.25
    bias = centre_bias(h, xy, radius)
    # reference: centre of the ellipse through many projected rim points (exact conic fit)
    s = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    for i in range(2):
        rim = apply_homography(h, xy[i] + radius * np.stack([np.cos(s), np.sin(s)], 1))
        o = rim.mean(axis=0)
        conic = fit_conic_lsq(((rim[:, 0] - o[0]) / 50)[None], ((rim[:, 1] - o[1]) / 50)[None], np.ones((1, 400)))
        c, _, _ = ellipse_params(conic, o[None], np.array([50.0]))
        assert np.allclose(bias[i], c[0] - apply_homography(h, xy[i]), atol=1e-6)
    assert np.linalg.norm(bias[0]) > 0.2  # large dots, strong tilt: a visible bias


def test_bias_correction_inverts_the_bias_exactly_for_noiseless_centres():
    plate = PLATE_S
    cam = design_camera(1)
    r, t = facing_pose(100.0, 30.0, 25.0, -20.0)
    h = plate_homography(cam, r, t)
    xy = plate.dot_centres_mm()[:, :2]
    projected = apply_homography(h, xy)
    ellipse_centres = projected + centre_bias(h, xy, plate.dot_diameter_mm / 2)
    corrected, _ = correct_bias(ellipse_centres, xy, plate.dot_diameter_mm / 2, iterations=3)
    assert np.max(np.linalg.norm(corrected - projected, axis=1)) < 1e-3


def test_chain_code_filter_keeps_rims_and_drops_lines_strokes_and_specks():
    img = np.zeros((200, 300), np.uint8)
    cv2.circle(img, (60, 60), 12, 255, 1)
    cv2.ellipse(img, (60, 140), (14, 8), 30, 0, 360, 255, 1)  # a tilted dot's rim
    cv2.line(img, (120, 20), (290, 40), 255, 1)  # long line
    cv2.line(img, (150, 100), (170, 104), 255, 1)  # short straight stroke
    cv2.rectangle(img, (200, 100), (203, 190), 255, 1)  # long thin box (text-like stroke)
    cv2.circle(img, (250, 60), 1, 255, 1)  # speck
    out, stats = filter_edges(img, 16.0, 40.0)
    assert out[40:80, 40:80].sum() == img[40:80, 40:80].sum()  # rims kept whole
    assert out[120:160, 40:80].sum() == img[120:160, 40:80].sum()
    assert out[:, 110:].sum() == 0  # everything else gone
    assert stats["contours"] > stats["kept"] >= 2


def test_grid_ordering_under_strong_perspective_and_with_strays():
    plate = PLATE_S
    cam = design_camera(1)
    r, t = facing_pose(80.0, -35.0, 40.0, 25.0)
    h = plate_homography(cam, r, t)
    pts = apply_homography(h, plate.dot_centres_mm()[:, :2])
    rng = np.random.default_rng(3)
    strays = rng.uniform(pts.min(0) - 300, pts.max(0) + 300, (15, 2))
    allp = np.vstack([strays, pts])
    perm = rng.permutation(len(allp))
    sizes = np.full(len(allp), 2.5 * cam.fx_px / 80.0)
    order = order_grid(allp[perm], plate, sizes=sizes[perm], expected_rotation_deg=-35.0)
    assert order.ok, order.reason
    assert np.allclose(allp[perm][order.index], pts)


def test_vignetting_and_uneven_light_do_not_move_blurred_dot_centres():
    """The flat-field step: a gain slope across a blurred rim moves a step fit by ~γ·σ².

    Plate b tilted 30° and defocused (σ 0.6–7.9 px), 750 px off the principal point, rendered
    noise-free with and without strong vignetting (0.3) and an illumination gradient (0.1). The
    gain slope pushes every dot the same way, so the grid's mean displacement is the measure:
    without the flat field it is ~0.03 px. (Each dot also moves by ~0.01 px RMS at random, as
    it does when the light level is only lowered uniformly: 8-bit quantisation of a noise-free
    render.)
    """
    T = pose([-8.0, 5.0, 84.0], 0.0, 30.0, 20.0)
    clean = render_plate_image(CAM2, PLATE_B, T, ImagingConditions.ideal(), seed=1)
    shaded = render_plate_image(CAM2, PLATE_B, T, ImagingConditions.ideal(vignetting=0.3, gradient=0.1), seed=1)

    def mean_shift_px(flat_field: bool) -> float:
        params = FrameworkParams(subpixel=SubpixelParams(flat_field=flat_field))
        a, b = (detect_rrht(img, PLATE_B, expected_rotation_deg=20.0, params=params) for img in (clean, shaded))
        assert a.ok and b.ok
        return float(np.linalg.norm((b.centres - a.centres).mean(axis=0)))

    assert mean_shift_px(True) < 0.003
    assert mean_shift_px(False) > 0.015


def test_pixel_edge_fit_does_not_lock_to_the_pixel_grid():
    """The pixel-level edge fit (tasks.vision.detection.edge_fit) against the ray rim fit alone.

    A frontal plate a at 300 mm (true intrinsics without distortion, noise-free, in focus: edge
    blur ≈ 1.0 px) moved by quarter pixels: the rim fit's centre errors depend on each rim's
    sub-pixel phase, which advances by a fixed step from dot to dot, so PnP reads them as a tilt
    that changes sign with the shift (±17″, 0.0012 px RMS when measured). Fitting the blurred
    ellipse edge to the pixels removes it (≤ 1.5″, 0.0004 px).
    """
    from tasks.core import se3
    from tasks.core.units import ARCSEC
    from tasks.vision.poses import estimate_pose

    cam = dataclasses.replace(CAM1, distortion=(0.0,) * 5, cx_px=1535.5, cy_px=1023.5)
    obj = PLATE_A.dot_centres_mm()
    mm_per_px = cam.pixel_size_mm * 300.0 / cam.focal_length_mm
    rays_only = FrameworkParams(subpixel=SubpixelParams(pixel_edge_fit=False))
    tilt = {True: [], False: []}
    rms = {True: [], False: []}
    for shift in (0.0, 0.25, 0.5, 0.75):
        T = pose([shift * mm_per_px, 0.5 * shift * mm_per_px, 300.0])
        img = render_plate_image(cam, PLATE_A, T, ImagingConditions.ideal(), seed=0, noiseless=True)
        truth = true_dot_centres(cam, PLATE_A, T)
        for pixel_fit in (True, False):
            det = detect_rrht(img, PLATE_A, expected_rotation_deg=0.0, params=None if pixel_fit else rays_only)
            assert det.ok, det.reason
            rms[pixel_fit].append(rms_px(det.centres, truth))
            est = estimate_pose(obj, det.centres, cam, sigma_px=0.005).T_cam_plate
            tilt[pixel_fit].append(se3.log(np.linalg.inv(T) @ est[None])[0][3:5] / ARCSEC)
    assert max(rms[True]) < 0.0006
    assert np.abs(tilt[True]).max() < 2.5
    # the rim fit alone, for scale: the effect the pixel fit removes is real on these images
    assert min(rms[False]) > 2 * max(rms[True])
    assert np.abs(tilt[False]).max() > 8.0


@pytest.mark.parametrize("blur_gradient", [None, [[0.02, -0.01], [-0.015, 0.03]]])
def test_pixel_edge_fit_jacobian_matches_finite_differences(blur_gradient):
    """The edge fit's analytic Jacobian (tasks.vision.detection.edge_fit.dot_model) against central
    differences, for two ellipses (one tilted, one near-circular) on pixels across the rim, with
    and without a blur that changes across the dot."""
    from tasks.vision.detection.edge_fit import N_PARAMS, dot_model

    rng = np.random.default_rng(0)
    q = np.array([[10.2, 11.3, 8.0, 6.5, 0.4, 30.0, 200.0, 0.9, 1e-3, -2e-3],
                  [11.0, 10.5, 7.2, 7.1, -1.2, 40.0, 180.0, 1.3, -2e-3, 1e-3]])
    x, y = rng.uniform(0.0, 22.0, (2, 2, 300))
    h_s = None if blur_gradient is None else np.array(blur_gradient)
    _, jac = dot_model(q, x, y, with_jacobian=True, blur_gradient=h_s)
    for j in range(N_PARAMS):
        h = 1e-6 * max(1.0, abs(q[:, j]).max())
        dq = np.zeros_like(q)
        dq[:, j] = h
        numeric = (dot_model(q + dq, x, y, blur_gradient=h_s) - dot_model(q - dq, x, y, blur_gradient=h_s)) / (2 * h)
        assert np.abs(numeric - jac[:, j]).max() <= 1e-6 * max(np.abs(numeric).max(), 1.0), j


def test_pixel_edge_fit_normal_equations_match_the_model_and_its_jacobian():
    """The fit's compiled normal equations (JᵀWJ, JᵀWr, Σ w r²) against the same sums formed from
    dot_model's values and Jacobian, with some pixels weighted out (which are then not evaluated)."""
    from tasks.vision.detection.edge_fit import _normal_equations, dot_model

    rng = np.random.default_rng(1)
    q = np.array([[10.2, 11.3, 8.0, 6.5, 0.4, 30.0, 200.0, 0.9, 1e-3, -2e-3],
                  [11.0, 10.5, 7.2, 7.1, -1.2, 40.0, 180.0, 1.3, -2e-3, 1e-3]])
    x, y = rng.uniform(0.0, 22.0, (2, 2, 300))
    z = rng.uniform(20.0, 210.0, (2, 300))
    w = (rng.uniform(size=(2, 300)) > 0.2).astype(float)
    value, jac = dot_model(q, x, y, with_jacobian=True)
    r = (value - z) * w
    jw = jac * w[:, None, :]
    got_value, jtj, jtr, cost = _normal_equations(q, x, y, z, w)
    np.testing.assert_allclose(got_value[w > 0], value[w > 0], rtol=1e-13)
    assert np.isnan(got_value[w == 0]).all()
    np.testing.assert_allclose(jtj, jw @ jac.transpose(0, 2, 1), rtol=1e-11, atol=1e-9 * np.abs(jtj).max())
    np.testing.assert_allclose(jtr, (jw @ r[:, :, None])[..., 0], rtol=1e-11, atol=1e-9 * np.abs(jtr).max())
    np.testing.assert_allclose(cost, (r * r).sum(axis=1), rtol=1e-12)


def test_a_small_grid_with_faint_halos_on_an_even_page_is_found():
    """Twelve 19 px dots (0.13 % of a 1600 × 1600 white page, noise σ 2 DN) each with a faint
    halo 8 DN deep, as in a real photograph of a printed target: the 1–99 % grey stretch spans
    only the paper's noise, the dots clip and the halos' rims make circles twice the dots' size
    (before: "no dot lattice found among 5 candidates"). The band is searched again stretched to
    the far tails, and the grid whose spacing over dot size matches the plate's is kept."""
    size, d, ratio = 1600, 19.0, 3.3
    hi = 4  # the disks drawn at 4× and area-averaged
    ink = np.zeros((size * hi, size * hi), np.uint8)
    truth = np.array([[size / 2 + (c - 1) * ratio * d + 0.3, size / 2 + (r - 1.5) * ratio * d + 0.2]
                      for r in range(4) for c in range(3)])
    for u, v in truth:
        cv2.circle(ink, (round(((u + 0.5) * hi - 0.5) * 16), round(((v + 0.5) * hi - 0.5) * 16)),
                   round(d / 2 * hi * 16), 255, -1, cv2.LINE_AA, shift=4)
    ink = cv2.GaussianBlur(cv2.resize(ink.astype(np.float32) / 255, (size, size), interpolation=cv2.INTER_AREA),
                           (0, 0), 1.0)
    halo = cv2.GaussianBlur(ink, (0, 0), d / 3)
    page = 250.0 - 240.0 * ink - 8.0 * halo / halo.max() + np.random.default_rng(0).normal(0, 2.0, ink.shape)
    img = np.clip(np.rint(page), 0, 255).astype(np.uint8)
    plate = DotPlate(4, 3, ratio, 1.0)
    det = detect_grid(img, plate, "rrht")
    assert det.ok, det.reason
    assert errors_up_to_symmetry(plate, det.centres, truth).max() < 0.1  # without a prior: up to symmetry


def test_a_region_of_another_size_than_the_circle_at_its_place_is_kept_on_request():
    """Merging region candidates into the Hough circles: a region at a circle's place is the same
    candidate; with ``other_sizes`` it is kept beside it when the circle is 0.6 of its size (on a
    strongly blurred dot the circle can lock on to a ring inside it), not when their sizes are alike;
    a region elsewhere is added either way."""
    from tasks.vision.detection.framework import merge_candidates
    from tasks.vision.detection.rrht import CoarseCircles

    def circles(centres, radii):
        c, r = np.asarray(centres, float), np.asarray(radii, float)
        return CoarseCircles(c, np.column_stack([r, r]), np.zeros(len(r)), np.ones(len(r)), np.ones(len(r)))

    hough = circles([[50, 50], [100, 50]], [10.0, 6.0])
    regions = circles([[51, 50], [101, 51], [200, 50]], [11.0, 10.0, 10.0])
    assert merge_candidates(hough, regions)[1].tolist() == [False, False, True]
    merged, added = merge_candidates(hough, regions, other_sizes=True)
    assert added.tolist() == [False, True, True]
    assert len(merged) == 4 and np.allclose(merged.centres[2:], [[101, 51], [200, 50]])


def test_pixel_edge_fit_holds_the_blur_gradient_of_a_tilted_defocused_plate():
    """Plate a of the campaigns (7 × 7 dots of 2.5 mm at 11 mm pitch) tilted 22° at 300 mm in front
    of camera 1 focused at 300 mm (full size, noise-free, no vignetting or gradient): the defocus
    blur grows with the distance from the focal plane, so it changes across each dot, and the
    more blurred side of a rim moves inwards by more (s²/(2ρ)). An edge fit with one blur per dot
    reads that as a centre shift towards the sharper side: the grid comes out compressed along
    the depth gradient, by 0.25 mpx per mm of depth when measured (0.0023 px RMS), which PnP and the
    self-calibration read as perspective (camera 1's focal length 15 ppm long over a full-size
    campaign's five-axis views). With the blur field's gradient held in each dot's model it falls
    to what is left with defocus switched off (0.07 against 0.05 mpx/mm; 0.0010 against 0.00095 px
    RMS)."""
    plate = DotPlate(7, 7, 11.0, 2.5, dark_dots=True, margin_mm=5.0, name="plate_a")
    T = pose([3.0, -2.0, 300.0], tilt_x=22.0, angle_deg=15.0)
    truth = true_dot_centres(CAM1, plate, T)
    depth = (plate.dot_centres_mm() @ T[:3, :3].T + T[:3, 3])[:, 2]
    along = np.linalg.lstsq(np.c_[truth - truth.mean(axis=0), np.ones(len(truth))], depth, rcond=None)[0][:2]
    along /= np.linalg.norm(along)  # image direction of increasing depth

    def compression(image, blur_gradient: bool) -> tuple[float, float]:
        params = FrameworkParams(subpixel=SubpixelParams(edge_fit=EdgeFitParams(blur_gradient=blur_gradient)))
        det = detect_rrht(image, plate, expected_rotation_deg=15.0, params=params)
        assert det.ok, det.reason
        err = det.centres - truth
        slope = np.polyfit(depth - depth.mean(), err @ along, 1)[0]  # px per mm of depth
        return 1e3 * slope, rms_px(det.centres, truth)

    defocused = render_plate_image(CAM1, plate, T, ImagingConditions.ideal(), seed=0, noiseless=True)
    sharp = render_plate_image(CAM1, plate, T, ImagingConditions.ideal(defocus=False), seed=0, noiseless=True)
    held, held_rms = compression(defocused, True)
    one_blur, one_blur_rms = compression(defocused, False)
    in_focus, in_focus_rms = compression(sharp, True)
    assert one_blur < -0.15 and one_blur_rms > 1.8 * in_focus_rms  # the effect is there without the gradient
    assert abs(held - in_focus) < 0.05 and held_rms < 1.25 * in_focus_rms


def test_blur_gradients_follow_a_smooth_blur_field():
    """The image's blur field from the dots' own blurs: σ² a quadratic in position (a plane with
    fewer than 9 dots) fitted once more without outliers; ∇s = ∇σ²/(2σ) at each dot."""
    from tasks.vision.detection.edge_fit import blur_gradients

    rng = np.random.default_rng(3)
    centres = rng.uniform(200.0, 1800.0, (49, 2))
    s2 = 1.0 + 4e-4 * centres[:, 0] - 2e-4 * centres[:, 1] + 1e-7 * centres[:, 0] ** 2
    sigma = np.sqrt(s2)
    sigma[5] = 4.0  # one dot blurred by a smudge: left out of the field
    grad = blur_gradients(centres, sigma, np.arange(49))
    expected = np.stack([4e-4 + 2e-7 * centres[:, 0], np.full(49, -2e-4)], axis=1) / (2 * np.sqrt(s2[:, None]))
    np.testing.assert_allclose(np.delete(grad, 5, axis=0), np.delete(expected, 5, axis=0), rtol=1e-6, atol=1e-12)
    assert np.allclose(blur_gradients(centres[:2], sigma[:2], np.arange(2)), 0.0)  # too few dots: no field
