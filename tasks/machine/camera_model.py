"""Pinhole camera with Brown–Conrady distortion (OpenCV's 5-parameter model).

Frames: the camera frame has +Z along the optical axis, +X to the right of the image
(increasing u) and +Y down (increasing v), as in OpenCV. Points are in mm; pixel coordinates
have their origin at the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera.

    width_px, height_px: sensor size in pixels.
    pixel_size_mm: pixel pitch (mm).
    focal_length_mm: lens focal length (mm); fx = fy = focal_length_mm / pixel_size_mm (px).
    cx_px, cy_px: principal point (px).
    distortion: (k1, k2, p1, p2, k3) in OpenCV order, dimensionless, on normalised coordinates.
    focus_distance_mm: object distance that is in perfect focus (mm, along +Z).
    f_number: aperture; sets how fast defocus blur grows away from focus.
    """

    width_px: int
    height_px: int
    pixel_size_mm: float
    focal_length_mm: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    focus_distance_mm: float = 100.0
    f_number: float = 8.0
    name: str = field(default="camera", compare=False)

    @property
    def fx_px(self) -> float:
        return self.focal_length_mm / self.pixel_size_mm

    @property
    def fy_px(self) -> float:
        return self.focal_length_mm / self.pixel_size_mm

    @property
    def matrix(self) -> np.ndarray:
        """3×3 intrinsic matrix K (px)."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    def scaled(self, factor: int) -> CameraModel:
        """The same optics on a sensor binned by ``factor`` (reduced-size images for fast tests).

        Pixel pitch grows by ``factor``; the field of view, the lens and the distortion
        (on normalised coordinates) are unchanged.
        """
        if factor == 1:
            return self
        return replace(
            self,
            width_px=self.width_px // factor,
            height_px=self.height_px // factor,
            pixel_size_mm=self.pixel_size_mm * factor,
            cx_px=(self.cx_px + 0.5) / factor - 0.5,
            cy_px=(self.cy_px + 0.5) / factor - 0.5,
        )

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "width_px": self.width_px,
            "height_px": self.height_px,
            "pixel_size_mm": self.pixel_size_mm,
            "focal_length_mm": self.focal_length_mm,
            "cx_px": self.cx_px,
            "cy_px": self.cy_px,
            "distortion": list(self.distortion),
            "focus_distance_mm": self.focus_distance_mm,
            "f_number": self.f_number,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        d = dict(d)
        d["distortion"] = tuple(float(x) for x in d.get("distortion", (0, 0, 0, 0, 0)))
        return cls(**d)


def distort_normalised(xy: np.ndarray, distortion) -> np.ndarray:
    """Apply Brown–Conrady distortion to normalised image coordinates.

    xy: (..., 2) undistorted normalised coordinates (X/Z, Y/Z). Returns (..., 2) distorted ones.
    """
    k1, k2, p1, p2, k3 = distortion
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def project_points(points_cam_mm: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Project points given in the camera frame (mm) to distorted pixel coordinates.

    points_cam_mm: (..., 3), Z > 0. Returns (..., 2) pixel coordinates (u, v).
    """
    p = np.asarray(points_cam_mm, dtype=float)
    xy = p[..., :2] / p[..., 2:3]
    xyd = distort_normalised(xy, camera.distortion)
    u = camera.fx_px * xyd[..., 0] + camera.cx_px
    v = camera.fy_px * xyd[..., 1] + camera.cy_px
    return np.stack([u, v], axis=-1)
