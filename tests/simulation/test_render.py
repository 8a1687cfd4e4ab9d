"""Tests of the plate image renderer (tasks/simulation/render.py).

Geometry as on the machine: 16 mm lens, 2.4 µm pixels (fx = fy ≈ 6666.7 px), 3072×2048;
camera 1 sees plate "a" (2.5 mm dots, 5 mm pitch) from ~280 mm, camera 2 sees plate "b"
(1.0 mm dots, 2 mm pitch) from ~80 mm.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from tasks.machine.camera_model import CameraModel, distort_normalised, project_points
from tasks.machine.distortion import (
    ExtraDistortion,
    UndistortionGrid,
    distort_normalised_ext,
    undistort_normalised,
    undistort_pixels,
)
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.render import (
    ImagingConditions,
    blur_sigma_px,
    gain_map,
    plate_in_view,
    render_plate_image,
    render_scene,
    true_dot_centres,
)

DIST = (-0.08, 0.12, 1e-4, -2e-4, -0.05)
CAM1 = CameraModel(3072, 2048, 0.0024, 16.0, 1535.7, 1023.2, DIST, focus_distance_mm=280.0, f_number=8.0)
CAM2 = CameraModel(3072, 2048, 0.0024, 16.0, 1538.1, 1020.6, DIST, focus_distance_mm=80.0, f_number=8.0)
PLATE_A = DotPlate(7, 7, 5.0, 2.5, dark_dots=True, margin_mm=5.0, name="a")
PLATE_B = DotPlate(7, 7, 2.0, 1.0, dark_dots=True, margin_mm=3.0, name="b")
PLATE_RECT = DotPlate(7, 7, 9.0, 2.5, dark_dots=True, margin_mm=5.0, name="rect", row_pitch_mm=6.0)
IDEAL = ImagingConditions.ideal()


def pose(t, rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    """T_cam_plate with the plate face (+Z_plate) towards the camera, tilted by rx, ry (deg)."""
    return facing_camera_pose(t, rx, ry, rz)


POSE_A = pose([3.0, -2.0, 280.0], 0.4, 0.3, 5.0)
POSE_B = pose([1.0, 1.0, 80.0], 0.3, 0.2, 3.0)


def centroids(img: np.ndarray, centres: np.ndarray, half: int, background: float) -> np.ndarray:
    """Intensity centroids of |img − background| in square windows around ``centres`` (px)."""
    img = np.asarray(img, dtype=float)
    out = []
    for u, v in centres:
        j0, i0 = round(u) - half, round(v) - half
        w = np.abs(img[i0 : i0 + 2 * half + 1, j0 : j0 + 2 * half + 1] - background)
        jj, ii = np.meshgrid(np.arange(j0, j0 + 2 * half + 1), np.arange(i0, i0 + 2 * half + 1))
        s = w.sum()
        out.append(((w * jj).sum() / s, (w * ii).sum() / s))
    return np.array(out)


def window_half(camera: CameraModel, plate: DotPlate, z_mm: float) -> int:
    """Half window: dot radius + blur margin, well short of the neighbouring dots (px)."""
    scale = camera.fx_px / z_mm  # px per mm
    return round(scale * (plate.dot_diameter_mm / 2 + 0.3 * (plate.pitch_range_mm[0] - plate.dot_diameter_mm)))


def ellipse_centres(camera: CameraModel, plate: DotPlate, T: np.ndarray) -> np.ndarray:
    """Centres (px) of the exact images of the dot circles under a distortion-free pinhole."""
    K = camera.matrix
    H = K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
    Hi = np.linalg.inv(H)
    R = plate.dot_diameter_mm / 2
    out = []
    for cx, cy, _ in plate.dot_centres_mm():
        C = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [-cx, -cy, cx * cx + cy * cy - R * R]])
        Ci = Hi.T @ C @ Hi
        out.append(-np.linalg.solve(Ci[:2, :2], Ci[:2, 2]))
    return np.array(out)


# --------------------------------------------------------------------------------------------
# Centroid accuracy
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("camera", "plate", "T"),
    [(CAM1, PLATE_A, POSE_A), (CAM2, PLATE_B, POSE_B), (CAM1, PLATE_RECT, POSE_A)],
    ids=["cam1-plate_a", "cam2-plate_b", "cam1-rectangular"],
)
@pytest.mark.parametrize("factor", [1, 4], ids=["full", "reduced"])
def test_centroid_matches_projected_centre_near_frontal(camera, plate, T, factor):
    cam = camera.scaled(factor)
    img = render_plate_image(cam, plate, T, IDEAL, seed=0, noiseless=True)
    assert img.dtype == np.uint8 and img.shape == (cam.height_px, cam.width_px)
    centres = true_dot_centres(cam, plate, T)
    c = centroids(img, centres, window_half(cam, plate, T[2, 3]), IDEAL.light_level)
    err = np.linalg.norm(c - centres, axis=1)
    assert err.max() <= 0.02, err.max()


def test_tilted_pose_centroid_is_ellipse_centre_not_projected_centre():
    """Under a 30° tilt the centroid of a dot is the centre of its image ellipse, which differs
    from the projected 3D centre by the known perspective bias (≈ f·(R/Z)²·tan θ-sized)."""
    cam = dataclasses.replace(CAM2, distortion=(0.0,) * 5)
    T = pose([0.5, -0.5, 80.0], 30.0, 8.0, 3.0)
    cond = ImagingConditions.ideal(defocus=False)
    scene = render_scene(cam, PLATE_B, T, cond)
    centres = true_dot_centres(cam, PLATE_B, T)
    ell = ellipse_centres(cam, PLATE_B, T)
    c = centroids(scene, centres, window_half(cam, PLATE_B, 80.0), cond.light_level)
    bias = ell - centres
    assert np.linalg.norm(bias, axis=1).max() > 0.05  # the effect is real at this tilt
    assert np.linalg.norm(c - ell, axis=1).max() <= 0.01
    # and the measured bias points the same way as the predicted one
    cos = np.sum((c - centres) * bias, axis=1) / np.linalg.norm(c - centres, axis=1) / np.linalg.norm(bias, axis=1)
    assert cos.min() > 0.95


def test_light_dots_on_dark_plate():
    plate = dataclasses.replace(PLATE_A, dark_dots=False)
    cam = CAM1.scaled(4)
    img = render_plate_image(cam, plate, POSE_A, IDEAL, seed=0, noiseless=True)
    centres = true_dot_centres(cam, plate, POSE_A)
    u, v = np.rint(centres[24]).astype(int)
    assert img[v, u] == round(IDEAL.light_level)  # dot centre is light
    c = centroids(img, centres, window_half(cam, plate, 280.0), IDEAL.dark_level)
    assert np.linalg.norm(c - centres, axis=1).max() <= 0.02


# --------------------------------------------------------------------------------------------
# Determinism and noise
# --------------------------------------------------------------------------------------------


def test_same_seed_same_bytes_different_seed_different_noise():
    cam = CAM2.scaled(4)
    cond = ImagingConditions()
    a = render_plate_image(cam, PLATE_B, POSE_B, cond, seed=7)
    b = render_plate_image(cam, PLATE_B, POSE_B, cond, seed=7)
    c = render_plate_image(cam, PLATE_B, POSE_B, cond, seed=8)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    assert np.mean(a != c) > 0.5  # noise everywhere, not in a few pixels
    # the noiseless image is the common mean
    n = render_plate_image(cam, PLATE_B, POSE_B, cond, seed=7, noiseless=True)
    assert abs(float(np.mean(a.astype(float) - n))) < 0.05


def test_noise_statistics_match_read_and_shot_parameters():
    cam = CAM1.scaled(4)
    read, gain_e = 2.0, 10.0
    cond = ImagingConditions.ideal(read_noise_dn=read, shot_noise_gain_e_per_dn=gain_e, background_level=20.0)
    plate = DotPlate(3, 3, 10.0, 1.0, dark_dots=True, margin_mm=4.0)  # big bare areas
    T = pose([0.0, 0.0, 280.0])
    imgs = [render_plate_image(cam, plate, T, cond, seed=s).astype(float) for s in (1, 2)]
    ref = render_plate_image(cam, plate, T, cond, seed=0, noiseless=True)
    diff = imgs[0] - imgs[1]
    for level in (cond.light_level, cond.background_level):
        flat = ref == level
        # keep away from edges: erode the flat mask by 3 px
        m = flat.copy()
        for ax in (0, 1):
            for s in (-3, 3):
                m &= np.roll(flat, s, axis=ax)
        assert m.sum() > 5000
        var = np.var(diff[m]) / 2.0 - 1.0 / 12.0  # minus the quantisation noise
        expected = read**2 + level / gain_e
        assert var == pytest.approx(expected, rel=0.06), (level, var, expected)
        assert np.mean(imgs[0][m]) == pytest.approx(level, abs=0.1)


# --------------------------------------------------------------------------------------------
# Optics: defocus, vignetting, gradient
# --------------------------------------------------------------------------------------------


def edge_width_px(scene: np.ndarray, centre, half: int, lo: float, hi: float) -> float:
    """Effective width (px) of a dot's edge ramp: area of the 10–90 % transition / perimeter."""
    u, v = np.rint(centre).astype(int)
    w = scene[v - half : v + half + 1, u - half : u + half + 1]
    f = (w - lo) / (hi - lo)
    inside = np.sum(f < 0.5)
    r = math.sqrt(inside / math.pi)
    return float(np.sum((f > 0.1) & (f < 0.9)) / (2 * math.pi * r))


