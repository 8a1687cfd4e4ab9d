"""Quick synthetic dot-plate images with exact ground truth (px), for tests and benchmarks.

Not the project's realistic renderer (``tasks.simulation.render``); this one maps the plate to the image by
a plain homography (no lens distortion), draws each dot with a one-pixel anti-aliasing ramp on
the exact signed distance to the projected circle, then adds defocus blur, an illumination
gradient with vignetting, Gaussian noise, 8-bit quantisation and optional clutter around the
plate. Ground truth is the projection of each dot centre (``H @ [x, y, 1]``), which differs from
the centre of the projected ellipse on a tilted plate (the perspective bias).

Frames: plate frame as in :mod:`tasks.machine.plate` (mm); image pixels (u right, v down), origin at
the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tasks.core import se3
from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate


def facing_pose(
    distance_mm: float,
    rotation_deg: float = 0.0,
    tilt_x_deg: float = 0.0,
    tilt_y_deg: float = 0.0,
    offset_mm: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Pose (R_cam_plate (3,3), t_cam_plate (3,) mm) of a plate facing the camera.

    At rotation 0 and no tilt the plate's +X (column) axis points along image +u and its +Y
    (row) axis along image −v, its +Z towards the camera. ``rotation_deg`` turns the plate about
    its own +Z, which appears counter-clockwise on screen; tilts turn it about the camera X / Y
    axes through the plate centre. ``offset_mm`` shifts the plate centre in camera X / Y.
    """
    r0 = np.diag([1.0, -1.0, -1.0])
    r = (se3.rot_x(np.radians(tilt_x_deg)) @ se3.rot_y(np.radians(tilt_y_deg)) @ r0
         @ se3.rot_z(np.radians(rotation_deg)))
    t = np.array([offset_mm[0], offset_mm[1], distance_mm], dtype=float)
    return r, t


def plate_homography(camera: CameraModel, r_cam_plate: np.ndarray, t_cam_plate: np.ndarray) -> np.ndarray:
    """(3,3) homography from plate (x, y) mm to undistorted image px: ``K [r1 r2 t]``."""
    m = np.column_stack([r_cam_plate[:, 0], r_cam_plate[:, 1], t_cam_plate])
    h = camera.matrix @ m
    return h / h[2, 2]


