"""Plate homography and the perspective bias of circle centres.

A circle on the plate projects to an ellipse whose centre is *not* the projection of the
circle's centre: under perspective the near half of the circle looks larger than the far half,
so the ellipse centre is displaced from the projected centre, by up to a few tenths of a pixel
for large dots on a tilted plate. With the plate → image homography H (plate mm → px), each dot
of radius ρ is the conic Q = [[1, 0, −x], [0, 1, −y], [−x, −y, x² + y² − ρ²]] on the plate and
C = H⁻ᵀ Q H⁻¹ in the image; the bias is centre(C) − H(x, y). It is subtracted from the measured
ellipse centres, H is re-estimated from the corrected centres and the correction repeated.

Lens distortion is ignored for the bias (it is a second-order local effect); the homography is
a least-squares fit (DLT on normalised points) of image px to plate mm.
"""

from __future__ import annotations

import cv2
import numpy as np

from tasks.detection.conics import conic_centre_h


def fit_homography(plate_xy_mm: np.ndarray, image_uv_px: np.ndarray) -> np.ndarray:
    """(3, 3) least-squares homography mapping plate (x, y) mm → image (u, v) px."""
    h, _ = cv2.findHomography(plate_xy_mm.astype(np.float64), image_uv_px.astype(np.float64), 0)
    if h is None:
        raise ValueError("homography fit failed (degenerate points)")
    return h / h[2, 2]


def project(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) plate mm → (N, 2) image px through homography h."""
    p = xy @ h[:, :2].T + h[:, 2]
    return p[:, :2] / p[:, 2:3]


def centre_bias(h: np.ndarray, plate_xy_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N, 2) px: centre of each projected circle's ellipse minus the projected circle centre."""
    x, y = plate_xy_mm[:, 0], plate_xy_mm[:, 1]
    n = len(x)
    q = np.zeros((n, 3, 3))
    q[:, 0, 0] = 1.0
    q[:, 1, 1] = 1.0
    q[:, 0, 2] = q[:, 2, 0] = -x
    q[:, 1, 2] = q[:, 2, 1] = -y
    q[:, 2, 2] = x * x + y * y - radius_mm**2
    hinv = np.linalg.inv(h)
    c = np.einsum("ji,njk,kl->nil", hinv, q, hinv)  # H⁻ᵀ Q H⁻¹, (N, 3, 3)
    return conic_centre_h(c) - project(h, plate_xy_mm)


def correct_bias(ellipse_centres_px: np.ndarray, plate_xy_mm: np.ndarray, radius_mm: float,
                 iterations: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Projected circle centres from ellipse centres (N, 2) px; returns (centres, homography).

    Iteration 0 fits H to the raw ellipse centres; each iteration computes the bias with the
    current H and subtracts it from the *measured* centres, then refits H.
    """
    h = fit_homography(plate_xy_mm, ellipse_centres_px)
    corrected = ellipse_centres_px
    for _ in range(iterations):
        corrected = ellipse_centres_px - centre_bias(h, plate_xy_mm, radius_mm)
        h = fit_homography(plate_xy_mm, corrected)
    return corrected, h


def correct_bias_local(ellipse_centres_px: np.ndarray, plate_xy_mm: np.ndarray, radius_mm: float,
                       row_col: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Like :func:`correct_bias`, with one homography per dot fitted to it and its neighbours.

    Under strong lens distortion (a fisheye) no single homography maps the plate into the image;
    around each dot, the dots at most one row and one column away (4 to 9 of them) still fit one,
    and the bias of that dot's ellipse centre is computed from it. ellipse_centres_px (N, 2) px,
    plate_xy_mm (N, 2) mm, row_col (N, 2) plate row and column of each dot. Returns (N, 2) px.
    """
    near = np.all(np.abs(row_col[:, None, :] - row_col[None, :, :]) <= 1, axis=2)  # (N, N)
    corrected = ellipse_centres_px.copy()
    for _ in range(iterations):
        new = ellipse_centres_px.copy()
        for k in range(len(new)):
            nb = near[k]
            h = fit_homography(plate_xy_mm[nb], corrected[nb])
            new[k] -= centre_bias(h, plate_xy_mm[k : k + 1], radius_mm)[0]
        corrected = new
    return corrected
