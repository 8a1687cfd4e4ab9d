"""Compiled Gauss–Newton iterations of the blurred-step fits (:func:`tasks.vision.detection.subpixel.step_fit`).

One iteration for N rays of T samples, laid out (T, N) so that every loop over rays is a row of
contiguous float32 values that the compiler turns into vector instructions:

1. :func:`step_arguments`: t − t_e, z = (t − t_e)/s and the arguments of the tanh of Φ(z) and
   of the exponential of φ(z); the caller applies numpy's own (vectorised float32) ``tanh`` and
   ``exp`` to them in place.
2. :func:`gauss_newton_step`: the Jacobian columns ∂/∂(t_e, a, b, log s, m) and the residuals per
   sample, their products summed over each ray's samples in sample order (float32), the float64
   normal equations with a 1e-9 ridge, their solution by Gaussian elimination (no pivoting: they
   are symmetric positive definite; a pivot below 1e-12 is taken as 1e-12), and the clipped update.

Every number is the one the numpy form of the same iteration gives (same operations, same order,
no fused multiply–adds), so the fits do not change. Units: px along the rays, grey levels (DN).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_COMPILED = {"cache": True, "nogil": True}
PHI_C1 = np.float32(0.7978845608)  # Φ(z) ≈ ½ + ½ tanh(z (C1 + C2 z²)): |error| < 2e-4, odd about 0
PHI_C2 = np.float32(0.0356774081)  # (no location bias)
GAUSS = np.float32(0.3989422804014327)  # 1/√(2π)
# which of the five columns (t_e, a, b, log s, m) the P fitted parameters are, by (free σ, free slope)
_COLUMNS = {(True, False): (0, 1, 2, 3), (False, False): (0, 1, 2), (True, True): (0, 1, 2, 3, 4),
            (False, True): (0, 1, 2, 4)}


def fitted_columns(free_sigma: bool, free_slope: bool) -> np.ndarray:
    """Indices into (t_e, a, b, log s, m) of the parameters a step fit solves for."""
    return np.array(_COLUMNS[(free_sigma, free_slope)], np.int64)


@njit(**_COMPILED)
def step_arguments(tt, te, inv_s, dt, z, tanh_arg, gauss_arg):  # pragma: no cover - compiled
    """(T, N) float32 outputs: t − t_e, z = (t − t_e)/s, z (C1 + C2 z²) and −z²/2 from the samples'
    t (T, N), t_e (N,) and 1/s (N,)."""
    half = np.float32(-0.5)
    for i in range(tt.shape[0]):
        t_i, dt_i, z_i, th_i, g_i = tt[i], dt[i], z[i], tanh_arg[i], gauss_arg[i]
        for k in range(t_i.shape[0]):
            d = t_i[k] - te[k]
            zz = d * inv_s[k]
            dt_i[k] = d
            z_i[k] = zz
            th_i[k] = zz * (PHI_C1 + (PHI_C2 * zz) * zz)
            g_i[k] = (half * zz) * zz


@njit(**_COMPILED)
def _columns(y, dt, z, tanh_z, gauss_z, a, b, m, inv_s, cols):  # pragma: no cover - compiled
    """cols (6, T, N): the Jacobian columns ∂I/∂(t_e, a, b, log s, m) of the model
    I = a + (b − a) Φ + m (t − t_e)(1 − Φ) and the residual y − I, per sample."""
    one = np.float32(1.0)
    half = np.float32(0.5)
    c = b - a
    for i in range(y.shape[0]):
        j0, j1, j2, j3, j4, res = cols[0, i], cols[1, i], cols[2, i], cols[3, i], cols[4, i], cols[5, i]
        y_i, dt_i, z_i, th_i, g_i = y[i], dt[i], z[i], tanh_z[i], gauss_z[i]
        for k in range(y_i.shape[0]):
            ph = half + half * th_i[k]
            de = g_i[k] * GAUSS
            d = dt_i[k]
            mdt = m[k] * d
            res[k] = y_i[k] - ((a[k] + c[k] * ph) + mdt * (one - ph))
            cd = c[k] * de - mdt * de
            j0[k] = (-cd) * inv_s[k] - m[k] * (one - ph)
            j1[k] = one - ph
            j2[k] = ph
            j3[k] = (-cd) * z_i[k]
            j4[k] = d * (one - ph)


@njit(**_COMPILED)
def _sum_products(u, v, out):  # pragma: no cover - compiled
    """out (N,) += Σ_i u[i] v[i] over the samples i of (T, N) u, v, in sample order (float32)."""
    for i in range(u.shape[0]):
        u_i, v_i = u[i], v[i]
        for k in range(out.shape[0]):
            out[k] += u_i[k] * v_i[k]


@njit(**_COMPILED)
def _solve(m, v, x):  # pragma: no cover - compiled
    """x (P, N) = m⁻¹ v per ray for m (P, P, N), v (P, N) float64 (both overwritten)."""
    n_p, n = v.shape
    piv = np.empty(n)
    for i in range(n_p):
        m_ii = m[i, i]
        for k in range(n):
            piv[k] = m_ii[k] if abs(m_ii[k]) > 1e-12 else 1e-12
        for j in range(i + 1, n_p):
            m_ji, v_j, v_i = m[j, i], v[j], v[i]
            f = m_ji / piv
            for col in range(i, n_p):
                m_jc, m_ic = m[j, col], m[i, col]
                for k in range(n):
                    m_jc[k] -= f[k] * m_ic[k]
            for k in range(n):
                v_j[k] -= f[k] * v_i[k]
    for i in range(n_p - 1, -1, -1):
        acc = v[i].copy()
        for j in range(i + 1, n_p):
            m_ij, x_j = m[i, j], x[j]
            for k in range(n):
                acc[k] -= m_ij[k] * x_j[k]
        m_ii, x_i = m[i, i], x[i]
        for k in range(n):
            x_i[k] = acc[k] / (m_ii[k] if abs(m_ii[k]) > 1e-12 else 1e-12)


@njit(**_COMPILED)
def _finite_f32(x):  # pragma: no cover - compiled
    """float64 → float32, NaN → 0 (±inf and values beyond float32's range → ±inf)."""
    return np.float32(0.0) if np.isnan(x) else np.float32(x)


@njit(**_COMPILED)
def gauss_newton_step(y, dt, z, tanh_z, gauss_z, a, b, m, te, ls, s, inv_s, columns):  # pragma: no cover
    """One Gauss–Newton step for N rays, in place on the (N,) float32 t_e, a, b, log s and m.

    y, dt, z: (T, N) float32 grey levels, t − t_e, (t − t_e)/s; tanh_z, gauss_z: (T, N) the tanh
    and the exponential of :func:`step_arguments`' last two outputs; s, inv_s: (N,) blur and 1/s
    px; columns: :func:`fitted_columns`. The t_e step is clipped to ± max(1, s) px (at most one
    blur width or 1 px), the log s step to ± 0.7."""
    n_t, n = y.shape
    n_p = columns.shape[0]
    cols = np.empty((6, n_t, n), np.float32)
    _columns(y, dt, z, tanh_z, gauss_z, a, b, m, inv_s, cols)
    jtj = np.empty((n_p, n_p, n))
    jtr = np.empty((n_p, n))
    sums = np.empty(n, np.float32)
    for p in range(n_p):
        sums[:] = 0.0
        _sum_products(cols[columns[p]], cols[5], sums)
        jtr[p] = sums
        for q in range(p, n_p):
            sums[:] = 0.0
            _sum_products(cols[columns[p]], cols[columns[q]], sums)
            jtj[p, q] = sums
            jtj[q, p] = sums
        jtj[p, p] += 1e-9
    step = np.empty((n_p, n))
    _solve(jtj, jtr, step)
    one = np.float32(1.0)
    for k in range(n):
        lim = s[k] if (s[k] > one or np.isnan(s[k])) else one
        st0 = step[0, k]
        if not (np.isnan(st0) or np.isnan(lim)):
            st0 = min(max(st0, -np.float64(lim)), np.float64(lim))
        te[k] = te[k] + _finite_f32(st0)
        a[k] = a[k] + _finite_f32(step[1, k])
        b[k] = b[k] + _finite_f32(step[2, k])
        for p in range(3, n_p):
            if columns[p] == 3:
                ls[k] = ls[k] + min(max(_finite_f32(step[p, k]), np.float32(-0.7)), np.float32(0.7))
            else:
                m[k] = m[k] + _finite_f32(step[p, k])
