"""The blurred printed dots around a dot along its rim rays: a model to take them out of its profiles.

Under a blur as wide as the gap between the dots (σ ≈ 2–3 px on 10–16 px dots 5–8 px apart) the
outer end of a dot's rim ray lies on the tail of its neighbour's blurred dot: the profile does not
level off at the plate's grey, the step fit puts the rim nearer on the neighbour's side, and the
centre moves away from the neighbours (0.2–1.2 px at the edge of a grid, whose neighbours are all on
one side). Each neighbour j is modelled as what it is, a printed ellipse of ink level a_j on the
plate's level b_j blurred by σ_j: at distance ρ from its centre, where its rim lies R from the centre
in that direction, it shifts the grey level by (a_j − b_j) F(ρ; R, σ_j), F the fraction of a disc of
radius R blurred by a Gaussian of σ that reaches ρ (:func:`disc_fill`); the shift is removed from
the profile before the step fit. Sharp dots' windows reach only a neighbour's rim itself, not its
tail (:func:`tails_at_rims`): there a straight blurred edge with the neighbour's step-fit levels is
enough (:func:`sharp_rims_shift`).

The blurred-step fit of a dot's own rays does not measure a_j, R and σ_j when σ is comparable to the
radius: its inside level is the blurred dot's partly filled centre, not the ink (under σ = 4.7 px on a
13 px dot 99 DN where the ink is 35 and the plate 215), and its rim with the first-order blur–curvature
shift lies 1 px outside the printed one. A model built from those levels predicts a third of the
neighbour's tail. :func:`fit_printed_dots` fits the blurred printed dots themselves to the rays of all
the dots the model reaches at once (one ink, one paper, one lens), and a printed ellipse's blur is
read from :func:`ellipse_fill`.
Units: px of the full-size image, grey levels of the profiles; angles rad from +u towards +v.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import chndtr, ndtr

N_NEIGHBOURS = 8  # the nearest other dots modelled per dot: a lattice's 8 surrounding ones


@dataclass
class DotRims:
    """The printed dots of an image, as neighbours: centres (N, 2) px, printed rims' semi-axes (N, 2) px
    (major, minor), major-axis angles (N,) rad, blur σ (N,) px, grey levels of the ink and of the plate
    around it (N,)."""

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


def tails_at_rims(model: DotRims, near: np.ndarray) -> float:
    """The largest fraction of its contrast that a neighbour's blurred rim adds at the rim of one of the
    dots ``near`` (indices into ``model``): Φ(−g/σ_j) for the gap g px between the two rim ellipses on
    the line between their centres and the neighbour's rim blur σ_j px, over the :data:`N_NEIGHBOURS`
    nearest dots (dots with a non-finite ellipse or blur left out)."""
    usable = np.flatnonzero(np.isfinite(model.centres).all(axis=1) & np.isfinite(model.axes).all(axis=1)
                            & np.isfinite(model.sigma))
    mine = near[np.isin(near, usable)]
    if len(usable) < 2 or not len(mine):
        return 0.0
    n_q = min(N_NEIGHBOURS + 1, len(usable))
    dist, j = cKDTree(model.centres[usable]).query(model.centres[mine], k=n_q)
    j = usable[j]
    d = model.centres[j] - model.centres[mine, None]  # (K, n_q, 2) from each dot to its neighbours

    def rim(k, du, dv):  # the rim's distance px from the centres of dots k along (du, dv)
        c, s = np.cos(model.theta[k]), np.sin(model.theta[k])
        return _rim_geometry(du * c + dv * s, -du * s + dv * c, model.axes[k, 0], model.axes[k, 1])[1]

    gap = dist - rim(mine[:, None], d[..., 0], d[..., 1]) - rim(j, -d[..., 0], -d[..., 1])
    tail = np.where(j != mine[:, None], ndtr(-gap / np.maximum(model.sigma[j], 1e-3)), 0.0)
    return float(tail.max())


def neighbour_shift(dots: DotRims, own: np.ndarray, cen: np.ndarray, ang: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K, R, T) grey levels the other blurred printed dots add at the samples of K dots' rays
    (:func:`ellipse_fill`).

    own: (K,) index of each ray origin's dot in ``dots`` (left out of its own model); cen: (K, 2) px
    ray origins; ang: (R,) ray angles; t: (K, R, T) px along the rays. Only the
    :data:`N_NEIGHBOURS` nearest other dots are modelled; dots whose fit is not finite are left out.
    """
    out = np.zeros(t.shape, np.float32)
    dots = replace(dots, sigma=np.where(np.isfinite(dots.level_in) & np.isfinite(dots.level_out), dots.sigma, np.nan))
    if len(own) == 0 or np.isfinite(dots.sigma).sum() < 2:
        return out
    u, v = _ray_points(cen, ang, t)
    for j, rho, rim, radius, sig in _fill_terms(dots, u, v):
        other = (j != own)[:, None, None]
        fill = disc_fill(np.maximum(radius + rho - rim, 0.0), radius, sig)
        out += np.where(other, (dots.level_in[j] - dots.level_out[j])[:, None, None] * fill, 0.0).astype(np.float32)
    return out


