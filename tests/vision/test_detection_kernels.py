"""The compiled loops of the sub-pixel stage give the numpy forms' results to every bit.

tasks/vision/detection/step_kernels.py, conic_kernels.py and ray_kernels.py replace numpy array
expressions by loops that do the same floating-point operations in the same order; each test runs
the numpy form (written out here as the reference) and the compiled one on random inputs shaped
like a plate's rays and compares the bytes. region_kernels.py replaces OpenCV's contour and convex
hull areas (exact sums of integer coordinates), compared with OpenCV's on random regions; the
candidate search's one-region-per-place pass and the Hough accumulator over its occupied bins are
compared with their direct forms.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.special import ndtr

from tasks.vision.detection import blobs, conics, rrht, step_kernels, subpixel
from tasks.vision.detection.chain_kernels import screen_contours
from tasks.vision.detection.chaincode import FREEMAN_CODE, chain_codes, filter_edges
from tasks.vision.detection.edges import N_DIRECTIONS, canny_edges
from tasks.vision.detection.ray_kernels import derivative_peaks, flatten, ray_coordinates
from tasks.vision.detection.region_kernels import contour_areas, convex_contour_areas, darker_than_mean
from tasks.vision.detection.rrht import local_maxima
from tasks.vision.detection.stats import percentile


def _solve_spd(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Gaussian elimination over the batch axis: m (n, n, N), v (n, N)."""
    n = m.shape[0]
    a, b = m.copy(), v.copy()
    for i in range(n):
        piv = np.where(np.abs(a[i, i]) > 1e-12, a[i, i], 1e-12)
        for j in range(i + 1, n):
            f = a[j, i] / piv
            a[j, i:] -= f * a[i, i:]
            b[j] -= f * b[i]
    x = np.empty_like(b)
    for i in range(n - 1, -1, -1):
        acc = b[i].copy()
        for j in range(i + 1, n):
            acc -= a[i, j] * x[j]
        x[i] = acc / np.where(np.abs(a[i, i]) > 1e-12, a[i, i], 1e-12)
    return x


def _gauss_newton_reference(y, tt, te, a, b, m, ls, free_sigma: bool, free_slope: bool):
    """One iteration of the blurred-step fit as numpy array expressions (returns te, a, b, ls, m)."""
    f32 = np.float32
    s = np.exp(ls)
    inv_s = f32(1.0) / s
    dt = tt - te
    z = dt * inv_s
    phi = 0.5 + 0.5 * np.tanh(z * (f32(0.7978845608) + f32(0.0356774081) * z * z))
    dens = np.exp(f32(-0.5) * z * z) * f32(0.3989422804014327)
    c = b - a
    mdt = m * dt
    r = y - ((a + c * phi) + mdt * (1 - phi))
    cd = c * dens - mdt * dens
    cols = [(-cd) * inv_s - m * (1 - phi), 1 - phi, phi, (-cd) * z, dt * (1 - phi)]
    used = [0, 1, 2] + ([3] if free_sigma else []) + ([4] if free_slope else [])
    n = len(used)
    jtj = np.empty((n, n, y.shape[1]))
    jtr = np.empty((n, y.shape[1]))
    for p, cp in enumerate(used):
        jtr[p] = np.cumsum(cols[cp] * r, axis=0, dtype=f32)[-1]  # float32 sums in sample order
        for q in range(p, n):
            jtj[p, q] = jtj[q, p] = np.cumsum(cols[cp] * cols[used[q]], axis=0, dtype=f32)[-1]
        jtj[p, p] += 1e-9
    step = _solve_spd(jtj, jtr)
    lim = np.maximum(1.0, s)
    step[0] = np.clip(step[0], -lim, lim)
    step = np.nan_to_num(step).astype(f32)
    te, a, b = te + step[0], a + step[1], b + step[2]
    if free_sigma:
        ls = ls + np.clip(step[3], -0.7, 0.7)
    if free_slope:
        m = m + step[n - 1]
    return te, a, b, ls, m


