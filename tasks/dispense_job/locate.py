"""Locate the dispensing areas in a tray image, the paper's pipeline step by step (§2.2–2.4).

Each step is a function of its input image, so that it can be run and looked at alone:

1. :func:`r_channel` — R channel (eq. 3 with W_R = 1: the capacitor stands out against any green or
   blue solder mask, Figure 2a); :func:`equalise` is the histogram equalisation of eqs. 1–2, for
   viewing: Otsu is computed on the channel itself, since equalisation (a monotone map, which keeps the
   classes' order) spreads the dominant dark mode of a tray image over the whole grey range, and
   Otsu's threshold then falls inside that mode;
2. :func:`smooth` — the 3 × 3 median filter (beside it the mean and Gaussian filters of Figure 3);
3. :func:`binarise` — Otsu's threshold (eqs. 4–13), computed over the boards' pixels and applied inside
   them (§2.2.3: the search area reduced to the objects; :func:`board_region`);
4. :func:`blobs` — morphology (opening, then closing) and blob analysis (connected components);
5. :func:`sobel_edges` — the Sobel gradient magnitude of a blob (eqs. 14–16), thresholded;
6. :func:`thin_edges` — thinning to one-pixel lines (the paper's Hilditch step; scikit-image's thinning);
7. :func:`min_area_rect` — the minimum-area rectangle of the thinned edge (§2.4.1, rotating calipers),
   its centre (eqs. 29–30), size, angle and the blob's area in pixels (§2.4.2);
8. :func:`refine_centre` — a step beyond the paper: the rectangle's four sides measured to a fraction
   of a pixel on the raw R channel (grey-level edge positions across each side, median per side),
   which moves the centre from the edge pixels' grid to the image's own edges; run twice, the second
   time from the first's sides.

The acceptance of an area (aspect ratio and area) is tasks.dispense_job.area_acceptance; the boards
(found on the colour saturation against the grey tray) and the pairing of areas with boards are
:func:`find_boards` and :func:`locate`.

Frames: image pixels, u right, v down, origin at the centre of the top-left pixel. Angles in degrees,
counter-clockwise as seen with v up (so a tray frame with y up keeps them), the long axis' in [0, 180).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage
from skimage.morphology import thin

from tasks.dispense_job.area_acceptance import AcceptanceRules, accept_area
from tasks.vision.detection.edges import gradient_magnitude

# of 255: the grey tray is below 0.2 after the median, every solder mask above 0.3 under the brightest glare;
# a fixed threshold, not Otsu's: Otsu's splits a blank tray's noise, and with boards it sits so high that
# glare on a dark mask falls below it and cuts a notch into the board's outline
BOARD_SATURATION = 64


def r_channel(rgb: np.ndarray) -> np.ndarray:
    """The R channel (uint8, contiguous) of an RGB image (H, W, 3) uint8."""
    return np.ascontiguousarray(rgb[..., 0])


def equalise(gray: np.ndarray) -> np.ndarray:
    """Histogram equalisation (eqs. 1–2) of a uint8 image."""
    return cv2.equalizeHist(gray)


def smooth(gray: np.ndarray, method: str = "median") -> np.ndarray:
    """3 × 3 ``median`` (the paper's choice), ``mean`` or ``gaussian`` filter of a uint8 image."""
    if method == "median":
        return cv2.medianBlur(gray, 3)
    if method == "mean":
        return cv2.blur(gray, (3, 3))
    if method == "gaussian":
        return cv2.GaussianBlur(gray, (3, 3), 0)
    raise ValueError(f"unknown filter {method!r}: median, mean or gaussian")


def binarise(gray: np.ndarray, region: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(binary uint8 0/255, Otsu's threshold) of a uint8 image: the bright class is the foreground.
    ``region`` (bool, the image's shape): Otsu's threshold from these pixels only, and the foreground
    kept inside them (the paper's search area reduced to the boards)."""
    if region is None or not region.any():
        t, out = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        return out, float(t)
    t, _ = cv2.threshold(gray[region].reshape(-1, 1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return np.where(region & (gray > t), 255, 0).astype(np.uint8), float(t)


def blobs(binary: np.ndarray, min_px: int = 20) -> tuple[np.ndarray, list[np.ndarray]]:
    """Opening then closing with a 3 × 3 square (drops specks, fills pin-holes), then the connected
    components of at least ``min_px`` pixels: (label image int32, list of (x, y, w, h, area) boxes)."""
    k = np.ones((3, 3), np.uint8)
    clean = cv2.morphologyEx(cv2.morphologyEx(binary, cv2.MORPH_OPEN, k), cv2.MORPH_CLOSE, k)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(clean, connectivity=8)
    keep = [stats[i] for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_px]
    ids = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_px]
    return labels, [np.append(s[:4], [s[4], i]) for s, i in zip(keep, ids, strict=True)]


def sobel_edges(mask: np.ndarray) -> np.ndarray:
    """Edge pixels (bool) of a blob mask (uint8 0/255): Sobel gradient magnitude (3 × 3, eq. 15) above
    half its maximum. The magnitudes are correctly rounded (``cv2.magnitude``'s ulp errors depend on
    the arrays' alignment in memory, which would move pixels at exactly half the maximum)."""
    mag = gradient_magnitude(cv2.Sobel(mask, cv2.CV_16S, 1, 0, ksize=3), cv2.Sobel(mask, cv2.CV_16S, 0, 1, ksize=3))
    return mag > 0.5 * mag.max() if mag.max() > 0 else np.zeros(mask.shape, bool)


def thin_edges(edges: np.ndarray) -> np.ndarray:
    """One-pixel-wide lines (bool) from thick edges (scikit-image's thinning, the Hilditch step)."""
    return thin(edges)


@dataclass(frozen=True)
class Rect:
    """A minimum-area rectangle: centre (u, v) px, long and short sides (px), long-axis angle (deg,
    counter-clockwise with v up, in [0, 180)), the four corners (4, 2) px."""

    u: float
    v: float
    length_px: float
    width_px: float
    angle_deg: float
    corners: np.ndarray = field(compare=False)


def min_area_rect(points_uv: np.ndarray) -> Rect:
    """Minimum-area rectangle of points (N, 2) px (OpenCV's rotating calipers over the convex hull,
    the boundary rotation of §2.4.1); centre = the diagonals' midpoint (eqs. 29–30)."""
    (u, v), (w, h), a = cv2.minAreaRect(points_uv.astype(np.float32))
    corners = cv2.boxPoints(((u, v), (w, h), a))
    if w < h:
        w, h, a = h, w, a + 90.0
    angle = (-a) % 180.0  # OpenCV's angle is clockwise on screen (v down)
    return Rect(float(u), float(v), float(w), float(h), float(angle), corners)


def refine_centre(r_channel: np.ndarray, rect: Rect, reach_px: float = 5.0, step_px: float = 0.25,
                  profiles: int = 25) -> Rect:
    """The rectangle's sides to a fraction of a pixel: across each side, ``profiles`` grey-level
    profiles of the raw channel (bilinear, ``step_px`` apart, ``reach_px`` either side, the corners'
    fifth of each side left out) find where the level crosses halfway between the outside and inside
    levels of that profile; each side's offset is the median of its crossings. Returns the rectangle
    rebuilt from the four offsets (same angle)."""
    t = np.deg2rad(rect.angle_deg)
    along = np.array([np.cos(t), -np.sin(t)])  # long axis in (u, v): v is down
    across = np.array([np.sin(t), np.cos(t)])
    c = np.array([rect.u, rect.v])
    f = r_channel.astype(np.float32)
    s = np.arange(-reach_px, reach_px + step_px / 2, step_px)
    offsets = []
    for axis, other, half, half_other in ((along, across, rect.length_px / 2, rect.width_px / 2),
                                          (across, along, rect.width_px / 2, rect.length_px / 2)):
        for sign in (1.0, -1.0):
            n = sign * axis
            pos = np.linspace(-0.6 * half_other, 0.6 * half_other, profiles)
            # sample points: (profiles, len(s), 2), from inside (s < 0) to outside (s > 0)
            pts = c + n * half + pos[:, None, None] * other + s[None, :, None] * n
            vals = ndimage.map_coordinates(f, [pts[..., 1], pts[..., 0]], order=1, mode="nearest")
            inside, outside = vals[:, :4].mean(axis=1), vals[:, -4:].mean(axis=1)
            mid = (inside + outside) / 2
            below = (vals - mid[:, None]) * np.sign(inside - outside)[:, None] < 0  # past the edge
            first = np.argmax(below, axis=1)
            ok = below.any(axis=1) & (first > 0) & (np.abs(inside - outside) > 10)
            if not ok.any():
                offsets.append(half)
                continue
            i = first[ok]
            rows = np.flatnonzero(ok)
            v0, v1 = vals[rows, i - 1], vals[rows, i]
            frac = (v0 - mid[ok]) / (v0 - v1)
            offsets.append(half + float(np.median(s[i - 1] + frac * step_px)))
    (lp, lm, wp, wm) = offsets
    centre = c + along * (lp - lm) / 2 + across * (wp - wm) / 2
    corners = np.array([centre + sa * along * (lp + lm) / 2 + sb * across * (wp + wm) / 2
                        for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return Rect(float(centre[0]), float(centre[1]), lp + lm, wp + wm, rect.angle_deg, corners)


@dataclass(frozen=True)
class Area:
    """A candidate dispensing area: its rectangle (refined), the paper's rectangle (before refinement),
    the blob's pixel count, accepted and the reason when not, the board it lies on ('' when none)."""

    rect: Rect
    paper_rect: Rect
    area_px: int
    accepted: bool
    reason: str
    board: int = -1


def find_areas(rgb: np.ndarray, rules: AcceptanceRules, mm_per_px: float, region: np.ndarray | None = None
               ) -> list[Area]:
    """Steps 1–8 on a tray image (H, W, 3) uint8 RGB: every R-channel blob as a candidate area with
    its rectangle and acceptance (aspect ratio and area at ``mm_per_px``). ``region``: where to look
    (bool mask, e.g. :func:`board_region`; None: everywhere)."""
    r_raw = r_channel(rgb)
    binary, _ = binarise(smooth(r_raw), region)
    min_px = max(int(rules.min_blob_mm2 / mm_per_px ** 2), 4)
    labels, boxes = blobs(binary, min_px)
    out = []
    for x, y, w, h, count, label in boxes:
        pad = 3
        x0, y0 = max(x - pad, 0), max(y - pad, 0)
        x1, y1 = min(x + w + pad, binary.shape[1]), min(y + h + pad, binary.shape[0])
        mask = np.where(labels[y0:y1, x0:x1] == label, 255, 0).astype(np.uint8)
        line = thin_edges(sobel_edges(mask))
        vv, uu = np.nonzero(line)
        if len(uu) < 5:
            continue
        paper = min_area_rect(np.column_stack([uu + x0, vv + y0]))
        ok, reason = accept_area(paper.length_px * mm_per_px, paper.width_px * mm_per_px, count * mm_per_px ** 2,
                                 rules)
        # twice: a speck merged into the blob moves the paper's side by pixels, and the first pass's
        # inside samples then straddle the true edge; the second starts from the first's sides
        rect = refine_centre(r_raw, refine_centre(r_raw, paper)) if ok else paper
        out.append(Area(rect, paper, int(count), ok, reason))
    return out


@dataclass(frozen=True)
class BoardBlob:
    """A board found in the image: its minimum-area rectangle (px), its outline (K, 2) px, the depth
    of its deepest notch (px) and whether it touches the image border."""

    rect: Rect
    outline: np.ndarray = field(compare=False)
    notch_px: float = 0.0
    cut_by_border: bool = False


def find_boards(rgb: np.ndarray, rules: AcceptanceRules, mm_per_px: float) -> list[BoardBlob]:
    """Boards against the black tray: the colour saturation (max − min) / max (a solder mask is
    coloured, the tray grey; a ratio, so the ring light's fall-off leaves it), 5 × 5 median, above
    :data:`BOARD_SATURATION`,
    blobs of at least half a board's area (``rules.board_mm``); each with its notch depth (convexity
    defects of its outline: a broken edge)."""
    r, g, b = cv2.split(np.ascontiguousarray(rgb))
    hi, lo = cv2.max(cv2.max(r, g), b).astype(np.float32), cv2.min(cv2.min(r, g), b).astype(np.float32)
    # below 32 DN the ratio is noise over noise: such pixels count as grey
    saturation = cv2.medianBlur(np.rint(255.0 * (hi - lo) / np.maximum(hi, 32.0)).astype(np.uint8), 5)
    binary = np.where(saturation > BOARD_SATURATION, 255, 0).astype(np.uint8)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    min_px = 0.5 * rules.board_mm[0] * rules.board_mm[1] / mm_per_px ** 2
    out = []
    height, width = binary.shape
    for cnt in contours:
        if cv2.contourArea(cnt) < min_px:
            continue
        pts = cnt.reshape(-1, 2)
        hull = cv2.convexHull(cnt, returnPoints=False)
        defects = cv2.convexityDefects(cnt, hull)
        notch = 0.0 if defects is None else float(defects.reshape(-1, 4)[:, 3].max()) / 256.0
        border = bool(pts[:, 0].min() <= 0 or pts[:, 1].min() <= 0 or pts[:, 0].max() >= width - 1
                      or pts[:, 1].max() >= height - 1)
        out.append(BoardBlob(min_area_rect(pts), pts, notch, border))
    return out


def board_region(boards: list[BoardBlob], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the inside of the boards' outlines. Otsu's threshold of the R channel over the
    whole tray splits the black tray from the dark masks when the boards are few; over the boards it
    splits the masks from what is bright on them."""
    mask = np.zeros(shape, np.uint8)
    cv2.drawContours(mask, [b.outline.reshape(-1, 1, 2).astype(np.int32) for b in boards], -1, 255, cv2.FILLED)
    return mask > 0


@dataclass(frozen=True)
class BoardResult:
    """One board's verdict: its blob, its accepted area (None when rejected), ok, and why not."""

    board: BoardBlob
    area: Area | None
    ok: bool
    reason: str


@dataclass(frozen=True)
class Located:
    """Everything found in one image: the boards with their verdicts and every candidate area."""

    boards: list[BoardResult]
    areas: list[Area]


def locate(rgb: np.ndarray, rules: AcceptanceRules | None = None, mm_per_px: float = 0.045) -> Located:
    """The boards and their dispensing areas in a tray image (H, W, 3) uint8 RGB at ``mm_per_px``
    (planar scale). A board is rejected (with its reason) when its outline is cut by the image border,
    has a notch deeper than ``rules.max_notch_mm`` (broken edge), or holds no accepted area, or more
    than one. Candidate areas off every board are kept in ``areas`` with board −1."""
    rules = rules or AcceptanceRules()
    boards = find_boards(rgb, rules, mm_per_px)
    areas = find_areas(rgb, rules, mm_per_px, board_region(boards, rgb.shape[:2]))
    placed = []
    for a in areas:
        inside = [i for i, b in enumerate(boards)
                  if cv2.pointPolygonTest(b.outline.reshape(-1, 1, 2).astype(np.int32), (a.rect.u, a.rect.v),
                                          False) >= 0]
        placed.append(Area(a.rect, a.paper_rect, a.area_px, a.accepted, a.reason, inside[0] if inside else -1))
    results = []
    for i, b in enumerate(boards):
        mine = [a for a in placed if a.board == i and a.accepted]
        if b.cut_by_border:
            results.append(BoardResult(b, None, False, "board cut by the image border"))
        elif b.notch_px * mm_per_px > rules.max_notch_mm:
            results.append(BoardResult(b, None, False, f"broken edge: a notch {b.notch_px * mm_per_px:.2f} mm deep "
                                                       f"in the board's outline"))
        elif not mine:
            near = [a.reason for a in placed if a.board == i]
            why = "; ".join(sorted(set(near))) if near else "nothing bright in R"
            results.append(BoardResult(b, None, False, f"no dispensing area (component missing?): {why}"))
        elif len(mine) > 1:
            results.append(BoardResult(b, None, False, f"{len(mine)} dispensing areas on one board"))
        else:
            results.append(BoardResult(b, mine[0], True, ""))
    return Located(results, placed)
