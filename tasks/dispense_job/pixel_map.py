"""Pixels to machine commands: the paper's planar map (§4.2, Table 2) and the calibrated one.

* **planar** (the paper's hand–eye calibration): an affine map from image pixels (u, v) to the
  machine's X/Y commands, fitted by least squares to pairs of a mark's pixel and the command at which
  the needle stands over it (Table 2 gives five such pairs). Z, A and C are fixed. It is exact for a
  distortion-free camera looking straight at a plane over a machine without errors; what the camera's
  distortion and the machine's errors leave is its residual.
* **calibrated**: each pixel is undistorted with camera 1's calibrated intrinsics and its ray met with
  the tray's surface at the camera pose that the identified machine model gives for the imaging
  command (the workpiece frame); the needle is then asked to stand ``standoff_mm`` above that point with
  the tool vertical (nominal inverse kinematics gives the desired tip pose), and the command is
  compensated by inverse kinematics of the identified model (tasks.analysis.compensation), so that the glue
  lands where the image says. Without a model (``model=None``) the nominal machine is used throughout:
  the uncompensated commands.

Frames: image pixels (u right, v down); workpiece frame (mm; the tray's surface at z =
``surface_z_mm``); commands X, Y, Z (mm), A, C (deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.analysis.compensation import compensate
from tasks.dispensing.measure import pixels_to_surface
from tasks.dispensing.tip import landing_points
from tasks.dispensing.workpiece import Workpiece, dispensing_commands
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel

# the paper's Table 2: pixel coordinates (u, v) and the needle's dispensing position (X, Y) in mm
PAPER_TABLE2_PX = np.array([[706.8, 433.9], [1874.5, 548.2], [1095.4, 1120.1], [2098.5, 2056.5], [526.3, 1599.5]])
PAPER_TABLE2_MM = np.array([[31.0, 19.0], [82.0, 24.0], [48.0, 49.0], [92.0, 90.0], [23.0, 70.0]])


@dataclass(frozen=True)
class PlanarMap:
    """(X, Y) = M · (u, v, 1): ``matrix`` (2, 3) (mm per px, mm), the rms of its fit residuals (mm)
    over ``pairs`` pairs."""

    matrix: np.ndarray
    residual_rms_mm: float
    pairs: int

    def apply(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) machine X/Y (mm) of pixels (N, 2)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return np.column_stack([uv, np.ones(len(uv))]) @ self.matrix.T

    def angle_deg(self, uv: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
        """(N,) directions (deg, counter-clockwise in X/Y, in [0, 180)) of image directions ``angle_deg``
        (counter-clockwise with v up) at pixels ``uv`` (the affine map turns and shears them)."""
        a = np.deg2rad(np.asarray(angle_deg, dtype=float))
        d = np.column_stack([np.cos(a), -np.sin(a)]) @ self.matrix[:, :2].T
        return np.rad2deg(np.arctan2(d[:, 1], d[:, 0])) % 180.0


def fit_planar_map(pixels: np.ndarray, machine_mm: np.ndarray) -> PlanarMap:
    """Least-squares affine map from pixels (N, 2) to machine X/Y (N, 2) mm; ValueError with fewer than
    3 pairs or pairs on one line."""
    uv = np.asarray(pixels, dtype=float).reshape(-1, 2)
    xy = np.asarray(machine_mm, dtype=float).reshape(-1, 2)
    if len(uv) < 3 or len(uv) != len(xy):
        raise ValueError(f"the planar map needs at least 3 pixel/machine pairs, got {len(uv)} and {len(xy)}")
    A = np.column_stack([uv, np.ones(len(uv))])
    if np.linalg.matrix_rank(A) < 3:
        raise ValueError("the planar map's pairs lie on one line: they do not fix the map")
    M, *_ = np.linalg.lstsq(A, xy, rcond=None)
    res = A @ M - xy
    return PlanarMap(M.T, float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))), len(uv))


def pixels_to_workpiece(machine: Machine, model: ErrorModel | None, camera: CameraModel, imaging: np.ndarray,
                        uv: np.ndarray, surface_z_mm: float) -> np.ndarray:
    """(N, 2) workpiece-frame points (mm) on the surface z = ``surface_z_mm`` seen at sensor pixels
    ``uv`` (N, 2) by camera 1 (``camera``: its calibrated intrinsics) at one imaging command (5,),
    the camera's pose from ``model`` (None: nominal)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    cmd = np.repeat(np.asarray(imaging, dtype=float).reshape(1, 5), len(uv), axis=0)
    return pixels_to_surface(machine, model, camera, cmd, uv, surface_z_mm)