def apply_homography(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Map (..., 2) points through the (3,3) homography ``h``."""
    xy = np.asarray(xy, dtype=float)
    p = xy @ h[:, :2].T + h[:, 2]
    return p[..., :2] / p[..., 2:3]


@dataclass
class SyntheticConditions:
    """Imaging conditions (levels in 8-bit grey values, lengths in px of the output image)."""

    blur_sigma_px: float = 1.2
    noise_sigma: float = 2.0
    plate_level: float = 215.0
    dot_level: float = 40.0
    background_level: float = 70.0
    gradient: float = 0.25  # peak-to-peak relative illumination change across the image
    vignetting: float = 0.15  # relative fall-off at the image corners
    gradient_angle_deg: float = 30.0
    clutter: int = 0  # number of clutter items (lines, text, blobs, boxes) around the plate


def _dot_coverage(
    h: np.ndarray, h_inv: np.ndarray, centre_mm: np.ndarray, radius_mm: float, shape: tuple[int, int]
) -> tuple[tuple[slice, slice], np.ndarray] | None:
    """Anti-aliased coverage of one dot in its bounding box: (slices, coverage in [0, 1])."""
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = centre_mm + radius_mm * np.stack([np.cos(t), np.sin(t)], axis=1)
    uv = apply_homography(h, ring)
    u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 3
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 4
    u0, v0 = max(u0, 0), max(v0, 0)
    u1, v1 = min(u1, shape[1]), min(v1, shape[0])
    if u1 <= u0 or v1 <= v0:
        return None
    uu, vv = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
    # plate coordinates of each pixel centre, and the Jacobian d(plate)/d(pixel)
    w = h_inv[2, 0] * uu + h_inv[2, 1] * vv + h_inv[2, 2]
    x = (h_inv[0, 0] * uu + h_inv[0, 1] * vv + h_inv[0, 2]) / w
    y = (h_inv[1, 0] * uu + h_inv[1, 1] * vv + h_inv[1, 2]) / w
    dxu = (h_inv[0, 0] - x * h_inv[2, 0]) / w
    dxv = (h_inv[0, 1] - x * h_inv[2, 1]) / w
    dyu = (h_inv[1, 0] - y * h_inv[2, 0]) / w
    dyv = (h_inv[1, 1] - y * h_inv[2, 1]) / w
    ex, ey = x - centre_mm[0], y - centre_mm[1]
    rho = np.hypot(ex, ey)
    f = rho - radius_mm  # signed distance in mm on the plate
    nx, ny = ex / np.maximum(rho, 1e-12), ey / np.maximum(rho, 1e-12)
    gu = nx * dxu + ny * dyu  # d f / d u
    gv = nx * dxv + ny * dyv
    d_px = f / np.maximum(np.hypot(gu, gv), 1e-12)
    cov = np.clip(0.5 - d_px, 0.0, 1.0)
    return (slice(v0, v1), slice(u0, u1)), cov


def render_synthetic(
    plate: DotPlate,
    h: np.ndarray,
    shape: tuple[int, int],
    conditions: SyntheticConditions | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Render a plate seen through homography ``h`` (plate mm → px).

    Returns (image (H, W) uint8, true centres (rows*cols, 2) px, row-major as
    ``plate.dot_centres_mm``). Dots cut by the image border are drawn as far as visible.
    """
    cond = conditions or SyntheticConditions()
    rng = np.random.default_rng(seed)
    hgt, wid = shape
    h = np.asarray(h, dtype=float)
    h_inv = np.linalg.inv(h)
    canvas = np.full(shape, round(cond.background_level), dtype=np.uint8)
    if cond.clutter:
        _draw_clutter(canvas, cond, rng)
    img = canvas.astype(np.float32)
    # plate body (light for dark dots, dark for light dots); no margin: the plate fills the image
    body = cond.plate_level if plate.dark_dots else cond.dot_level
    dot_val = cond.dot_level if plate.dark_dots else cond.plate_level
    hx, hy = plate.half_extent_mm
    if plate.margin_mm > 0:
        corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]], dtype=float)
        poly = np.round(apply_homography(h, corners) * 16).astype(np.int32)
        mask = np.zeros(shape, np.uint8)
        cv2.fillPoly(mask, [poly], 255, lineType=cv2.LINE_AA, shift=4)
        a = mask.astype(np.float32) / 255.0
        img = img * (1 - a) + body * a
    else:
        img[:] = body
    centres_mm = plate.dot_centres_mm()[:, :2]
    r_mm = plate.dot_diameter_mm / 2.0
    for c in centres_mm:
        res = _dot_coverage(h, h_inv, c, r_mm, shape)
        if res is None:
            continue
        sl, cov = res
        img[sl] = img[sl] * (1 - cov) + dot_val * cov
    # optics: defocus blur, illumination gradient and vignetting
    if cond.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cond.blur_sigma_px)
    vv, uu = np.mgrid[0:hgt, 0:wid].astype(np.float32)
    un, vn = (uu - wid / 2) / (wid / 2), (vv - hgt / 2) / (hgt / 2)
    ang = np.radians(cond.gradient_angle_deg)
    illum = 1.0 + 0.5 * cond.gradient * (np.cos(ang) * un + np.sin(ang) * vn)
    illum *= 1.0 - cond.vignetting * (un**2 + vn**2) / 2.0
    img = img * illum
    if cond.noise_sigma > 0:
        img = img + rng.normal(0.0, cond.noise_sigma, size=shape).astype(np.float32)
    out = np.clip(np.round(img), 0, 255).astype(np.uint8)
    truth = apply_homography(h, centres_mm)
    return out, truth


def _draw_clutter(img: np.ndarray, cond: SyntheticConditions, rng: np.random.Generator) -> None:
    """Lines, text, boxes and stray blobs (some of dot-like size) on the background, in place."""
    hgt, wid = img.shape
    scale = max(hgt, wid) / 768.0
    for _ in range(cond.clutter):
        kind = rng.integers(0, 4)
        level = round(float(rng.choice([cond.dot_level, cond.plate_level, 150.0])))
        p0 = (int(rng.integers(0, wid)), int(rng.integers(0, hgt)))
        if kind == 0:
            p1 = (int(rng.integers(0, wid)), int(rng.integers(0, hgt)))
            cv2.line(img, p0, p1, level, max(1, int(rng.integers(1, 4) * scale)), cv2.LINE_AA)
        elif kind == 1:
            text = "".join(rng.choice(list("ABCDEOQ0o8%@#"), size=int(rng.integers(2, 7))))
            cv2.putText(img, text, p0, cv2.FONT_HERSHEY_SIMPLEX, float(rng.uniform(0.5, 2.0) * scale),
                        level, max(1, int(2 * scale)), cv2.LINE_AA)
        elif kind == 2:
            rad = int(rng.uniform(3, 30) * scale)
            cv2.circle(img, p0, rad, level, -1, cv2.LINE_AA)
        else:
            p1 = (p0[0] + int(rng.integers(10, 80) * scale), p0[1] + int(rng.integers(10, 80) * scale))
            cv2.rectangle(img, p0, p1, level, max(1, int(2 * scale)), cv2.LINE_AA)


def design_camera(factor: int = 1) -> CameraModel:
    """The seed's camera (3072×2048 px, 2.4 µm pixels, 16 mm lens), optionally binned by ``factor``."""
    cam = CameraModel(3072, 2048, 0.0024, 16.0, 1535.5, 1023.5, name="synthetic")
    return cam.scaled(factor)
