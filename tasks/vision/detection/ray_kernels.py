"""Compiled per-sample loops of the rim rays (:mod:`tasks.vision.detection.subpixel`).

:func:`ray_coordinates` gives the image coordinates of every ray sample for ``cv2.remap`` and
whether it lies inside the image; :func:`derivative_peaks` finds pass 1's rim on each ray. Both
do, per sample, the floating-point operations of the numpy form in the same order and precision
(float32 where it was float32), so their results are the same to every bit, without the dozen
(K, R, T) temporaries. Units: px; ray angles enter through their float32 cosines and sines.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_COMPILED = {"cache": True, "nogil": True}


@njit(**_COMPILED)
def ray_coordinates(centres, cos_a, sin_a, t, origin, size, level):  # pragma: no cover - compiled
    """Sample positions in a crop for ``cv2.remap``: (map x (K·R, T) float32, map y (K·R, T)
    float32, inside the image (K, R, T)).

    centres (K, 2) px; cos_a, sin_a (R,) float32; t (K, R, T) px along the rays; origin (u0, v0)
    full-size px of the crop's top-left pixel; size (H, W) of the full image; level the crop's
    area-averaging factor (a full-size u maps to (u − u0 + 0.5) / level − 0.5)."""
    k_dots, n_rays, n_t = t.shape
    u0, v0 = origin
    h, w = size
    mx = np.empty((k_dots * n_rays, n_t), np.float32)
    my = np.empty((k_dots * n_rays, n_t), np.float32)
    inside = np.empty((k_dots, n_rays, n_t), np.bool_)
    half = np.float32(0.5)
    lv = np.float32(level)
    for k in range(k_dots):
        cu = np.float32(centres[k, 0] - u0)
        cv = np.float32(centres[k, 1] - v0)
        for r in range(n_rays):
            row = k * n_rays + r
            cs, sn = cos_a[r], sin_a[r]
            for i in range(n_t):
                tt = np.float32(t[k, r, i])
                x = cu + cs * tt
                y = cv + sn * tt
                inside[k, r, i] = (x >= -u0) and (x <= w - 1 - u0) and (y >= -v0) and (y <= h - 1 - v0)
                if level > 1:
                    x = (x + half) / lv - half
                    y = (y + half) / lv - half
                mx[row, i] = x
                my[row, i] = y
    return mx, my, inside


@njit(**_COMPILED)
def derivative_peaks(prof, t, inside, sign, step):  # pragma: no cover - compiled
    """Pass-1 rim per ray: (t_peak (K, R) px, peak height (K, R), FWHM of the peak (K, R) px).

    prof (K, R, T) float32 grey levels at t (K, R, T) px, inside (K, R, T); sign +1 for dark dots,
    −1 for light ones; step (K,) sample spacing px. The polarity-signed central difference
    (per px; −inf where a sample is outside the image or t was clipped, so that it repeats) is
    maximised along each ray (the first maximum) and refined by a parabola through it and its
    neighbours (offset within ± ½ sample); the FWHM counts the differences above half the peak."""
    k_dots, n_rays, n_t = prof.shape
    n_d = n_t - 2
    tp = np.empty((k_dots, n_rays))
    peak = np.empty((k_dots, n_rays))
    fwhm = np.empty((k_dots, n_rays))
    d = np.empty(n_d)
    sgn = np.float32(sign)
    for k in range(k_dots):
        for r in range(n_rays):
            pr, tr, ins = prof[k, r], t[k, r], inside[k, r]
            j = 0
            for i in range(n_d):
                dt = tr[i + 2] - tr[i]
                if dt > 1e-6 and ins[i + 2] and ins[i]:
                    d[i] = np.float64((pr[i + 2] - pr[i]) * sgn) / max(dt, 1e-6)
                else:
                    d[i] = -np.inf
                if d[i] > d[j]:
                    j = i
            jc = min(max(j, 1), n_d - 2)
            d0, dm, dp = d[jc], d[jc - 1], d[jc + 1]
            pk = d[j]
            den = dm - 2 * d0 + dp
            off = 0.5 * (dm - dp) / den if (den < 0 and np.isfinite(den)) else 0.0
            off = min(max(off, -0.5), 0.5)
            tp[k, r] = tr[jc + 1] + off * step[k] if j == jc else tr[j + 1]
            count = 0
            for i in range(n_d):
                if d[i] > 0.5 * pk and np.isfinite(d[i]):
                    count += 1
            peak[k, r] = pk
            fwhm[k, r] = count * step[k]
    return tp, peak, fwhm


@njit(**_COMPILED)
def flatten(prof, t, gradient, cos_a, sin_a):  # pragma: no cover - compiled
    """Profiles (K, R, T) float32 divided by the gain relative to each ray's origin,
    1 + ∇g/g·(p − c) clipped to [0.5, 2] (float32): gradient (K, 2) ∇g/g 1/px at the origins,
    t (K, R, T) px along the rays at angles with cosines and sines cos_a, sin_a (R,)."""
    k_dots, n_rays, n_t = prof.shape
    out = np.empty_like(prof)
    for k in range(k_dots):
        for r in range(n_rays):
            along = gradient[k, 0] * cos_a[r] + gradient[k, 1] * sin_a[r]
            for i in range(n_t):
                rel = 1.0 + t[k, r, i] * along
                if rel < 0.5:
                    rel = 0.5
                elif rel > 2.0:
                    rel = 2.0
                out[k, r, i] = prof[k, r, i] / np.float32(rel)
    return out
