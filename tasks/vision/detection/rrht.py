"""Revised random Hough transform (RRHT) for dot rims on the coarse edge map.

Steps (seed paper §4.1), all in coarse-image px:

1. *Gradient threshold*: only edge pixels with |∇I| ≥ ``grad_threshold`` may seed a sample.
2. *Gradient-guided sampling*: from a randomly drawn seed pixel p1, walk along the direction in
   which the dot interior lies (−∇I for dark dots, +∇I for light ones) over the diameters
   allowed, and take the first edge pixel p2 whose gradient is antiparallel to p1's. p1 and p2
   are then opposite ends of a diameter, so one sample gives centre (p1+p2)/2 and radius
   |p2−p1|/2 — unlike the three blind random points of the classic RHT, which rarely fall on the
   same circle in a cluttered image.
3. *Accumulation*: the (centre) votes go to a 2-px grid; peaks of the 3×3-summed grid are
   candidate circles with the mean radius of their votes.
4. *Candidate screening, dynamic accumulator threshold*: a peak needs at least a fixed fraction
   of the votes a full rim of its radius would collect at the sampling rate used (so the
   threshold scales with the theoretical circumference 2πr).
5. *True circle determination and least squares*: edge pixels met along rays from the
   candidate centre are fitted with a least-squares ellipse (a circle seen in perspective); the
   candidate is kept when the fraction of its rim covered by edge pixels — on-rim edge pixels
   over the theoretical circumference — reaches ``min_rim_ratio``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from tasks.vision.detection.conics import abs_sampson_distance, ellipse_params, fit_conic_lsq, is_ellipse
from tasks.vision.detection.edges import N_DIRECTIONS, EdgeMap, direction_codes, pixels_where


@dataclass
class RRHTParams:
    n_samples: int = 3000  # seed pixels drawn per image
    antiparallel_cos: float = 0.85  # |angle| between opposite rim gradients ≤ ~32°
    bin_px: int = 2  # accumulator bin size (coarse px)
    min_votes: int = 3
    vote_fraction: float = 0.15  # of the votes a complete rim would get
    n_rays: int = 48  # rays per candidate for the least-squares fit and rim ratio
    min_rim_ratio: float = 0.6
    max_candidates: int = 600


@dataclass
class CoarseCircles:
    """Circles found on the coarse image (px of the coarse image)."""

    centres: np.ndarray  # (K, 2) ellipse centres (u, v)
    axes: np.ndarray  # (K, 2) semi-axes (major, minor)
    theta: np.ndarray  # (K,) major-axis angle, rad
    votes: np.ndarray  # (K,) accumulator votes
    rim_ratio: np.ndarray  # (K,) covered fraction of the rim

    @staticmethod
    def empty() -> CoarseCircles:
        z = np.zeros((0, 2))
        return CoarseCircles(z, z.copy(), np.zeros(0), np.zeros(0), np.zeros(0))

    def __len__(self) -> int:
        return len(self.centres)

    def subset(self, keep: np.ndarray) -> CoarseCircles:
        """The circles selected by a (K,) bool mask or an index array."""
        return CoarseCircles(self.centres[keep], self.axes[keep], self.theta[keep], self.votes[keep],
                             self.rim_ratio[keep])


_COMPILED = {"cache": True, "nogil": True}  # compiled once per machine (see tasks.vision.detection.edge_fit)


@njit(**_COMPILED)
def _code_matches(code: int, target: int, tol: int, n_codes: int) -> bool:
    """An edge pixel (code ≠ 255) whose gradient direction is within ``tol`` of ``n_codes`` codes per
    turn (a power of two) of ``target``."""
    if code == 255:
        return False
    d = (code - target) & (n_codes - 1)  # the modulo, without a division
    return min(d, n_codes - d) <= tol


@njit(**_COMPILED)
def _walk_to_opposite_rim(us, vs, inward, opposite, t_all, flat, wp, pad, tol, n_codes):  # pragma: no cover
    """Per seed pixel (us, vs (S,) int, unit ``inward`` (S, 2)): the first diameter of ``t_all``
    (T,) px whose far end, rounded to a pixel of the padded direction-code map ``flat`` (row
    width ``wp``, padding ``pad``), is an edge pixel whose code is within ``tol`` of
    ``opposite`` (S,) (``n_codes`` codes per turn); NaN where none is."""
    n = us.shape[0]
    d = np.full(n, np.nan)
    for i in range(n):
        for j in range(t_all.shape[0]):
            t = t_all[j]
            pu = np.int64(np.rint(us[i] + inward[i, 0] * t)) + pad
            pv = np.int64(np.rint(vs[i] + inward[i, 1] * t)) + pad
            if _code_matches(np.int64(flat[pv * wp + pu]), np.int64(opposite[i]), tol, n_codes):
                d[i] = t
                break
    return d


@njit(**_COMPILED)
def _first_rim_points(centres, radii, cs, sn, steps, ray_code, flat, wp, h, w, pad, n_codes):  # pragma: no cover
    """Per candidate (centres (K, 2), radii (K,)) and ray (cos, sin (R,)): the first pixel at
    ``steps`` (T,) × radius along the ray that is an edge pixel of the padded direction-code map
    ``flat`` with a code within 45° of ``ray_code`` (R,; ``n_codes`` codes per turn): (x, y (K, R) px,
    found (K, R)); where none is found, the ray's first pixel."""
    k, nr, nt = centres.shape[0], cs.shape[0], steps.shape[0]
    x = np.empty((k, nr))
    y = np.empty((k, nr))
    has = np.zeros((k, nr), np.bool_)
    for i in range(k):
        for r in range(nr):
            for j in range(nt):
                rad = radii[i] * steps[j]
                pu = np.int64(np.int32(np.rint(centres[i, 0] + cs[r] * rad)))
                pv = np.int64(np.int32(np.rint(centres[i, 1] + sn[r] * rad)))
                if j == 0:
                    x[i, r], y[i, r] = pu, pv
                if -pad <= pu < w + pad and -pad <= pv < h + pad:
                    code = np.int64(flat[(pv + pad) * wp + (pu + pad)])
                    if _code_matches(code, np.int64(ray_code[r]), n_codes // 8, n_codes):
                        x[i, r], y[i, r] = pu, pv
                        has[i, r] = True
                        break
    return x, y, has


def _padded(dirs: np.ndarray, pad: int, have: tuple[np.ndarray, int, int] | None = None) -> tuple[np.ndarray, int, int]:
    """Direction-code map padded with 255 (no edge) so that ray lookups need no bounds checks:
    (flat map, row width, padding). ``have``: the map padded already, used when its padding suffices."""
    if have is not None and have[2] >= pad:
        return have
    big = cv2.copyMakeBorder(dirs, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    return big.ravel(), big.shape[1], pad


def sample_diameters(em: EdgeMap, dirs: np.ndarray, dark_dots: bool, r_min: float, r_max: float,
                     grad_threshold: float, params: RRHTParams, rng: np.random.Generator,
                     padded: tuple[np.ndarray, int, int] | None = None):
    """Gradient-guided diameter samples: (centres (S, 2), radii (S,), n_seeds) in coarse px.

    dirs: direction-code map of the filtered edges (:func:`tasks.vision.detection.edges.direction_codes`);
    padded: that map padded already (:func:`_padded`), used when its padding suffices.
    """
    vs, us = pixels_where(dirs != 255)
    g1 = np.stack([em.gx[vs, us], em.gy[vs, us]], axis=1).astype(float)
    mag = np.linalg.norm(g1, axis=1)
    strong = mag >= grad_threshold
    vs, us, g1, mag = vs[strong], us[strong], g1[strong], mag[strong]
    n_seeds = len(vs)
    if n_seeds == 0:
        return np.zeros((0, 2)), np.zeros(0), 0
    if n_seeds > params.n_samples:
        pick = np.sort(rng.choice(n_seeds, size=params.n_samples, replace=False))
        vs, us, g1, mag = vs[pick], us[pick], g1[pick], mag[pick]
    g1 /= np.maximum(mag, 1e-6)[:, None]
    inward = -g1 if dark_dots else g1
    t_all = np.arange(max(2.0, 2 * r_min - 1), 2 * r_max + 2, 1.0)  # (T,) candidate diameters
    flat, wp, pad = _padded(dirs, int(t_all[-1]) + 2, padded)
    opposite = (dirs[vs, us].astype(np.int16) + N_DIRECTIONS // 2) % N_DIRECTIONS
    tol = int(np.degrees(np.arccos(params.antiparallel_cos)) / (360.0 / N_DIRECTIONS))
    d = _walk_to_opposite_rim(us, vs, inward, opposite, t_all, flat, wp, pad, tol, N_DIRECTIONS)
    has = np.isfinite(d)
    d = d[has]
    p1 = np.stack([us[has], vs[has]], axis=1).astype(float)
    centres = p1 + inward[has] * (d[:, None] / 2.0)
    return centres, d / 2.0, n_seeds


def accumulate(centres: np.ndarray, radii: np.ndarray, shape: tuple[int, int], params: RRHTParams,
               sample_rate: float):
    """Accumulator peaks: (centres (K, 2), radii (K,), votes (K,)) passing the dynamic threshold."""
    b = params.bin_px
    h, w = shape
    hb, wb = h // b + 1, w // b + 1
    iu = np.clip((centres[:, 0] / b).astype(np.int64), 0, wb - 1)
    iv = np.clip((centres[:, 1] / b).astype(np.int64), 0, hb - 1)
    # a few thousand samples in up to millions of bins: sums over the occupied bins only (each bin's
    # samples added in their order, as a bincount over all bins does), spread into float32 maps
    occupied, slot = np.unique(iv * wb + iu, return_inverse=True)

    def binned(weights: np.ndarray | None) -> np.ndarray:
        out = np.zeros(hb * wb, np.float32)
        out[occupied] = np.bincount(slot, weights=weights, minlength=len(occupied))
        return out.reshape(hb, wb)

    n, su, sv, sr = binned(None), binned(centres[:, 0]), binned(centres[:, 1]), binned(radii)
    box = (3, 3)
    n3 = cv2.boxFilter(n, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    # strict local maxima: ties (plateaus of equal 3×3 sums) are broken by the centre bin's own
    # count, then by a tiny deterministic ramp, so that each dot yields one peak
    ramp = np.arange(hb * wb, dtype=np.float32).reshape(hb, wb) * np.float32(1e-3 / (hb * wb))
    score = n3 + np.float32(0.01) * n + ramp
    pv, pu = local_maxima(score, n3 >= params.min_votes)
    if len(pv) == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    votes = n3[pv, pu].astype(float)
    su3 = cv2.boxFilter(su, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)[pv, pu]
    sv3 = cv2.boxFilter(sv, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)[pv, pu]
    sr3 = cv2.boxFilter(sr, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)[pv, pu]
    c = np.stack([su3 / votes, sv3 / votes], axis=1)
    r = sr3 / votes
    # dynamic threshold: a fraction of the votes a complete rim of radius r would collect
    expected = sample_rate * 2 * np.pi * r
    keep = votes >= np.maximum(params.min_votes, params.vote_fraction * expected)
    order = np.argsort(-votes[keep])[: params.max_candidates]
    return c[keep][order], r[keep][order], votes[keep][order]


def local_maxima(score: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the cells of ``where`` ((H, W) bool) whose ``score`` ((H, W)) is at least each
    of its 3 × 3 neighbours' inside the map, in row-major order: ``where & (score >= cv2.dilate(score,
    3 × 3))`` (the maximum is exact), taken only at the cells of ``where`` (a few thousand accumulator
    bins with votes among millions)."""
    v, u = pixels_where(where)
    h, w = score.shape
    best = score[v, u]
    peak = np.ones(len(v), bool)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            vn, un = v + dv, u + du
            inside = (vn >= 0) & (vn < h) & (un >= 0) & (un < w)
            peak &= ~inside | (best >= score[np.clip(vn, 0, h - 1), np.clip(un, 0, w - 1)])
    return v[peak], u[peak]


def fit_candidates(dirs: np.ndarray, centres: np.ndarray, radii: np.ndarray, dark_dots: bool,
                   params: RRHTParams, padded: tuple[np.ndarray, int, int] | None = None):
    """Least-squares ellipse and rim ratio for each candidate (batched over candidates).

    Along ``n_rays`` rays from each candidate centre, the first edge pixel in [0.4 r, 1.7 r]
    whose gradient points along the ray (outward for dark dots, within ±45°) is a rim point.
    Returns (centre (K, 2), axes (K, 2), theta (K,), rim_ratio (K,)), NaN where the fit fails.
    padded: the map padded already (:func:`_padded`), used when its padding suffices.
    """
    nr = params.n_rays
    ang = np.arange(nr) * (2 * np.pi / nr)
    cs, sn = np.cos(ang), np.sin(ang)
    steps = np.linspace(0.4, 1.7, 27)  # relative to r
    flat, wp, pad = _padded(dirs, int(np.ceil(1.7 * radii.max())) + 2, padded)
    h, w = dirs.shape  # a refitted centre may lie far off the map: rays off it find nothing
    ray_code = np.rint(ang * (N_DIRECTIONS / (2 * np.pi))).astype(np.int16)
    if not dark_dots:
        ray_code = (ray_code + N_DIRECTIONS // 2) % N_DIRECTIONS
    x, y, has = _first_rim_points(np.ascontiguousarray(centres, dtype=float), np.ascontiguousarray(radii, dtype=float),
                                  cs, sn, steps, ray_code, flat, wp, h, w, pad, N_DIRECTIONS)
    scale = np.maximum(radii, 1.0)
    xn = (x - centres[:, 0:1]) / scale[:, None]
    yn = (y - centres[:, 1:2]) / scale[:, None]
    wts = has.astype(float)
    conic = fit_conic_lsq(xn, yn, wts, sampson_iterations=0)
    # one robust pass: drop points far from the first fit, refit
    dist = abs_sampson_distance(conic, xn, yn) * scale[:, None]
    conic = fit_conic_lsq(xn, yn, wts * (dist < 1.5), sampson_iterations=1)
    ok = is_ellipse(conic)
    centre, axes, theta = ellipse_params(conic, centres, scale)
    # rim ratio: fraction of ray directions whose rim point lies within 1.5 px of the ellipse
    dist = abs_sampson_distance(conic, xn, yn) * scale[:, None]
    ratio = ((dist < 1.5) & has).sum(axis=1) / nr
    ratio = np.where(ok, ratio, 0.0)
    return centre, axes, theta, ratio


def _suppress_duplicates(centres: np.ndarray, minor: np.ndarray) -> np.ndarray:
    """Greedy suppression (best first): drop circles centred within half a minor axis of a kept one."""
    n = len(centres)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    d = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=2)  # (n, n)
    near = d < 0.5 * minor[:, None]
    alive = np.ones(n, dtype=bool)
    kept = []
    for i in range(n):
        if alive[i]:
            kept.append(i)
            alive &= ~near[i]
    return np.array(kept, dtype=np.int64)


def rrht_circles(em: EdgeMap, edges: np.ndarray, dark_dots: bool, r_min: float, r_max: float,
                 params: RRHTParams | None = None, seed: int = 0,
                 timings: dict | None = None) -> CoarseCircles:
    """Run sampling, accumulation, screening and least-squares fitting on one coarse edge map."""
    params = params or RRHTParams()
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    dirs = direction_codes(em, edges)
    # padded once for the longest walk (a diameter up to 2 r_max + 2), which also covers the rim rays
    padded = _padded(dirs, int(2 * r_max + 2) + 2)
    c, r, n_seeds = sample_diameters(em, dirs, dark_dots, r_min, r_max, em.high, params, rng, padded)
    if len(c) == 0:
        return CoarseCircles.empty()
    rate = min(1.0, params.n_samples / max(n_seeds, 1))
    c, r, votes = accumulate(c, r, edges.shape, params, rate)
    t1 = time.perf_counter()
    if timings is not None:
        timings["sampling"] = timings.get("sampling", 0.0) + t1 - t0
    if len(c) == 0:
        return CoarseCircles.empty()
    centre, axes, theta, ratio = fit_candidates(dirs, c, r, dark_dots, params, padded)
    # second iteration from the fitted ellipses: rays now start at the right centre
    again = np.isfinite(centre).all(axis=1) & np.isfinite(axes).all(axis=1) & (ratio > 0.3)
    if again.any():
        r2 = np.clip(np.sqrt(axes[again, 0] * axes[again, 1]), r_min, r_max)
        c2, a2, t2, q2 = fit_candidates(dirs, centre[again], r2, dark_dots, params, padded)
        better = q2 >= ratio[again]
        ia = np.flatnonzero(again)[better]
        centre[ia], axes[ia], theta[ia], ratio[ia] = c2[better], a2[better], t2[better], q2[better]
    keep = (ratio >= params.min_rim_ratio) & np.isfinite(centre).all(axis=1)
    keep &= (axes[:, 1] >= 0.6 * r_min) & (axes[:, 0] <= 1.4 * r_max)
    idx = np.flatnonzero(keep)
    # non-maximum suppression: duplicates from neighbouring accumulator peaks
    score = ratio[idx] * 1000 + votes[idx]
    idx = idx[np.argsort(-score)]
    sel = _suppress_duplicates(centre[idx], axes[idx, 1])
    sel = idx[sel]
    if timings is not None:
        timings["fitting_coarse"] = timings.get("fitting_coarse", 0.0) + time.perf_counter() - t1
    return CoarseCircles(centre[sel], axes[sel], theta[sel], votes[sel], ratio[sel])
