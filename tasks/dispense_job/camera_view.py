"""The tray as camera 1 of the virtual machine sees it, and the marks of the paper's hand–eye calibration.

The tray lies on the C table in plate a's place: its frame is the workpiece frame, its surface at
z = ``surface_z_mm``. The planar image of tasks.dispense_job.boards (tray frame, ``mm_per_px``) is the
tray's printed texture; camera 1, at an imaging command on the true machine (true error model, the
camera's true intrinsics with their distortion), sees it through :func:`camera_image`: every sensor
pixel's ray meets the surface, and the texture is sampled there (bilinear).
"""

from __future__ import annotations

import cv2
import numpy as np

from tasks.core import se3
from tasks.dispense_job.boards import TRAY_RGB, TraySpec, tray_to_pixels
from tasks.machine.camera_model import CameraModel, project_points
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward

CAMERA = "camera1"
MAP_STEP_PX = 16  # the pixel → surface map is computed on this grid and interpolated (distortion is smooth)


def camera_pose(machine: Machine, model: ErrorModel | None, imaging: np.ndarray) -> np.ndarray:
    """(4, 4) T_cam_wp: workpiece-frame points (mm) into camera 1's frame at the imaging command (5,)."""
    return forward(machine, np.asarray(imaging, float).reshape(1, 5), model).relative(machine.workpiece, CAMERA)[0]


def project_to_camera(machine: Machine, model: ErrorModel | None, camera: CameraModel, imaging: np.ndarray,
                      points_mm: np.ndarray, surface_z_mm: float) -> np.ndarray:
    """(N, 2) sensor pixels where camera 1 sees workpiece points (N, 2) mm on the surface."""
    T = camera_pose(machine, model, imaging)
    pts = np.column_stack([np.asarray(points_mm, float).reshape(-1, 2), np.full(len(points_mm), surface_z_mm)])
    return project_points(pts @ T[:3, :3].T + T[:3, 3], camera)


def camera_image(texture: np.ndarray, spec: TraySpec, machine: Machine, model: ErrorModel | None,
                 camera: CameraModel, imaging: np.ndarray, surface_z_mm: float) -> np.ndarray:
    """Camera 1's image (height_px, width_px, 3) uint8 of the tray texture (planar image of ``spec``)
    at the imaging command (5,) on the machine ``model`` describes, through ``camera`` (true intrinsics)."""
    T = se3.inverse(camera_pose(machine, model, imaging))  # camera in workpiece
    us = np.arange(0, camera.width_px + MAP_STEP_PX, MAP_STEP_PX, dtype=np.float64)
    vs = np.arange(0, camera.height_px + MAP_STEP_PX, MAP_STEP_PX, dtype=np.float64)
    uu, vv = np.meshgrid(us, vs)
    norm = cv2.undistortPoints(
        np.column_stack([uu.ravel(), vv.ravel()]).reshape(-1, 1, 2), camera.matrix, camera.dist_coeffs,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    rays = np.column_stack([norm, np.ones(len(norm))]) @ T[:3, :3].T
    s = (surface_z_mm - T[2, 3]) / rays[:, 2]
    hit = T[:3, 3][:2] + s[:, None] * rays[:, :2]
    tex = tray_to_pixels(spec, hit).reshape(len(vs), len(us), 2).astype(np.float32)
    # grid point (i, j) sits at sensor pixel (j·step, i·step): sample the coarse map there, bilinear
    jj, ii = np.meshgrid(np.arange(camera.width_px, dtype=np.float32) / MAP_STEP_PX,
                         np.arange(camera.height_px, dtype=np.float32) / MAP_STEP_PX)
    maps = cv2.remap(tex, jj, ii, cv2.INTER_LINEAR)
    # beyond the texture the tray's own black carries on
    return cv2.remap(texture, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=TRAY_RGB)


def hand_eye_marks(spec: TraySpec, rows: int = 3, cols: int = 3) -> np.ndarray:
    """(rows·cols, 2) workpiece points (mm) of the hand–eye calibration's marks: a grid over the tray's
    pockets (the paper's Table 2 uses five)."""
    w, h = spec.size_mm
    xs = np.linspace(-0.4 * w, 0.4 * w, cols)
    ys = np.linspace(-0.4 * h, 0.4 * h, rows)
    return np.array([[x, y] for y in ys for x in xs])