@pytest.mark.parametrize("free_sigma", [True, False])
@pytest.mark.parametrize("free_slope", [False, True])
def test_gauss_newton_step_is_the_numpy_iteration_to_every_bit(free_sigma, free_slope):
    rng = np.random.default_rng(7 + 2 * free_sigma + free_slope)
    n_t, n = 14, 700  # samples per ray, rays (several of the compiled loops' vector widths and a tail)
    f32 = np.float32
    te0 = rng.uniform(-1.0, 1.0, n).astype(f32)
    tt = np.linspace(-6.0, 6.0, n_t).astype(f32)[:, None] + rng.uniform(-0.2, 0.2, (1, n)).astype(f32)
    sig = rng.uniform(0.5, 3.0, n).astype(f32)
    truth = 40 + 160 / (1 + np.exp(-(tt - te0) / sig))
    y = (truth + rng.normal(0, 3, truth.shape)).astype(f32)
    a, b = rng.uniform(30, 50, n).astype(f32), rng.uniform(190, 210, n).astype(f32)
    m = rng.uniform(-0.05, 0.05, n).astype(f32) if free_slope else np.zeros(n, f32)
    ls = np.log(sig * rng.uniform(0.7, 1.4, n)).astype(f32)
    te = np.zeros(n, f32)
    want = _gauss_newton_reference(y, tt, te, a, b, m, ls, free_sigma, free_slope)
    got = [v.copy() for v in (te, a, b, ls, m)]
    s = np.exp(got[3])
    inv_s = f32(1.0) / s
    dt, z, tanh_z, gauss_z = (np.empty(y.shape, f32) for _ in range(4))
    step_kernels.step_arguments(tt, got[0], inv_s, dt, z, tanh_z, gauss_z)
    np.tanh(tanh_z, out=tanh_z)
    np.exp(gauss_z, out=gauss_z)
    step_kernels.gauss_newton_step(y, dt, z, tanh_z, gauss_z, got[1], got[2], got[4], got[0], got[3], s, inv_s,
                                   step_kernels.fitted_columns(free_sigma, free_slope))
    for name, w, g in zip(("t_e", "a", "b", "log s", "m"), want, got, strict=True):
        assert w.dtype == g.dtype and w.tobytes() == g.tobytes(), name


def test_step_fit_finds_blurred_rims():
    rng = np.random.default_rng(3)
    k, r, n_t = 3, 40, 16
    t = np.broadcast_to(np.linspace(-6.0, 6.0, n_t), (k, r, n_t)).copy()
    te0 = rng.uniform(-1.0, 1.0, (k, r))
    prof = (50 + 150 * ndtr((t - te0[..., None]) / 1.7)).astype(np.float32)  # a step blurred by σ 1.7 px
    te, _, good, lev_in, _, _ = subpixel.step_fit(prof, t, np.zeros((k, r)), prof[..., 0], prof[..., -1],
                                                  np.full(k, 1.0), 6)
    assert good.all() and np.abs(te - te0).max() < 0.01 and np.abs(lev_in - 50).max() < 0.5


