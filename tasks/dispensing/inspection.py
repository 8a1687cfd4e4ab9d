"""Inspection of dispensed dots (§4.3) and their sub-pixel centres (§4.1, dispensed-dot branch).

§4.3, per image (or per region of interest): Gaussian smoothing; both polarities thresholded
(background ± k·σ_noise), each opened and closed; the polarity with more valid contours wins, then
the one with the larger total area; candidate regions within the area limits, regions touching the
border excluded; per region area A, perimeter P, equivalent diameter d = √(4A/π), circularity
C = 4πA/P², NSD_r = σ_r/μ_r of the contour radii from the centroid (eqs. of §4.3) and CoV_I = σ_I/μ_I
of the grey levels inside; qualified when A_min ≤ A ≤ A_max, C ≥ C_min, NSD_r ≤ τ_r, CoV_I ≤ τ_I
(thresholds: :class:`InspectionConfig`, from a TOML file; defaults in inspection_defaults.toml,
justified in docs/dispensing-test.md).

The measurement itself is sub-pixel: each region's outline is refined along its radii to where the
smoothed grey level crosses halfway between the background and the region's own level, the blur's
pull of that crossing towards the centre of curvature (σ²/2R) taken out, and the centre is the
least-squares circle through the refined outline. A, P, d, C and NSD_r are those of the refined
outline.

§4.1, for the ring target: CLAHE, Canny edges, edges filtered by length and convexity, the ring
as two concentric circles, accepted when enough of the fitted circle is edge (the effective pixel
ratio); then both ring edges refined as above and the centre is the mean of their least-squares
circles. The dot is looked for in the circular region of interest inside the ring only.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, fields, replace
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

DEFAULTS_FILE = Path(__file__).with_name("inspection_defaults.toml")
CANDIDATE_CONTRAST_SHARE = 0.25


@dataclass(frozen=True)
class InspectionConfig:
    """Parameters of the inspection (px, DN, dimensionless). See inspection_defaults.toml."""

    smoothing_sigma_px: float = 1.0
    threshold_sigmas: float = 5.0
    morphology_px: int = 3
    region_min_px2: float = 12.0
    region_max_px2: float = 5000.0
    area_min_px2: float = 180.0
    area_max_px2: float = 340.0
    circularity_min: float = 0.90
    nsd_r_max: float = 0.05
    cov_i_max: float = 0.03
    ring_min_edge_ratio: float = 0.6
    ring_min_convexity: float = 0.9
    ring_min_length_px: float = 60.0
    roi_margin_px: float = 4.0


def load_config(path: str | Path | None = None) -> InspectionConfig:
    """The inspection parameters: the defaults file, overridden by the keys of ``path`` (TOML, section
    [inspection]); ValueError naming the file for an unknown key or a non-number."""
    values: dict = {}
    for p in (DEFAULTS_FILE, path):
        if p is None:
            continue
        doc = tomllib.loads(Path(p).read_text()).get("inspection", {})
        known = {f.name for f in fields(InspectionConfig)}
        unknown = set(doc) - known
        if unknown:
            raise ValueError(f"{p}: unknown inspection parameter(s) {sorted(unknown)}; known: {sorted(known)}")
        for k, v in doc.items():
            if not isinstance(v, int | float) or isinstance(v, bool):
                raise ValueError(f"{p}: inspection parameter {k} = {v!r} is not a number")
            values[k] = v
    cfg = InspectionConfig(**values)
    return replace(cfg, morphology_px=int(cfg.morphology_px))


@dataclass
class Region:
    """One candidate region: sub-pixel centre (px, least-squares circle), A (px²), P (px), d (px),
    C, NSD_r, CoV_I, its polarity ("bright"/"dark"), whether it touches the border, and the verdict."""

    x_px: float
    y_px: float
    area_px2: float
    perimeter_px: float
    diameter_px: float
    circularity: float
    nsd_r: float
    cov_i: float
    polarity: str
    touches_border: bool
    qualified: bool = False
    reason: str = ""


def smoothed_noise_sigma(gray: np.ndarray, roi: np.ndarray, smoothing_sigma_px: float) -> float:
    """The noise σ (DN) of the smoothed image inside ``roi``: the raw pixel noise from the robust
    spread of horizontal neighbour differences (edges and dots are too few to move their median
    absolute deviation), divided by 2√π·σ, what Gaussian smoothing of white noise leaves of it."""
    g = gray.astype(np.float64)
    both = roi[:, 1:] & roi[:, :-1]
    d = (g[:, 1:] - g[:, :-1])[both]
    raw = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0)
    return float(raw / (2.0 * np.sqrt(np.pi) * smoothing_sigma_px))


def _binary(smooth: np.ndarray, roi: np.ndarray, background: float, threshold: float, bright: bool,
            morphology_px: int) -> np.ndarray:
    mask = (smooth > background + threshold) if bright else (smooth < background - threshold)
    mask = (mask & roi).astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (morphology_px, morphology_px))
    return cv2.morphologyEx(cv2.morphologyEx(mask, cv2.MORPH_OPEN, k), cv2.MORPH_CLOSE, k)


def _contours(mask: np.ndarray):
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return contours


def _touches(contour: np.ndarray, border: np.ndarray) -> bool:
    pts = contour[:, 0, :]
    return bool(border[pts[:, 1], pts[:, 0]].any())


def _valid(contours, border: np.ndarray, cfg: InspectionConfig) -> list:
    return [c for c in contours if cfg.region_min_px2 <= cv2.contourArea(c) <= cfg.region_max_px2
            and not _touches(c, border)]


def flatten_background(smooth: np.ndarray, background: np.ndarray) -> np.ndarray:
    """``smooth`` less the tilt of a plane fitted to its ``background`` pixels (bool mask): an
    illumination gradient across a dot would otherwise move its mid-level crossings one way on both
    sides, shifting its centre by about the gradient's change across half the dot / the edge slope."""
    yy, xx = np.nonzero(background)
    if len(xx) < 10:
        return smooth
    A = np.column_stack([xx, yy, np.ones(len(xx))]).astype(float)
    (gx, gy, _), *_ = np.linalg.lstsq(A, smooth[yy, xx], rcond=None)
    rows, cols = np.mgrid[0:smooth.shape[0], 0:smooth.shape[1]]
    return smooth - gx * (cols - xx.mean()) - gy * (rows - yy.mean())