def directions_to_workpiece(machine: Machine, model: ErrorModel | None, camera: CameraModel, imaging: np.ndarray,
                            uv: np.ndarray, angle_deg: np.ndarray, surface_z_mm: float,
                            step_px: float = 10.0) -> np.ndarray:
    """(N,) directions (deg, counter-clockwise about the workpiece z, in [0, 180)) of image directions
    ``angle_deg`` (counter-clockwise with v up) at pixels ``uv`` (N, 2): the map of a ``step_px`` step."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    a = np.deg2rad(np.asarray(angle_deg, dtype=float))
    step = step_px * np.column_stack([np.cos(a), -np.sin(a)])
    p0 = pixels_to_workpiece(machine, model, camera, imaging, uv - step, surface_z_mm)
    p1 = pixels_to_workpiece(machine, model, camera, imaging, uv + step, surface_z_mm)
    d = p1 - p0
    return np.rad2deg(np.arctan2(d[:, 1], d[:, 0])) % 180.0


def commands_at(machine: Machine, model: ErrorModel | None, points_mm: np.ndarray, surface_z_mm: float,
                standoff_mm: float, orientation: str = "full") -> np.ndarray:
    """(N, 5) commands (mm, deg) holding the needle's opening ``standoff_mm`` above workpiece points
    (N, 2) mm on the surface z = ``surface_z_mm``, tool vertical: the nominal machine's commands with
    A = C = 0 (:func:`jog_over` on the nominal machine), then compensated by inverse kinematics of
    ``model`` (None: the nominal commands)."""
    nominal = jog_over(machine, None, points_mm, surface_z_mm, standoff_mm)
    if model is None:
        return nominal
    return compensate(machine, model, nominal, orientation).commands


def jog_over(machine: Machine, model: ErrorModel | None, points_mm: np.ndarray, surface_z_mm: float,
             standoff_mm: float, iterations: int = 4) -> np.ndarray:
    """(N, 5) commands with A = C = 0 and Z at the nominal dispensing height (the needle's opening
    ``standoff_mm`` above the surface over the workpiece origin), X and Y moved until the needle of the
    machine ``model`` describes stands over each workpiece point (N, 2) mm: the paper's hand–eye
    calibration, where the operator jogs X and Y only (fixed-point steps on the landing error)."""
    target = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    piece = Workpiece(standoff_mm=standoff_mm)
    z = dispensing_commands(machine, piece, np.zeros((1, 2)), np.array([surface_z_mm]), np.zeros((1, 5)))[0, 2]
    cmd = np.zeros((len(target), 5))
    cmd[:, 2] = z
    for _ in range(iterations):
        cmd[:, :2] += target - landing_points(machine, model, cmd)
    return cmd


def check_travel(machine: Machine, commands: np.ndarray, labels) -> list[str]:
    """One message per command (N, 5) outside an axis' stroke, naming its label and the axis."""
    strokes = machine.strokes_command()
    out = []
    for cmd, label in zip(np.asarray(commands, dtype=float).reshape(-1, 5), labels, strict=True):
        for i, axis in enumerate(("X", "Y", "Z", "A", "C")):
            lo, hi = strokes[i]
            if not lo <= cmd[i] <= hi:
                out.append(f"{label}: {axis} = {cmd[i]:.1f} outside the travel {lo:g}…{hi:g}")
    return out
