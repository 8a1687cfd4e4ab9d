"""Why a lattice without a complete window of the plate is refused: partly out of the image, or dots missing.

A lattice grown from the candidates (:func:`tasks.vision.detection.grid.build_lattice`) that holds no
complete rows × cols window is refused. Which reason is true depends on where the window's missing
dots would lie: the plate is partly out of the image only when they lie beyond the image's border
(or so near it that the border cuts them); when they lie inside it, dots the image shows were not
found (a shadow, blur, a dot of another size than its neighbours), whatever the border nearby.

The windows considered are every placement of a rows × cols (or cols × rows) window that overlaps
the lattice, also beyond its extent; those holding the most lattice points are the plate's most
likely places. The missing dots' places are extrapolated with the affine map from lattice
coordinates to image px fitted to the lattice's points (one to three steps beyond them: a
perspective or lens would bend them by a fraction of a step, well within the border margin's
tolerance for the verdict).

Frames: image px (u right, v down), whatever image the points are in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BORDER_MARGIN_STEPS = 0.3
"""A missing dot counts as out of the image when its extrapolated centre lies less than this
fraction of a lattice step inside the border (a plate dot's radius is a third of a step at a pitch
of 1.5 diameters, so the border cuts such a dot)."""


@dataclass(frozen=True, eq=False)
class WindowFill:
    """The best placement of the plate's window over a lattice: ``count`` of the plate's dots in it,
    ``missing_inside`` of its missing dots whose places lie inside the image, ``missing_outside`` of
    them out of it (or cut by the border); ``window`` (row, col, height, width) and ``missing_cells``
    (K, 2) (row, col) in the lattice's coordinates less their minimum (they may be negative or
    beyond the lattice's extent)."""

    count: int
    missing_inside: int
    missing_outside: int
    window: tuple[int, int, int, int] = (0, 0, 0, 0)
    missing_cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))


def best_window_fill(points: np.ndarray, lattice_coords: np.ndarray, rows: int, cols: int,
                     image_shape: tuple[int, int] | None) -> WindowFill:
    """The placement of a rows × cols (or cols × rows) window over the lattice that holds the most of
    its points, and among those the one with the fewest missing dots inside the image.

    points (L, 2) px: the lattice's points; lattice_coords (L, 2) int their (row, col) lattice
    coordinates (any origin); image_shape (H, W) px, None: every missing dot counts as inside."""
    g = np.asarray(lattice_coords, int)
    g = g - g.min(axis=0)
    pad = max(rows, cols)
    hh, ww = (g.max(axis=0) + 1).tolist()
    occ = np.zeros((hh + 2 * pad, ww + 2 * pad), int)
    occ[g[:, 0] + pad, g[:, 1] + pad] = 1
    cum = np.pad(occ.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    design = np.column_stack([g + pad, np.ones(len(g))])  # padded (row, col, 1) → u, v
    coef, *_ = np.linalg.lstsq(design, np.asarray(points, float), rcond=None) if len(g) >= 3 else (None,)
    step = (0.5 * (np.linalg.norm(coef[0]) + np.linalg.norm(coef[1]))) if coef is not None else 0.0
    best: WindowFill | None = None
    for h, w in {(rows, cols), (cols, rows)}:
        counts = cum[h:, w:] - cum[:-h, w:] - cum[h:, :-w] + cum[:-h, :-w]
        top = int(counts.max())
        if best is not None and top < best.count:
            continue
        for a0, b0 in zip(*np.nonzero(counts == top), strict=True):
            empty = np.argwhere(occ[a0 : a0 + h, b0 : b0 + w] == 0) + np.array([a0, b0])
            outside = _out_of_image(empty, coef, step, image_shape)
            fill = WindowFill(top, int((~outside).sum()), int(outside.sum()), (int(a0) - pad, int(b0) - pad, h, w),
                              empty - pad)
            if best is None or (fill.count, -fill.missing_inside) > (best.count, -best.missing_inside):
                best = fill
    return best


def _out_of_image(cells: np.ndarray, coef: np.ndarray | None, step: float,
                  image_shape: tuple[int, int] | None) -> np.ndarray:
    """(K,) bool: whether each lattice cell (K, 2) (padded row, col) lies out of the image, or within
    :data:`BORDER_MARGIN_STEPS` of a step of its border, by the affine map ``coef`` (3, 2)."""
    if coef is None or image_shape is None or len(cells) == 0:
        return np.zeros(len(cells), bool)
    uv = np.column_stack([cells, np.ones(len(cells))]) @ coef
    h, w = image_shape
    m = BORDER_MARGIN_STEPS * step
    return (uv[:, 0] < m) | (uv[:, 0] > w - 1 - m) | (uv[:, 1] < m) | (uv[:, 1] > h - 1 - m)


def incomplete_lattice_reason(fill: WindowFill, shape_txt: str, n_lattice: int, rows: int, cols: int) -> str:
    """The refusal of a lattice (``shape_txt`` "HxW", ``n_lattice`` points) whose best window is ``fill``:
    "partial view" when every missing dot of that window lies out of the image, else "missing dots"."""
    need = rows * cols
    if fill.missing_inside == 0 and fill.missing_outside > 0:
        return (f"partial view: plate partly out of the image ({shape_txt} lattice of {n_lattice} dots; "
                f"the other {fill.missing_outside} of a {rows}x{cols} window would lie beyond the border)")
    where = f", {fill.missing_inside} of the missing inside the image" if fill.missing_outside else ""
    return (f"missing dots: {shape_txt} lattice of {n_lattice} dots, at most {fill.count} of {need} in a "
            f"{rows}x{cols} window{where}")
