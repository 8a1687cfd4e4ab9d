"""The blurred rims of a dot's neighbours along its rim rays: a model to take them out of its profiles.

Under a blur as wide as the gap between the dots (σ ≈ 2–3 px on 10–16 px dots 5–8 px apart) the
outer end of a dot's rim ray lies on the tail of its neighbour's blurred rim: the profile does not
level off at the plate's grey, and the step fit puts the rim further out on the neighbour's side,
pulling the centre towards the neighbours (0.2–0.6 px at the edge of the grid, where the neighbours
are all on one side). Each neighbour j is modelled as its fitted ellipse's rim
blurred by its own edge σ s_j: at a point d px outside that ellipse (along the line to its centre)
it shifts the grey level by (a_j − b_j) Φ(−(d + s_j²/(2 r_j)) / s_j), a_j and b_j its fitted levels
inside and outside the rim, r_j its mean semi-axis (the blurred rim's half level lies s²/(2 r) inside
the rim); the shift is removed from the profile before the step fit. Units: px of the full-size
image, grey levels of the profiles; angles rad from +u towards +v.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtr

N_NEIGHBOURS = 8  # the nearest other dots modelled per dot: a lattice's 8 surrounding ones


@dataclass
class DotRims:
    """The fitted dots of an image, as neighbours: centres (N, 2) px, semi-axes (N, 2) px (major,
    minor), major-axis angles (N,) rad, edge blur σ (N,) px, grey levels inside and outside the
    rim (N,)."""

    centres: np.ndarray
    axes: np.ndarray
    theta: np.ndarray
    sigma: np.ndarray
    level_in: np.ndarray
    level_out: np.ndarray


TAIL_SIGMAS = 4.0
"""A neighbour's blurred rim further than this many of its σ beyond a dot's rays shifts them by less
than 1e-4 of its contrast: :func:`within_reach` leaves it out."""


def within_reach(dots: DotRims, reach_px: np.ndarray) -> np.ndarray:
    """(N,) bool: the dots whose rays, reaching ``reach_px`` (N,) px beyond their rims, come within
    :data:`TAIL_SIGMAS` σ of another dot's rim (rims bounded by the major semi-axes: a cheap test that
    never misses a dot :func:`neighbour_shift` would shift)."""
    n = len(dots.centres)
    usable = np.isfinite(dots.centres).all(axis=1) & np.isfinite(dots.axes).all(axis=1) & np.isfinite(dots.sigma)
    pool = np.flatnonzero(usable)
    out = np.zeros(n, bool)
    if len(pool) < 2:
        return out
    n_q = min(N_NEIGHBOURS + 1, len(pool))
    dist, near = cKDTree(dots.centres[pool]).query(dots.centres[pool], k=n_q)
    near = pool[near]
    me = pool[:, None]
    gap = dist - dots.axes[me, 0] - dots.axes[near, 0]
    close = (near != me) & (gap < reach_px[me] + TAIL_SIGMAS * dots.sigma[near])
    out[pool] = close.any(axis=1)
    return out


def neighbour_shift(dots: DotRims, own: np.ndarray, cen: np.ndarray, ang: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K, R, T) grey levels the blurred rims of the other dots add at the samples of K dots' rays.

    own: (K,) index of each ray origin's dot in ``dots`` (left out of its own model); cen: (K, 2) px
    ray origins; ang: (R,) ray angles; t: (K, R, T) px along the rays. Only the
    :data:`N_NEIGHBOURS` nearest other dots are modelled; dots whose fit is not finite are left out.
    """
    k = len(own)
    out = np.zeros(t.shape, np.float32)
    usable = np.isfinite(dots.centres).all(axis=1) & np.isfinite(dots.axes).all(axis=1) & np.isfinite(dots.sigma)
    usable &= np.isfinite(dots.level_in) & np.isfinite(dots.level_out)
    pool = np.flatnonzero(usable)
    if k == 0 or len(pool) < 2:
        return out
    n_q = min(N_NEIGHBOURS + 1, len(pool))
    _, near = cKDTree(dots.centres[pool]).query(cen, k=n_q)
    near = pool[np.asarray(near).reshape(k, n_q)]  # (K, Q)
    u = cen[:, 0, None, None] + np.cos(ang)[None, :, None] * t  # (K, R, T)
    v = cen[:, 1, None, None] + np.sin(ang)[None, :, None] * t
    for q in range(n_q):
        j = near[:, q]
        other = j != own
        if not other.any():
            continue
        du = u - dots.centres[j, 0, None, None]
        dv = v - dots.centres[j, 1, None, None]
        c, s = np.cos(dots.theta[j])[:, None, None], np.sin(dots.theta[j])[:, None, None]
        x = (du * c + dv * s) / dots.axes[j, 0, None, None]
        y = (-du * s + dv * c) / dots.axes[j, 1, None, None]
        dist = np.hypot(du, dv) * (1.0 - 1.0 / np.maximum(np.hypot(x, y), 1e-6))  # outside the ellipse > 0
        sig = dots.sigma[j, None, None]
        # the blurred rim's half level lies σ²/(2 r) inside the rim (its curvature, r the mean semi-axis)
        dist = dist + sig**2 / (2.0 * np.sqrt(dots.axes[j, 0] * dots.axes[j, 1]))[:, None, None]
        shift = (dots.level_in[j] - dots.level_out[j])[:, None, None] * ndtr(-dist / sig)
        out += np.where(other[:, None, None], shift, 0.0).astype(np.float32)
    return out