def test_sampson_distances_and_ransac_are_the_numpy_forms_to_every_bit():
    rng = np.random.default_rng(11)
    k, n = 49, 64
    ang = np.arange(n) * (2 * np.pi / n)
    x = rng.uniform(0.8, 1.0, (k, 1)) * np.cos(ang) + rng.normal(0, 0.01, (k, n))
    y = rng.uniform(0.5, 0.8, (k, 1)) * np.sin(ang) + rng.normal(0, 0.01, (k, n))
    x[:, ::9] += 0.2  # outliers
    valid = rng.random((k, n)) > 0.1
    conic = conics.fit_conic_lsq(x, y, valid.astype(float), sampson_iterations=1)
    want = np.abs(conics.sampson_distance(conic[:, None, :], x, y))
    assert want.tobytes() == conics.abs_sampson_distance(conic, x, y).tobytes()
    samples = conics.ransac_samples(k, n, 16, rng)
    thr = np.full(k, 0.02)
    kk = np.arange(k)[:, None, None]  # the numpy form of ransac_ellipse
    xs, ys, vs = x[kk, samples], y[kk, samples], valid[kk, samples]
    xs, ys = np.where(vs, xs, 0.0), np.where(vs, ys, 0.0)
    d5 = np.stack([xs * xs, xs * ys, ys * ys, xs, ys], axis=-1)
    ok = np.abs(np.linalg.det(d5)) > 1e-12
    p = np.linalg.solve(np.where(ok[..., None, None], d5, np.eye(5)), np.ones((*xs.shape, 1)))[..., 0]
    hyp = np.concatenate([p, -np.ones((k, 16, 1))], axis=-1)
    hyp = np.where(ok[..., None], hyp / np.linalg.norm(hyp, axis=-1, keepdims=True), np.nan)
    good = vs.all(axis=-1) & conics.is_ellipse(hyp)
    inl = (np.abs(conics.sampson_distance(hyp[:, :, None, :], x[:, None, :], y[:, None, :])) < thr[:, None, None]) \
        & valid[:, None, :]
    score = np.where(good, inl.sum(axis=-1), -1)
    best = np.argmax(score, axis=1)
    mask = inl[np.arange(k), best] & (score[np.arange(k), best] >= 5)[:, None]
    got = conics.ransac_ellipse(x, y, valid, thr, samples)
    assert np.array_equal(got, mask)
    clean = valid.copy()
    clean[:, ::9] = False
    assert (got & clean).sum() > 0.85 * clean.sum() and (got[:, ::9]).mean() < 0.5  # most outliers are left out


def test_conic_least_squares_is_the_numpy_form_to_every_bit():
    rng = np.random.default_rng(5)
    k, n = 30, 50
    ang = rng.uniform(0, 2 * np.pi, (k, n))
    x, y = 0.9 * np.cos(ang) + rng.normal(0, 0.01, (k, n)), 0.6 * np.sin(ang) + rng.normal(0, 0.01, (k, n))
    w = (rng.random((k, n)) > 0.2).astype(float)
    w[0, 4:] = 0.0  # too few points: NaN
    m = np.stack([x * x - y * y, x * y, x, y, np.ones_like(x)], axis=-1)
    ww, want = w.copy(), None
    for _ in range(3):
        mtw = np.swapaxes(m * ww[..., None], 1, 2)
        ata = np.matmul(mtw, m)
        ata = ata + 1e-12 * np.trace(ata, axis1=1, axis2=2)[:, None, None] * np.eye(5)
        ata[0] = np.eye(5)
        p = np.linalg.solve(ata, np.matmul(mtw, -(y * y)[..., None]))[..., 0]
        want = np.stack([p[:, 0], p[:, 1], 1.0 - p[:, 0], p[:, 2], p[:, 3], p[:, 4]], axis=-1)
        _, qx, qy = conics.conic_value_and_grad(want[:, None, :], x, y)
        g2 = qx * qx + qy * qy
        ref = (w * g2).sum(axis=1, keepdims=True) / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
        ww = w * (ref / np.maximum(g2, 1e-6 * ref))
    want[0] = np.nan
    got = conics.fit_conic_lsq(x, y, w, sampson_iterations=2)
    assert got.tobytes() == want.tobytes()
    _, axes, _ = conics.ellipse_params(got[1:], np.zeros((k - 1, 2)), np.ones(k - 1))
    assert np.allclose(axes, [0.9, 0.6], atol=0.01)