def choose_polarity(smooth: np.ndarray, roi: np.ndarray, border: np.ndarray, background: float, threshold: float,
                    cfg: InspectionConfig) -> tuple[str, list, list]:
    """§4.3's automatic polarity: both binaries, opened and closed; more valid contours wins, then
    larger total area. Returns (polarity, its valid contours, all its contours)."""
    scored = []
    for name, bright in (("bright", True), ("dark", False)):
        allc = _contours(_binary(smooth, roi, background, threshold, bright, cfg.morphology_px))
        valid = _valid(allc, border, cfg)
        scored.append((len(valid), sum(cv2.contourArea(c) for c in valid), name, valid, allc))
    best = max(scored, key=lambda s: (s[0], s[1]))
    return best[2], best[3], best[4]


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares circle (algebraic, Kåsa) through points: centre (px) and radius (px)."""
    A = np.column_stack([x, y, np.ones_like(x)])
    b = x * x + y * y
    (a0, a1, a2), *_ = np.linalg.lstsq(A, b, rcond=None)
    cx, cy = a0 / 2, a1 / 2
    return float(cx), float(cy), float(np.sqrt(a2 + cx * cx + cy * cy))


def refine_edges(smooth: np.ndarray, cx: float, cy: float, angles: np.ndarray, radii: np.ndarray, inside: float,
                 outside: float, window_px: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel edge radii along rays from (cx, cy) at ``angles`` (rad), each searched within
    ± ``window_px`` of ``radii`` (px) for the crossing of the level halfway between ``inside`` and
    ``outside`` (DN) nearest the start. Returns (radii (N,), ok (N,) bool)."""
    steps = np.arange(-window_px, window_px + 1e-9, 0.25)
    rr = radii[:, None] + steps[None, :]
    xs = cx + rr * np.cos(angles)[:, None]
    ys = cy + rr * np.sin(angles)[:, None]
    prof = ndimage.map_coordinates(smooth, [ys.ravel(), xs.ravel()], order=3, mode="nearest").reshape(rr.shape)
    level = 0.5 * (inside + outside)
    sign = np.sign(inside - outside)
    f = sign * (prof - level)  # > 0 inside
    cross = (f[:, :-1] > 0) & (f[:, 1:] <= 0)
    centre = len(steps) // 2
    dist = np.where(cross, np.abs(np.arange(len(steps) - 1) - centre + 0.5), np.inf)
    j = np.argmin(dist, axis=1)
    ok = np.isfinite(dist[np.arange(len(j)), j])
    f0, f1 = f[np.arange(len(j)), j], f[np.arange(len(j)), j + 1]
    frac = np.where(ok, f0 / np.where(f0 - f1 == 0, 1, f0 - f1), 0.0)
    return rr[np.arange(len(j)), j] + frac * 0.25, ok