def sharp_rims_shift(dots: DotRims, own: np.ndarray, cen: np.ndarray, ang: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K, R, T) grey levels the blurred rims of the other dots add at the samples of K dots' rays, each
    dot j's rim a straight edge of its step fit's levels ``dots.level_in``/``level_out`` blurred by its
    rim blur s_j: at d px outside its ellipse (along the line to its centre) (a_j − b_j) Φ(−(d + s_j²/(2
    r_j)) / s_j), r_j its mean semi-axis (the blurred rim's half level lies s²/(2 r) inside the rim).
    The model of sharp dots, where only a neighbour's rim itself, not its tail, reaches a dot's window
    (:func:`tails_at_rims`); under a blur as wide as the gap :func:`neighbour_shift`.

    own: (K,) index of each ray origin's dot in ``dots`` (left out of its own model); cen: (K, 2) px
    ray origins; ang: (R,) ray angles; t: (K, R, T) px along the rays. Only the
    :data:`N_NEIGHBOURS` nearest other dots are modelled; dots whose fit is not finite are left out.
    """
    out = np.zeros(t.shape, np.float32)
    usable = _modelled(dots) & np.isfinite(dots.level_in) & np.isfinite(dots.level_out)
    if len(own) == 0 or usable.sum() < 2:
        return out
    near = _nearest_dots(dots, usable, cen)
    u, v = _ray_points(cen, ang, t)
    for q in range(near.shape[1]):
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


def disc_fill(rho: np.ndarray, radius: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The fraction of a disc's level at distance ``rho`` px from its centre once blurred by a Gaussian
    of ``sigma`` px (radius ``radius`` px; arrays broadcast): P(|X| < R) for X ~ N(ρ, σ² I₂), the
    non-central χ² distribution of 2 degrees of freedom at R²/σ² with non-centrality ρ²/σ². Read
    bilinearly from a table of it over R/σ < 10 (steps of 0.05 σ: within 2e-4); for larger discs
    Φ((R − ρ)/σ − σ/(2R)), a blurred edge moved inwards by its curvature (within 7e-4)."""
    s = np.maximum(sigma, 1e-3)
    rs, ps = np.broadcast_arrays(np.asarray(radius / s, dtype=float), np.asarray(rho / s, dtype=float))
    table = _disc_table()
    i = np.clip(rs, 0.0, _TABLE_R) / _TABLE_STEP
    j = np.clip(ps, 0.0, _TABLE_RHO) / _TABLE_STEP
    i0 = np.minimum(i.astype(np.int64), table.shape[0] - 2)
    j0 = np.minimum(j.astype(np.int64), table.shape[1] - 2)
    fi, fj = i - i0, j - j0
    near = ((table[i0, j0] * (1 - fj) + table[i0, j0 + 1] * fj) * (1 - fi)
            + (table[i0 + 1, j0] * (1 - fj) + table[i0 + 1, j0 + 1] * fj) * fi)
    far = ndtr(rs - ps - 0.5 / np.maximum(rs, 1e-9))
    return np.where(rs < _TABLE_R, near, far)


_TABLE_R, _TABLE_RHO, _TABLE_STEP = 10.0, 20.0, 0.05  # R/σ and ρ/σ of the table (beyond ρ/σ 20 a disc adds < 1e-9)
_TABLES: list[np.ndarray] = []


def _disc_table() -> np.ndarray:
    """The table of :func:`disc_fill` over R/σ and ρ/σ (made on first use, 0.03 s)."""
    if not _TABLES:
        r = np.arange(0.0, _TABLE_R + 2 * _TABLE_STEP, _TABLE_STEP)
        rho = np.arange(0.0, _TABLE_RHO + 2 * _TABLE_STEP, _TABLE_STEP)
        _TABLES.append(chndtr((r**2)[:, None], 2.0, (rho**2)[None, :]))
    return _TABLES[0]


def fit_printed_dots(dots: DotRims, near: np.ndarray, prof: np.ndarray, ang: np.ndarray, t: np.ndarray,
                     use: np.ndarray, iterations: int = 4) -> DotRims:
    """The blurred printed dots that the rays of the dots ``near`` see, fitted to them jointly: one ink
    level a and one plate level b, one blur scale g and one rim scale κ, each dot j a printed ellipse
    of κ × its fitted semi-axes blurred by g × its fitted rim blur (``dots.sigma``):
    prof ≈ b + (a − b) Σ_j F(ρ_j; κ R_j, g σ_j) over the dot itself and its neighbours (:func:`disc_fill`).

    Under a blur as wide as the gap neither level is reached between the dots, and a fit of each dot
    alone with its neighbours' tails held fixed settles on a lower contrast and a narrower blur that
    explain the same profiles (a level free per dot takes up the neighbours' tails); the joint fit
    does not. The levels are shared because one ink is printed on one paper (the profiles are
    flattened by the gain field); the scales because one lens blurs them all.

    dots: every fitted dot (its rim ellipses and rim blurs; levels ignored; dots with a non-finite
    ellipse or blur are none); near: (K,) indices of the
    dots whose rays are given; prof, t: (K, R, T) flattened grey levels and px from each dot's centre
    along rays at angles ang (R,); use: (K, R) rays to fit. Gauss–Newton on (ln g, ln κ) with numerical
    derivatives (steps clipped to ±0.3, halved while the residual rises), (a, b) by linear least squares
    at each step. Returns ``dots`` with the fitted levels, blurs and semi-axes.
    """
    w = use[..., None].astype(float) * np.ones(prof.shape[-1])
    y = np.where(w > 0, prof, 0.0).astype(float)
    cen = dots.centres[near]
    u = cen[:, 0, None, None] + np.cos(ang)[None, :, None] * t
    v = cen[:, 1, None, None] + np.sin(ang)[None, :, None] * t

    terms = _fill_terms(dots, u, v)

    def fill(p):  # Σ_j F at the samples (K, R, T) for p = (ln g, ln κ), the dot itself included
        g, kappa = np.exp(p)
        out = np.zeros(u.shape)
        for _, rho, rim, radius, sig in terms:  # κ scales the rim's distance and its curvature radius alike
            out += disc_fill(np.maximum(kappa * (radius - rim) + rho, 0.0), kappa * radius, g * sig)
        return out

    def levels(f):  # (a, b, gains (K,), cost): y ≈ g_k (b + (a − b) f), the gains' median 1
        g = np.ones(len(near))
        for _ in range(3):
            wg = w * g[:, None, None] ** 2
            yg = y / g[:, None, None]
            sw, sf, sff = wg.sum(), (wg * f).sum(), (wg * f * f).sum()
            sy, syf = (wg * yg).sum(), (wg * yg * f).sum()
            det = sw * sff - sf**2
            c = (sw * syf - sf * sy) / det if abs(det) > 1e-9 else 0.0
            b = (sy - c * sf) / max(sw, 1e-9)
            m = w * (b + c * f)
            g = (m * y).sum((1, 2)) / np.maximum((m * m).sum((1, 2)), 1e-9)
            g = np.where(g > 0, g, 1.0)
            g = g / np.median(g)
        return b + c, b, g, float(((w * (y - g[:, None, None] * (b + c * f))) ** 2).sum())

    p = np.zeros(2)
    f = fill(p)
    a, b, gains, cost = levels(f)
    h = 1e-3
    for _ in range(iterations):
        r = w * (y - gains[:, None, None] * (b + (a - b) * f))
        jac = np.stack([-(a - b) * gains[:, None, None] * w * (fill(p + h * np.eye(2)[i]) - f) / h
                        for i in range(2)], axis=-1)
        jj = np.einsum("krti,krtj->ij", jac, jac) + 1e-9 * np.eye(2)
        step = np.clip(np.nan_to_num(-np.linalg.solve(jj, np.einsum("krti,krt->i", jac, r))), -0.3, 0.3)
        for _ in range(4):
            f_new = fill(p + step)
            a_new, b_new, gains_new, cost_new = levels(f_new)
            if np.isfinite(cost_new) and cost_new < cost:
                p, f, a, b, gains, cost = p + step, f_new, a_new, b_new, gains_new, cost_new
                break
            step = 0.5 * step
        else:
            break
    gain = np.ones(len(dots.centres))
    gain[near] = gains
    return DotRims(dots.centres, dots.axes * np.exp(p[1]), dots.theta, dots.sigma * np.exp(p[0]), gain * a, gain * b)


def _ray_points(cen: np.ndarray, ang: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (K, R, T) px of the samples at ``t`` (K, R, T) px along rays at ``ang`` (R,) from ``cen`` (K, 2)."""
    return (cen[:, 0, None, None] + np.cos(ang)[None, :, None] * t,
            cen[:, 1, None, None] + np.sin(ang)[None, :, None] * t)


def _modelled(dots: DotRims) -> np.ndarray:
    """(N,) bool: the dots with a finite ellipse and rim blur, which can be modelled as neighbours."""
    return np.isfinite(dots.centres).all(axis=1) & np.isfinite(dots.axes).all(axis=1) & np.isfinite(dots.sigma)


def _nearest_dots(dots: DotRims, usable: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(K, Q) indices of the :data:`N_NEIGHBOURS` + 1 dots of ``usable`` (N,) bool nearest each of the
    points ``at`` (K, 2) px (Q: fewer where fewer are usable)."""
    pool = np.flatnonzero(usable)
    n_q = min(N_NEIGHBOURS + 1, len(pool))
    _, near = cKDTree(dots.centres[pool]).query(at, k=n_q)
    return pool[np.asarray(near).reshape(len(at), n_q)]


def _fill_terms(dots: DotRims, u: np.ndarray, v: np.ndarray) -> list[tuple[np.ndarray, ...]]:
    """The geometry of :func:`ellipse_fill` for the dots near the points (u, v) (K, R, T) px: per term
    (the dots j (K,), then ρ, the rim's distance R, the disc radius √(ρ_c R) and σ, each (K, R, T)), for the
    :data:`N_NEIGHBOURS` + 1 dots nearest each ray's first sample (dots with a non-finite ellipse or blur
    left out), the terms no sample comes within 8 σ of left out."""
    near = _nearest_dots(dots, _modelled(dots), np.stack([u[:, 0, 0], v[:, 0, 0]], axis=1))
    terms = []
    for q in range(near.shape[1]):
        j = near[:, q]
        c, s = np.cos(dots.theta[j])[:, None, None], np.sin(dots.theta[j])[:, None, None]
        du, dv = u - dots.centres[j, 0, None, None], v - dots.centres[j, 1, None, None]
        x, y = du * c + dv * s, -du * s + dv * c
        rho, rim, radius = _rim_geometry(x, y, dots.axes[j, 0, None, None], dots.axes[j, 1, None, None])
        sig = np.broadcast_to(dots.sigma[j, None, None], u.shape)
        if ((rho - rim) < 8.0 * sig).any():
            terms.append((j, rho, rim, radius, sig))
    return terms


def ellipse_fill(du: np.ndarray, dv: np.ndarray, a: np.ndarray, b: np.ndarray, theta: np.ndarray,
                 sigma: np.ndarray) -> np.ndarray:
    """The fraction of a printed ellipse's level at offsets (du, dv) px from its centre once blurred by a
    Gaussian of ``sigma`` px (semi-axes a ≥ b px, major axis at ``theta`` rad; arrays broadcast): the
    blurred disc (:func:`disc_fill`) at the same distance outside its rim as the point is outside the
    ellipse's (along the line from the centre), of radius √(ρ_c R): R the rim's distance from the centre
    on that line, ρ_c its radius of curvature there. A blurred tail is set by the rim's curvature
    nearby, which on a dot foreshortened to 0.77 of its width is 1.7× R at the ends of the minor axis
    and 0.6× at the ends of the major one; the disc of radius R misses blurred ellipses of axis ratio
    0.67–0.77 (σ 2–4 px, 4–7 px semi-axes, supersampled renders) by up to 7 % of their level, ρ_c by
    6 %, √(ρ_c R) by 3 %."""
    c, s = np.cos(theta), np.sin(theta)
    rho, rim, radius = _rim_geometry(du * c + dv * s, -du * s + dv * c, a, b)
    return disc_fill(np.maximum(radius + rho - rim, 0.0), radius, sigma)


def _rim_geometry(x, y, a, b):
    """(ρ, R, √(ρ_c R)) px of points (x, y) px in an ellipse's frame (semi-axes a, b along x, y): their
    distance from its centre, the rim's on the same line, and the disc radius of :func:`ellipse_fill`."""
    rho = np.hypot(x, y)
    q = np.hypot(x / a, y / b)
    rim = np.where(q > 1e-9, rho / np.maximum(q, 1e-9), b)
    tpar = np.arctan2(a * y, b * x)  # the rim point's parametric angle (x = a cos, y = b sin)
    curv = (a**2 * np.sin(tpar) ** 2 + b**2 * np.cos(tpar) ** 2) ** 1.5 / (a * b)
    return rho, rim, np.sqrt(curv * rim)
