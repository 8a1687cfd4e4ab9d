"""Sub-pixel ellipse fits of dot rims at full resolution, batched over all dots.

Each dot is searched in a circular ROI around its coarse ellipse: grey-level profiles are
sampled along rays from the dot centre (bilinear interpolation, one ``cv2.remap`` call for all
dots and rays), and the rim is located on each ray from the grey levels, not from pixel-quantised
contours:

* pass 1 (robust): the maximum of the polarity-signed derivative along each ray, refined by a
  parabola; a RANSAC ellipse over these points rejects rays hit by clutter, dust or a neighbour.
  The width of the derivative peak gives the edge blur σ of each dot.
* pass 2 (precise): a window of ±(``window_sigmas`` σ + pad) around the pass-1 rim on every ray;
  an area (first-moment) locator gives a start, then a per-ray least-squares fit of a blurred
  step I(t) = a + (b − a) Φ((t − t_e)/s) gives the rim t_e and the local blur s. For blurry rims
  the rays sample a ``level``× area-averaged copy of the image (same information, fewer samples).
* blur–curvature correction: blurring moves a curved rim inwards by s²/(2ρ) (ρ: radius of
  curvature); s varies across a dot on a tilted, defocused plate, so the shift is removed per ray.
* flat field: vignetting and uneven light multiply the image by a gain that changes across a dot.
  Along a ray a gain slope γ moves the fitted rim by about γ·s² (0.01 px for a 7 px blur near the
  edge of the field). One smooth gain field is fitted to the grey levels at the far ends of all
  rays of the image, and every profile is divided by it before the step fits.

* cast shadows: a shadow's edge across a dot multiplies the dot and the plate beside it by the
  same factor on one side. Where the dot is printed darker than the shadow (a light dot on a dark
  sheet, its lit part saturated, the rest at 0.35 of the light), the lit part's step down to the
  shadowed part is steeper than the shadowed rim: the candidate search finds the lit part alone,
  the derivative peaks of pass 1 lie on the shadow's edge, and the rim ellipse is the lit part's
  (centres 0.5–9 px off on renders). Dots lit unevenly or with a rough rim fit are fitted again on
  a log scale, where the shadow's edge is a smaller step than the rim on either side of it
  (:func:`lit_spread`, :func:`shadow_suspects`, :func:`log_levels`).
* neighbours: where a dot's rays reach a neighbour's blurred rim (a blur as wide as the gap between
  the dots), the neighbours are modelled as blurred printed ellipses fitted to the reached dots' rays
  together, the gain field is fitted again without their tails, edges beyond the dots (the sheet's)
  are fitted beyond the windows, all are taken out of the profiles, and the dot is fitted again
  (:func:`_neighbour_refits`, :mod:`tasks.vision.detection.neighbour_rims`); where the windows reach
  only sharp rims (their tails at the dots' rims under ``neighbour_tail_min`` of the contrast) the
  neighbours are straight blurred edges with their step fits' levels instead.

A least-squares ellipse (Sampson-weighted, with outlier rejection) through the rim points gives
the ellipse centre. Dots whose rim blur is at most 1.5 px are then refitted to the pixels
themselves (:mod:`tasks.vision.detection.edge_fit`): the rays' interpolation locks sharp rims to the
pixel grid. Units: px of the full-size image unless a name says ``level``; ray angles in
rad from +u towards +v.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.special import ndtr

from tasks.vision.detection.conics import (
    abs_sampson_distance,
    ellipse_params,
    ellipse_radius_along,
    fit_conic_lsq,
    is_ellipse,
    ransac_ellipse,
    ransac_samples,
)
from tasks.vision.detection.edge_fit import EdgeFitParams, fit_dot_edges
from tasks.vision.detection.neighbour_rims import (
    DotRims,
    ellipse_fill,
    fit_printed_dots,
    neighbour_shift,
    sharp_rims_shift,
    tails_at_rims,
    within_reach,
)
from tasks.vision.detection.parallel import over_dots, over_dots_compiled, resize_area
from tasks.vision.detection.ray_kernels import derivative_peaks, flatten, ray_coordinates
from tasks.vision.detection.stats import masked_median
from tasks.vision.detection.step_kernels import fitted_columns, gauss_newton_step, step_arguments

INTERP = cv2.INTER_LINEAR  # ray sampling (bilinear; cubic was not more accurate on rendered rims)


@dataclass
class SubpixelParams:
    pass1_rays: int = 32
    pass1_samples: int = 28  # samples per pass-1 ray (spread over the search band)
    ransac_hypotheses: int = 16
    rays_per_px: float = 0.5  # pass-2 rays per px of rim length (at the sampling level)
    min_rays: int = 48
    max_rays: int = 128
    window_sigmas: float = 2.5  # pass-2 window half-width = window_sigmas × σ + window_pad_px × level
    window_sigmas_blurry: float = 4.0
    window_pad_px: float = 1.5
    max_level: int = 4  # largest area-averaging factor for blurry rims …
    sigma_per_level: float = 1.25  # … level = ⌊median σ / sigma_per_level⌋
    erf_iterations: int = 2
    # inner_slope: a dot whose contrast changes by more than min_shading from its centre to its rim on
    # one side is refitted with a sloped inside (step_fit, shading); off by default: on real photographs
    # it did not agree better with a hand-fit-like rim truth (docs/detector-comparison.md)
    inner_slope: bool = False
    min_shading: float = 0.1
    shared_blur_iterations: int = 1  # then (t_e, a, b) refits with σ from the per-dot blur model
    max_refine: int = 3  # pass-2 repetitions at most (each re-centres the rays) …
    refine_bias_px: float = 0.002  # … repeated while shift·(σ/b)² of a dot exceeds this
    blur_curvature_correction: bool = True
    flat_field: bool = True  # divide the profiles by the image's gain field (see module docstring)
    # neighbours: dots whose rays meet a neighbour's blurred rim, by more than neighbour_min_shift of their
    # contrast, are fitted again (up to neighbour_iterations times) with it taken out (neighbour_rims)
    neighbour_iterations: int = 2
    neighbour_min_shift: float = 0.02
    # where a neighbour's blurred rim adds more than this fraction of the contrast at a reached dot's own
    # rim (0.1 DN on a 100 DN contrast, under 8 bits' quantisation noise of 0.29 DN), the neighbours are
    # fitted as blurred printed dots; below it they are modelled from their step fits (sharp dots: at most
    # 3.4e-4 on bench_stress --envelope 8,12; σ = 2 px of extra blur on 10–16 px dots: 4e-3 and more)
    neighbour_tail_min: float = 1e-3
    neighbour_model_rounds: int = 1  # per refit: printed-dot fits alternating with their neighbours' tails
    far_edges: bool = True  # and edges beyond the printed dots (the sheet's) taken out too (_far_edges) …
    far_edge_contrast: float = 0.1  # … where they step by more than this fraction of the dots' contrast
    pixel_edge_fit: bool = True  # then refit sharp dots to the pixels themselves (tasks.vision.detection.edge_fit)
    edge_fit: EdgeFitParams = field(default_factory=EdgeFitParams)
    # dots whose rays' bright ends differ by more than this in ln grey level (lit_spread; a shadow at
    # ≤ 0.78 of the light) are fitted again on a log scale (refine_ellipses)
    shadow_refit: bool = True
    shadow_spread: float = 0.25
    shadow_rms_px: float = 0.15  # … and so are dots whose rim residual exceeds this and …
    shadow_rms_ratio: float = 3.0  # … this many times the median dot's (shadow_suspects)
    shadow_keep: float = 0.5  # an unevenly lit suspect keeps its log-scale refit where that halves its rim residual
    # the pixel edge fit also on dark dots lit unevenly (lit_spread above shadow_spread) that keep their first
    # fit. Off: across a shadow's edge the sheet beside such a dot, its rim's bright side, steps by the
    # shadow's factor, and the edge fit's one level outside the rim pulls the dot towards the shadow (up to
    # 0.44 px on bench/bench_shadow_sweep.py's dark dots, 0.27 px without it); on by default, as on the garden
    # sets' unevenly lit dots the edge fit helps as often as it harms (docs/detector-comparison.md)
    uneven_dark_edge_fit: bool = True


@dataclass
class EllipseFits:
    """Full-resolution ellipse fits of K dots (px)."""

    centres: np.ndarray  # (K, 2) ellipse centres
    axes: np.ndarray  # (K, 2) semi-axes (major, minor)
    theta: np.ndarray  # (K,) major-axis angle, rad
    residual_rms_px: np.ndarray  # (K,) RMS distance of inlier rim points to the ellipse
    support: np.ndarray  # (K,) fraction of pass-2 rays that gave an inlier rim point
    edge_sigma_px: np.ndarray  # (K,) median edge blur σ from the step fits
    ok: np.ndarray  # (K,) bool
    shadowed: np.ndarray  # (K,) bool: refitted on a log scale under a cast shadow's edge (refine_ellipses)


@dataclass
class Crop:
    """``level``× area-averaged copy of the image region that holds every ROI.

    origin: (u0, v0) full-size px of the region's top-left pixel; full: (H, W) of the image.
    A full-size point u maps to (u − u0 + 0.5) / level − 0.5 in the crop.
    """

    data: np.ndarray
    origin: tuple[int, int]
    full: tuple[int, int]
    level: int = 1


def crop_rois(image: np.ndarray, centres: np.ndarray, reach: float, level: int = 1) -> Crop:
    """Crop covering every centre ± reach px, area-averaged by ``level`` (uint8, not copied at level 1).

    Rays sample it with bilinear interpolation rounded to whole grey levels: a uniform ±0.5 DN
    error (σ 0.29 DN) per sample, negligible beside sensor noise, and no float copy of the plate.
    """
    h, w = image.shape
    u0 = int(max(0, np.floor(centres[:, 0].min() - reach - 2)))
    v0 = int(max(0, np.floor(centres[:, 1].min() - reach - 2)))
    u1 = int(min(w, np.ceil(centres[:, 0].max() + reach + 3)))
    v1 = int(min(h, np.ceil(centres[:, 1].max() + reach + 3)))
    if level > 1:  # whole blocks only, so that the level grid stays aligned with the origin
        u1 = u0 + max(level, (u1 - u0) // level * level)
        v1 = v0 + max(level, (v1 - v0) // level * level)
        data = resize_area(image[v0:v1, u0:u1], level)
    else:
        data = image[v0:v1, u0:u1]
    return Crop(data, (u0, v0), (h, w), level)


def sample_profiles(crop: Crop, centres: np.ndarray, angles: np.ndarray, t: np.ndarray):
    """Grey levels along rays: centres (K, 2) px, angles (R,), t (K, R, T) px → (K, R, T) float32.

    Also returns the (K, R, T) mask of samples inside the full image.
    """
    k, r, n = t.shape
    mx, my, inside = ray_coordinates(np.ascontiguousarray(centres, dtype=float), np.cos(angles).astype(np.float32),
                                     np.sin(angles).astype(np.float32), np.ascontiguousarray(t),
                                     crop.origin, crop.full, crop.level)
    out = np.empty((k * r, n), crop.data.dtype)
    step = 30000  # cv2.remap map height must stay below SHRT_MAX
    for i in range(0, k * r, step):
        out[i : i + step] = cv2.remap(crop.data, mx[i : i + step], my[i : i + step], INTERP,
                                      borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(k, r, n).astype(np.float32), inside


def robust_ellipse_fit(x, y, w, origin, scale, iterations: int = 1):
    """LSQ ellipses (K sets) with iterative rejection beyond 4 robust σ.

    x, y, w: (K, N) px and validity; origin (K, 2), scale (K,) px for normalisation. Returns
    (conic (K, 6) in normalised coordinates, inlier mask (K, N), distances (K, N) px).
    """
    xn = (x - origin[:, 0:1]) / scale[:, None]
    yn = (y - origin[:, 1:2]) / scale[:, None]
    wts = w.astype(float)
    conic = fit_conic_lsq(xn, yn, wts, sampson_iterations=1)
    for _ in range(iterations):
        d = abs_sampson_distance(conic, xn, yn) * scale[:, None]
        mad = masked_median(d, (wts > 0) & np.isfinite(d), default=1.0)
        thr = np.maximum(4.0 * 1.4826 * mad, 0.05)
        wts = w * (d < thr[:, None])
        conic = fit_conic_lsq(xn, yn, wts, sampson_iterations=1)
    d = abs_sampson_distance(conic, xn, yn) * scale[:, None]
    return conic, wts > 0, d


def step_fit(prof, t, t0, i_in, i_out, sigma0, iterations: int, fixed_sigma: np.ndarray | None = None,
             slope: np.ndarray | None = None, free_slope: bool = False):
    """Per-ray least-squares fit of a blurred step I(t) = a + (b − a) Φ((t − t_e) / s).

    prof, t: (K, R, T) grey levels and their distances along each ray; t0, i_in, i_out: (K, R)
    starting values; sigma0: (K,) starting blur (px). Gauss–Newton on (t_e, a, b, log s), or on
    (t_e, a, b) with s = ``fixed_sigma`` (K, R), all rays at once (arrays laid out (T, K·R); each
    iteration is two compiled loops over rows of rays, :mod:`tasks.vision.detection.step_kernels`,
    around numpy's float32 tanh and exp). Unlike the area locator,
    which weights every sample of the window equally, this weights samples by how much they tell
    about the edge position, so the noise of the flat parts of the window hardly enters t_e.
    slope: (K, R) a slope m of the dot's level towards the rim (grey levels / px), the model then
    I(t) + m (t − t_e)(1 − Φ) (a dot darker on one side, :func:`odd_part`); free_slope: m is
    fitted too (starting from ``slope`` or 0).
    Returns (t_e (K, R), s (K, R) px, converged (K, R), a (K, R), b (K, R), m (K, R)): a and b
    are the fitted grey levels inside (at the rim) and outside the rim, m the slope.
    """
    f32 = np.float32
    shape = t0.shape
    n_t = prof.shape[-1]
    y = np.ascontiguousarray(prof.reshape(-1, n_t).T, dtype=f32)  # (T, N)
    tt = np.ascontiguousarray(t.reshape(-1, n_t).T, dtype=f32)
    te = t0.reshape(-1).astype(f32)
    a = i_in.reshape(-1).astype(f32)
    b = i_out.reshape(-1).astype(f32)
    if fixed_sigma is None:
        ls = np.broadcast_to(np.log(np.maximum(sigma0, 0.3))[:, None], shape).reshape(-1).astype(f32)
    else:
        ls = np.log(np.maximum(fixed_sigma, 0.3)).reshape(-1).astype(f32)
    m = np.zeros_like(te) if slope is None else slope.reshape(-1).astype(f32)
    columns = fitted_columns(fixed_sigma is None, free_slope)
    dt, z, tanh_z, gauss_z = (np.empty(y.shape, f32) for _ in range(4))
    for _ in range(iterations):
        s = np.exp(ls)
        inv_s = f32(1.0) / s
        step_arguments(tt, te, inv_s, dt, z, tanh_z, gauss_z)
        np.tanh(tanh_z, out=tanh_z)
        np.exp(gauss_z, out=gauss_z)
        gauss_newton_step(y, dt, z, tanh_z, gauss_z, a, b, m, te, ls, s, inv_s, columns)
    te = te.astype(float).reshape(shape)
    s = np.exp(ls.astype(float)).reshape(shape)
    good = np.isfinite(te) & np.isfinite(s) & (np.abs(te - t0) < 3.0 * np.maximum(sigma0[:, None], 1.0))
    return (np.where(good, te, t0), np.where(good, s, np.nan), good, a.astype(float).reshape(shape),
            b.astype(float).reshape(shape), m.astype(float).reshape(shape))


def odd_slope(m: np.ndarray, ok: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """(K, 2): per dot, (m_x, m_y) of the fit m ≈ m_x cos + m_y sin of the rays' inner slopes m
    (K, R) over the ``ok`` rays (angles ``ang`` (R,)): the dot's shading gradient (grey levels /
    px). Shading across a dot gives slopes odd in the ray angle; the blurred rim's curvature and
    an ellipse's changing radius give even ones."""
    ok = ok & np.isfinite(m)
    c, sn = np.cos(ang)[None, :], np.sin(ang)[None, :]
    w = ok.astype(float)
    mw = np.where(ok, m, 0.0)
    scc, sss, scs = (w * c * c).sum(1), (w * sn * sn).sum(1), (w * c * sn).sum(1)
    bc, bs = (mw * c).sum(1), (mw * sn).sum(1)
    det = scc * sss - scs ** 2
    good = det > 1e-6 * np.maximum(scc * sss, 1e-12)
    mx = np.where(good, (bc * sss - bs * scs) / np.where(good, det, 1.0), 0.0)
    my = np.where(good, (bs * scc - bc * scs) / np.where(good, det, 1.0), 0.0)
    return np.stack([mx, my], axis=1)