def test_defocus_blur_grows_with_distance_from_focus():
    cam = CAM2
    widths, predicted = [], []
    for dz in (0.0, 1.0, 2.0, 4.0):
        T = pose([0.0, 0.0, 80.0 + dz])
        scene = render_scene(cam, PLATE_B, T, IDEAL)
        centre = true_dot_centres(cam, PLATE_B, T)[24]
        widths.append(edge_width_px(scene, centre, 70, IDEAL.dark_level, IDEAL.light_level))
        s = float(blur_sigma_px(cam, IDEAL, 80.0 + dz))
        predicted.append(2.563 * math.sqrt(s * s + 1.0 / 12.0))  # 10–90 % width of a Gaussian edge
    assert all(b > a * 1.2 for a, b in itertools.pairwise(widths)), widths
    assert np.allclose(widths, predicted, rtol=0.15), (widths, predicted)
    # closer than focus blurs too
    T = pose([0.0, 0.0, 78.0])
    scene = render_scene(cam, PLATE_B, T, IDEAL)
    w_near = edge_width_px(scene, true_dot_centres(cam, PLATE_B, T)[24], 70, IDEAL.dark_level, IDEAL.light_level)
    assert w_near > widths[0] * 1.5


def test_spatially_varying_defocus_on_a_tilted_plate():
    """Tilted about the image x axis: dots nearer the focus plane are sharper."""
    cam = CAM2.scaled(2)
    T = pose([0.0, 0.0, 80.0], 20.0, 0.0, 0.0)
    scene = render_scene(cam, PLATE_B, T, IDEAL)
    centres = true_dot_centres(cam, PLATE_B, T)
    depth = (PLATE_B.dot_centres_mm() @ T[:3, :3].T + T[:3, 3])[:, 2]
    w = [edge_width_px(scene, centres[i], 30, IDEAL.dark_level, IDEAL.light_level) for i in (3, 24, 45)]
    d = np.abs(depth[[3, 24, 45]] - 80.0)
    assert d[1] < 0.01 and d[0] > 1.0 and d[2] > 1.0
    assert w[1] < 0.7 * w[0] and w[1] < 0.7 * w[2], w


