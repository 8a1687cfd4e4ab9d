"""Sub-pixel dot ellipses fitted to the pixels themselves, batched over all dots.

The rim fits of :mod:`tasks.detection.subpixel` locate the rim on rays through bilinearly
interpolated grey levels. Interpolating a sharp edge (blur σ ≲ 1.5 px) gives a profile whose
shape depends on where the edge falls between pixel centres, so each rim point is off by an
amount that repeats every pixel (pixel locking). Across a plate the phase advances by a fixed
fraction of a pixel per dot, and the errors form a smooth ramp that a pose estimate reads as a
tilt. On noise-free renders of the full-size campaign's X sweep, the rim fit's tilt errs by up
to 7″ at a position (0.0013 px RMS centre error); after this fit, by 1.5″ (0.0008 px).

The model of one dot's image, per pixel centre p (px):

    I(p) = (1 + g · (p − c)) · (L_out + (L_in − L_out) · Φ(−d(p) / s))

with d(p) the signed distance (px, positive outside) from p to the ellipse (centre c, semi-axes
a ≥ b, angle θ), to first order: d = (F − 1) / |∇F|, F the ellipse's normalised radius. s is the
edge blur σ and g the local gain slope (vignetting, uneven light). Ten parameters per dot, fitted
by Levenberg–Marquardt with an analytic Jacobian on the pixels of a band of ±(3s + 2) px
around the starting rim; pixels whose residual exceeds four robust standard deviations (dust,
a stray edge) are dropped after the third iteration. Units: px of the full-size image; θ in rad
from +u towards +v.

The blur of a convex rim moves its 50 % contour inwards by s²/(2ρ) (ρ: radius of curvature);
with one s per dot that changes the fitted axes, not the centre, and the axes are corrected by
s²/(2√(ab)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from tasks.detection.stats import masked_median

N_PARAMS = 10  # cx, cy, a, b, θ, L_in, L_out, s, g_u, g_v


@dataclass
class EdgeFitParams:
    max_sigma_px: float = 1.5  # dots blurrier than this keep the ray fit (curvature, defocus)
    band_sigmas: float = 3.0  # pixels within band_sigmas · s + band_pad_px of the rim
    band_pad_px: float = 2.0
    iterations: int = 8
    outlier_sigmas: float = 4.0
    max_shift_px: float = 0.25  # a fit that moves the centre further than this is not trusted


@dataclass
class EdgeFits:
    """Pixel-level fits of K dots (px); ``ok`` False where the ray fit should stand."""

    centres: np.ndarray  # (K, 2)
    axes: np.ndarray  # (K, 2) semi-axes (major, minor), blur-curvature corrected
    theta: np.ndarray  # (K,)
    sigma: np.ndarray  # (K,) edge blur σ
    residual_rms: np.ndarray  # (K,) DN
    ok: np.ndarray  # (K,) bool


def signed_distance(x, y, cx, cy, a, b, theta, *, with_gradient: bool = False):
    """First-order signed distance d (px, positive outside) from points (x, y) to ellipses:
    d = (F − 1) F / |(u/a², v/b²)| with F² = (u/a)² + (v/b)² in the ellipse's axes (u, v).

    with_gradient: also return ∂d/∂(cx, cy, a, b, θ), a list of five arrays.
    """
    ct, st = np.cos(theta), np.sin(theta)
    dx, dy = x - cx, y - cy
    u = dx * ct + dy * st
    v = -dx * st + dy * ct
    a2, b2 = a * a, b * b
    F = np.sqrt(u * u / a2 + v * v / b2)
    gr = np.maximum(np.sqrt((u / a2) ** 2 + (v / b2) ** 2), 1e-12)
    d = (F - 1.0) * F / gr
    if not with_gradient:
        return d
    Fs = np.maximum(F, 1e-12)
    # ∂d through F and |∇F| with respect to u, v, a and b; (cx, cy, θ) act through u and v
    k = (2.0 * F - 1.0) / (Fs * gr)
    m = d / (gr * gr)
    d_u = u * (k / a2 - m / (a2 * a2))
    d_v = v * (k / b2 - m / (b2 * b2))
    d_a = u * u / (a2 * a) * (2.0 * m / a2 - k)
    d_b = v * v / (b2 * b) * (2.0 * m / b2 - k)
    return d, [-ct * d_u + st * d_v, -st * d_u - ct * d_v, d_a, d_b, v * d_u - u * d_v]


def dot_model(params: np.ndarray, x: np.ndarray, y: np.ndarray, *, with_jacobian: bool = False):
    """Grey levels (DN) of the model at pixel centres x, y (K, M) for parameters (K, 10);
    with_jacobian: also the (K, 10, M) derivatives (analytic), parameter-major so that each
    parameter's row is contiguous."""
    cx, cy, a, b, th, l_in, l_out, s, gu, gv = (params[:, i, None] for i in range(N_PARAMS))
    a, b, s = np.abs(a), np.abs(b), np.maximum(np.abs(s), 0.05)
    out = signed_distance(x, y, cx, cy, a, b, th, with_gradient=with_jacobian)
    d, dd = out if with_jacobian else (out, None)
    gain = 1.0 + gu * (x - cx) + gv * (y - cy)
    z = -d / s
    p_in = ndtr(z)
    level = l_out + (l_in - l_out) * p_in
    value = gain * level
    if not with_jacobian:
        return value
    jac = np.empty((x.shape[0], N_PARAMS, x.shape[1]))
    dens = gain * (l_in - l_out) * np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)  # ∂I/∂z
    di_dd = -dens / s
    for j in range(5):
        jac[:, j] = di_dd * dd[j]
    jac[:, 0] -= gu * level
    jac[:, 1] -= gv * level
    jac[:, 5] = gain * p_in
    jac[:, 6] = gain * (1.0 - p_in)
    jac[:, 7] = dens * d / (s * s)
    jac[:, 8] = (x - cx) * level
    jac[:, 9] = (y - cy) * level
    return value, jac


