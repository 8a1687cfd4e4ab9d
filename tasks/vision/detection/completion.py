"""Look again, at the one place the lattice says a dot must be, for a dot no candidate search found.

When every search refuses and the most plate-like lattice (``CoarseAttempt.plate_likeness``) fills
all but one or two places of a rows × cols window, and those places lie inside the image, the dots
there were missed by the candidate searches, not left out of the picture: a dot whose region a
shadow edge or a dark blob next to it merged into a larger one, a Hough rim broken by the edge.
Its place is known to a fraction of a step (a quadratic map from lattice coordinates to image px
fitted to the window's dots: perspective and a lens bend a 4 × 3 window smoothly), and so are its
size (its neighbours') and its grey levels. There, and only there, a dark (light) region is
thresholded halfway between the darkest part of the place and the paper around it (the lower
quartile of a ring between the place and its neighbours: the shadowed side, if a shadow edge
crosses it), and the region the place holds becomes a candidate if it has a dot's size and shape
and its disc looks like a dot (the disc half of the candidates' test,
:func:`tasks.vision.detection.verify.dot_appearance`; its ring half, against the dot's own
contrast, fails where a shadow edge crosses the ring, and the threshold here already measures the
paper on the darker side).
The lattice is then ordered again with it, and every check of a window applies as before
(unique window, strays, the 2 × 2 cells closing): nothing is labelled that the lattice would not
label had the candidate search found the dot.

Units: px of the coarse image the attempt searched.
"""

from __future__ import annotations

import cv2
import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.grid_order import SIMILAR_SIZE
from tasks.vision.detection.lattice_reason import best_window_fill
from tasks.vision.detection.rrht import CoarseCircles
from tasks.vision.detection.stats import percentile

MAX_MISSING_FRACTION = 1 / 6
"""At most this fraction of the plate's dots (at least one) are looked for again: a window that
lacks more is not the plate's with a few dots missed."""
MAX_PLACE_OFFSET_STEPS = 0.3
"""A region is the missing dot only within this fraction of a step of its predicted place."""
MIN_CONTRAST_FRACTION = 0.25
"""… and only where the place is darker (lighter) than the paper around it by this fraction of the
window dots' median contrast (a shadow halves the contrast; paper with no dot has none)."""