def test_ray_coordinates_derivative_peaks_and_flattening_are_the_numpy_forms_to_every_bit():
    rng = np.random.default_rng(2)
    k, r, n_t = 7, 32, 28
    centres = rng.uniform(30, 200, (k, 2))
    ang = np.arange(r) * (2 * np.pi / r)
    t = np.clip(rng.uniform(5, 40, (k, r, 1)) + np.linspace(-8, 8, n_t), 6.0, 44.0)  # clipped: repeated samples
    cs, sn = np.cos(ang).astype(np.float32), np.sin(ang).astype(np.float32)
    for level in (1, 3):
        origin, full = (11, 23), (240, 250)
        t32 = t.astype(np.float32)
        mx = (centres[:, 0, None, None] - origin[0]).astype(np.float32) + cs[None, :, None] * t32
        my = (centres[:, 1, None, None] - origin[1]).astype(np.float32) + sn[None, :, None] * t32
        inside = ((mx >= -origin[0]) & (mx <= full[1] - 1 - origin[0])
                  & (my >= -origin[1]) & (my <= full[0] - 1 - origin[1]))
        if level > 1:
            mx, my = (mx + 0.5) / float(level) - 0.5, (my + 0.5) / float(level) - 0.5
        got = ray_coordinates(centres, cs, sn, t, origin, full, level)
        assert got[0].tobytes() == mx.reshape(k * r, n_t).tobytes()
        assert got[1].tobytes() == my.reshape(k * r, n_t).tobytes()
        assert np.array_equal(got[2], inside) and 0 < inside.sum() < inside.size
    prof = rng.integers(0, 256, (k, r, n_t)).astype(np.float32)  # whole grey levels: ties in the peaks
    step = rng.uniform(0.3, 1.0, k)
    for sign in (1.0, -1.0):
        dt = t[..., 2:] - t[..., :-2]
        d = (prof[..., 2:] - prof[..., :-2]) * sign
        d = np.where((dt > 1e-6) & inside[..., 2:] & inside[..., :-2], d / np.maximum(dt, 1e-6), -np.inf)
        j = np.argmax(d, axis=2)
        kk, rr = np.meshgrid(np.arange(k), np.arange(r), indexing="ij")
        jc = np.clip(j, 1, d.shape[2] - 2)
        d0, dm, dp = d[kk, rr, jc], d[kk, rr, jc - 1], d[kk, rr, jc + 1]
        peak = d[kk, rr, j]
        with np.errstate(all="ignore"):
            den = dm - 2 * d0 + dp
            off = np.clip(np.where((den < 0) & np.isfinite(den), 0.5 * (dm - dp) / den, 0.0), -0.5, 0.5)
        st = np.broadcast_to(step[:, None], (k, r))
        tp = np.where(j == jc, t[kk, rr, jc + 1] + off * st, t[kk, rr, j + 1])
        fwhm = ((d > 0.5 * peak[..., None]) & np.isfinite(d)).sum(axis=2) * st
        got = derivative_peaks(prof, t, inside, sign, step)
        for name, w, g in zip(("t", "peak", "fwhm"), (tp, peak, fwhm), got, strict=True):
            assert w.tobytes() == g.tobytes(), (name, sign)
    grad = rng.normal(0, 3e-3, (k, 2))
    rel = 1.0 + t * (grad[:, 0, None, None] * np.cos(ang)[None, :, None]
                     + grad[:, 1, None, None] * np.sin(ang)[None, :, None])
    want = prof / np.clip(rel, 0.5, 2.0).astype(np.float32)
    assert want.tobytes() == flatten(prof, t, grad, np.cos(ang), np.sin(ang)).tobytes()


