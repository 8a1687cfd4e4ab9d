"""Look one step beyond a complete window for dots that carry the plate's lattice on: a larger plate.

The strays rule (:func:`tasks.vision.detection.grid.order_grid`) refuses a window when plate-like
lattice points lie beyond it, but it sees only the candidates the searches found. A row of a larger
plate can be missed by every candidate search while the window's own dots are found: through a
fisheye the dots near the lens's axis are larger than one search band holds, a shadow takes their
contrast, the region of one merges with the paper's edge. Asked for a 3 × 3 plate, a photograph of a
4 × 3 sheet would then be labelled as one of its 3 × 3 windows, and the 4 × 3 sheet asked for as
3 × 4 with a 2 × 3 would be labelled too: a wrong labelling where a refusal is right.

So, on a grid found without predicted dot positions, a dot is looked for one step beyond each dot on
the window's edge, outwards along its row or column: at the edge dot plus the step from the dot behind
it, grown by the ratio of the two candidates' sizes (the step grows with the dots' size, both with the
local magnification of perspective or a fisheye). There alone a region is thresholded as when
looking again for a missed dot (:func:`tasks.vision.detection.completion.find_dot_at`: within 0.3 of
a step of the place, convex and elliptical, darker (lighter) than the paper by a quarter of the
window's contrast); it counts when its disc passes the candidates' test, it carries on the edge
dot's size and grey levels (:func:`tasks.vision.detection.lattice_check.like_the_dot_behind`, the
edge dot measured by the same thresholding) and it has the edge dot's shape: the same printed disc
one step on, seen through nearly the same local projection (:func:`shape_stretch` under
:data:`~tasks.vision.detection.grid_order.SIMILAR_SIZE`; a clutter disc half hidden by the plate's
edge, or round where the dots are foreshortened, is not). As many such dots as the strays rule's limit
(:func:`tasks.vision.detection.lattice_check.extra_dot_limit`, 2 for a 4 × 3 plate) refuse the
window. Paper, the sheet's edge and the clipboard beyond a plate of the size asked hold no such dot.
A window two dots wide through a strong fisheye predicts the place beyond it to within half a step
only (the step grows faster than the dots there): such a row can still be missed.

Units: px of the coarse image the grid was found on.
"""

from __future__ import annotations

import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.completion import find_dot_at
from tasks.vision.detection.grid_order import SIMILAR_SIZE
from tasks.vision.detection.lattice_check import extra_dot_limit, like_the_dot_behind
from tasks.vision.detection.rrht import CoarseCircles
from tasks.vision.detection.verify import dot_appearance


