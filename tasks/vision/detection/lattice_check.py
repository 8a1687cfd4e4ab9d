"""Check a labelled window of dots against its own lattice before it is trusted.

Growth (:func:`tasks.vision.detection.grid.build_lattice`) takes, one local step from a dot, the
candidate nearest the predicted position within 30 % of a step. Where the step changes fast
(near the rim of a fisheye, a grid off its axis) the carried step overshoots, and a stray blob
near the true dot's position may win the claim: the window is complete, but one dot is wrong.

Every 2 × 2 cell of a plate's lattice is nearly a parallelogram in the image, and nearly the same
one as its neighbours, under perspective and smooth lens distortion: its mixed second difference
p(i, j) − p(i−1, j) − p(i, j−1) + p(i−1, j−1) changes little from cell to cell against its steps
(the true grids of 3000 random stress cases, ``detector_stress.random_case``: at most 0.10 of a
step without fisheye, 0.28 through the fisheye lens at 49° of tilt). A wrong dot moves its cells'
by its own offset. So:

1. each dot of the window is predicted from every complete cell it is a corner of (the other
   three corners, parallelogram rule); where another candidate of a similar size lies clearly
   nearer that prediction than the dot taken, and the dot taken lies off it, the other candidate
   replaces it;
2. afterwards every cell must close to within ``max_cell_misfit`` of its mean step, or the window
   is refused with the dot and the misfit named (a wrong labelling is worse than none).

Units: the px of whatever image the points are in; the misfits are fractions of a step.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.vision.detection.grid_order import SIMILAR_SIZE

MAX_CELL_MISFIT = 0.35
"""Largest mixed second difference of a 2 × 2 cell, as a fraction of its mean side, for a window to
be accepted."""
SWAP_MARGIN = 2.0
"""A candidate replaces a dot when it lies this many times nearer the dot's predicted position."""
MIN_SWAP_OFFSET = 0.1
"""… and the dot taken lies at least this fraction of a step off that position."""


def cell_misfits(grid_uv: np.ndarray) -> np.ndarray:
    """(h−1, w−1) how far each 2 × 2 cell of ``grid_uv`` (h, w, 2) px is from closing like the
    others: its mixed second difference minus the window's median one (with three cells or more;
    a lens or a tilt bends every cell of a small window alike), over the mean length of its four
    sides."""
    p00, p01, p10, p11 = grid_uv[:-1, :-1], grid_uv[:-1, 1:], grid_uv[1:, :-1], grid_uv[1:, 1:]
    mixed = p11 - p10 - p01 + p00
    if mixed.shape[0] * mixed.shape[1] >= 3:
        mixed = mixed - np.median(mixed.reshape(-1, 2), axis=0)
    sides = (np.linalg.norm(p01 - p00, axis=2) + np.linalg.norm(p11 - p10, axis=2)
             + np.linalg.norm(p10 - p00, axis=2) + np.linalg.norm(p11 - p01, axis=2)) / 4.0
    return np.linalg.norm(mixed, axis=2) / np.maximum(sides, 1e-9)


