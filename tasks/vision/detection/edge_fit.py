"""Sub-pixel dot ellipses fitted to the pixels themselves, batched over all dots.

The rim fits of :mod:`tasks.vision.detection.subpixel` locate the rim on rays through bilinearly
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
a stray edge) are dropped after the first iteration (the ray fit starts within about 0.01 px).
Units: px of the full-size image; θ in rad from +u towards +v.

The per-pixel model, its Jacobian and the normal equations JᵀWJ, JᵀWr are one compiled loop
(numba, cached on disk, releasing the GIL for the image threads). The numpy form of the same
sums held a (K, 10, M) Jacobian and a dozen (K, M) temporaries per evaluation; with the earlier
outlier pass and the unevaluated last step, the whole fit became about 4× faster (two full-size
camera 1 images, 49 dots each: 25 ms against 100 ms per image; docs/measure.md).
:func:`dot_model` evaluates the same per-pixel function for analyses and tests.

The blur of a convex rim moves its 50 % contour inwards by s²/(2ρ) (ρ: radius of curvature);
with one s per dot that changes the fitted axes, not the centre, and the axes are corrected by
s²/(2√(ab)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from tasks.vision.detection.parallel import one_blas_thread, over_dots, over_ranges
from tasks.vision.detection.stats import masked_median

N_PARAMS = 10  # cx, cy, a, b, θ, L_in, L_out, s, g_u, g_v
_COMPILED = {"cache": True, "nogil": True}  # compiled once per machine; other threads run meanwhile
_SQRT1_2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@dataclass
class EdgeFitParams:
    max_sigma_px: float = 1.5  # dots blurrier than this keep the ray fit (curvature, defocus)
    band_sigmas: float = 3.0  # pixels within band_sigmas · s + band_pad_px of the rim
    band_pad_px: float = 2.0
    iterations: int = 8
    outlier_iteration: int = 1  # drop outlier pixels here; test the centres' convergence from here on
    outlier_sigmas: float = 4.0
    max_shift_px: float = 0.25  # a fit that moves the centre further than this is not trusted
    blur_gradient: bool = True  # hold each dot's blur gradient from the image's blur field (module docstring)


@dataclass
class EdgeFits:
    """Pixel-level fits of K dots (px); ``ok`` False where the ray fit should stand."""

    centres: np.ndarray  # (K, 2)
    axes: np.ndarray  # (K, 2) semi-axes (major, minor), blur-curvature corrected
    theta: np.ndarray  # (K,)
    sigma: np.ndarray  # (K,) edge blur σ
    residual_rms: np.ndarray  # (K,) DN
    ok: np.ndarray  # (K,) bool


@njit(inline="always", **_COMPILED)
def _ellipse_distance(dx, dy, ia2, ib2, ct, st):
    """First-order signed distance d (px, positive outside) from the offset (dx, dy) to an ellipse
    centred at the origin (1/a², 1/b², cos θ, sin θ): d = (F − 1) F / |(u/a², v/b²)| with
    F² = (u/a)² + (v/b)² in the ellipse's axes (u, v). Returns d, u, v, u/a², v/b², F, 1/|∇F|/2."""
    u = dx * ct + dy * st
    v = dy * ct - dx * st
    ua = u * ia2
    vb = v * ib2
    f = math.sqrt(u * ua + v * vb)
    igr = 1.0 / max(math.sqrt(ua * ua + vb * vb), 1e-12)
    return (f - 1.0) * f * igr, u, v, ua, vb, f, igr


@njit(inline="always", **_COMPILED)
def _unpack(q):
    """One dot's parameters as the per-pixel model takes them (reciprocals once per dot, not per
    pixel): cx, cy, 1/a, 1/b, cos θ, sin θ, L_in, L_out, 1/s, g_u, g_v."""
    return (q[0], q[1], 1.0 / abs(q[2]), 1.0 / abs(q[3]), math.cos(q[4]), math.sin(q[4]), q[5], q[6],
            1.0 / max(abs(q[7]), 0.05), q[8], q[9])