def test_vignetting_darker_at_corners_and_gradient_direction():
    cam = CAM1.scaled(4)
    plate = DotPlate(7, 7, 5.0, 2.5, margin_mm=0.0)  # no margin: the plate fills the frame
    T = pose([2.5, 2.5, 280.0])  # the principal point sees bare plate between four dots
    cond = ImagingConditions.ideal(vignetting=0.3)
    img = render_plate_image(cam, plate, T, cond, seed=0, noiseless=True).astype(float)
    L = cond.light_level
    assert img[0, 0] == pytest.approx(0.7 * L, abs=1.0)
    assert img[-1, -1] == pytest.approx(0.7 * L, abs=1.0)
    assert img[0, cam.width_px // 2] > img[0, 0] + 10
    assert img[round(cam.cy_px), round(cam.cx_px)] == pytest.approx(L, abs=0.5)
    g = gain_map(cam, ImagingConditions.ideal(gradient=0.1, gradient_angle_deg=0.0))
    assert g[:, -1].mean() - g[:, 0].mean() == pytest.approx(0.1, abs=1e-3)  # +5 % right, −5 % left
    g = gain_map(cam, ImagingConditions.ideal(gradient=0.1, gradient_angle_deg=90.0))
    assert g[-1].mean() - g[0].mean() == pytest.approx(0.1, abs=1e-3)


def test_background_outside_plate_and_plate_edge_position():
    cam = CAM1.scaled(4)
    cond = IDEAL
    T = pose([0.0, 0.0, 280.0])
    scene = render_scene(cam, PLATE_A, T, cond)
    assert scene[5, 5] == pytest.approx(cond.background_level)
    # the right plate edge (X = +hx) crosses the row through the principal point at u_edge
    hx = PLATE_A.half_extent_mm[0]
    u_edge = project_points((T @ [hx, 0.0, 0.0, 1.0])[:3], cam)[0]
    row = scene[round(cam.cy_px)]
    j = np.arange(cam.width_px)
    seg = (j > u_edge - 8) & (j < u_edge + 8)
    f = (row[seg] - cond.background_level) / (cond.light_level - cond.background_level)
    u_est = j[seg][0] - 0.5 + f.sum()  # area under the falling edge = position of the 50 % point
    assert u_est == pytest.approx(u_edge, abs=0.02)


# --------------------------------------------------------------------------------------------
# Distortion: coarse-grid inversion and extra terms
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "extra", [None, ExtraDistortion(k4=0.3, s1=2e-3, s2=-1e-3, s3=-1.5e-3, s4=5e-4)], ids=["5-param", "extra"]
)
def test_coarse_grid_inversion_accuracy(extra):
    cam = CAM1
    grid = UndistortionGrid(cam, extra)
    rng = np.random.default_rng(1)
    ti = np.concatenate([[0, 0, grid.nty - 1, grid.nty - 1], rng.integers(0, grid.nty, 600)])
    tj = np.concatenate([[0, grid.ntx - 1, 0, grid.ntx - 1], rng.integers(0, grid.ntx, 600)])
    xy = grid.tiles(ti, tj)  # (N, T, T, 2)
    T = grid.tile_px
    v = ti[:, None, None] * T + np.arange(T)[None, :, None] + 0 * np.arange(T)[None, None, :]
    u = tj[:, None, None] * T + np.arange(T)[None, None, :] + 0 * np.arange(T)[None, :, None]
    exact = undistort_pixels(np.stack([u, v], -1).astype(float), cam, extra)
    err_px = np.abs(xy - exact).max(axis=-1) * cam.fx_px
    assert err_px.max() <= 0.002, err_px.max()
    # arbitrary positions use the same interpolation
    uv = rng.uniform(-0.5, [cam.width_px - 0.5, cam.height_px - 0.5], size=(2000, 2))
    err_px = np.abs(grid.at_pixels(uv) - undistort_pixels(uv, cam, extra)).max() * cam.fx_px
    assert err_px <= 0.002, err_px


