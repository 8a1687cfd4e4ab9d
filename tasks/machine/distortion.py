"""Lens distortion beyond OpenCV's 5-parameter model, and its exact and gridded inverses.

The renderer distorts with it (:mod:`tasks.simulation.render`); the vision side undistorts measured
pixels with the same model (:mod:`tasks.vision.camera_calibration`), so it belongs to the camera, not
to either side.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from tasks.machine.camera_model import CameraModel, distort_normalised, project_points

TILE_PX = 16
# --------------------------------------------------------------------------------------------
# Distortion beyond the 5-parameter model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExtraDistortion:
    """Distortion terms the 5-parameter Brown–Conrady model cannot absorb (dimensionless).

    On undistorted normalised coordinates (x, y), r² = x² + y², the full model is::

        radial = 1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸
        x_d = x·radial + 2 p1 x y + p2 (r² + 2x²) + s1 r² + s2 r⁴
        y_d = y·radial + p1 (r² + 2y²) + 2 p2 x y + s3 r² + s4 r⁴

    k1, k2, p1, p2, k3 come from ``CameraModel.distortion``.  s1..s4 are OpenCV's thin-prism
    coefficients (same formula as its 12/14-parameter model).  **k4 here multiplies r⁸ in the
    numerator**; it is *not* OpenCV's k4 (which sits in the rational model's denominator).
    """

    k4: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0
    s4: float = 0.0

    @property
    def is_zero(self) -> bool:
        return self.k4 == 0.0 and self.s1 == 0.0 and self.s2 == 0.0 and self.s3 == 0.0 and self.s4 == 0.0


def _as_extra(extra: ExtraDistortion | Sequence[float] | None) -> ExtraDistortion | None:
    if extra is None:
        return None
    if not isinstance(extra, ExtraDistortion):
        extra = ExtraDistortion(*(float(e) for e in extra))
    return None if extra.is_zero else extra


def distort_normalised_ext(
    xy: np.ndarray, distortion: Sequence[float], extra: ExtraDistortion | Sequence[float] | None = None
) -> np.ndarray:
    """Apply the 5-parameter model plus :class:`ExtraDistortion` to normalised coordinates.

    xy: (..., 2) undistorted normalised coordinates (X/Z, Y/Z).  Returns (..., 2) distorted.
    With ``extra=None`` this is exactly :func:`tasks.machine.camera_model.distort_normalised`.
    """
    extra = _as_extra(extra)
    xy = np.asarray(xy, dtype=float)
    if extra is None:
        return distort_normalised(xy, distortion)
    k1, k2, p1, p2, k3 = distortion
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * extra.k4)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + r2 * (extra.s1 + r2 * extra.s2)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + r2 * (extra.s3 + r2 * extra.s4)
    return np.stack([xd, yd], axis=-1)


def _distort_with_jacobian(x, y, distortion, extra: ExtraDistortion | None):
    """Distorted (xd, yd) and the 2×2 Jacobian entries ∂(xd, yd)/∂(x, y), elementwise."""
    k1, k2, p1, p2, k3 = distortion
    k4, s1, s2, s3, s4 = (0.0,) * 5 if extra is None else (extra.k4, extra.s1, extra.s2, extra.s3, extra.s4)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    dradial = k1 + r2 * (2.0 * k2 + r2 * (3.0 * k3 + r2 * 4.0 * k4))  # d(radial)/d(r²)
    px_ = s1 + r2 * s2
    py_ = s3 + r2 * s4
    dpx = s1 + 2.0 * r2 * s2  # d(r² px_)/d(r²)
    dpy = s3 + 2.0 * r2 * s4
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + r2 * px_
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + r2 * py_
    dxx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * x * dpx
    dxy = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * y * dpx
    dyx = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * x * dpy
    dyy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * y * dpy
    return xd, yd, dxx, dxy, dyx, dyy


def undistort_normalised(
    xy_d: np.ndarray,
    distortion: Sequence[float],
    extra: ExtraDistortion | Sequence[float] | None = None,
    *,
    iterations: int = 30,
    tol: float = 1e-15,
) -> np.ndarray:
    """Exact inverse of :func:`distort_normalised_ext` by vectorised Newton iterations.

    xy_d: (..., 2) distorted normalised coordinates.  Returns (..., 2) undistorted ones,
    converged to |residual| < ~1e-14 (≈1e-10 px) for the mild distortions of real lenses.
    """
    extra = _as_extra(extra)
    xy_d = np.asarray(xy_d, dtype=float)
    xd_t, yd_t = xy_d[..., 0], xy_d[..., 1]
    x, y = xd_t.copy(), yd_t.copy()
    for _ in range(iterations):
        xd, yd, a, b, c, d = _distort_with_jacobian(x, y, distortion, extra)
        ex, ey = xd - xd_t, yd - yd_t
        det = a * d - b * c
        dx = (d * ex - b * ey) / det
        dy = (a * ey - c * ex) / det
        x -= dx
        y -= dy
        if float(np.max(np.abs(dx), initial=0.0) + np.max(np.abs(dy), initial=0.0)) < tol:
            break
    return np.stack([x, y], axis=-1)


def project_points_ext(
    points_cam_mm: np.ndarray, camera: CameraModel, extra: ExtraDistortion | Sequence[float] | None = None
) -> np.ndarray:
    """Project camera-frame points (mm, Z > 0) to pixels with the 5-parameter model + extra terms.

    Identical to :func:`tasks.machine.camera_model.project_points` when ``extra`` is None or zero.
    """
    extra = _as_extra(extra)
    if extra is None:
        return project_points(points_cam_mm, camera)
    p = np.asarray(points_cam_mm, dtype=float)
    xyd = distort_normalised_ext(p[..., :2] / p[..., 2:3], camera.distortion, extra)
    return np.stack([camera.fx_px * xyd[..., 0] + camera.cx_px, camera.fy_px * xyd[..., 1] + camera.cy_px], -1)


def undistort_pixels(
    uv: np.ndarray, camera: CameraModel, extra: ExtraDistortion | Sequence[float] | None = None
) -> np.ndarray:
    """Exact: pixel coordinates (..., 2) → undistorted normalised coordinates (..., 2)."""
    uv = np.asarray(uv, dtype=float)
    xy_d = np.stack([(uv[..., 0] - camera.cx_px) / camera.fx_px, (uv[..., 1] - camera.cy_px) / camera.fy_px], -1)
    return undistort_normalised(xy_d, camera.distortion, extra)


# --------------------------------------------------------------------------------------------
# Coarse undistortion grid
# --------------------------------------------------------------------------------------------


def _catmull_rom_weights(t: np.ndarray) -> np.ndarray:
    """(len(t), 4) Catmull–Rom weights of nodes −1, 0, 1, 2 at fractional positions t ∈ [0, 1]."""
    t = np.asarray(t, dtype=float)
    t2, t3 = t * t, t * t * t
    return 0.5 * np.stack([-t3 + 2 * t2 - t, 3 * t3 - 5 * t2 + 2, -3 * t3 + 4 * t2 + t, t3 - t2], axis=-1)


class UndistortionGrid:
    """Pixel → undistorted normalised coordinates, exact on a coarse grid, interpolated between.

    Nodes sit on tile corners, u = j·tile_px − ½ for j = −1 … ceil(W/tile_px) + 1 (likewise v),
    i.e. one extra node ring for the 4×4 Catmull–Rom stencil.  Node values are exact Newton
    inversions of the full model (5 parameters + :class:`ExtraDistortion`).

    Build cost is ~25k Newton solves at full size; instances are cached by exact parameters
    (:func:`undistortion_grid`), so a 'focal_drift' image with new intrinsics gets its own grid.
    """

    def __init__(
        self,
        camera: CameraModel,
        extra: ExtraDistortion | Sequence[float] | None = None,
        tile_px: int = TILE_PX,
    ):
        self.camera = camera
        self.extra = _as_extra(extra)
        self.tile_px = int(tile_px)
        self.ntx = -(-camera.width_px // self.tile_px)
        self.nty = -(-camera.height_px // self.tile_px)
        ju = np.arange(-1, self.ntx + 2) * self.tile_px - 0.5
        iv = np.arange(-1, self.nty + 2) * self.tile_px - 0.5
        uu, vv = np.meshgrid(ju, iv)
        nodes = undistort_pixels(np.stack([uu, vv], -1), camera, self.extra)
        nodes.setflags(write=False)
        self.nodes = nodes  # (nty + 3, ntx + 3, 2)
        t = (np.arange(self.tile_px) + 0.5) / self.tile_px
        self._w = _catmull_rom_weights(t)  # (T, 4)

    def corner_nodes(self) -> np.ndarray:
        """(nty + 1, ntx + 1, 2) node values at the tile corners (no padding ring)."""
        return self.nodes[1:-1, 1:-1]

    def tiles(self, ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
        """Normalised undistorted coordinates of all pixels of tiles (ti, tj): (N, T, T, 2);
        element [n, a, b] is pixel (u, v) = (tj[n]·T + b, ti[n]·T + a)."""
        ti = np.asarray(ti, dtype=np.intp).ravel()
        tj = np.asarray(tj, dtype=np.intp).ravel()
        k = np.arange(4)
        g = self.nodes[ti[:, None, None] + k[None, :, None], tj[:, None, None] + k[None, None, :]]  # N,4,4,2
        w = self._w
        n, tp = ti.size, self.tile_px
        a = np.matmul(g.transpose(0, 1, 3, 2), w.T)  # contract columns: (N, 4, 2, T)
        b = np.matmul(w, a.reshape(n, 4, 2 * tp))  # contract rows: (N, T, 2·T)
        return b.reshape(n, tp, 2, tp).transpose(0, 1, 3, 2)

    def at_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Same interpolation at arbitrary pixel positions (..., 2) → (..., 2) normalised."""
        uv = np.asarray(uv, dtype=float)
        fu = (uv[..., 0] + 0.5) / self.tile_px
        fv = (uv[..., 1] + 0.5) / self.tile_px
        j0 = np.clip(np.floor(fu).astype(np.intp), 0, self.ntx)
        i0 = np.clip(np.floor(fv).astype(np.intp), 0, self.nty)
        wu = _catmull_rom_weights(fu - j0)
        wv = _catmull_rom_weights(fv - i0)
        out = np.zeros((*uv.shape[:-1], 2))
        for a in range(4):
            for b in range(4):
                out += (wv[..., a] * wu[..., b])[..., None] * self.nodes[i0 + a, j0 + b]
        return out


@lru_cache(maxsize=8)
def _cached_grid(camera: CameraModel, extra: ExtraDistortion | None, tile_px: int) -> UndistortionGrid:
    return UndistortionGrid(camera, extra, tile_px)


def undistortion_grid(
    camera: CameraModel, extra: ExtraDistortion | Sequence[float] | None = None, tile_px: int = TILE_PX
) -> UndistortionGrid:
    """Cached :class:`UndistortionGrid`, keyed by the exact camera and distortion parameters."""
    return _cached_grid(camera, _as_extra(extra), int(tile_px))