def parallelogram_predictions(grid_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per dot of ``grid_uv`` (h, w, 2) px: the median of its predictions from the other three
    corners of every cell it belongs to (h, w, 2) px, and the median mean side of those cells (h, w) px."""
    h, w, _ = grid_uv.shape
    c = {(a, b): grid_uv[a:h - 1 + a, b:w - 1 + b] for a in (0, 1) for b in (0, 1)}  # the cells' corners
    side = (((np.linalg.norm(c[0, 1] - c[0, 0], axis=2) + np.linalg.norm(c[1, 1] - c[1, 0], axis=2))
             + np.linalg.norm(c[1, 0] - c[0, 0], axis=2)) + np.linalg.norm(c[1, 1] - c[0, 1], axis=2)) / 4.0
    preds = np.full((h, w, 4, 2), np.nan)  # up to four cells per dot, one slot per corner role
    sides = np.full((h, w, 4), np.nan)
    for a in (0, 1):
        for b in (0, 1):
            preds[a:h - 1 + a, b:w - 1 + b, 2 * a + b] = c[a, 1 - b] + c[1 - a, b] - c[1 - a, 1 - b]
            sides[a:h - 1 + a, b:w - 1 + b, 2 * a + b] = side
    return np.nanmedian(preds, axis=2), np.nanmedian(sides, axis=2)


def check_window(points: np.ndarray, sizes: np.ndarray | None, window: np.ndarray,
                 max_cell_misfit: float = MAX_CELL_MISFIT) -> tuple[np.ndarray, str]:
    """(window, reason): ``window`` (h, w) indices into ``points`` (N, 2) px, with dots replaced by
    better-fitting candidates (step 1 of the module docstring; ``sizes`` (N,) px bound how
    similar a replacement must be, within ``SIMILAR_SIZE``); reason is "" when every cell closes
    (step 2), else why the window is refused."""
    window = window.copy()
    h, w = window.shape
    if h < 2 or w < 2:
        return window, ""
    tree = cKDTree(points)
    for _ in range(h * w):  # one replacement at a time, the dot furthest off its prediction first
        pred, side = parallelogram_predictions(points[window])
        off = np.linalg.norm(points[window] - pred, axis=2)
        worst = cell_misfits(points[window]).max()
        taken = set(window.ravel().tolist())
        swapped = False
        for flat in np.argsort(-(off / side).ravel()):
            i, j = divmod(int(flat), w)
            if off[i, j] <= MIN_SWAP_OFFSET * side[i, j]:
                break
            dist, near = tree.query(pred[i, j], k=min(4, len(points)))
            for d, k in zip(np.atleast_1d(dist), np.atleast_1d(near), strict=True):
                if d > off[i, j] / SWAP_MARGIN or k in taken:
                    continue
                own = None if sizes is None else sizes[window[i, j]]
                if own is not None and not (own / SIMILAR_SIZE < sizes[k] < own * SIMILAR_SIZE):
                    continue
                trial = window.copy()
                trial[i, j] = k
                if cell_misfits(points[trial]).max() < worst:  # only a replacement that mends the lattice
                    window, swapped = trial, True
                break
            if swapped:
                break
        if not swapped:
            break
    misfit = cell_misfits(points[window])
    if misfit.max() > max_cell_misfit:
        i, j = np.unravel_index(int(np.argmax(misfit)), misfit.shape)
        return window, (f"irregular lattice: a 2x2 cell of dots (window rows {i}-{i + 1}, columns {j}-{j + 1}) "
                        f"is off a parallelogram by {misfit[i, j]:.2f} of its step (at most {max_cell_misfit}); "
                        "one of its dots may be a stray blob")
    return window, ""


STRAY_MAX_STEP_MISFIT = 0.3
"""A lattice point beyond the window is like a plate dot only within this fraction of a step of its
place extrapolated from the window (second order from the three dots behind it in line: the true
dots next to a 4 × 3 window of 80 random fisheye stress cases, ``detector_stress.random_fisheye_case``,
reach 0.24 with the coarse search's centres)."""
STRAY_SIZE_RANGE = (0.75, 1.4)
"""… with a size within this factor of the size extrapolated (linearly) from the two dots behind it
(true dots: 0.83–1.36) …"""
STRAY_MAX_LEVEL_CHANGE = (0.35, 0.65)
"""… and grey levels inside the dot and on the ring around it within these fractions of the dot's
contrast of the dot behind it (true dots, under shadow edges: 99 % within 0.24 and 0.38, at most
1.07 and 0.62)."""


def plate_like_strays(points: np.ndarray, sizes: np.ndarray, levels: np.ndarray, lattice: np.ndarray,
                      window: tuple[int, int, int, int]) -> np.ndarray:
    """(S,) bool per lattice point beyond the window: could it be a dot of the plate?

    points (N, 2) px, sizes (N,) diameters px, levels (N, 2) grey inside the dot and on the ring
    around it (:func:`tasks.vision.detection.verify.dot_appearance`); lattice (H, W) indices into
    ``points`` (−1: empty); window (h, w, a0, b0) the complete rows × cols window in it. A stray is
    clutter (False) when, along every line through it with three window dots behind it, it lies off
    the place, size or grey levels those three carry on to (:data:`STRAY_MAX_STEP_MISFIT`,
    :data:`STRAY_SIZE_RANGE`, :data:`STRAY_MAX_LEVEL_CHANGE`); without such a line it counts as a
    plate dot. A printed plate bigger than the window (a wrong plate asked for) continues its
    lattice, its size and its grey levels; clutter that growth took for the lattice's next dot
    rarely does all three.
    """
    h, w, a0, b0 = window
    hh, ww = lattice.shape
    in_window = np.zeros((hh, ww), bool)
    in_window[a0:a0 + h, b0:b0 + w] = True
    places = [(r, c) for r, c in zip(*np.nonzero((lattice >= 0) & ~in_window), strict=True)]
    like = np.ones(len(places), bool)
    for s, (r, c) in enumerate(places):
        verdicts = []
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            behind = [(r - j * dr, c - j * dc) for j in (1, 2, 3)]
            if not all(0 <= a < hh and 0 <= b < ww and in_window[a, b] for a, b in behind):
                continue
            k1, k2, k3 = (int(lattice[a, b]) for a, b in behind)
            verdicts.append(_continues(points, sizes, levels, k3, k2, k1, int(lattice[r, c])))
        like[s] = not verdicts or any(verdicts)
    return like


def _continues(points, sizes, levels, k3: int, k2: int, k1: int, k: int) -> bool:
    """Whether point ``k`` continues the line of points k3, k2, k1 (in that order) in place, size and
    grey levels (:func:`plate_like_strays`)."""
    delta = points[k1] - points[k2]
    ahead = points[k1] + 2.0 * delta - (points[k2] - points[k3])
    if np.linalg.norm(points[k] - ahead) > STRAY_MAX_STEP_MISFIT * np.linalg.norm(delta):
        return False
    return like_the_dot_behind(sizes[k], 2.0 * sizes[k1] - sizes[k2], levels[k], levels[k1])


def like_the_dot_behind(size: float, size_ahead: float, levels: np.ndarray, levels_behind: np.ndarray) -> bool:
    """Whether a dot of diameter ``size`` px and grey levels ``levels`` (2,) (inside, ring) continues a line of
    the plate's dots: its size within :data:`STRAY_SIZE_RANGE` of ``size_ahead`` (px, extrapolated along the
    line) and its levels within :data:`STRAY_MAX_LEVEL_CHANGE` of the contrast of the dot behind it
    (``levels_behind`` (2,))."""
    if not STRAY_SIZE_RANGE[0] < size / max(size_ahead, 1e-9) < STRAY_SIZE_RANGE[1]:
        return False
    contrast = abs(levels_behind[1] - levels_behind[0])
    change = np.abs(levels - levels_behind) / max(contrast, 1e-9)
    if not np.isfinite(change).all():  # a dot without samples in the image: its levels cannot tell
        return True
    return bool(np.all(change <= np.array(STRAY_MAX_LEVEL_CHANGE)))


def extra_dot_limit(rows: int, cols: int) -> int:
    """How many plate-like dots beyond a complete rows × cols window refuse it (\"extra dots\"): one may be
    clutter that happens to sit on the lattice; a row or column of a larger plate holds more."""
    return max(2, (min(rows, cols) + 1) // 2)