def test_contour_areas_are_opencvs_contour_and_hull_areas_to_every_bit():
    rng = np.random.default_rng(11)
    img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.uint8), (0, 0), 2.0)
    contours, _ = cv2.findContours((img < 120).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contours = [*contours, np.array([[[5, 5]], [[9, 5]], [[13, 5]], [[17, 5]], [[21, 5]], [[25, 5]]], np.int32)]
    lens = np.array([len(c) for c in contours])
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    points = np.concatenate(contours).reshape(-1, 2).astype(float)
    area, hull = contour_areas(points, starts, lens, 0.0, np.inf)
    big = lens >= 6
    assert big.sum() > 50 and np.isnan(area[~big]).all() and np.isnan(hull[~big]).all()
    want_area = np.array([cv2.contourArea(c) for c in contours])[big]
    want_hull = np.array([cv2.contourArea(cv2.convexHull(c)) for c in contours])[big]
    assert area[big].tobytes() == want_area.tobytes() and hull[big].tobytes() == want_hull.tobytes()
    assert hull[-1] == 0.0  # collinear points: no hull area
    a_min, a_max = np.quantile(want_area, [0.3, 0.7])
    area, _ = contour_areas(points, starts, lens, a_min, a_max)
    inside = (want_area >= a_min) & (want_area <= a_max)
    assert np.array_equal(np.isfinite(area[big]), inside)


def test_convex_contour_areas_decide_as_the_hull_area_does():
    rng = np.random.default_rng(12)
    img = cv2.GaussianBlur(rng.integers(0, 256, (480, 640)).astype(np.uint8), (0, 0), 1.5)
    for u, v, a, b, ang in zip(*rng.uniform((0, 0, 2, 2, 0), (640, 480, 12, 12, 180), (60, 5)).T, strict=True):
        cv2.ellipse(img, (int(u), int(v)), (int(a), int(b)), ang, 0, 360, 0, -1)  # convex regions
    cv2.rectangle(img, (10, 10), (30, 22), 0, -1)  # a box: convex by the bounding-box bound
    counts = np.zeros(2, int)
    for level in (90, 120, 150):
        contours, _ = cv2.findContours((img < level).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        lens = np.array([len(c) for c in contours])
        starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
        points = np.concatenate(contours).reshape(-1, 2).astype(float)
        for a_min, a_max, c in ((1.0, np.inf, 0.9), (10.0, 400.0, 0.9), (1.0, np.inf, 0.6), (1.0, np.inf, 0.99)):
            area, hull = contour_areas(points, starts, lens, a_min, a_max)
            got_area, convex = convex_contour_areas(points, starts, lens, a_min, a_max, c)
            with np.errstate(invalid="ignore"):
                want = (hull > 0) & (area / hull >= c)
            assert got_area.tobytes() == area.tobytes() and np.array_equal(convex, want)
            counts += want.sum(), np.isfinite(area).sum() - want.sum()
    assert (counts > 50).all()  # both answers, many times


def test_octagon_lies_in_the_hull_and_the_box_is_the_bounding_boxs():
    from tasks.vision.detection.region_kernels import _octagon_and_box
    rng = np.random.default_rng(4)
    for _ in range(200):
        pts = rng.integers(0, 40, (int(rng.integers(3, 30)), 2)).astype(float)
        octagon, box = _octagon_and_box(pts[:, 0].copy(), pts[:, 1].copy())
        hull = cv2.contourArea(cv2.convexHull(pts.astype(np.float32)))
        assert octagon <= hull + 1e-9 and box == np.ptp(pts[:, 0]) * np.ptp(pts[:, 1]) >= hull - 1e-9
    square = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])  # every extreme point a corner
    assert _octagon_and_box(square[:, 0].copy(), square[:, 1].copy()) == (16.0, 16.0)


def test_darker_than_mean_is_opencvs_compare_against_the_mean_less_the_offset():
    rng = np.random.default_rng(5)
    src = cv2.GaussianBlur(rng.integers(0, 256, (181, 243)).astype(np.uint8), (0, 0), 1.2).astype(np.float32)
    for k, offset in ((7, 3.7), (31, 0.8), (63, 12.25)):
        mean = cv2.blur(src, (k, k), borderType=cv2.BORDER_REFLECT)
        threshold = mean.copy()
        threshold -= offset  # the numpy form: in place, float32
        want = cv2.compare(src, threshold, cv2.CMP_LT)
        got = darker_than_mean(src, mean, np.float32(offset))
        assert got.dtype == np.uint8 and np.array_equal(got, want)
        assert 0.05 < (got > 0).mean() < 0.6