def test_exact_inversion_round_trip():
    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.3, 0.3, size=(1000, 2))
    extra = ExtraDistortion(k4=0.3, s1=2e-3, s2=-1e-3, s3=-1.5e-3, s4=5e-4)
    for e in (None, extra):
        back = undistort_normalised(distort_normalised_ext(xy, DIST, e), DIST, e)
        assert np.abs(back - xy).max() < 1e-13
    assert np.array_equal(distort_normalised_ext(xy, DIST, None), distort_normalised(xy, DIST))


def test_extra_distortion_shifts_centres_as_documented():
    k4, s1, s2, s3, s4 = 5.0, 1e-2, -5e-3, -8e-3, 2e-3
    extra = ExtraDistortion(k4, s1, s2, s3, s4)
    cam = CAM1
    T = pose([35.0, 15.0, 280.0], 0.4, 0.3, 5.0)  # off-centre: r up to ~0.2
    assert plate_in_view(cam, PLATE_A, T, extra)
    base = true_dot_centres(cam, PLATE_A, T)
    shifted = true_dot_centres(cam, PLATE_A, T, extra)
    assert np.allclose(base, true_dot_centres(cam, PLATE_A, T, (0.0,) * 5))
    p = PLATE_A.dot_centres_mm() @ T[:3, :3].T + T[:3, 3]
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    r2 = x * x + y * y
    du = cam.fx_px * (k4 * r2**4 * x + s1 * r2 + s2 * r2**2)
    dv = cam.fy_px * (k4 * r2**4 * y + s3 * r2 + s4 * r2**2)
    assert np.allclose(shifted - base, np.stack([du, dv], 1), atol=1e-9)
    assert np.abs(shifted - base).max() > 0.5  # the effect is visible
    # the rendered dots follow the extra-distorted centres
    img = render_plate_image(cam, PLATE_A, T, IDEAL, seed=0, extra_distortion=extra, noiseless=True)
    c = centroids(img, shifted, window_half(cam, PLATE_A, 280.0), IDEAL.light_level)
    assert np.linalg.norm(c - shifted, axis=1).max() <= 0.02


