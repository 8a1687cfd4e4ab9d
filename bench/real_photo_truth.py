"""Image-based truth for real photographs of a large dot grid, cut down to a 4 × 3 grid.

    .venv/bin/python bench/real_photo_truth.py --out DIR [--variants 1,0.5,1:360x320] NAME=PHOTO[@X,Y,W,H]...

Each PHOTO is a photograph of a plate of many dark dots in a regular square lattice (e.g. the
UCL grid of SciKit-Surgery/scikit-surgeryimage, tests/data/calib-ucl-circles, BSD-3-Clause:
25 × 18 dots, pitch 2.5 diameters, four large fiducial dots; the photographs are not committed
here). Written to DIR per photograph and scale:

* ``NAME[_xVARIANT].png``: the photograph in grey with only the rows × cols block of dots nearest
  the image centre left; every other dot and fiducial is inpainted from the paper around it
  (``cv2.inpaint``). The dots kept are the photograph's own pixels. With ``--variants`` the image
  is also resized (``cv2.INTER_AREA`` down, a more distant view of the same dots; ``INTER_CUBIC``
  up, larger dots with the blur scaled alike) to a whole number of pixels and cropped around the
  block (a small frame), or resampled as through a fisheye lens (:func:`fisheye_view`: the block
  off the axis, dots squeezed by the barrel distortion); the truth is mapped alike, pixel
  centres at integers (through the fisheye the mapped rim centre, not the centre of an ellipse
  fitted to the distorted rim).
  With ``@X,Y,W,H`` only that window of the photograph is used (e.g. one of two grids in it).
* ``NAME[_xVARIANT].json``: the truth of the block, row-major like
  :meth:`tasks.machine.plate.DotPlate.dot_centres_mm` for ``DotPlate(rows, cols, ratio, 1)`` along the
  photograph's lattice, px, origin at the centre of the top-left pixel.

What the truth is (no detector of ours is involved): ``truth_px``, the centre of the ellipse
through each dot's visible rim (:func:`rim_ellipse_centres`: on 120 rays the point halfway
between the ray's own dot and paper levels, ``cv2.fitEllipse``), as one fits an ellipse by hand
to the edge. It is the ellipse centre, without a perspective-bias correction (the bias is a few
hundredths of a px on these views). Recorded beside it, to judge it:

* ``centroid_px``: a second estimator, the background-subtracted intensity centroid
  (:func:`intensity_centroids`; equal to the ellipse centre for a uniformly dark dot under
  symmetric blur). Where the two disagree the dot's image is not uniform (shading inside the dot,
  smear, colour fringes), and a centroid-type estimator is pulled towards its darker side.
* ``rim_in_image_px``: the same rim-ellipse estimator run on the written image itself (resized,
  cropped or through the fisheye lens), started from ``truth_px``: through the lens it is the
  centre of the ellipse fitted to the distorted dot, which is what a hand fit on that image gives,
  and differs from the mapped centre ``truth_px``.
* ``centroid_vs_neighbour_map_px``: each block dot's centroid against a plate → image map
  (homography times a cubic) fitted to the centroids of the dots around the block
  (:func:`predict_hole`): a check that the labels follow the lattice (a mislabelled dot would be
  a pitch off); it also shows how regular the printed plate and the lens are.

How the image was made is recorded too, so that a test can remake it from the photograph alone:
``crop_xywh`` (the window of the photograph), ``inpaint_ellipses`` (the regions inpainted, as
``cv2.ellipse`` boxes (u, v, width, height, angle deg) in that window) and ``window_origin``
(the W × H crop of the resized image, px, or null).

Regions are found (only found) with :func:`tasks.vision.detection.blobs.contour_candidates` and
labelled with :func:`tasks.vision.detection.grid.build_lattice`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tasks.vision.detection.blobs import contour_candidates
from tasks.vision.detection.grid import build_lattice, reduce_lattice
from tasks.vision.detection.perspective import fit_homography
from tasks.vision.detection.perspective import project as hproject

RIM_POINTS = 64


def intensity_centroids(grey: np.ndarray, centres: np.ndarray, radii: np.ndarray, iterations: int = 3) -> np.ndarray:
    """(K, 2) px: background-subtracted intensity centroids of dark dots near ``centres`` (K, 2) px
    with radii (K,) px, see the module docstring."""
    img = grey.astype(np.float64)
    h, w = img.shape
    out = centres.astype(float).copy()
    for k in range(len(out)):
        r = float(radii[k])
        half = int(np.ceil(2.3 * r)) + 2
        for _ in range(iterations):
            u0, v0 = out[k]
            x0, y0 = round(u0) - half, round(v0) - half
            if x0 < 0 or y0 < 0 or x0 + 2 * half + 1 > w or y0 + 2 * half + 1 > h:
                out[k] = np.nan
                break
            patch = img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]
            yy, xx = np.mgrid[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]
            du, dv = xx - u0, yy - v0
            dist = np.hypot(du, dv)
            ring = (dist >= 1.6 * r) & (dist <= 2.2 * r)
            a = np.stack([np.ones(ring.sum()), du[ring], dv[ring]], axis=1)
            coef = np.linalg.lstsq(a, patch[ring], rcond=None)[0]
            dark = coef[0] + coef[1] * du + coef[2] * dv - patch
            win = np.clip(1.35 * r + 0.5 - dist, 0.0, 1.0)
            wt = dark * win
            s = wt.sum()
            if s <= 0:
                out[k] = np.nan
                break
            out[k] = [(wt * xx).sum() / s, (wt * yy).sum() / s]
    return out


def rim_ellipse_centres(grey: np.ndarray, centres: np.ndarray, radii: np.ndarray, sloped: bool = False,
                        n_rays: int = 120, iterations: int = 2) -> np.ndarray:
    """(K, 2) px: the centre of the ellipse through each dot's rim, the rim on each of ``n_rays``
    rays being where the profile crosses halfway between that ray's own dot level and paper level
    (medians of the ray's samples at 0.5–0.7 and 1.35–1.65 radii; ``sloped``: straight lines
    fitted to its samples at 0.3–0.7 and 1.35–1.65 radii, taken at the same distance, so that a
    linear shading across the dot does not move the crossing), linearly interpolated (bilinear
    samples every 0.1 px); ``cv2.fitEllipse`` on the crossings, twice with rays more than 3 median
    deviations off dropped, re-centred ``iterations`` times. The flat levels are what fitting an
    ellipse by hand to the visible edge measures."""
    img = grey.astype(np.float32)
    out = centres.astype(float).copy()
    ang = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    for k in range(len(out)):
        r = float(radii[k])
        t = np.arange(0.3 * r, 1.7 * r, 0.1)
        for _ in range(iterations):
            pts = out[k][None, None, :] + t[None, :, None] * dirs[:, None, :]
            prof = cv2.remap(img, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
            inner = _line_fit(t, prof, (t >= (0.3 if sloped else 0.5) * r) & (t <= 0.7 * r), sloped)
            outer = _line_fit(t, prof, (t >= 1.35 * r) & (t <= 1.65 * r), sloped)
            half_t = 0.5 * (inner[0][:, None] + inner[1][:, None] * t + outer[0][:, None] + outer[1][:, None] * t)
            band = (t >= 0.6 * r) & (t <= 1.4 * r)
            tb, pb = t[band], prof[:, band] - half_t[:, band]
            above = pb >= 0  # paper side of the local half level (dark dots)
            cross = np.argmax(above[:, :-1] != above[:, 1:], axis=1)  # first crossing outwards
            contrast = (outer[0] + outer[1] * r) - (inner[0] + inner[1] * r)
            has = (above[:, :-1] != above[:, 1:]).any(axis=1) & (contrast > 5)
            i0 = cross
            p0, p1 = pb[np.arange(n_rays), i0], pb[np.arange(n_rays), i0 + 1]
            frac = np.clip(-p0 / np.where(p1 != p0, p1 - p0, 1), 0, 1)
            rim_t = tb[i0] + frac * (tb[1] - tb[0])
            rim = out[k] + rim_t[:, None] * dirs
            use = has.copy()
            if use.sum() < 12:
                out[k] = np.nan
                break
            for _ in range(2):
                (cu, cv_), (w, h), th = cv2.fitEllipse(rim[use].astype(np.float32))
                a, b = w / 2, h / 2
                c, s_ = np.cos(np.radians(th)), np.sin(np.radians(th))
                du, dv = rim[:, 0] - cu, rim[:, 1] - cv_
                x, y = c * du + s_ * dv, -s_ * du + c * dv
                dev = np.abs(np.hypot(x / a, y / b) - 1) * np.sqrt(a * b)
                use = has & (dev < 3 * max(np.median(dev[use]) * 1.4826, 0.05))
            out[k] = [cu, cv_]
    return out


def _line_fit(t: np.ndarray, prof: np.ndarray, sel: np.ndarray, sloped: bool) -> tuple[np.ndarray, np.ndarray]:
    """(intercept, slope) (R,) of a straight line through each profile's samples ``sel`` of t, or
    (median, 0) unless ``sloped``."""
    tt, pp = t[sel], prof[:, sel]
    if not sloped:
        return np.median(pp, axis=1), np.zeros(len(pp))
    tm, pm = tt.mean(), pp.mean(axis=1)
    slope = ((tt - tm) * (pp - pm[:, None])).sum(axis=1) / ((tt - tm) ** 2).sum()
    return pm - slope * tm, slope


def find_dots(grey: np.ndarray, ratio_guess: float, rows: int, cols: int, margin: int = 3,
              min_dot_px: float = 6.0):
    """One photograph's regular dots (at least ``min_dot_px`` across) near the rows × cols block
    closest to the image centre:
    (centres (N, 2) px intensity centroids, lattice (N, 2) int, radii (N,) px, the block's indices
    (rows*cols,) into them or None, all regions (centres, axes, theta), region index of each dot)."""
    blobs = contour_candidates(grey, True, min_dot_px, max(grey.shape) / 6.0)
    regions = (blobs.centres, blobs.axes, blobs.theta)
    d = 2 * np.sqrt(blobs.axes[:, 0] * blobs.axes[:, 1])
    common = np.flatnonzero(np.abs(d / np.median(d) - 1.0) < 0.4)  # the grid's dots, not its fiducials
    pts, dd = blobs.centres[common], d[common]
    mn, assigned = build_lattice(pts, dd, ratio_guess)
    sel = np.flatnonzero(assigned)
    g = reduce_lattice(mn[sel])
    block = pick_block(g, pts[sel], grey.shape, rows, cols)
    if block is None:
        return None
    lo, hi = g[block].min(axis=0) - margin, g[block].max(axis=0) + margin
    near = np.flatnonzero(np.all((g >= lo) & (g <= hi), axis=1))
    c = intensity_centroids(grey, pts[sel[near]], dd[sel[near]] / 2)
    ok = np.isfinite(c).all(axis=1)
    if not ok[np.searchsorted(near, block)].all():
        return None
    near = near[ok]
    block_in_near = np.searchsorted(near, block)
    return (c[ok], g[near], dd[sel[near]] / 2, block_in_near, regions, common[sel[near]])


def rim_points(lattice: np.ndarray, radius: float) -> np.ndarray:
    """(K, RIM_POINTS, 3) plate points on each dot's rim (plate units, pitch 1)."""
    t = np.linspace(0, 2 * np.pi, RIM_POINTS, endpoint=False)
    ring = radius * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    centre = np.column_stack([lattice.astype(float), np.zeros(len(lattice))])
    return centre[:, None, :] + ring[None]