def test_contours_too_short_to_enclose_the_smallest_area_enclose_less():
    """blobs.can_enclose drops contours of n points only when n² / 2π < a_min, which the isoperimetric
    bound says they cannot reach: every dropped contour's area is below a_min, on specks and on thin,
    self-retracing regions (lines one pixel wide)."""
    rng = np.random.default_rng(8)
    img = cv2.GaussianBlur(rng.integers(0, 256, (300, 400)).astype(np.uint8), (0, 0), 0.8)
    cv2.line(img, (20, 280), (380, 270), 0, 1)
    cv2.circle(img, (200, 150), 9, 0, -1)
    contours, _ = cv2.findContours((img < 100).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    lens = np.array([len(c) for c in contours])
    area = np.array([cv2.contourArea(c) for c in contours])
    for a_min in (4.0, 17.0, 60.0):
        kept = blobs.can_enclose(lens, a_min)
        assert (area[~kept] < a_min).all() and (~kept).sum() > 100
        assert kept[area >= a_min].all()
    area, convex = blobs._convex_areas(contours, 17.0, 1e9, 0.9)  # the kept ones measured as before
    want_area, want_convex = convex_contour_areas(
        np.concatenate(contours).reshape(-1, 2).astype(float), np.concatenate([[0], np.cumsum(lens)[:-1]]), lens,
        17.0, 1e9, 0.9)
    assert area.tobytes() == want_area.tobytes() and np.array_equal(convex, want_convex) and convex.sum() >= 1


def test_region_search_with_a_store_of_means_gives_the_same_candidates():
    rng = np.random.default_rng(9)
    img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.uint8), (0, 0), 1.0)
    for u, v in rng.uniform((20, 20), (300, 220), (25, 2)):
        cv2.circle(img, (int(u), int(v)), 6, 20, -1)
    store: dict = {}
    for offset in (0.08, 0.04, 0.02):
        want = blobs.contour_candidates(img, True, 6.0, 30.0, offset)
        got = blobs.contour_candidates(img, True, 6.0, 30.0, offset, means=store)
        assert len(want) > 10
        for name in ("centres", "axes", "theta", "votes"):
            assert getattr(got, name).tobytes() == getattr(want, name).tobytes()
    assert sorted(k for _, k in store) == [0, 13, 25, 49, 97]  # the image and one mean per window, made once


def _filter_edges_numpy(edges, d_min_px, d_max_px, min_distinct=6, max_code_fraction=0.4, max_aspect=4.0):
    """chaincode.filter_edges' numpy form: per-point codes, one histogram, the kept contours redrawn."""
    contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    lens = np.array([len(c) for c in contours])
    pts = np.concatenate(contours, axis=0)[:, 0, :].astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    w = np.maximum.reduceat(pts[:, 0], starts) - np.minimum.reduceat(pts[:, 0], starts) + 1
    h = np.maximum.reduceat(pts[:, 1], starts) - np.minimum.reduceat(pts[:, 1], starts) + 1
    big, small = np.maximum(w, h), np.minimum(w, h)
    size_ok = (big >= 0.45 * d_min_px) & (big <= 1.3 * d_max_px + 3) & (big <= max_aspect * small + 2)
    codes = chain_codes(pts, starts, lens)
    seg = np.repeat(np.arange(len(contours)), lens)
    good = codes >= 0
    hist = np.bincount(seg[good] * 8 + codes[good], minlength=8 * len(contours)).reshape(-1, 8)
    frac = hist.max(axis=1) / np.maximum(hist.sum(axis=1), 1)
    keep = size_ok & ((hist > 0).sum(axis=1) >= min_distinct) & (frac <= max_code_fraction)
    out = np.zeros_like(edges)
    cv2.drawContours(out, [contours[i] for i in np.flatnonzero(keep)], -1, 255, 1)
    return out & edges, int(keep.sum())