def blur_model(s: np.ndarray, ok: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """Smooth per-dot blur: σ²(θ) = c0 + c1 cos θ + c2 sin θ fitted to per-ray σ (K, R) → σ² (K, R).

    A plate tilted out of focus has a blur that changes linearly across each dot; single rays
    measure σ noisily, the three-term model averages them.
    """
    basis = np.stack([np.ones_like(ang), np.cos(ang), np.sin(ang)], axis=1)  # (R, 3)
    w = ok.astype(float)
    s2 = np.where(ok, s, 0.0) ** 2
    a = np.einsum("kr,ri,rj->kij", w, basis, basis) + 1e-9 * np.eye(3)
    b = np.einsum("kr,ri,kr->ki", w, basis, s2)
    coef = np.linalg.solve(a, b[..., None])[..., 0]  # (K, 3)
    return np.clip(coef @ basis.T, 0.01, None)


@dataclass
class GainField:
    """log g(u, v) up to a constant: a plane or quadratic in normalised image position.

    coef: (5,) coefficients of u, v, u², uv, v² (the last three zero for a plane); origin (2,)
    and scale px normalise the position. A zero field (no correction) has coef zeros(5).
    """

    coef: np.ndarray
    origin: np.ndarray
    scale: float

    @classmethod
    def flat(cls) -> GainField:
        return cls(np.zeros(5), np.zeros(2), 1.0)

    def gradient(self, uv: np.ndarray) -> np.ndarray:
        """∇g/g (N, 2) 1/px at image points uv (N, 2) px."""
        c = self.coef
        x = (uv[:, 0] - self.origin[0]) / self.scale
        y = (uv[:, 1] - self.origin[1]) / self.scale
        gx = c[0] + 2 * c[2] * x + c[3] * y
        gy = c[1] + c[3] * x + 2 * c[4] * y
        return np.stack([gx, gy], axis=1) / self.scale


def fit_gain_field(prof: np.ndarray, t: np.ndarray, ok: np.ndarray, cen: np.ndarray, ang: np.ndarray,
                   n_end: int = 2) -> GainField:
    """The image's smooth gain field (vignetting × illumination gradient) around the dots.

    Vignetting and the illumination gradient multiply the dots and the plate alike and change
    smoothly over the image. The last ``n_end`` samples at each end of every ray lie about
    3.5–4 blur σ from the rim (window_sigmas + pad, unless the dot's size or the gap to its
    neighbour clips the window), where the grey level is the dot's or the plate's own whatever
    the blur. Their logarithm is fitted, over all dots at once, by one level per end (dot, plate)
    plus a quadratic in image position (a plane with fewer than 9 dots). Per-dot planes were too
    noisy (3 DN of sample noise gives ∼2e-5 /px per dot, against a vignetting gradient of
    3e-5 /px), and levels nearer the rim mix in the blur, which changes across a tilted,
    defocused dot. Weights ∝ grey level (shot noise on a logarithm); one refit drops samples
    beyond 4 robust σ (dust, a neighbour's tail). prof, t: (K, R, T) grey levels and px along
    the rays; ok: (K, R) rays to use; cen: (K, 2) ray origins px; ang: (R,) rad.
    """
    k = prof.shape[0]
    cs, sn = np.cos(ang)[None, :, None], np.sin(ang)[None, :, None]
    ends = (slice(0, n_end), slice(-n_end, None))
    v = np.concatenate([prof[..., e] for e in ends], axis=2).astype(float)  # (K, R, 2n)
    tt = np.concatenate([t[..., e] for e in ends], axis=2)
    outer = np.zeros(v.shape, bool)
    outer[..., n_end:] = True
    use = np.broadcast_to(ok[..., None], v.shape) & (v > 0.5)
    if k < 3 or use.sum() < 20:
        return GainField.flat()
    origin = cen.mean(axis=0)
    scale = max(float(np.ptp(cen, axis=0).max()), 50.0)
    xn = ((cen[:, 0, None, None] + tt * cs - origin[0]) / scale)[use]
    yn = ((cen[:, 1, None, None] + tt * sn - origin[1]) / scale)[use]
    on = outer[use]
    cols = [~on, on, xn, yn] + ([xn * xn, xn * yn, yn * yn] if k >= 9 else [])
    a = np.stack(cols, axis=1).astype(float)  # (N, P)
    lv = np.log(v[use])
    w = v[use]
    keep = np.ones(len(lv), bool)
    for _ in range(2):
        wk = w * keep  # normal equations: (N, ≤7) with normalised columns, well conditioned
        coef = np.linalg.solve(a.T @ (a * wk[:, None]) + 1e-12 * np.eye(a.shape[1]), a.T @ (wk * lv))
        r = lv - a @ coef
        keep = np.abs(r) < 4.0 * (1.4826 * np.median(np.abs(r[keep])) + 1e-12)
    return GainField(np.pad(coef[2:], (0, 7 - len(coef))), origin, scale)


def flatten_profiles(prof: np.ndarray, t: np.ndarray, cen: np.ndarray, ang: np.ndarray,
                     gain: GainField) -> np.ndarray:
    """Profiles (K, R, T) divided by the gain relative to each dot centre, 1 + ∇g/g·(p − c)."""
    return flatten(np.ascontiguousarray(prof, dtype=np.float32), np.ascontiguousarray(t, dtype=float),
                   np.ascontiguousarray(gain.gradient(cen)), np.cos(ang), np.sin(ang))


def curvature_correction(s2: np.ndarray, ang: np.ndarray, axes: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Outward shift (K, R) px that moves blurred-rim points back onto the sharp rim.

    Blurring a disk by a Gaussian of σ moves its 50 % contour inwards by σ²/(2ρ), ρ the local
    radius of curvature. A uniform σ only shrinks the ellipse, but on a tilted, defocused plate σ
    changes across a dot, and the uneven shift moves the centre. s2: (K, R) σ² per ray (from
    :func:`blur_model`); ρ is the ellipse's curvature radius where ray θ meets it.
    """
    phi = ang[None, :] - theta[:, None]
    ea, eb = axes[:, 0:1], axes[:, 1:2]
    tpar = np.arctan2(ea * np.sin(phi), eb * np.cos(phi))  # parametric angle of the hit point
    rho_c = (ea**2 * np.sin(tpar) ** 2 + eb**2 * np.cos(tpar) ** 2) ** 1.5 / (ea * eb)
    return s2 / (2.0 * rho_c)


def _pass1_profiles(crop, centres, axes, theta, out_lim, coarse_factor, p):
    """Pass-1 rays of K dots, all at once (one ``cv2.remap``, which spreads itself over OpenCV's
    threads): (grey levels (K, R1, T1), t (K, R1, T1) px, inside (K, R1, T1), ray angles (R1,),
    search band (K,) ± px)."""
    ang = np.arange(p.pass1_rays) * (2 * np.pi / p.pass1_rays)
    rho0 = ellipse_radius_along(centres, axes, theta, ang)  # (K, R1)
    band = np.maximum(np.maximum(4.0, 2.0 * coarse_factor), 0.35 * axes[:, 1])  # (K,) ± px
    u = np.linspace(-1.0, 1.0, p.pass1_samples)
    t = rho0[:, :, None] + u[None, None, :] * band[:, None, None]
    t = np.clip(t, 0.25 * axes[:, 1, None, None], out_lim[:, None, None])
    prof, inside = sample_profiles(crop, centres, ang, t)
    return prof, t, inside, ang, band


def _pass1(prof, t, inside, band, centres, axes, theta, samples, *, ang, sign, p):
    """Robust rim ellipses and blur σ per dot (see module docstring) from the pass-1 rays
    (:func:`_pass1_profiles`); samples: (K, H, 5) RANSAC draws (:func:`ransac_samples`)."""
    tp, peak, fwhm = derivative_peaks(np.ascontiguousarray(prof), np.ascontiguousarray(t), np.ascontiguousarray(inside),
                                      sign, 2.0 * band / (p.pass1_samples - 1))
    good = np.isfinite(peak) & (peak > 0)
    med_peak = masked_median(peak, good, default=np.inf)
    valid = good & (peak > 0.3 * med_peak[:, None])
    sigma = np.clip(masked_median(fwhm / 2.355, valid, default=1.0), 0.5, None)
    x = centres[:, 0:1] + np.cos(ang)[None, :] * tp
    y = centres[:, 1:2] + np.sin(ang)[None, :] * tp
    scale = np.maximum(axes[:, 0], 1.0)
    xn = (x - centres[:, 0:1]) / scale[:, None]
    yn = (y - centres[:, 1:2]) / scale[:, None]
    thr = np.maximum(1.0, 0.03 * axes[:, 0]) / scale
    inl = ransac_ellipse(xn, yn, valid, thr, samples)
    conic = fit_conic_lsq(xn, yn, inl.astype(float), sampson_iterations=1)
    ok = is_ellipse(conic) & (inl.sum(axis=1) >= 10)
    c1, ax1, th1 = ellipse_params(conic, centres, scale)
    bad = ~ok | ~np.isfinite(c1).all(axis=1) | ~np.isfinite(ax1).all(axis=1)
    c1[bad], ax1[bad], th1[bad] = centres[bad], axes[bad], theta[bad]  # pass 2 starts from coarse
    return c1, ax1, th1, sigma


def _step_fits(prof, t, te, i_in, i_out, sigma, contrast, med_c, inside, *, ang, p, free_slope: bool):
    """The two step fits of pass 2 (σ free, then σ from the per-dot blur model), optionally with a
    sloped dot level (:func:`step_fit`): (t_e, converged, s, s² of the blur model, usable, fitted levels
    inside and outside the rim) (K, R)."""
    te, s, conv, lev_in, lev_out, _ = step_fit(prof, t, te, i_in, i_out, sigma, p.erf_iterations,
                                               free_slope=free_slope)
    usable = inside.all(axis=2) & conv & (contrast > 0.5 * med_c[:, None])
    s2 = blur_model(s, usable, ang)
    if p.shared_blur_iterations:
        # refit with σ from the smooth per-dot model: t_e no longer trades off against a noisy s
        te, _, conv, lev_in, lev_out, _ = step_fit(prof, t, te, lev_in, lev_out, sigma,
                                                   p.shared_blur_iterations + int(free_slope) * p.erf_iterations,
                                                   fixed_sigma=np.sqrt(s2), free_slope=free_slope)
    return te, conv, s, s2, usable, lev_in, lev_out


def shading(prof, t, te, s, ok, ang, contrast, minor_axes) -> np.ndarray:
    """(K,) how much each dot's contrast changes from its centre to its rim on its darker side, as a
    fraction of the contrast ``contrast`` (K,): per ray the slope m of a straight line through the
    samples of the dot's inside (more than 2 s (K, R) inside the rim t_e (K, R)), then the part of
    m odd in the ray angle (:func:`odd_slope`, over the ``ok`` rays with 3 such samples or more)
    times the minor semi-axis (K,)."""
    w = (t < (te - 2.0 * s)[..., None]).astype(np.float64)
    n = w.sum(axis=2)
    tm = (w * t).sum(axis=2) / np.maximum(n, 1)
    pm = (w * prof).sum(axis=2) / np.maximum(n, 1)
    dt = (t - tm[..., None]) * w
    var = (dt * dt).sum(axis=2)
    m = np.where(var > 0, (dt * (prof - pm[..., None])).sum(axis=2) / np.where(var > 0, var, 1.0), np.nan)
    grad = odd_slope(m, ok & (n >= 3), ang)
    return np.hypot(grad[:, 0], grad[:, 1]) * minor_axes / np.where(np.isfinite(contrast), contrast, np.inf)


def _window_half_widths(sigma, axs, gap_ratio, lv, p):
    """(K,) px: the pass-2 windows' half-widths round the rim, ±(k σ + pad) (see :func:`_pass2_profiles`)."""
    ksig = p.window_sigmas + (p.window_sigmas_blurry - p.window_sigmas) * np.clip(sigma - 1.0, 0.0, 1.0)
    half_w = ksig * sigma + p.window_pad_px * lv  # (K,)
    half_w = np.minimum(half_w, np.maximum(1.0 * axs[:, 1], 2.0 * lv))
    return np.minimum(half_w, np.maximum(1.6 * gap_ratio * axs[:, 1], 2.0 * lv))


def _pass2_profiles(crop, cen, axs, ths, sigma, gap_ratio, p):
    """Pass-2 rays of K dots: (grey levels (K, R, T), t (K, R, T) px along the rays, samples inside
    the image (K, R, T), ray angles (R,), window half-widths (K,) px, window centres (K, R) px).
    The ray count follows the median dot, the window length the widest window."""
    lv = crop.level
    a_med = float(np.median(axs[:, 0]))
    n_rays = int(np.clip(round(p.rays_per_px * 2 * np.pi * a_med / lv), p.min_rays, p.max_rays))
    ang = np.arange(n_rays) * (2 * np.pi / n_rays)
    # window: ±(k σ + pad); k grows from window_sigmas (sharp rims, where extra flat samples only
    # add interpolation artefacts) to window_sigmas_blurry for σ ≥ 2 px (blurry rims, whose
    # tails are not Gaussian and need the wider view)
    half_w = _window_half_widths(sigma, axs, gap_ratio, lv, p)
    n2 = int(np.ceil(2 * half_w.max() / lv)) + 1
    u2 = np.linspace(-1.0, 1.0, n2)
    rho = ellipse_radius_along(cen, axs, ths, ang)  # (K, R)
    t = rho[:, :, None] + u2[None, None, :] * half_w[:, None, None]
    prof, inside = sample_profiles(crop, cen, ang, t)
    return prof, t, inside, ang, half_w, rho


def _pass2_rims(prof, t, inside, cen, axs, ths, sigma, half_w, rho, shift=None, *, sign, ang, gain, p):
    """Precise rim points of K dots from their pass-2 rays (:func:`_pass2_profiles`): (x, y,
    valid (K, R), s (K, R), median fitted grey level inside and outside the rim over the valid rays
    (K,)). gain: the image's gain field (used with ``p.flat_field``); shift: (K, R, T) grey levels the
    neighbours' blurred rims add to the (flattened) profiles, taken out before the fits
    (:func:`tasks.vision.detection.neighbour_rims.neighbour_shift`)."""
    if p.flat_field:
        prof = flatten_profiles(prof, t, cen, ang, gain)
    if shift is not None:
        prof = prof - shift
    n2 = t.shape[2]
    ne = max(2, n2 // 6)
    i_in = prof[..., :ne].mean(axis=2)
    i_out = prof[..., -ne:].mean(axis=2)
    contrast = (i_out - i_in) * sign  # (K, R)
    med_c = masked_median(contrast, contrast > 0, default=np.inf)
    # area (first-moment) start: t_e = t_start + ∫ (1 − normalised profile) dt
    span = np.where(np.abs(i_out - i_in) > 1e-6, i_out - i_in, 1.0)
    g = 1.0 - np.clip((prof - i_in[..., None]) / span[..., None], -0.25, 1.25)
    dts = (2 * half_w / (n2 - 1))[:, None]
    te = t[..., 0] + (g[..., 1:] + g[..., :-1]).sum(axis=2) * 0.5 * dts
    te, conv, s, s2, usable, lev_in, lev_out = over_dots_compiled(_step_fits, len(te), prof, t, te, i_in, i_out, sigma,
                                                                  contrast, med_c, inside, ang=ang, p=p,
                                                                  free_slope=False)
    if p.inner_slope:  # dots darker on one side: refit them with a sloped inside, which would move t_e
        shaded = shading(prof, t, te, np.sqrt(s2), usable, ang, med_c, axs[:, 1]) > p.min_shading
        if shaded.any():
            k = np.flatnonzero(shaded)
            fits = _step_fits(prof[k], t[k], te[k], i_in[k], i_out[k], sigma[k], contrast[k], med_c[k], inside[k],
                              ang=ang, p=p, free_slope=True)
            for full, part in zip((te, conv, s, s2, usable, lev_in, lev_out), fits, strict=True):
                full[k] = part
    valid = inside.all(axis=2) & conv & (contrast > 0.5 * med_c[:, None])
    valid &= np.abs(te - rho) < half_w[:, None] - np.minimum(np.sqrt(s2), half_w[:, None] / 2)
    if p.blur_curvature_correction:
        te = te + curvature_correction(s2, ang, axs, ths)
    x = cen[:, 0:1] + np.cos(ang)[None, :] * te
    y = cen[:, 1:2] + np.sin(ang)[None, :] * te
    return x, y, valid, s, masked_median(lev_in, valid), masked_median(lev_out, valid)


def _rim_ellipses(x, y, valid, s, c0, a0, *, n_rays):
    """Robust LSQ ellipses through K dots' rim points (x, y, valid (K, R) px; rim blur s (K, R) px;
    ray origins c0 (K, 2) px and semi-axes a0 (K, 2) px): (fitted, centres (K, 2), semi-axes (K, 2),
    angles (K,), residual RMS (K,) px, median s (K,) px, support (K,): inlier rays / n_rays)."""
    scale = np.maximum(a0[:, 0], 1.0)
    conic, inl, dist = robust_ellipse_fit(x, y, valid, c0, scale)
    okp = is_ellipse(conic) & (inl.sum(axis=1) >= 12)
    cn, an, tn = ellipse_params(conic, c0, scale)
    okp &= np.isfinite(cn).all(axis=1) & np.isfinite(an).all(axis=1)
    rms = np.sqrt((np.where(inl, dist, 0.0) ** 2).sum(axis=1) / np.maximum(inl.sum(axis=1), 1))
    s_med = masked_median(s, valid & np.isfinite(s))
    return okp, cn, an, tn, rms, s_med, inl.sum(axis=1) / n_rays


def rim_reach_px(major_semi_axes_px: np.ndarray, gap_ratio: float) -> np.ndarray:
    """How far from a dot's centre (px) the rim rays look: beyond the rim by up to 60 % of the
    radius, and never past 80 % of the gap to the neighbouring dot (``gap_ratio``: (pitch −
    diameter) / diameter)."""
    return (1.0 + min(0.8 * gap_ratio, 0.6)) * np.asarray(major_semi_axes_px, dtype=float)


def lit_spread(prof: np.ndarray, inside: np.ndarray, sign: float) -> np.ndarray:
    """(K,) how unevenly each dot is lit: the 10–90 % range over its rays of the logarithm of the
    grey level at the rays' bright end (the plate's side for dark dots, the dot's for light ones;
    the mean of the last or first sixth of each pass-2 window). prof: (K, R, T) grey levels along
    the rays; inside: (K, R, T) samples in the image; sign +1 for dark dots, −1 for light ones.

    A cast shadow across a dot multiplies the dot and the plate beside it by the same factor on
    one side of its edge: the bright end's level steps by that factor between rays (0.35 of the
    light: 1.05). Vignetting and a light gradient change it by a few per cent across a dot.
    """
    ne = max(2, prof.shape[2] // 6)
    end = prof[..., -ne:] if sign > 0 else prof[..., :ne]
    level = np.log(np.maximum(end.mean(axis=2), 1.0))
    use = inside.all(axis=2)
    n = use.sum(axis=1)
    ranked = np.sort(np.where(use, level, 1e30), axis=1)  # the rays in the image first

    def quantile(f: float) -> np.ndarray:  # linear between order statistics, as np.percentile
        pos = f * np.maximum(n - 1, 0)
        lo = np.floor(pos).astype(int)
        hi = np.minimum(lo + 1, np.maximum(n - 1, 0))
        take = np.take_along_axis
        return take(ranked, lo[:, None], 1)[:, 0] * (1 - (pos - lo)) + take(ranked, hi[:, None], 1)[:, 0] * (pos - lo)

    return np.where(n >= 8, quantile(0.9) - quantile(0.1), 0.0)


def log_levels(prof: np.ndarray) -> np.ndarray:
    """ln of grey levels (float32, levels below 1 DN taken as 1). On a log scale a cast shadow's
    edge is a step of ln(shadow factor) (≥ −1.05 for a shadow at 0.35 of the light), below a
    printed dot's rim (ln of the dot-to-plate ratio, 2 for 30 against 220 DN) on either side of
    the shadow: the rim locators then take the rim, not the shadow's edge, and a step fit across
    both is pulled less."""
    return np.log(np.maximum(prof, 1.0)).astype(np.float32)


def _rim_passes(image, centres, axes, theta, sign, gap_ratio, coarse_factor, p, rng, *, log_scale=False,
                blur_px=None):
    """Pass 1, the pass-2 repetitions and the neighbours' refits of :func:`refine_ellipses` on K dots
    (see the module docstring); log_scale: every profile through :func:`log_levels`, without the gain
    field or the neighbours' rims (modelled in grey levels); blur_px: as :func:`refine_ellipses`'s.
    Returns (centres (K, 2), semi-axes (K, 2), angles (K,), fitted (K,), residual RMS (K,) px,
    support (K,), median rim blur (K,) px, :func:`lit_spread` of the first pass 2 (K,), seconds
    spent fitting ellipses)."""
    clock = time.perf_counter
    k = len(centres)
    out_lim = rim_reach_px(axes[:, 0], gap_ratio)
    reach = float(out_lim.max()) + 4.0 * coarse_factor
    crop1 = crop_rois(image, centres, reach)
    t0 = clock()
    if blur_px is None:
        samples = ransac_samples(k, p.pass1_rays, p.ransac_hypotheses, rng)
        prof1, t1, inside1, ang1, band1 = _pass1_profiles(crop1, centres, axes, theta, out_lim, coarse_factor, p)
        if log_scale:
            prof1 = log_levels(prof1)
        cen, axs, ths, sigma = over_dots(_pass1, k, prof1, t1, inside1, band1, centres, axes, theta, samples,
                                         ang=ang1, sign=sign, p=p)
    else:
        cen, axs, ths, sigma = centres, axes, theta, np.clip(np.asarray(blur_px, dtype=float), 0.5, None)
    t_fit = clock() - t0
    level = int(np.clip(np.floor(np.median(sigma) / p.sigma_per_level), 1, p.max_level))
    crop2 = crop1 if level == 1 else crop_rois(image, centres, reach, level)
    cen, axs, ths = cen.copy(), axs.copy(), ths.copy()
    ok = np.zeros(k, bool)
    rms = np.full(k, np.nan)
    support = np.zeros(k)
    s_med = np.full(k, np.nan)
    spread = np.zeros(k)
    todo = np.arange(k)
    gain = GainField.flat() if log_scale else None
    lev_in, lev_out = np.full(k, np.nan), np.full(k, np.nan)
    for repeat in range(p.max_refine):
        c0, a0, h0, s0 = cen[todo], axs[todo], ths[todo], sigma[todo]
        prof, t, inside, ang, half_w, rho = _pass2_profiles(crop2, c0, a0, h0, s0, gap_ratio, p)
        if repeat == 0:  # every dot
            spread = lit_spread(prof, inside, sign)
        if log_scale:
            prof = log_levels(prof)
        if p.flat_field and gain is None:  # fitted on the first pass, which sees every dot
            gain = fit_gain_field(prof, t, inside.all(axis=2), c0, ang)
        x, y, valid, s, lev_in[todo], lev_out[todo] = over_dots(_pass2_rims, len(todo), prof, t, inside, c0, a0, h0,
                                                                s0, half_w, rho, sign=sign, ang=ang, gain=gain, p=p)
        t0 = clock()
        okp, cn, an, tn, rms_p, s_med_p, support_p = over_dots(_rim_ellipses, len(todo), x, y, valid, s, c0, a0,
                                                               n_rays=len(ang))
        shift = np.linalg.norm(np.where(okp[:, None], cn - c0, 0.0), axis=1)
        upd = todo[okp]
        cen[upd], axs[upd], ths[upd] = cn[okp], an[okp], tn[okp]
        ok[todo], rms[todo], s_med[todo], support[todo] = okp, rms_p, s_med_p, support_p
        t_fit += clock() - t0
        # rays cast from an off-centre point cross a strongly blurred, curved rim obliquely, with
        # an error of order shift·(σ/b)²: dots where that can still matter get another pass
        oblique = shift * (s0 / np.maximum(an[:, 1], 1.0)) ** 2
        todo = todo[okp & (oblique > p.refine_bias_px)]
        if len(todo) == 0:
            break
    if p.neighbour_iterations and not log_scale and ok.sum() >= 2:
        t0 = clock()
        fits = (cen, axs, ths, ok, rms, support, s_med, lev_in, lev_out)
        _neighbour_refits(image, crop2, fits, sigma, gap_ratio, sign, gain, p)
        t_fit += clock() - t0
    return cen, axs, ths, ok, rms, support, s_med, spread, t_fit


def _neighbour_refits(image, crop, fits, sigma, gap_ratio, sign, gain, p):
    """Fit again, in place, the dots whose pass-2 windows reach a neighbour's blurred dot, with the
    neighbours taken out of their profiles (:mod:`tasks.vision.detection.neighbour_rims`), up to
    ``p.neighbour_iterations`` times. fits: the (K,)-leading arrays of :func:`_rim_passes` (centres,
    semi-axes, angles, fitted, residual RMS, support, median rim blur, levels inside and outside the
    rim), updated in place; sigma: (K,) pass-1 blur px; gain: the image's gain field.

    Where no neighbour's blurred rim reaches a dot's own rim by more than ``p.neighbour_tail_min`` of
    the contrast (:func:`~tasks.vision.detection.neighbour_rims.tails_at_rims`: sharp dots, whose
    windows reach only the far ends of the neighbours' tails) the neighbours are modelled from their
    step fits (levels inside and outside the rim, rim blur and rim ellipse), rebuilt before each
    refit. Else each pass samples the reached dots' rays and, ``p.neighbour_model_rounds`` times,
    refits the gain field to the rays' ends without the neighbours' tails (else its smooth field takes
    up part of them and the model takes them out twice) and the blurred printed dots to every reached
    dot's rays at once (:func:`~tasks.vision.detection.neighbour_rims.fit_printed_dots`: one ink and one
    plate level, one scale of the dots' rim blurs and one of their rims); then takes the other dots and
    the edges beyond them (:func:`_far_edges`) out of the profiles and fits the rims again. Where the
    printed fit's levels come out of the dots' polarity the dots are modelled from their step fits."""
    cen, axs, ths, ok, rms, support, s_med, lev_in, lev_out = fits
    # a dot whose fit failed is no model of its rim: left out as a neighbour (NaN level)
    model = DotRims(cen, axs, ths, s_med, np.where(ok, lev_in, np.nan), lev_out)
    near = np.flatnonzero(ok & within_reach(model, _window_half_widths(sigma, axs, gap_ratio, crop.level, p)))
    if not len(near):
        return
    printed = tails_at_rims(model, near) > p.neighbour_tail_min
    model = DotRims(*(np.array(v, dtype=float, copy=True) for v in (cen, axs, ths, s_med, model.level_in, lev_out)))
    for i in range(p.neighbour_iterations):
        if not printed and i:  # the step fits' model, rebuilt from the refitted dots
            model = DotRims(cen, axs, ths, s_med, np.where(ok, lev_in, np.nan), lev_out)
            near = np.flatnonzero(ok & within_reach(model, _window_half_widths(sigma, axs, gap_ratio, crop.level, p)))
            if not len(near):
                return
        prof, t, inside, ang, half_w, rho = _pass2_profiles(crop, cen[near], axs[near], ths[near], sigma[near],
                                                            gap_ratio, p)
        if printed:
            model.centres[near], model.theta[near] = cen[near], ths[near]
        shift = (neighbour_shift if printed else sharp_rims_shift)(model, near, cen[near], ang, t)
        reached = np.abs(shift).max(axis=(1, 2)) > p.neighbour_min_shift * np.abs(lev_out - lev_in)[near]
        if not reached.any():
            return
        if printed:
            model, shift, gain = _printed_model(image, crop, fits, model, near, prof, t, inside, ang, half_w, rho,
                                                shift, sign, gain, p)
        x, y, valid, s, li, lo = _pass2_rims(prof[reached], t[reached], inside[reached], cen[near[reached]],
                                             axs[near[reached]], ths[near[reached]], sigma[near[reached]],
                                             half_w[reached], rho[reached], shift[reached], sign=sign, ang=ang,
                                             gain=gain, p=p)
        todo = near[reached]
        okp, cn, an, tn, rms_p, s_med_p, support_p = _rim_ellipses(x, y, valid, s, cen[todo], axs[todo],
                                                                   n_rays=len(ang))
        upd = todo[okp]
        cen[upd], axs[upd], ths[upd] = cn[okp], an[okp], tn[okp]
        rms[upd], s_med[upd], support[upd], lev_in[upd], lev_out[upd] = (
            rms_p[okp], s_med_p[okp], support_p[okp], li[okp], lo[okp])


def _printed_model(image, crop, fits, model, near, prof, t, inside, ang, half_w, rho, shift, sign, gain, p):
    """The neighbours of the dots ``near`` as blurred printed ellipses fitted to their rays, with the gain
    field refitted without their tails and the edges beyond them (:func:`_far_edges`): (model, the grey
    levels (K, R, T) they add at the samples t, gain field). See :func:`_neighbour_refits`."""
    cen, axs, ths, ok, _, _, s_med, lev_in, lev_out = fits
    use = inside.all(axis=2)
    for _ in range(p.neighbour_model_rounds):  # the printed dots and the gain field without them, in turn
        if p.flat_field and len(near) >= 3:
            gain = fit_gain_field(prof - shift, t, use, cen[near], ang)
        flat = flatten_profiles(prof, t, cen[near], ang, gain) if p.flat_field else prof
        every = slice(None, None, 2)  # half the rays: the levels, blurs and rim scales hardly need more
        fitted = fit_printed_dots(DotRims(cen, np.where(ok[:, None], axs, np.nan), ths, s_med, lev_in, lev_out),
                                  near, flat[:, every], ang[every], t[:, every], use[:, every])
        if not sign * (fitted.level_out[0] - fitted.level_in[0]) > 0:
            break
        model = DotRims(fitted.centres, fitted.axes, fitted.theta, fitted.sigma,
                        np.where(ok, fitted.level_in, np.nan), fitted.level_out)
        shift = neighbour_shift(model, near, cen[near], ang, t)
    if p.flat_field and len(near) >= 3:
        gain = fit_gain_field(prof - shift, t, use, cen[near], ang)
    if p.far_edges:
        shift = shift + _far_edges(image, crop.level, model, near, ang, t, half_w, rho, gain, p)
    return model, shift, gain


def _far_edges(image, level, model, near, ang, t, half_w, rho, gain, p):
    """(K, R, T) grey levels that edges beyond the printed dots (the sheet's edge, a shadow's, clutter)
    add at the pass-2 samples t (K, R, T) px of the dots ``near`` (K,) along rays at angles ang (R,).

    Under a blur as wide as the gap the sheet's edge a few mm beyond the outer dots is within reach of
    their rays as much as their neighbours are: on the stress set's sheet (3 mm of paper beyond the
    outer dots' rims, then a background 125 DN darker) it moves the outer dots towards the grid's
    middle, by as much as the neighbours moved them away. Beyond each window (half-widths half_w (K,),
    centred on rho (K, R) px) the rays are sampled over 3 blurs more, the printed dots
    (``model``, :class:`DotRims` with :func:`~tasks.vision.detection.neighbour_rims.fit_printed_dots`'
    levels) are taken out, and where what is left steps by more than ``p.far_edge_contrast`` of the
    dots' contrast, away from any other dot, a blurred step (its width fitted) is fitted to it; its
    tail inside the window is returned. gain: the image's gain field."""
    k, r = t.shape[:2]
    sig = model.sigma[near]
    contrast = abs(float(model.level_in[near[0]] - model.level_out[near[0]]))
    step = (t[:, :, 1] - t[:, :, 0])[..., None]
    n_far = int(np.clip(np.ceil(3.0 * np.nanmax(sig) / np.nanmin(step)), 4, 24))
    t_far = (rho + half_w[:, None])[..., None] + step * np.arange(1, n_far + 1)
    cen = model.centres[near]
    crop = crop_rois(image, cen, float(np.nanmax(t_far)), level)
    prof, inside = sample_profiles(crop, cen, ang, t_far)
    if p.flat_field:
        prof = flatten_profiles(prof, t_far, cen, ang, gain)
    u = cen[:, 0, None, None] + np.cos(ang)[None, :, None] * t_far
    v = cen[:, 1, None, None] + np.sin(ang)[None, :, None] * t_far
    own = ellipse_fill(u - cen[:, 0, None, None], v - cen[:, 1, None, None], model.axes[near, 0, None, None],
                       model.axes[near, 1, None, None], model.theta[near, None, None], sig[:, None, None])
    others = neighbour_shift(model, near, cen, ang, t_far)
    a, b = model.level_in[near, None, None], model.level_out[near, None, None]
    left = prof - b - (a - b) * own - others  # the levels the printed dots do not explain
    clear = inside.all(axis=2) & (np.abs(others).max(axis=2) < p.far_edge_contrast * contrast)
    ne = max(2, n_far // 4)
    lo, hi = left[..., :ne].mean(axis=2), left[..., -ne:].mean(axis=2)
    cand = clear & (np.abs(hi - lo) > p.far_edge_contrast * contrast)
    out = np.zeros(t.shape, np.float32)
    if not cand.any():
        return out
    te0 = np.broadcast_to(t_far[..., n_far // 2], (k, r))
    te, s_e, conv, a_e, b_e, _ = step_fit(left, t_far, te0, lo, hi, sig, p.erf_iterations + 2)
    # the edge's own blur, not the dots': where the sheet's edge is sharper than the dots' fitted blur, a
    # tail as wide as theirs reaches into the window further than the edge's and is taken out too far
    s_e = np.nan_to_num(s_e, nan=1.0)
    edge = cand & conv & (np.abs(b_e - a_e) > p.far_edge_contrast * contrast) & (te > t_far[..., 0] - sig[:, None])
    tail = (b_e - a_e)[..., None] * ndtr((t - te[..., None]) / s_e[..., None])
    return np.where(edge[..., None], tail, 0.0).astype(np.float32)


def shadow_suspects(spread: np.ndarray, rms: np.ndarray, ok: np.ndarray, p: SubpixelParams) -> np.ndarray:
    """(K,) dots that may have a cast shadow's edge across them: lit unevenly (``spread``, :func:`lit_spread`,
    above ``p.shadow_spread``), or fitted (``ok``) with a rim residual ``rms`` (px) above
    ``p.shadow_rms_px`` and ``p.shadow_rms_ratio`` times the median of the fitted dots (a rim fitted to
    the lit part of a dot and the shadow's edge is no ellipse; a dot found as its lit part only has
    its rays' windows there, and the bright ends of its rays are all lit)."""
    med = masked_median(rms[None, :], (ok & np.isfinite(rms))[None, :], default=np.inf)[0]
    rough = ok & (rms > np.maximum(p.shadow_rms_px, p.shadow_rms_ratio * med))
    return (spread > p.shadow_spread) | rough


def shadow_starts(axes: np.ndarray, theta: np.ndarray, fitted_axes: np.ndarray, fitted_theta: np.ndarray,
                  trusted: np.ndarray, shadowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starting semi-axes (S, 2) px and angles (S,) rad of the ``shadowed`` dots' refit (S of K).

    A dot cut by a shadow's edge may have been found as its lit part only, a coarse ellipse much
    narrower than the dot: where its minor semi-axis is below 3/4 of the median fitted one of the
    ``trusted`` dots (of all dots if fewer than 3 are), it starts from that median ellipse.
    axes, theta: the coarse ellipses (K, 2), (K,); fitted_axes, fitted_theta: the first fits.
    """
    ref = trusted if trusted.sum() >= 3 else np.ones(len(axes), bool)
    med_axes = np.median(fitted_axes[ref], axis=0)
    med_theta = float(np.median(fitted_theta[ref]))
    a, th = axes[shadowed].copy(), theta[shadowed].copy()
    narrow = a[:, 1] < 0.75 * med_axes[1]
    a[narrow], th[narrow] = med_axes, med_theta
    return a, th


def refine_ellipses(image: np.ndarray, centres: np.ndarray, axes: np.ndarray, theta: np.ndarray,
                    dark_dots: bool, gap_ratio: float, coarse_factor: int,
                    params: SubpixelParams | None = None, seed: int = 0,
                    timings: dict | None = None, blur_px: np.ndarray | None = None) -> EllipseFits:
    """Refine coarse ellipses (already mapped to full-size px) to sub-pixel ellipse fits.

    gap_ratio: (pitch − diameter) / diameter of the plate, bounding how far outside the rim a ray
    may look before it reaches the neighbouring dot. coarse_factor: downsampling factor of the
    coarse search (sets the pass-1 search band). timings: optional dict that receives the seconds
    spent in "rim_sampling" (profiles and rim location) and "ellipse_fitting". blur_px: (K,) edge blur σ
    px of ellipses known to be close already (a fitted neighbour's): pass 1 is then skipped and pass 2
    starts from the ellipses given.

    Dots that may have a cast shadow's edge across them (:func:`shadow_suspects`) are fitted again
    on a log scale (:func:`log_levels`) from their coarse ellipses (:func:`shadow_starts`); a dot
    keeps that ray fit where its rim residual drops (an unevenly lit one: below ``params.shadow_keep``
    times the first), without the pixel edge fit (whose model has no shadow), and is marked in
    ``EllipseFits.shadowed``. With ``params.uneven_dark_edge_fit`` off, a dark dot lit unevenly that
    keeps its first fit keeps it without the pixel edge fit too (see :class:`SubpixelParams`).
    """
    p = params or SubpixelParams()
    rng = np.random.default_rng(seed)
    clock = time.perf_counter
    t_begin = clock()
    sign = 1.0 if dark_dots else -1.0
    cen, axs, ths, ok, rms, support, s_med, spread, t_fit = _rim_passes(image, centres, axes, theta, sign, gap_ratio,
                                                                        coarse_factor, p, rng, blur_px=blur_px)
    shadowed = np.zeros(len(centres), bool)
    suspect = shadow_suspects(spread, rms, ok, p) if p.shadow_refit else shadowed
    if suspect.any():
        sel = np.flatnonzero(suspect)
        a_sel, th_sel = shadow_starts(axes, theta, axs, ths, ok & ~suspect, suspect)
        *fit, _, t_log = _rim_passes(image, centres[sel], a_sel, th_sel, sign, gap_ratio, coarse_factor, p,
                                     np.random.default_rng(seed + 1), log_scale=True)
        # fitted, and nearer an ellipse than before; much nearer where the dot is lit unevenly (light
        # falling off across a dot, common in photographs, is no shadow edge: a refit on a log scale
        # there is another estimator, not a better one)
        keep = np.where(spread[sel] > p.shadow_spread, p.shadow_keep, 1.0)
        better = fit[3] & (~ok[sel] | (fit[4] < keep * rms[sel]))
        for full, part in zip((cen, axs, ths, ok, rms, support, s_med), fit, strict=True):
            full[sel[better]] = part[better]
        shadowed[sel[better]] = True
        t_fit += t_log
    plain = ok & ~shadowed
    if not p.uneven_dark_edge_fit:
        plain &= ~(dark_dots & suspect & (spread > p.shadow_spread))
    if p.pixel_edge_fit and plain.any():
        t0 = clock()
        sel = np.flatnonzero(plain)
        edges = fit_dot_edges(image, cen[sel], axs[sel], ths[sel], s_med[sel], p.edge_fit)
        use = sel[edges.ok]
        cen[use], axs[use], ths[use] = edges.centres[edges.ok], edges.axes[edges.ok], edges.theta[edges.ok]
        t_fit += clock() - t0
    if timings is not None:
        timings["ellipse_fitting"] = timings.get("ellipse_fitting", 0.0) + t_fit
        timings["rim_sampling"] = timings.get("rim_sampling", 0.0) + clock() - t_begin - t_fit
    return EllipseFits(cen, axs, ths, rms, support, s_med * 1.0, ok, shadowed)