@njit(inline="always", **_COMPILED)
def _pixel(px, py, cx, cy, ia, ib, ct, st, l_in, l_out, i_s, gu, gv, hu, hv, grad):
    """Grey level (DN) of one dot's model (as :func:`_unpack` gives it, with the blur's gradient
    (hu, hv) px/px held) at the pixel centre (px, py); writes ∂I/∂params into grad (10,)."""
    dx = px - cx
    dy = py - cy
    ia2 = ia * ia
    ib2 = ib * ib
    d, u, v, ua, vb, f, igr = _ellipse_distance(dx, dy, ia2, ib2, ct, st)
    # ∂d through F and |∇F| with respect to u, v, a and b; (cx, cy, θ) act through u and v
    k = (2.0 * f - 1.0) / max(f, 1e-12) * igr
    m = d * igr * igr
    d_u = ua * (k - m * ia2)
    d_v = vb * (k - m * ib2)
    # the blur here, s + e, and the part of its rim's inward shift (s + e)²/(2ρ) beyond the dot's
    # own s²/(2ρ) (that part only shrinks the axes): ρ = √(ab)
    s = 1.0 / i_s
    e = hu * dx + hv * dy
    sp = max(s + e, 0.05)
    i_rho = math.sqrt(ia * ib)
    corr = (sp * sp - s * s) * 0.5 * i_rho
    deff = d + corr
    gain = 1.0 + gu * dx + gv * dy
    z = -deff / sp
    p_in = 0.5 * math.erfc(-z * _SQRT1_2)  # Φ(z)
    level = l_out + (l_in - l_out) * p_in
    dens = gain * (l_in - l_out) * math.exp(-0.5 * z * z) * _INV_SQRT_2PI  # ∂I/∂z
    di_dd = -dens / sp
    dz_dc = i_rho - deff / (sp * sp)  # ∂z/∂(cx, cy) through the blur, per unit of (hu, hv)
    grad[0] = di_dd * (st * d_v - ct * d_u) + dens * hu * dz_dc - gu * level
    grad[1] = -di_dd * (st * d_u + ct * d_v) + dens * hv * dz_dc - gv * level
    grad[2] = di_dd * ua * u * ((2.0 * m * ia2 - k) * ia) + dens * 0.5 * ia * corr / sp
    grad[3] = di_dd * vb * v * ((2.0 * m * ib2 - k) * ib) + dens * 0.5 * ib * corr / sp
    grad[4] = di_dd * (v * d_u - u * d_v)
    grad[5] = gain * p_in
    grad[6] = gain - grad[5]
    grad[7] = dens * (deff / (sp * sp) - (sp - s) * i_rho / sp)
    grad[8] = dx * level
    grad[9] = dy * level
    return gain * level


@njit(**_COMPILED)
def _model_values(params, blur_gradient, x, y, value, jac, with_jacobian):
    grad = np.empty(N_PARAMS)
    for k in range(x.shape[0]):
        cx, cy, ia, ib, ct, st, l_in, l_out, i_s, gu, gv = _unpack(params[k])
        hu, hv = blur_gradient[k, 0], blur_gradient[k, 1]
        for i in range(x.shape[1]):
            value[k, i] = _pixel(x[k, i], y[k, i], cx, cy, ia, ib, ct, st, l_in, l_out, i_s, gu, gv, hu, hv, grad)
            if with_jacobian:
                jac[k, :, i] = grad


def dot_model(params: np.ndarray, x: np.ndarray, y: np.ndarray, *, with_jacobian: bool = False,
              blur_gradient: np.ndarray | None = None):
    """Grey levels (DN) of the model at pixel centres x, y (K, M) for parameters (K, 10);
    with_jacobian: also the (K, 10, M) derivatives (analytic), parameter-major so that each
    parameter's row is contiguous. blur_gradient: (K, 2) ∇s (px/px) held in each dot (default 0)."""
    params, x, y = (np.ascontiguousarray(v, dtype=float) for v in (params, x, y))
    value = np.empty(x.shape)
    jac = np.empty((x.shape[0], N_PARAMS, x.shape[1]) if with_jacobian else (0, N_PARAMS, 0))
    _model_values(params, _gradients(blur_gradient, len(params)), x, y, value, jac, with_jacobian)
    return (value, jac) if with_jacobian else value