def test_filter_edges_keeps_and_draws_what_its_numpy_form_does():
    rng = np.random.default_rng(13)
    img = cv2.GaussianBlur(rng.integers(0, 256, (600, 800)).astype(np.uint8), (0, 0), 1.2)
    for u, v, a, b, ang in zip(*rng.uniform((0, 0, 3, 3, 0), (800, 600, 40, 40, 180), (80, 5)).T, strict=True):
        cv2.ellipse(img, (int(u), int(v)), (int(a), int(b)), ang, 0, 360, int(u) % 256, -1)
    edges = cv2.Canny(img, 40, 90)
    edges[5, 5:40] = 255  # a straight line, and single pixels
    edges[::97, ::89] = 255
    for d_min, d_max in ((4.0, 16.0), (6.0, 40.0), (20.0, 90.0)):
        want, n_kept = _filter_edges_numpy(edges, d_min, d_max)
        got, stats = filter_edges(edges, d_min, d_max)
        assert got.tobytes() == want.tobytes() and stats["kept"] == n_kept > 20


def test_screen_contours_leaves_a_contour_with_a_jump_to_opencv():
    ring = cv2.ellipse2Poly((20, 20), (8, 8), 0, 0, 360, 5)[:-1].astype(np.int64)  # steps of several px
    u, v = ring[:, 0].copy(), ring[:, 1].copy()
    out = np.zeros((40, 40), np.uint8)
    keep, drawn = screen_contours(u, v, np.array([0]), np.array([len(u)]), 3.0, 30.0, 4.0, 6, 0.4, FREEMAN_CODE, out)
    assert keep.tolist() == [False] and not out.any()  # no unit steps: no codes, refused
    step = np.array([[0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 2], [0, 2], [0, 1]])  # a 3 × 3 square
    keep, drawn = screen_contours(step[:, 0].copy(), step[:, 1].copy(), np.array([0]), np.array([8]), 1.0, 30.0,
                                  4.0, 4, 0.4, FREEMAN_CODE, out)
    assert keep.tolist() == [True] and drawn.tolist() == [True] and out[:3, :3].sum() == 8 * 255
    jump = np.concatenate([step, [[5, 5], [1, 1]]])  # the same square with a jump out and back
    out[:] = 0
    keep, drawn = screen_contours(jump[:, 0].copy(), jump[:, 1].copy(), np.array([0]), np.array([10]), 1.0, 30.0,
                                  4.0, 4, 0.4, FREEMAN_CODE, out)
    assert keep.tolist() == [True] and drawn.tolist() == [False] and not out.any()


