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

from tasks.vision.detection.conics import conic_centre_h
from tasks.vision.detection.parallel import over_dots


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
    return centre_bias_each(np.broadcast_to(h, (len(plate_xy_mm), 3, 3)), plate_xy_mm, radius_mm)


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


def corrected_centres(ellipse_centres_px: np.ndarray, plate_xy_mm: np.ndarray, radius_mm: float,
                      row_col: np.ndarray, iterations: int, distorted_misfit_px: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The detector's perspective correction: (projected circle centres (N, 2) px, plate homography).

    :func:`correct_bias` with one homography; when it leaves an RMS misfit above
    ``distorted_misfit_px`` (lens distortion), :func:`correct_bias_local` with one per neighbourhood
    (the homography returned is then still the single one). ellipse_centres_px (N, 2) px,
    plate_xy_mm (N, 2) mm, row_col (N, 2) plate row and column of each dot."""
    centres, hom = correct_bias(ellipse_centres_px, plate_xy_mm, radius_mm, iterations)
    misfit = np.sqrt(np.mean(np.sum((project(hom, plate_xy_mm) - centres) ** 2, axis=1)))
    if misfit > distorted_misfit_px:
        centres = correct_bias_local(ellipse_centres_px, plate_xy_mm, radius_mm, row_col, iterations)
    return centres, hom


def local_homographies(plate_xy_mm: np.ndarray, image_uv_px: np.ndarray, member: np.ndarray) -> np.ndarray:
    """(N, 3, 3) homographies plate mm → image px, the k-th fitted to the points ``member[k]`` selects.

    member: (N, M) bool over the M point pairs (at least 4 per row, not three on a line). A
    normalised DLT (Hartley) for all N at once: each point set is centred and scaled, the 9
    homography entries are the eigenvector of the smallest eigenvalue of AᵀA (batched ``eigh``).
    """
    w = member.astype(float)[:, :, None]  # (N, M, 1)
    cnt = w.sum(axis=1)  # (N, 1)

    def normaliser(pts: np.ndarray) -> np.ndarray:  # (N, 3, 3): centre at the mean, mean distance √2
        mean = (w * pts[None]).sum(axis=1) / cnt  # (N, 2)
        dist = (w[..., 0] * np.linalg.norm(pts[None] - mean[:, None], axis=2)).sum(axis=1) / cnt[:, 0]
        sc = np.sqrt(2.0) / np.maximum(dist, 1e-12)
        t = np.zeros((len(mean), 3, 3))
        t[:, 0, 0] = t[:, 1, 1] = sc
        t[:, :2, 2] = -sc[:, None] * mean
        t[:, 2, 2] = 1.0
        return t

    tp, ti = normaliser(plate_xy_mm), normaliser(image_uv_px)
    xp = np.einsum("nij,mj->nmi", tp[:, :2, :2], plate_xy_mm) + tp[:, None, :2, 2]  # (N, M, 2)
    xi = np.einsum("nij,mj->nmi", ti[:, :2, :2], image_uv_px) + ti[:, None, :2, 2]
    x, y = xp[..., 0], xp[..., 1]
    u, v = xi[..., 0], xi[..., 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    r1 = np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], axis=-1)  # (N, M, 9)
    r2 = np.stack([zero, zero, zero, x, y, one, -v * x, -v * y, -v], axis=-1)
    ata = np.einsum("nmi,nmj->nij", r1 * w, r1) + np.einsum("nmi,nmj->nij", r2 * w, r2)
    _, vec = np.linalg.eigh(ata)
    hn = vec[:, :, 0].reshape(-1, 3, 3)
    h = np.linalg.inv(ti) @ hn @ tp
    return h / h[:, 2:3, 2:3]


def correct_bias_local(ellipse_centres_px: np.ndarray, plate_xy_mm: np.ndarray, radius_mm: float,
                       row_col: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Like :func:`correct_bias`, with one homography per dot fitted to it and its neighbours.

    Under lens distortion no single homography maps the plate into the image; around each dot,
    the dots at most one row and one column away (4 to 9 of them) still fit one, and the bias of
    that dot's ellipse centre is computed from it. ellipse_centres_px (N, 2) px, plate_xy_mm
    (N, 2) mm, row_col (N, 2) plate row and column of each dot. Returns (N, 2) px.
    """
    near = np.all(np.abs(row_col[:, None, :] - row_col[None, :, :]) <= 1, axis=2)  # (N, N)
    corrected = ellipse_centres_px
    for _ in range(iterations):  # each dot's homography and bias on its own: spread over the threads
        bias, = over_dots(_local_bias, len(near), near, plate_xy_mm, all_xy_mm=plate_xy_mm, all_uv_px=corrected,
                          radius_mm=radius_mm)
        corrected = ellipse_centres_px - bias
    return corrected


def _local_bias(member: np.ndarray, own_xy_mm: np.ndarray, *, all_xy_mm: np.ndarray, all_uv_px: np.ndarray,
                radius_mm: float) -> tuple[np.ndarray]:
    """(bias (K, 2) px,) of K dots at own_xy_mm (K, 2), each through the homography of the dots that
    ``member`` (K, M) selects among all M (all_xy_mm, all_uv_px)."""
    return (centre_bias_each(local_homographies(all_xy_mm, all_uv_px, member), own_xy_mm, radius_mm),)


def centre_bias_each(hs: np.ndarray, plate_xy_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N, 2) px: :func:`centre_bias` of dot k through its own homography ``hs[k]`` (N, 3, 3)."""
    x, y = plate_xy_mm[:, 0], plate_xy_mm[:, 1]
    n = len(x)
    q = np.zeros((n, 3, 3))
    q[:, 0, 0] = 1.0
    q[:, 1, 1] = 1.0
    q[:, 0, 2] = q[:, 2, 0] = -x
    q[:, 1, 2] = q[:, 2, 1] = -y
    q[:, 2, 2] = x * x + y * y - radius_mm**2
    hinv = np.linalg.inv(hs)
    c = np.einsum("nji,njk,nkl->nil", hinv, q, hinv)  # H⁻ᵀ Q H⁻¹ per dot
    p = np.einsum("nij,nj->ni", hs, np.column_stack([x, y, np.ones(n)]))
    return conic_centre_h(c) - p[:, :2] / p[:, 2:3]