def polygon_centroids(poly: np.ndarray) -> np.ndarray:
    """(K, 2) area centroids of closed polygons (K, M, 2)."""
    x, y = poly[..., 0], poly[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * y1 - x1 * y
    a = cr.sum(axis=1) / 2
    return np.stack([((x + x1) * cr).sum(axis=1), ((y + y1) * cr).sum(axis=1)], axis=1) / (6 * a[:, None])


def poly_terms(xy: np.ndarray, degree: int = 3) -> np.ndarray:
    """(N, T) monomials x^i y^j, i + j <= degree, of plate points (N, 2) centred and scaled."""
    return np.stack([xy[:, 0] ** i * xy[:, 1] ** j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=1)


class LocalMap:
    """Plate → image map near a hole: a homography times a cubic correction, fitted to dots around it."""

    def __init__(self, plate_xy: np.ndarray, image_uv: np.ndarray, centre: np.ndarray, degree: int = 3):
        self.centre, self.degree = centre, degree
        self.h = fit_homography(plate_xy - centre, image_uv)
        a = poly_terms(plate_xy - centre, degree)
        self.coef = np.linalg.lstsq(a, image_uv - hproject(self.h, plate_xy - centre), rcond=None)[0]

    def __call__(self, plate_xy: np.ndarray) -> np.ndarray:
        q = plate_xy - self.centre
        return hproject(self.h, q) + poly_terms(q, self.degree) @ self.coef


def area_centroids(fmap: LocalMap, lattice: np.ndarray, radius: float) -> np.ndarray:
    """(K, 2) area centroids of the dots' rims mapped through ``fmap``."""
    rim = rim_points(lattice, radius)[..., :2]
    return polygon_centroids(fmap(rim.reshape(-1, 2)).reshape(len(lattice), RIM_POINTS, 2))


def predict_hole(lattice: np.ndarray, centroids: np.ndarray, hole: np.ndarray, radius: float, margin: int = 3):
    """Predict the dots ``hole`` (indices) from the others within ``margin`` lattice steps of it
    (step 4): (centre (K, 2), area centroid (K, 2), RMS residual of the map on the others px, n)."""
    lo, hi = lattice[hole].min(axis=0) - margin, lattice[hole].max(axis=0) + margin
    near = np.all((lattice >= lo) & (lattice <= hi), axis=1)
    near[hole] = False
    idx = np.flatnonzero(near)
    xy = lattice.astype(float)
    centre = xy[hole].mean(axis=0)
    fmap = LocalMap(xy[idx], centroids[idx], centre)  # first on the centroids: the rim shift is tiny
    for _ in range(2):
        shift = area_centroids(fmap, lattice[idx], radius) - fmap(xy[idx])
        fmap = LocalMap(xy[idx], centroids[idx] - shift, centre)
    res = np.linalg.norm(area_centroids(fmap, lattice[idx], radius) - centroids[idx], axis=1)
    inl = res < max(4 * np.median(res), 0.3)
    fmap = LocalMap(xy[idx[inl]], (centroids[idx] - shift)[inl], centre)
    res = np.linalg.norm(area_centroids(fmap, lattice[idx[inl]], radius) - centroids[idx[inl]], axis=1)
    rms = float(np.sqrt(np.mean(res ** 2)))
    return fmap(xy[hole]), area_centroids(fmap, lattice[hole], radius), rms, int(inl.sum())


def pick_block(lattice: np.ndarray, centroids: np.ndarray, shape, rows: int, cols: int) -> np.ndarray | None:
    """Indices (rows*cols,) row-major of the complete rows × cols block nearest the image centre."""
    h, w = shape
    have = {tuple(g): i for i, g in enumerate(lattice)}
    order = np.argsort(np.linalg.norm(centroids - [w / 2, h / 2], axis=1))
    for seed in order[:40]:
        lo = lattice[seed] - [rows // 2, cols // 2]
        idx = [have.get((lo[0] + r, lo[1] + c)) for r in range(rows) for c in range(cols)]
        if all(i is not None for i in idx):
            return np.array(idx)
    return None


FISHEYE = (170.0, -0.35, 0.1)
"""The fisheye view (:func:`fisheye_view`): focal length (px), k1, k2 (OpenCV radial model, as
the fisheye stress case)."""


def fisheye_view(img: np.ndarray, block_centre: np.ndarray, half_extent: np.ndarray, w: int,
                 h: int) -> tuple[np.ndarray, object]:
    """A W × H frame of ``img`` through strong barrel distortion (:data:`FISHEYE`), the block
    (centre, half extent (2,) px with its dots) moved off the optical axis as far as it stays
    whole in the frame (at most 30 % of the frame): (frame (h, w) uint8, map of ``img`` px
    (N, 2) → frame px). The frame is resampled bilinearly from ``img`` at the undistorted
    position of each of its pixels."""
    f, k1, k2 = FISHEYE
    cx, cy = (w - 1) / 2, (h - 1) / 2
    offset = np.clip(np.array([w / 2, h / 2]) - half_extent - 6.0, 0.0, 0.3 * np.array([w, h]))
    axis = block_centre - offset  # img px on the optical axis
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (uu - cx) / f, (vv - cy) / f
    rd = np.hypot(xd, yd)
    ru = rd.copy()
    for _ in range(30):  # invert r_d = r_u (1 + k1 r_u² + k2 r_u⁴)
        ru = rd / (1 + k1 * ru ** 2 + k2 * ru ** 4)
    scale = np.where(rd > 0, ru / np.maximum(rd, 1e-12), 1.0)
    map_u = (axis[0] + f * xd * scale).astype(np.float32)
    map_v = (axis[1] + f * yd * scale).astype(np.float32)
    frame = cv2.remap(img, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def to_frame(uv: np.ndarray) -> np.ndarray:
        x, y = (uv[:, 0] - axis[0]) / f, (uv[:, 1] - axis[1]) / f
        r2 = x * x + y * y
        g = 1 + k1 * r2 + k2 * r2 * r2
        return np.column_stack([cx + f * x * g, cy + f * y * g])

    return frame, to_frame


def inpaint_regions(grey: np.ndarray, boxes: list) -> np.ndarray:
    """``grey`` with the ellipses ``boxes`` (u, v, width, height, angle deg; px) inpainted from the
    pixels around them (``cv2.INPAINT_TELEA``, radius 5 px)."""
    mask = np.zeros(grey.shape, np.uint8)
    for u, v, w, h, deg in boxes:
        cv2.ellipse(mask, ((u, v), (w, h), deg), 255, -1)
    return cv2.inpaint(grey, mask, 5, cv2.INPAINT_TELEA)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="+", help="NAME=PATH[@X,Y,W,H]: one photograph (or that window of it)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rows", type=int, default=4)
    ap.add_argument("--cols", type=int, default=3)
    ap.add_argument("--ratio", type=float, default=2.5, help="pitch / diameter of the photographed plate")
    ap.add_argument("--min-dot-px", type=float, default=6.0, help="smallest dot searched for, px")
    ap.add_argument("--variants", default="1", help="comma-separated SCALE[:WxH[:fisheye]]: the cut-down image "
                    "resized by SCALE (INTER_AREA down, INTER_CUBIC up), then cropped to W x H px around the "
                    "block, or seen through a fisheye lens (fisheye_view); e.g. 1,0.5,1:360x320,1:320x360:fisheye")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    radius = 0.5 / args.ratio  # plate units: pitch 1
    for spec in args.photos:
        name, path = spec.split("=", 1)
        path, _, window = path.partition("@")
        grey = cv2.cvtColor(cv2.imread(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
        crop_xywh = [int(x) for x in window.split(",")] if window else None
        if crop_xywh is not None:
            x, y, w, h = crop_xywh
            grey = grey[y:y + h, x:x + w]
        found = find_dots(grey, args.ratio, args.rows, args.cols, min_dot_px=args.min_dot_px)
        if found is None:
            print(f"{name}: no complete {args.rows}x{args.cols} block of measurable dots")
            continue
        c, g, r, block, (centres_r, axes_r, theta_r), region_idx = found
        rim = rim_ellipse_centres(grey, c[block], r[block])
        rim_sloped = rim_ellipse_centres(grey, c[block], r[block], sloped=True)
        spread = np.linalg.norm(c[block] - rim, axis=1)
        _, predicted, map_rms, n_others = predict_hole(g, c, block, radius)
        to_map = np.linalg.norm(c[block] - predicted, axis=1)  # labelling check: the lattice holds
        keep = np.zeros(len(centres_r), bool)
        keep[region_idx[block]] = True
        boxes = [(float(u), float(v), float(2.6 * a + 6), float(2.6 * b + 6), float(np.degrees(th)))
                 for (u, v), (a, b), th, kk in zip(centres_r, axes_r, theta_r, keep, strict=True)
                 if not kk]  # inpaint every region but the block's dots
        cut = inpaint_regions(grey, boxes)
        for variant in args.variants.split(","):
            scale_txt, _, rest = variant.partition(":")
            crop_txt, _, lens = rest.partition(":")
            scale = float(scale_txt)
            size = (round(cut.shape[1] * scale), round(cut.shape[0] * scale))
            img = cut if scale == 1 else cv2.resize(cut, size, interpolation=cv2.INTER_AREA if scale < 1
                                                    else cv2.INTER_CUBIC)
            sx, sy = img.shape[1] / cut.shape[1], img.shape[0] / cut.shape[0]
            mid = np.array([(c[block, 0].mean() + 0.5) * sx - 0.5, (c[block, 1].mean() + 0.5) * sy - 0.5])
            to_out, origin = None, None
            if crop_txt:
                w, h = (int(x) for x in crop_txt.split("x"))
                if lens == "fisheye":
                    ext = (np.ptp(c[block], axis=0) / 2 + r[block].max()) * np.array([sx, sy])
                    img, to_out = fisheye_view(img, mid, ext, w, h)
                else:  # a window of W x H px centred on the block (inside the image)
                    origin = np.clip(np.round(mid - [w / 2, h / 2]), 0, [img.shape[1] - w, img.shape[0] - h])
                    x0, y0 = int(origin[0]), int(origin[1])
                    img = img[y0:y0 + h, x0:x0 + w]
                    to_out = lambda uv, o=origin: uv - o  # noqa: E731

            def scaled(uv, sx=sx, sy=sy, to_out=to_out):
                q = np.column_stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5])
                return q if to_out is None else to_out(q)

            # the rim ellipse fitted again on the image as delivered (through the lens: the centre
            # of the distorted dot's ellipse, what a hand fit on that image measures)
            ring = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], axis=1)
            r_out = np.array([np.median(np.linalg.norm(scaled(cc + rr * ring) - scaled(cc[None]), axis=1))
                              for cc, rr in zip(rim, r[block], strict=True)])
            rim_here = rim_ellipse_centres(img, scaled(rim), r_out)
            stem = name + ("" if variant == "1" else "_x" + variant.replace(":", "_"))
            cv2.imwrite(str(args.out / f"{stem}.png"), img)
            truth = {"source": path, "variant": variant, "crop_xywh": crop_xywh, "inpaint_ellipses": boxes,
                     "window_origin": None if origin is None else origin.tolist(),
                     "rows": args.rows, "cols": args.cols,
                     "pitch_over_diameter": args.ratio, "dot_diameter_px": float(np.median(2 * r[block])) * sx,
                     "truth_px": scaled(rim).tolist(), "centroid_px": scaled(c[block]).tolist(),
                     "rim_sloped_px": scaled(rim_sloped).tolist(),
                     "rim_in_image_px": rim_here.tolist(),
                     "block_lattice": g[block].tolist(),
                     "centroid_vs_truth_px": (spread * sx).tolist(),
                     "neighbour_map_rms_px": map_rms * sx, "neighbour_map_n_dots": n_others,
                     "centroid_vs_neighbour_map_px": (to_map * sx).tolist()}
            (args.out / f"{stem}.json").write_text(json.dumps(truth, indent=1))
        print(f"{name}: {len(g)} dots, block d {np.median(2 * r[block]):.1f} px; rim ellipse vs intensity centroid "
              f"median {np.median(spread):.3f} max {spread.max():.3f} px; block vs the map of {n_others} "
              f"neighbours median {np.median(to_map):.3f} max {to_map.max():.3f} px (map RMS {map_rms:.3f})",
              flush=True)


if __name__ == "__main__":
    main()