def test_canny_gradients_are_the_two_sobel_derivatives():
    rng = np.random.default_rng(14)
    for shape in ((37, 53), (240, 321)):
        img = cv2.GaussianBlur(rng.integers(0, 256, shape).astype(np.uint8), (0, 0), 1.0)
        img[: shape[0] // 3] = 255 * (rng.random((shape[0] // 3, shape[1])) < 0.5)  # the steepest steps
        em = canny_edges(img)
        assert np.array_equal(em.gx, cv2.Sobel(img, cv2.CV_16S, 1, 0, ksize=3))
        assert np.array_equal(em.gy, cv2.Sobel(img, cv2.CV_16S, 0, 1, ksize=3))


def test_percentile_is_numpys_to_every_bit():
    rng = np.random.default_rng(7)
    for _ in range(3000):
        values = rng.integers(0, 256, int(rng.integers(1, 3000))).astype(np.float32)  # a window's grey levels
        for q in (5.0, 25.0, 50.0, 97.5):
            assert np.float32(percentile(values, q)).tobytes() == np.percentile(values, q).tobytes()
    assert percentile(np.array([3.0, 1.0]), 40.0) == np.percentile([3.0, 1.0], 40.0)


def test_direction_codes_wrap_by_a_bit_mask():
    # the rim walks of tasks.vision.detection.rrht take the codes' difference modulo the count by a mask
    assert N_DIRECTIONS & (N_DIRECTIONS - 1) == 0
    d = np.arange(-2 * N_DIRECTIONS, 2 * N_DIRECTIONS)
    assert np.array_equal(d & (N_DIRECTIONS - 1), d % N_DIRECTIONS)


def test_local_maxima_are_the_dilation_peaks():
    rng = np.random.default_rng(15)
    for shape in ((1, 1), (3, 7), (120, 90)):
        score = rng.integers(0, 4, shape).astype(np.float32)  # many ties, peaks on the border
        where = rng.random(shape) < 0.5
        v, u = local_maxima(score, where)
        want = np.nonzero(where & (score >= cv2.dilate(score, np.ones((3, 3), np.uint8))))
        assert np.array_equal(v, want[0]) and np.array_equal(u, want[1])


def test_first_of_each_place_keeps_what_the_pass_over_all_earlier_regions_keeps():
    rng = np.random.default_rng(5)
    for n, spread in ((1, 10.0), (300, 60.0), (2000, 400.0)):
        centres = rng.uniform(0, spread, (n, 2))
        centres[n // 2 :: 7] = centres[: len(centres[n // 2 :: 7])]  # exact repeats: distance 0
        reach = rng.uniform(0.5, 6.0, n)
        want = np.ones(n, bool)
        for i in range(n):  # the pass over all later regions (the definition)
            if want[i]:
                d = np.hypot(centres[i + 1 :, 0] - centres[i, 0], centres[i + 1 :, 1] - centres[i, 1])
                want[i + 1 :] &= d > reach[i]
        got = blobs.first_of_each_place(centres, reach)
        assert np.array_equal(got, want) and (n == 1 or 0 < got.sum() < n)


def _accumulate_dense(centres, radii, shape, params, sample_rate):
    """rrht.accumulate with every accumulator map a bincount over all bins (the definition)."""
    b = params.bin_px
    hb, wb = shape[0] // b + 1, shape[1] // b + 1
    iu = np.clip((centres[:, 0] / b).astype(np.int64), 0, wb - 1)
    iv = np.clip((centres[:, 1] / b).astype(np.int64), 0, hb - 1)
    flat = iv * wb + iu
    maps = [np.bincount(flat, weights=w, minlength=hb * wb).reshape(hb, wb).astype(np.float32)
            for w in (None, centres[:, 0], centres[:, 1], radii)]
    box = [cv2.boxFilter(m, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT) for m in maps]
    ramp = np.arange(hb * wb, dtype=np.float32).reshape(hb, wb) * np.float32(1e-3 / (hb * wb))
    score = box[0] + np.float32(0.01) * maps[0] + ramp
    peak = (box[0] >= params.min_votes) & (score >= cv2.dilate(score, np.ones((3, 3), np.uint8)))
    pv, pu = np.nonzero(peak)
    votes = box[0][pv, pu].astype(float)
    c = np.stack([box[1][pv, pu] / votes, box[2][pv, pu] / votes], axis=1)
    r = box[3][pv, pu] / votes
    keep = votes >= np.maximum(params.min_votes, params.vote_fraction * sample_rate * 2 * np.pi * r)
    order = np.argsort(-votes[keep])[: params.max_candidates]
    return c[keep][order], r[keep][order], votes[keep][order]


@pytest.mark.parametrize("shape,n", [((2016, 1512), 3000), ((480, 640), 400), ((300, 200), 5000)])
def test_accumulate_over_the_occupied_bins_gives_the_dense_accumulators_peaks(shape, n):
    rng = np.random.default_rng(n)
    centres = rng.uniform(-2.0, max(shape) + 2.0, (n, 2))
    centres[: n // 3] = centres[n // 3 : 2 * (n // 3)] + rng.normal(0.0, 0.8, (n // 3, 2))  # clustered votes
    radii = rng.uniform(3.0, 9.0, n)
    params = rrht.RRHTParams()
    got = rrht.accumulate(centres, radii, shape, params, 0.4)
    want = _accumulate_dense(centres, radii, shape, params, 0.4)
    assert len(got[0]) > 10
    assert all(g.tobytes() == w.tobytes() for g, w in zip(got, want, strict=True))