def _gradients(blur_gradient: np.ndarray | None, n_dots: int) -> np.ndarray:
    """(K, 2) contiguous float blur gradients, zeros when None."""
    if blur_gradient is None:
        return np.zeros((n_dots, 2))
    return np.ascontiguousarray(blur_gradient, dtype=float).reshape(n_dots, 2)


def _normal_equations(params, x, y, z, w, blur_gradient=None):
    """Model values (K, M) at the pixels of weight 1 (NaN elsewhere: they are not evaluated), and
    per dot JᵀWJ (K, 10, 10), JᵀWr (K, 10) and the cost Σ w r² (K,), r = model − z; w holds 0/1
    pixel weights. The dots are shared among :func:`kernel_threads` threads (each dot's numbers
    are its own: the same whatever the split)."""
    n_dots, n_px = x.shape
    value = np.empty((n_dots, n_px))
    jtj = np.empty((n_dots, N_PARAMS, N_PARAMS))
    jtr = np.empty((n_dots, N_PARAMS))
    cost = np.zeros(n_dots)
    h = _gradients(blur_gradient, n_dots)
    over_ranges(lambda lo, hi: _normal_equations_into(params, h, x, y, z, w, lo, hi, value, jtj, jtr, cost), n_dots)
    return value, jtj, jtr, cost


@njit(**_COMPILED)
def _normal_equations_into(params, blur_gradient, x, y, z, w, lo, hi, value, jtj, jtr,
                           cost):  # pragma: no cover - compiled
    """:func:`_normal_equations` of dots lo … hi − 1, written into its outputs."""
    n_px = x.shape[1]
    grad = np.empty(N_PARAMS)
    # one dot's weighted Jacobian and residuals at a time: the products then go to BLAS
    jac_w = np.empty((N_PARAMS, n_px))
    res_w = np.empty(n_px)
    for k in range(lo, hi):
        cx, cy, ia, ib, ct, st, l_in, l_out, i_s, gu, gv = _unpack(params[k])
        hu, hv = blur_gradient[k, 0], blur_gradient[k, 1]
        for i in range(n_px):
            if w[k, i] == 0.0:
                value[k, i] = np.nan
                res_w[i] = 0.0
                jac_w[:, i] = 0.0
                continue
            val = _pixel(x[k, i], y[k, i], cx, cy, ia, ib, ct, st, l_in, l_out, i_s, gu, gv, hu, hv, grad)
            value[k, i] = val
            res_w[i] = val - z[k, i]
            jac_w[:, i] = grad
        jtj[k] = jac_w @ jac_w.T
        jtr[k] = jac_w @ res_w
        cost[k] = res_w @ res_w


@njit(**_COMPILED)
def _band_kernel(image, centres, axes, theta, width, half):
    """Each dot's pixels (window order) with |d| ≤ width: x, y, d in (K, M) rows packed to the widest
    band M, the padding repeating the row's first pixel (0 for a row without any), and counts."""
    h, w = image.shape
    n_dots = centres.shape[0]
    side = 2 * half + 1
    xs = np.empty((n_dots, side * side))
    ys = np.empty((n_dots, side * side))
    ds = np.empty((n_dots, side * side))
    counts = np.zeros(n_dots, np.int64)
    for k in range(n_dots):
        cx, cy = centres[k, 0], centres[k, 1]
        a, b = axes[k, 0], axes[k, 1]
        ia2, ib2 = 1.0 / (a * a), 1.0 / (b * b)
        ct, st = math.cos(theta[k]), math.sin(theta[k])
        # the band lies inside the ring of radii b − width − 1 … a + width + 1 (d is first order)
        r_in = max(b - width[k] - 1.0, 0.0)
        r_out = a + width[k] + 1.0
        ju0, iv0 = round(cx) - half, round(cy) - half
        for iv in range(iv0, iv0 + side):
            for ju in range(ju0, ju0 + side):
                if ju < 0 or ju >= w or iv < 0 or iv >= h:
                    continue
                dx, dy = ju - cx, iv - cy
                r2 = dx * dx + dy * dy
                if r2 < r_in * r_in or r2 > r_out * r_out:
                    continue
                d = _ellipse_distance(dx, dy, ia2, ib2, ct, st)[0]
                if abs(d) <= width[k]:
                    n = counts[k]
                    xs[k, n], ys[k, n], ds[k, n] = ju, iv, d
                    counts[k] = n + 1
    m = max(counts.max(), 1)
    for k in range(n_dots):
        first = 0 if counts[k] > 0 else -1
        for n in range(counts[k], m):
            if first < 0:
                xs[k, n], ys[k, n], ds[k, n] = 0.0, 0.0, 0.0
            else:
                xs[k, n], ys[k, n], ds[k, n] = xs[k, first], ys[k, first], ds[k, first]
    return xs[:, :m], ys[:, :m], ds[:, :m], counts