def _band_pixels(image: np.ndarray, centres, axes, theta, sigma, p: EdgeFitParams):
    """Pixel centres (K, M) and grey levels of each dot's rim band, with a validity mask."""
    h, w = image.shape
    half = np.ceil(axes[:, 0] + p.band_sigmas * sigma + p.band_pad_px + 1).astype(int)
    n = int(2 * half.max() + 1)
    off = np.arange(n) - half.max()
    ju = np.rint(centres[:, 0]).astype(int)[:, None, None] + off[None, None, :]
    iv = np.rint(centres[:, 1]).astype(int)[:, None, None] + off[None, :, None]
    ju, iv = np.broadcast_arrays(ju, iv)
    k = len(centres)
    x = ju.reshape(k, -1).astype(float)
    y = iv.reshape(k, -1).astype(float)
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    d = signed_distance(x, y, centres[:, 0, None], centres[:, 1, None], axes[:, 0, None], axes[:, 1, None],
                        theta[:, None])
    band = inside & (np.abs(d) <= (p.band_sigmas * sigma + p.band_pad_px)[:, None])
    # keep the band's pixels only, packed to a common width
    m = int(band.sum(axis=1).max())
    order = np.argsort(~band, axis=1, kind="stable")[:, :m]
    x = np.take_along_axis(x, order, axis=1)
    y = np.take_along_axis(y, order, axis=1)
    mask = np.take_along_axis(band, order, axis=1)
    iy = np.clip(y.astype(int), 0, h - 1)
    ix = np.clip(x.astype(int), 0, w - 1)
    return x, y, image[iy, ix].astype(float), mask