def test_per_image_focal_drift_moves_the_dots():
    """Intrinsics may change per image (focal drift ~1e-4): the render follows exactly."""
    cam = CAM1
    drift = dataclasses.replace(cam, focal_length_mm=cam.focal_length_mm * (1 + 1e-4))
    c0 = true_dot_centres(cam, PLATE_A, POSE_A)
    c1 = true_dot_centres(drift, PLATE_A, POSE_A)
    assert np.abs(c1 - c0).max() > 0.03
    img = render_plate_image(drift, PLATE_A, POSE_A, IDEAL, seed=0, noiseless=True)
    c = centroids(img, c1, window_half(cam, PLATE_A, 280.0), IDEAL.light_level)
    assert np.linalg.norm(c - c1, axis=1).max() <= 0.02


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def test_plate_in_view():
    assert plate_in_view(CAM1, PLATE_A, POSE_A)
    assert plate_in_view(CAM2, PLATE_B, POSE_B)
    assert plate_in_view(CAM1.scaled(4), PLATE_A, POSE_A)
    # shift plate a so the right-most dot column sits across the image edge (u ≈ W)
    x_edge = (CAM1.width_px - CAM1.cx_px) / CAM1.fx_px * 280.0  # mm at the right image border
    T = pose([x_edge - 15.0, 0.0, 280.0])  # dots at X = +15 mm land on the border
    assert not plate_in_view(CAM1, PLATE_A, T)
    assert plate_in_view(CAM1, PLATE_A, pose([x_edge - 15.0 - 3.0, 0.0, 280.0]))
    assert not plate_in_view(CAM1, PLATE_A, pose([0.0, 0.0, -280.0]))  # behind the camera


def test_true_dot_centres_order_and_shape():
    c = true_dot_centres(CAM1, PLATE_A, POSE_A)
    assert c.shape == (49, 2)
    pts = PLATE_A.dot_centres_mm() @ POSE_A[:3, :3].T + POSE_A[:3, 3]
    assert np.allclose(c, project_points(pts, CAM1))