def edge_blur_sigma(smooth: np.ndarray, cx: float, cy: float, angles: np.ndarray, radii: np.ndarray,
                    contrast: float) -> float:
    """The total blur σ (px) at an edge: contrast / (√(2π) · steepest mean radial slope)."""
    steps = np.arange(-4.0, 4.0 + 1e-9, 0.25)
    rr = radii[:, None] + steps[None, :]
    prof = ndimage.map_coordinates(smooth, [(cy + rr * np.sin(angles)[:, None]).ravel(),
                                            (cx + rr * np.cos(angles)[:, None]).ravel()],
                                   order=3, mode="nearest").reshape(rr.shape).mean(axis=0)
    slope = np.max(np.abs(np.diff(prof))) / 0.25
    return float(abs(contrast) / (np.sqrt(2 * np.pi) * slope)) if slope > 0 else 0.0


def _outline_features(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Area (shoelace), perimeter, NSD_r about the centroid, and the centroid distance spread of a
    closed polygon (px)."""
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    per = float(np.hypot(xn - x, yn - y).sum())
    gx = ((x + xn) * cross).sum() / (6 * area)
    gy = ((y + yn) * cross).sum() / (6 * area)
    rho = np.hypot(x - gx, y - gy)
    return float(abs(area)), per, float(rho.std() / rho.mean()), float(rho.mean())


def measure_region(smooth: np.ndarray, contour: np.ndarray, background: float, polarity: str,
                   border: np.ndarray, cfg: InspectionConfig, n_rays: int = 128) -> Region | None:
    """Sub-pixel outline and §4.3 features of one region (None if its outline cannot be refined)."""
    mask = np.zeros(smooth.shape, np.uint8)
    cv2.drawContours(mask, [contour], -1, 1, thickness=-1)
    m = cv2.moments(contour)
    if m["m00"] <= 0:
        return None
    cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
    inner = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))
    level = float(np.median(smooth[inner > 0] if inner.any() else smooth[mask > 0]))
    pts = contour[:, 0, :].astype(float)
    ang_c = np.arctan2(pts[:, 1] - cy, pts[:, 0] - cx)
    rad_c = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy)
    angles = np.linspace(-np.pi, np.pi, n_rays, endpoint=False)
    order = np.argsort(ang_c)
    start = np.interp(angles, ang_c[order], rad_c[order], period=2 * np.pi)
    radii, ok = refine_edges(smooth, cx, cy, angles, start, level, background)
    if ok.sum() < 0.8 * n_rays:
        return None
    angles, radii = angles[ok], radii[ok]
    blur = edge_blur_sigma(smooth, cx, cy, angles, radii, level - background)
    radii = radii + blur ** 2 / (2 * np.mean(radii))  # the mid-level of a blurred disk sits σ²/2R inside
    x, y = cx + radii * np.cos(angles), cy + radii * np.sin(angles)
    ox, oy, _ = fit_circle(x, y)
    area, per, nsd, _ = _outline_features(x, y)
    # CoV_I inside the outline less the blurred rim (2σ + ½ px), where the grey level is the dot's own
    core_r = np.maximum(radii - (2 * blur + 0.5), 0.0)
    poly = np.rint(np.column_stack([cx + core_r * np.cos(angles), cy + core_r * np.sin(angles)]) * 16).astype(np.int32)
    core_mask = np.zeros(smooth.shape, np.uint8)
    cv2.fillPoly(core_mask, [poly], 1, shift=4)
    cov_pixels = smooth[core_mask > 0] if core_mask.sum() >= 5 else smooth[mask > 0]
    cov = float(cov_pixels.std() / cov_pixels.mean()) if cov_pixels.mean() > 0 else float("inf")
    return Region(x_px=ox, y_px=oy, area_px2=area, perimeter_px=per, diameter_px=float(np.sqrt(4 * area / np.pi)),
                  circularity=float(4 * np.pi * area / per ** 2), nsd_r=nsd, cov_i=cov, polarity=polarity,
                  touches_border=_touches(contour, border))


def pixel_region(contour: np.ndarray, polarity: str, touches_border: bool) -> Region:
    """A region from its pixel contour alone (centroid, area, length; NSD_r and CoV_I NaN, so never
    qualified), for one whose outline cannot be refined (cut by the border, or not star-shaped)."""
    m = cv2.moments(contour)
    area, per = float(cv2.contourArea(contour)), float(cv2.arcLength(contour, True))
    cx, cy = (m["m10"] / m["m00"], m["m01"] / m["m00"]) if m["m00"] > 0 else contour[0, 0].astype(float)
    return Region(x_px=float(cx), y_px=float(cy), area_px2=area, perimeter_px=per,
                  diameter_px=float(np.sqrt(4 * area / np.pi)),
                  circularity=float(4 * np.pi * area / per ** 2) if per > 0 else float("nan"), nsd_r=float("nan"),
                  cov_i=float("nan"), polarity=polarity, touches_border=touches_border)


def classify(region: Region, cfg: InspectionConfig) -> Region:
    """§4.3's decision: qualified when A_min ≤ A ≤ A_max, C ≥ C_min, NSD_r ≤ τ_r, CoV_I ≤ τ_I and
    the region does not touch the border; otherwise the reasons, ';'-joined."""
    reasons = []
    if region.touches_border:
        reasons.append("touches the border")
    if not cfg.area_min_px2 <= region.area_px2 <= cfg.area_max_px2:
        reasons.append(f"area {region.area_px2:.0f} px² outside [{cfg.area_min_px2:g}, {cfg.area_max_px2:g}]")
    if region.circularity < cfg.circularity_min:
        reasons.append(f"circularity {region.circularity:.3f} < {cfg.circularity_min:g}")
    if not np.isfinite(region.nsd_r) or not np.isfinite(region.cov_i):
        reasons.append("outline not measurable")
    if region.nsd_r > cfg.nsd_r_max:
        reasons.append(f"NSD_r {region.nsd_r:.3f} > {cfg.nsd_r_max:g}")
    if region.cov_i > cfg.cov_i_max:
        reasons.append(f"CoV_I {region.cov_i:.3f} > {cfg.cov_i_max:g}")
    region.qualified = not reasons
    region.reason = "; ".join(reasons)
    return region


def inspect_regions(gray: np.ndarray, cfg: InspectionConfig, roi: np.ndarray | None = None
                    ) -> tuple[list[Region], str, float]:
    """§4.3 on a grey image (rows, cols) uint8, inside ``roi`` (bool mask; None: the whole image).
    Returns (the regions, border-touching ones included and flagged, classified; the polarity;
    the background level (DN))."""
    smooth = cv2.GaussianBlur(gray.astype(np.float64), (0, 0), cfg.smoothing_sigma_px)
    roi = np.ones(gray.shape, bool) if roi is None else roi
    inside = smooth[roi]
    background = float(np.median(inside))
    threshold = cfg.threshold_sigmas * max(smoothed_noise_sigma(gray, roi, cfg.smoothing_sigma_px), 0.25)
    smooth = flatten_background(smooth, roi & (np.abs(smooth - background) < threshold))
    # the border: the image edge and the edge of the region of interest
    border = ~cv2.erode(roi.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                        borderValue=0).astype(bool)
    polarity, _, allc = choose_polarity(smooth, roi, border, background, threshold, cfg)
    # candidates at a quarter of the contrast at least: a sensitive threshold alone lets the blurred
    # tails of neighbouring dots merge them in the closing
    deviation = (smooth[roi] - background) * (1 if polarity == "bright" else -1)
    contrast = float(np.percentile(deviation, 99.5))
    if CANDIDATE_CONTRAST_SHARE * contrast > threshold:
        allc = _contours(_binary(smooth, roi, background, CANDIDATE_CONTRAST_SHARE * contrast,
                                 polarity == "bright", cfg.morphology_px))
    regions = []
    for c in allc:
        if not cfg.region_min_px2 <= cv2.contourArea(c) <= cfg.region_max_px2:
            continue
        r = measure_region(smooth, c, background, polarity, border, cfg)
        if r is None:  # cut by the border, or an outline the rays cannot follow: reported from its pixels
            r = pixel_region(c, polarity, _touches(c, border))
        regions.append(classify(r, cfg))
    return regions, polarity, background


@dataclass
class Ring:
    """A ring target: sub-pixel centre (px), inner and outer radii (px), effective edge ratio."""

    x_px: float
    y_px: float
    inner_px: float
    outer_px: float
    edge_ratio: float


def convexity(contour: np.ndarray, tolerance_px: float = 1.5) -> float:
    """Share of an edge contour's points within ``tolerance_px`` of its convex hull: 1 for a convex
    curve (an edge traced along both of its sides included), low for a wiggly or concave one."""
    hull = cv2.convexHull(contour)
    pts = contour[:, 0, :].astype(np.float32)
    dist = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), True) for x, y in pts])
    return float(np.mean(dist <= tolerance_px))


def find_ring(gray: np.ndarray, cfg: InspectionConfig) -> Ring | None:
    """The ring target nearest the image centre (§4.1's dispensed-dot branch), or None."""
    smooth = cv2.GaussianBlur(gray.astype(np.float64), (0, 0), cfg.smoothing_sigma_px)
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(4, 4)).apply(gray)
    edges = cv2.Canny(cv2.GaussianBlur(clahe, (0, 0), cfg.smoothing_sigma_px), 40, 120)
    contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    circles = []
    for c in contours:
        if cv2.arcLength(c, True) < cfg.ring_min_length_px:
            continue
        if convexity(c) < cfg.ring_min_convexity:
            continue
        p = c[:, 0, :].astype(float)
        circles.append(fit_circle(p[:, 0], p[:, 1]))
    if not circles:
        return None
    h, w = gray.shape
    # nearest the image centre first, the larger first among those as near
    circles.sort(key=lambda c: (round(np.hypot(c[0] - (w - 1) / 2, c[1] - (h - 1) / 2) / 5.0), -c[2]))
    cx, cy, _ = circles[0]
    radii = np.sort([c[2] for c in circles if np.hypot(c[0] - cx, c[1] - cy) < 2.0])[::-1]
    # Canny draws each edge as two contours a pixel apart: edges are radii more than 2 px apart
    edges_r = [radii[0]]
    for r in radii[1:]:
        if edges_r[-1] - r > 2.0:
            edges_r.append(r)
    if len(edges_r) < 2:
        return None
    r_out, r_in = edges_r[0], edges_r[1]
    # the effective pixel ratio: how much of each fitted circle is edge
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    near = cv2.dilate(edges, np.ones((3, 3), np.uint8)) > 0
    ratios = []
    for r in (r_in, r_out):
        xs, ys = np.rint(cx + r * np.cos(angles)).astype(int), np.rint(cy + r * np.sin(angles)).astype(int)
        inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
        ratios.append(float(near[ys[inside], xs[inside]].sum()) / len(angles))
    ratio = min(ratios)
    if ratio < cfg.ring_min_edge_ratio:
        return None
    # sub-pixel: both edges refined between the substrate and the ring's own level
    mid = 0.5 * (r_in + r_out)
    ring_level = float(np.median(ndimage.map_coordinates(smooth, [cy + mid * np.sin(angles), cx + mid * np.cos(angles)],
                                                          order=1)))
    outside = float(np.median(ndimage.map_coordinates(
        smooth, [cy + (r_out + 4) * np.sin(angles), cx + (r_out + 4) * np.cos(angles)], order=1, mode="nearest")))
    fits = []
    # the inner edge has the substrate inside it, the outer edge the ring
    for r, inner_level, outer_level in ((r_in, outside, ring_level), (r_out, ring_level, outside)):
        rad, ok = refine_edges(smooth, cx, cy, angles, np.full(len(angles), r), inner_level, outer_level)
        if ok.sum() < 0.8 * len(angles):
            return None
        fits.append(fit_circle(cx + rad[ok] * np.cos(angles[ok]), cy + rad[ok] * np.sin(angles[ok])))
    (x0, y0, ri), (x1, y1, ro) = fits
    return Ring(x_px=0.5 * (x0 + x1), y_px=0.5 * (y0 + y1), inner_px=ri, outer_px=ro, edge_ratio=ratio)


@dataclass
class RingInspection:
    """The result of one ring image: the ring (None: no ring), the dot (None: none qualified
    or found), every region found inside the ring, the polarity and the row's verdict."""

    ring: Ring | None
    dot: Region | None
    regions: list[Region]
    polarity: str
    qualified: bool
    reason: str


def inspect_ring_image(gray: np.ndarray, cfg: InspectionConfig) -> RingInspection:
    """The dispensing-test inspection of one image of a ring: the ring's centre, then §4.3 inside
    its circular region of interest. Verdicts: qualified; or a reason (no ring, no dot, two dots,
    the dot touches the border, or the §4.3 features that fail)."""
    ring = find_ring(gray, cfg)
    if ring is None:
        return RingInspection(None, None, [], "", False, "no ring")
    h, w = gray.shape
    yy, xx = np.mgrid[0:h, 0:w]
    roi = np.hypot(xx - ring.x_px, yy - ring.y_px) < ring.inner_px - cfg.roi_margin_px
    regions, polarity, _ = inspect_regions(gray, cfg, roi)
    inside = [r for r in regions if not r.touches_border]
    if not regions:
        return RingInspection(ring, None, regions, polarity, False, "no dot")
    if not inside:
        return RingInspection(ring, regions[0], regions, polarity, False, "dot touches the border")
    if len(regions) > 1:
        main = max(regions, key=lambda r: r.area_px2)
        return RingInspection(ring, main, regions, polarity, False, f"{len(regions)} dots in the ring")
    dot = inside[0]
    return RingInspection(ring, dot, regions, polarity, dot.qualified, dot.reason)