def predict_missing(points: np.ndarray, coords: np.ndarray, sizes: np.ndarray, rows: int, cols: int,
                    image_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(places (K, 2) px, diameters (K,) px, step px) of the missing dots of the best window over a
    lattice, or None when it lacks none, too many, or any outside the image.

    points (L, 2) px and their lattice coordinates ``coords`` (L, 2) int; sizes (L,) diameters px."""
    need = rows * cols
    fill = best_window_fill(points, coords, rows, cols, image_shape)
    missing = need - fill.count
    if fill.missing_outside or not 0 < missing <= max(1, int(need * MAX_MISSING_FRACTION)):
        return None
    g = coords - coords.min(axis=0)
    a0, b0, h, w = fill.window
    inside = (g[:, 0] >= a0) & (g[:, 0] < a0 + h) & (g[:, 1] >= b0) & (g[:, 1] < b0 + w)
    if inside.sum() < 6:
        return None

    def design(rc: np.ndarray) -> np.ndarray:
        i, j = rc[:, 0].astype(float), rc[:, 1].astype(float)
        return np.column_stack([np.ones_like(i), i, j, i * i, i * j, j * j])

    d_in = design(g[inside])
    rank = np.linalg.matrix_rank(d_in)
    if rank < 6:  # a window one dot wide in one direction: an affine map
        d_in = d_in[:, :3]
    coef, *_ = np.linalg.lstsq(d_in, points[inside], rcond=None)
    cells = fill.missing_cells
    places = design(cells)[:, : d_in.shape[1]] @ coef
    own = points[inside]
    nn = np.linalg.norm(own[:, None] - own[None], axis=2)
    np.fill_diagonal(nn, np.inf)
    step = float(np.median(nn.min(axis=1)))
    adjacent = np.abs(g[inside][None, :, :] - cells[:, None, :]).sum(axis=2) == 1  # (K, window dots)
    med = float(np.median(sizes[inside]))
    diam = np.array([np.median(sizes[inside][a]) if a.any() else med for a in adjacent])
    return places, diam, step


def find_dot_at(image: np.ndarray, place: np.ndarray, diameter: float, step: float, dark_dots: bool,
                contrast: float, any_size: bool = False) -> np.ndarray | None:
    """(u, v, major semi-axis, minor semi-axis, major-axis angle rad) of the dot-like region of
    ``image`` (uint8) at ``place`` (px), or None: the region darker (lighter) than halfway between
    the place's darkest grey and the paper around it, within :data:`MAX_PLACE_OFFSET_STEPS` of a step
    of the place, of the expected ``diameter`` (within :data:`SIMILAR_SIZE` in area's diameter; with
    ``any_size``, of any size that leaves the region inside 1.5 steps around the place), convex and
    elliptical; ``contrast`` is the window dots' median contrast (grey levels)."""
    h, w = image.shape
    half = int(np.ceil(0.75 * step))
    u0, v0 = int(np.rint(place[0])) - half, int(np.rint(place[1])) - half
    if u0 < 0 or v0 < 0 or u0 + 2 * half >= w or v0 + 2 * half >= h:
        return None
    crop = image[v0 : v0 + 2 * half + 1, u0 : u0 + 2 * half + 1].astype(np.float32)
    src = crop if dark_dots else 255.0 - crop
    # squared distances from the place, px², a row and a column broadcast (hypot over the window cost more
    # than the rest of the search)
    du, dv = np.arange(src.shape[1]) - (place[0] - u0), np.arange(src.shape[0]) - (place[1] - v0)
    r2 = du[None, :] ** 2 + dv[:, None] ** 2
    core = src[r2 <= (MAX_PLACE_OFFSET_STEPS * step + 0.25 * diameter) ** 2]
    ring = src[(r2 >= (0.45 * step) ** 2) & (r2 <= (0.6 * step) ** 2)]
    if core.size == 0 or ring.size == 0:
        return None
    dot_level, paper = percentile(core, 5), percentile(ring, 25)
    if paper - dot_level < MIN_CONTRAST_FRACTION * contrast:
        return None
    mask = (src < 0.5 * (dot_level + paper)).astype(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        return None
    d = np.linalg.norm(centroids[1:] + np.array([u0, v0]) - place, axis=1)
    k = int(np.argmin(d)) + 1
    if d[k - 1] > MAX_PLACE_OFFSET_STEPS * step:
        return None
    x, y, bw, bh, area = stats[k]
    if x == 0 or y == 0 or x + bw >= src.shape[1] or y + bh >= src.shape[0]:
        return None  # the region runs beyond the place: merged with something larger than a dot
    if not any_size and not diameter / SIMILAR_SIZE < 2.0 * np.sqrt(area / np.pi) < diameter * SIMILAR_SIZE:
        return None
    contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(contours, key=cv2.contourArea)
    if len(c) < 6:
        return None
    hull = cv2.contourArea(cv2.convexHull(c))
    if hull <= 0 or cv2.contourArea(c) / hull < 0.85:
        return None
    (cu, cv_), (ew, eh), ang = cv2.fitEllipse(c)
    a, b = max(ew, eh) / 2, min(ew, eh) / 2
    if b <= 0 or abs(cv2.contourArea(c) / (np.pi * a * b) - 1.0) > 0.15:
        return None
    theta = np.radians(ang) + (np.pi / 2 if eh > ew else 0.0)
    return np.array([cu + u0, cv_ + v0, a, b, (theta + np.pi / 2) % np.pi - np.pi / 2])


def missed_dots(image: np.ndarray, circles: CoarseCircles, lattice_index: np.ndarray, lattice_coords: np.ndarray,
                levels: np.ndarray, plate: DotPlate) -> CoarseCircles:
    """The dots found at the missing places of the best window of a refused lattice (module docstring),
    as candidates (possibly none). image: the coarse image the circles were found on; circles, levels
    (K, 2): every candidate and its grey levels; lattice_index (L,), lattice_coords (L, 2): the lattice."""
    pts = circles.centres[lattice_index]
    sizes = 2.0 * circles.axes[lattice_index, 0]
    pred = predict_missing(pts, np.asarray(lattice_coords), sizes, plate.rows, plate.cols, image.shape)
    if pred is None:
        return CoarseCircles.empty()
    places, diam, step = pred
    lv = levels[lattice_index]
    contrast = float(np.median(np.abs(lv[:, 1] - lv[:, 0])))
    found = [f for p, dm in zip(places, diam, strict=True)
             if (f := find_dot_at(image, p, dm, step, plate.dark_dots, contrast)) is not None]
    if not found:
        return CoarseCircles.empty()
    f = np.array(found)
    return CoarseCircles(f[:, :2].copy(), f[:, 2:4].copy(), f[:, 4].copy(), np.zeros(len(f)), np.ones(len(f)))