def _band_pixels(image: np.ndarray, centres, axes, theta, sigma, p: EdgeFitParams):
    """Pixel centres (K, M) of each dot's rim band, their grey levels, signed distances to the
    starting ellipse (px) and a validity mask. Rows are packed to the widest band; the padding
    repeats a band pixel of its row (finite values, masked out)."""
    width = p.band_sigmas * sigma + p.band_pad_px  # (K,) half-width of the band, px
    half = int(np.ceil(axes[:, 0] + width + 1).max())
    xs, ys, ds, counts = _band_kernel(np.ascontiguousarray(image), np.ascontiguousarray(centres, dtype=float),
                                      np.ascontiguousarray(axes, dtype=float), np.asarray(theta, dtype=float),
                                      np.asarray(width, dtype=float), half)
    mask = np.arange(xs.shape[1])[None, :] < counts[:, None]
    return xs, ys, image[ys.astype(int), xs.astype(int)].astype(float), ds, mask


def _levenberg_marquardt(q: np.ndarray, h: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                         mask: np.ndarray, p: EdgeFitParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched LM over the dots' parameters q (K, 10), blur gradients h (K, 2) held, on their band
    pixels; returns (q, pixel weights
    (K, M), cost (K,)). Each iteration evaluates the model and the normal equations once, at the
    trial point, and keeps them when the step is accepted. The outlier pass removes the dropped
    pixels' terms from the normal equations (evaluating those pixels only). From then on a dot
    whose centre step falls below 1e-5 px takes that step without another evaluation and leaves
    the active set, so the last iterations cost only the few dots that converge slowly; its
    returned cost is the one before that last step."""
    w = mask.astype(float)
    lam = np.full(len(q), 1e-3)
    value, jtj, jtr, cost = _normal_equations(q, x, y, z, w, h)
    active = np.ones(len(q), bool)
    eye = np.eye(N_PARAMS)
    for it in range(p.iterations):
        if it == p.outlier_iteration:  # drop outliers once the fit is close
            r = value - z  # every band pixel was evaluated so far
            scale = 1.4826 * masked_median(np.abs(r), mask)
            kept_px = mask & (np.abs(r) <= p.outlier_sigmas * np.maximum(scale, 0.5)[:, None])
            _, jtj_out, jtr_out, cost_out = _normal_equations(q, x, y, z, (mask & ~kept_px).astype(float), h)
            jtj, jtr, cost = jtj - jtj_out, jtr - jtr_out, cost - cost_out
            w = kept_px.astype(float)
        a = np.flatnonzero(active)
        if a.size == 0:
            break
        diag = np.einsum("kii->ki", jtj[a])
        # the floor keeps θ of a near-circular dot (no signal) from making the system singular
        diag = np.maximum(diag, 1e-9 * diag.max(axis=1, keepdims=True))
        lhs = jtj[a] + (lam[a, None] * diag)[:, :, None] * eye + 1e-12 * eye
        step = np.linalg.solve(lhs, -jtr[a][..., None])[..., 0]
        if it >= p.outlier_iteration:  # centres settled to 0.00001 px: take the step, stop
            settled = np.all(np.abs(step[:, :2]) < 1e-5, axis=1)
            q[a[settled]] += step[settled]
            active[a[settled]] = False
            a, step = a[~settled], step[~settled]
            if a.size == 0:
                break
        # while every dot is active, pass the arrays themselves, not gathered copies
        x_a, y_a, z_a, w_a, h_a = (x, y, z, w, h) if a.size == len(q) else (x[a], y[a], z[a], w[a], h[a])
        q_new = q[a] + step
        value_new, jtj_new, jtr_new, cost_new = _normal_equations(q_new, x_a, y_a, z_a, w_a, h_a)
        better = np.isfinite(cost_new) & (cost_new < cost[a])
        kept = a[better]
        q[kept], value[kept], jtj[kept], jtr[kept] = q_new[better], value_new[better], jtj_new[better], jtr_new[better]
        cost[kept] = cost_new[better]
        lam[a] = np.where(better, lam[a] / 10.0, lam[a] * 10.0)
    return q, w, cost


def blur_gradients(centres: np.ndarray, sigma: np.ndarray, at: np.ndarray) -> np.ndarray:
    """∇s (len(at), 2) px/px at the dots ``at`` of the image's smooth blur field.

    centres (K, 2) px and sigma (K,) px: every dot of the image and its edge blur. σ² is fitted
    over the image as a quadratic in position (a plane with fewer than 9 dots; no gradient with
    fewer than 3), once more without dots beyond 4 robust σ; ∇s = ∇σ²/(2σ) at each dot. On a
    plate tilted out of the focal plane the defocus blur grows with the distance from it, so the
    blur changes across each dot (s ∝ |Z − Z_focus|: a 20° tilt 15 mm off focus at 300 mm gives
    ∇s ≈ 1e-3 px/px for camera 1 at full size)."""
    ok = np.isfinite(centres).all(axis=1) & np.isfinite(sigma)
    out = np.zeros((len(at), 2))
    n = int(ok.sum())
    if n < 3:
        return out
    origin = centres[ok].mean(axis=0)
    scale = max(float(np.ptp(centres[ok], axis=0).max()), 1.0)

    def basis(uv):
        x, y = ((uv - origin) / scale).T
        cols = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if n >= 9 else [])
        return np.stack(cols, axis=1)

    a, s2 = basis(centres[ok]), sigma[ok] ** 2
    keep = np.ones(n, bool)
    for _ in range(2):
        coef = np.linalg.lstsq(a[keep], s2[keep], rcond=None)[0]
        r = s2 - a @ coef
        keep = np.abs(r) <= 4.0 * (1.4826 * np.median(np.abs(r[keep])) + 1e-12)
    coef = np.pad(coef, (0, 6 - len(coef)))
    x, y = ((centres[at] - origin) / scale).T
    grad_s2 = np.stack([coef[1] + 2 * coef[3] * x + coef[4] * y,
                        coef[2] + coef[4] * x + 2 * coef[5] * y], axis=1) / scale
    s_here = np.sqrt(np.clip(basis(centres[at]) @ coef[:a.shape[1]], 0.01, None))
    out[:] = np.nan_to_num(grad_s2 / (2.0 * s_here[:, None]))
    return out


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
    x, y, z, d0, mask = _band_pixels(image, centres[idx], axes[idx], theta[idx], s0, p)
    far = (2.0 * s0 + 1.0)[:, None]
    l_in = masked_median(z, mask & (d0 < -far))
    l_out = masked_median(z, mask & (d0 > far))
    q = np.column_stack([centres[idx], axes[idx], theta[idx], l_in, l_out, s0, np.zeros((idx.size, 2))])
    h = blur_gradients(centres, sigma, idx) if p.blur_gradient else np.zeros((idx.size, 2))
    with one_blas_thread():
        q, w, cost = over_dots(_levenberg_marquardt, idx.size, q, h, x, y, z, mask, p=p)
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