def _levenberg_marquardt(q: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, mask: np.ndarray,
                         p: EdgeFitParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched LM over the dots' parameters q (K, 10) on their band pixels; returns (q, pixel weights
    (K, M), cost (K,)). The model and its Jacobian are evaluated once per iteration, at the trial
    point, and kept when the step is accepted; a dot whose centre step falls below 1e-5 px after
    the outlier pass leaves the active set, so the last iterations cost only the few dots that
    converge slowly."""
    w = mask.astype(float)
    lam = np.full(len(q), 1e-3)
    value, jac = dot_model(q, x, y, with_jacobian=True)
    r = (value - z) * w
    cost = (r * r).sum(axis=1)
    active = np.ones(len(q), bool)
    for it in range(p.iterations):
        if it == 3:  # drop outliers once the fit is close
            scale = 1.4826 * masked_median(np.abs(r), mask)
            w = (mask & (np.abs(r) <= p.outlier_sigmas * np.maximum(scale, 0.5)[:, None])).astype(float)
            r = (value - z) * w
            cost = (r * r).sum(axis=1)
        a = np.flatnonzero(active)
        if a.size == 0:
            break
        wa = w[a]
        ja = jac[a]
        jw = ja * wa[:, None, :]
        jtj = jw @ ja.transpose(0, 2, 1)
        jtr = (jw @ r[a, :, None])[..., 0]
        diag = np.einsum("kii->ki", jtj)
        # the floor keeps θ of a near-circular dot (no signal) from making the system singular
        diag = np.maximum(diag, 1e-9 * diag.max(axis=1, keepdims=True))
        lhs = jtj + (lam[a, None] * diag)[:, :, None] * np.eye(N_PARAMS) + 1e-12 * np.eye(N_PARAMS)
        step = np.linalg.solve(lhs, -jtr[..., None])[..., 0]
        q_new = q[a] + step
        value_new, jac_new = dot_model(q_new, x[a], y[a], with_jacobian=True)
        r_new = (value_new - z[a]) * wa
        cost_new = (r_new * r_new).sum(axis=1)
        better = np.isfinite(cost_new) & (cost_new < cost[a])
        kept = a[better]
        q[kept], value[kept], jac[kept] = q_new[better], value_new[better], jac_new[better]
        r[kept], cost[kept] = r_new[better], cost_new[better]
        lam[a] = np.where(better, lam[a] / 10.0, lam[a] * 10.0)
        if it >= 3:  # centres settled to 0.00001 px
            active[a[np.all(np.abs(step[:, :2]) < 1e-5, axis=1)]] = False
    return q, w, cost


def fit_dot_edges(image: np.ndarray, centres: np.ndarray, axes: np.ndarray, theta: np.ndarray,
                  sigma: np.ndarray, params: EdgeFitParams | None = None) -> EdgeFits:
    """Fit each dot's ellipse to its pixels, starting from ray-fit ellipses (full-size px).

    image: (H, W) grey levels. centres (K, 2), axes (K, 2) semi-axes, theta (K,), sigma (K,)
    edge blur σ: the starting ellipses. Dots with σ above ``max_sigma_px``, or a start that is
    not finite, are returned with ``ok`` False and their start values.
    """
    p = params or EdgeFitParams()
    k = len(centres)
    start_ok = (np.isfinite(centres).all(axis=1) & np.isfinite(axes).all(axis=1) & np.isfinite(theta)
                & np.isfinite(sigma) & (sigma <= p.max_sigma_px))
    out = EdgeFits(centres.copy(), axes.copy(), theta.copy(), sigma.copy(), np.full(k, np.nan),
                   np.zeros(k, bool))
    idx = np.flatnonzero(start_ok)
    if idx.size == 0:
        return out
    s0 = np.maximum(sigma[idx], 0.3)
    x, y, z, mask = _band_pixels(image, centres[idx], axes[idx], theta[idx], s0, p)
    d0 = signed_distance(x, y, centres[idx, 0, None], centres[idx, 1, None], axes[idx, 0, None],
                         axes[idx, 1, None], theta[idx, None])
    far = (2.0 * s0 + 1.0)[:, None]
    l_in = masked_median(z, mask & (d0 < -far))
    l_out = masked_median(z, mask & (d0 > far))
    q = np.column_stack([centres[idx], axes[idx], theta[idx], l_in, l_out, s0, np.zeros((idx.size, 2))])
    q, w, cost = _levenberg_marquardt(q, x, y, z, mask, p)
    a_fit, b_fit = np.abs(q[:, 2]), np.abs(q[:, 3])
    s_fit = np.abs(q[:, 7])
    shift = np.linalg.norm(q[:, :2] - centres[idx], axis=1)
    good = np.isfinite(q).all(axis=1) & (shift <= p.max_shift_px) & (s_fit <= 2.0 * p.max_sigma_px)
    curv = s_fit**2 / (2.0 * np.sqrt(a_fit * b_fit))
    major = np.maximum(a_fit, b_fit) + curv
    minor = np.minimum(a_fit, b_fit) + curv
    th = np.where(a_fit >= b_fit, q[:, 4], q[:, 4] + np.pi / 2)
    th = (th + np.pi / 2) % np.pi - np.pi / 2
    n_used = np.maximum(w.sum(axis=1) - N_PARAMS, 1.0)
    g = idx[good]
    out.centres[g] = q[good, :2]
    out.axes[g] = np.column_stack([major, minor])[good]
    out.theta[g] = th[good]
    out.sigma[g] = s_fit[good]
    out.residual_rms[idx] = np.sqrt(cost / n_used)
    out.ok[g] = True
    return out