def beyond_places(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(places (M, 2), edge dots (M, 2), dots behind them (M, 2)) as (row, col) lattice coordinates: the
    place one step beyond each dot on the edge of a rows × cols window, outwards along a row or column,
    the window's dot next to it and the dot behind that one (the edge dot itself in a window one wide)."""
    places, edge, behind = [], [], []
    for r in range(rows):
        for c in range(cols):
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                if 0 <= r + dr < rows and 0 <= c + dc < cols:
                    continue
                places.append((r + dr, c + dc))
                edge.append((r, c))
                back = (r - dr, c - dc)
                behind.append(back if 0 <= back[0] < rows and 0 <= back[1] < cols else (r, c))
    return np.array(places), np.array(edge), np.array(behind)


def shape_stretch(ellipse: np.ndarray, other: np.ndarray) -> float:
    """How far (≥ 1) one of two ellipses (major semi-axis, minor semi-axis, major axis's angle rad) must be
    stretched along some direction, its area kept, to take the other's shape: 1 for the same aspect and
    angle at any size, the square root of the ratio of their aspects for the same angle, more where the
    angles differ."""

    def unit_shape(a: float, b: float, theta: float) -> np.ndarray:
        c, s = np.cos(theta), np.sin(theta)
        rot = np.array([[c, -s], [s, c]])
        return rot @ np.diag([a / b, b / a]) @ rot.T

    eig = np.linalg.eigvals(np.linalg.solve(unit_shape(*ellipse), unit_shape(*other))).real
    return float(np.sqrt(eig.max()))


def dots_beyond(image: np.ndarray, circles: CoarseCircles, index: np.ndarray, levels: np.ndarray, plate: DotPlate,
                min_fill_inside: float) -> np.ndarray:
    """(K, 2) coarse px: the plate-like dots one step beyond the window (module docstring).

    image: the coarse image (uint8) the candidates ``circles`` were found on, ``levels`` (N, 2) their grey
    levels (inside, ring); index (rows*cols,) the candidate of each plate dot, row-major, all found. The
    dot on the edge is measured as the dot beyond it is, by the region at its centre (the candidates'
    sizes are the searches': the blur fallback scales them by up to 1.8)."""
    rows, cols = plate.rows, plate.cols
    pts = circles.centres[index]
    lv = levels[index]
    contrast = float(np.median(np.abs(lv[:, 1] - lv[:, 0])))
    _, edge, behind = beyond_places(rows, cols)
    at = np.ravel_multi_index(edge.T, (rows, cols))
    back = np.ravel_multi_index(behind.T, (rows, cols))
    dot_over_step = plate.dot_diameter_mm / plate.pitch_range_mm[1]  # the core searched: the smaller dot

    def region(place: np.ndarray, step: float) -> np.ndarray | None:
        """(u, v, a, b, theta, inside level, ring level, area's diameter) of the dot-like region at
        ``place``, or None."""
        f = find_dot_at(image, place, step * dot_over_step, step, plate.dark_dots, contrast, any_size=True)
        if f is None:
            return None
        fill_in, _, f_levels = dot_appearance(image, f[None, :2], f[None, 2:4], f[None, 4], plate.dark_dots)
        return np.concatenate([f, f_levels[0], [2.0 * np.sqrt(f[2] * f[3])]]) if fill_in[0] >= min_fill_inside \
            else None

    sizes = circles.axes[index, 0]
    measured: dict[tuple[int, int], np.ndarray | None] = {}
    found = []
    for k, kb in zip(at.tolist(), back.tolist(), strict=True):
        if k == kb:  # a window one dot wide: no line to carry on
            continue
        step = float(np.linalg.norm(pts[k] - pts[kb]))
        # the step grows with the dots' size (both with the local magnification: perspective, a fisheye);
        # the ratio of two candidates' sizes holds where their scale does not
        growth = float(np.clip(sizes[k] / sizes[kb], 1 / SIMILAR_SIZE, SIMILAR_SIZE))
        beyond = region(pts[k] + growth * (pts[k] - pts[kb]), growth * step)
        if beyond is None:
            continue
        if (k, kb) not in measured:
            measured[k, kb] = region(pts[k], step)
        dot = measured[k, kb]
        if dot is not None and like_the_dot_behind(beyond[7], growth * dot[7], beyond[5:7], dot[5:7]) \
                and shape_stretch(beyond[2:5], dot[2:5]) < SIMILAR_SIZE:
            found.append(beyond[:2])
    return np.array(found).reshape(-1, 2)


def continued_beyond(image: np.ndarray, circles: CoarseCircles, index: np.ndarray, levels: np.ndarray,
                     plate: DotPlate, min_fill_inside: float) -> str:
    """The refusal reason when as many plate-like dots as :func:`extra_dot_limit` lie one step beyond the
    complete window (:func:`dots_beyond`, same arguments), else ''."""
    n = len(dots_beyond(image, circles, index, levels, plate, min_fill_inside))
    if n < extra_dot_limit(plate.rows, plate.cols):
        return ""
    return (f"extra dots: {n} dots one step beyond the {plate.rows}x{plate.cols} window carry its lattice, size and "
            "grey levels on (a larger plate, or rows and columns other than its own?)")