def test_conditions_are_frozen_and_levels_swap():
    c = ImagingConditions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.light_level = 1.0  # type: ignore[misc]
    assert c.plate_and_dot_levels(PLATE_A) == (c.light_level, c.dark_level)
    assert c.plate_and_dot_levels(dataclasses.replace(PLATE_A, dark_dots=False)) == (c.dark_level, c.light_level)


def test_back_facing_and_edge_on_plates_show_no_dots():
    cam = CAM1.scaled(4)
    back = pose([0.0, 0.0, 280.0], 180.0)  # printed face pointing away from the camera
    assert not plate_in_view(cam, PLATE_A, back)
    scene = render_scene(cam, PLATE_A, back, IDEAL)
    inside = scene[round(cam.cy_px) - 20 : round(cam.cy_px) + 20, round(cam.cx_px) - 20 : round(cam.cx_px) + 20]
    assert np.all(inside == IDEAL.light_level)  # blank back of the plate
    edge_on = pose([0.0, 0.0, 280.0], 90.0)
    assert not plate_in_view(cam, PLATE_A, edge_on)
    img = render_plate_image(cam, PLATE_A, edge_on, IDEAL, seed=0)
    assert np.all(img == round(IDEAL.background_level))


def test_edge_pixels_are_the_pixel_integral_of_the_blurred_edge():
    """The closed form against brute-force quadrature over the pixel square (200×200 points)
    of Φ((t + n·δ)/σ): any normal direction (axis-aligned included), σ = 0 (area coverage)."""
    from scipy.special import ndtr

    from tasks.simulation.render import _blurred_edge_coverage

    rng = np.random.default_rng(3)
    g = (np.arange(200) + 0.5) / 200 - 0.5
    du, dv = np.meshgrid(g, g)
    for angle in (0.0, 1e-5, 0.3, math.pi / 4, 1.2, math.pi / 2):
        nu, nv = math.cos(angle), math.sin(angle)
        for sigma in (0.0, 0.3, 0.81, 1.5):
            t = rng.uniform(-2.5, 2.5, 12)
            got = _blurred_edge_coverage(t, np.full(12, nu), np.full(12, nv), sigma)
            dist = t[:, None, None] + nu * du + nv * dv
            want = (dist > 0).mean(axis=(1, 2)) if sigma == 0 else ndtr(dist / sigma).mean(axis=(1, 2))
            tol = 2e-4 if sigma else 6e-3  # a step sampled at 200 points is good to 1/200
            assert np.abs(got - want).max() < tol, (angle, sigma)


def test_in_focus_blur_is_aberration_and_the_aperture_diffraction():
    """0.42 λ N_w at the working f-number: 0.81 px for f/8 focused at 300 mm (2.4 µm pixels),
    0.96 px at 80 mm; added in quadrature to the aberration σ; a quarter on the binned sensor."""
    from tasks.simulation.render import diffraction_sigma_px

    assert diffraction_sigma_px(CAM1, 0.55) == pytest.approx(0.42 * 0.55e-3 * 8.0 * 280 / 264 / 0.0024)
    cam300 = dataclasses.replace(CAM1, focus_distance_mm=300.0)
    assert diffraction_sigma_px(cam300, 0.55) == pytest.approx(0.813, abs=0.001)
    assert diffraction_sigma_px(CAM2, 0.55) == pytest.approx(0.9625, abs=0.001)
    assert diffraction_sigma_px(CAM2.scaled(4), 0.55) == pytest.approx(0.9625 / 4, abs=0.001)
    s = float(blur_sigma_px(CAM2, IDEAL, 80.0))
    assert s == pytest.approx(math.hypot(IDEAL.aberration_sigma_px, 0.9625), abs=0.001)
    no_diffraction = dataclasses.replace(IDEAL, diffraction=False)
    assert float(blur_sigma_px(CAM2, no_diffraction, 80.0)) == pytest.approx(IDEAL.aberration_sigma_px)
