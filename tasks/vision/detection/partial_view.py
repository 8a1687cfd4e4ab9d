"""Order a plate that is partly out of the image, with a prior on where its dots should be.

Frames: image px (u right, v down), the same frame as the detected points; plate rows/cols as in
:class:`tasks.machine.plate.DotPlate`.

A plate larger than the part of the field a sweep keeps it in leaves the image at the sweep's
ends. Its visible dots still form a lattice (:func:`tasks.vision.detection.grid.build_lattice`), but
which plate rows and columns they are cannot be told from the lattice alone: the missing ones
may be on either side. The prior settles it: ``expected_centres`` (rows*cols, 2) are the dots'
positions predicted from the commanded axes through the nominal kinematics and the nominal camera
(:func:`tasks.vision.pipeline.expected_homographies`). It need only be right to a fraction of the pitch:
each lattice point votes for the plate dot predicted nearest to it, and the one lattice-to-plate
map (of the eight symmetries of the lattice, each with its integer offset) that most votes agree
on labels every point.

The contract stays strict: every dot that the prior puts inside the image, farther than
``border_margin_px`` from its edge, must be found (a dot hidden by dirt or clutter still fails
the view), and at least ``min_fraction`` of the plate's dots must be found. Dots predicted
within the margin may be missing: their rims may be cut by the border, and the detector drops
such rims rather than fit them (:mod:`tasks.vision.detection.framework`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.machine.plate import DotPlate
from tasks.vision.detection.grid_order import GridOrder, fail_order, rotation_of

MIN_FRACTION = 0.5
"""Fewest dots of a partial view, as a fraction of the plate's: half the grid still fixes both
tilts of the plate (at least ⌈rows/2⌉ rows or columns across)."""
VOTE_RADIUS = 0.35
"""A lattice point votes for the predicted dot within this fraction of the predicted pitch."""
MIN_AGREEMENT = 0.8
"""Share of the voting points that the chosen lattice-to-plate map must agree with."""

_SIGNED_PERMUTATIONS = np.array([[[a, 0], [0, b]] for a in (1, -1) for b in (1, -1)]
                                + [[[0, a], [b, 0]] for a in (1, -1) for b in (1, -1)])


def too_few_dots(n_found: int, n_dots: int, min_fraction: float = MIN_FRACTION) -> str | None:
    """The reason a partial view of ``n_found`` of a plate's ``n_dots`` dots is refused, or None."""
    if n_found >= min_fraction * n_dots:
        return None
    return f"partial view: {n_found} of {n_dots} dots wholly in the image, fewer than {min_fraction:.0%} of the plate"


def predicted_pitch_px(expected_centres: np.ndarray) -> float:
    """Median distance (px) from each predicted dot to its nearest predicted neighbour."""
    e = expected_centres[np.all(np.isfinite(expected_centres), axis=1)]
    if len(e) < 2:
        return float("nan")
    return float(np.median(cKDTree(e).query(e, k=2)[0][:, 1]))


def required_dots(expected_centres: np.ndarray, image_shape: tuple[int, int], border_margin_px: float) -> np.ndarray:
    """(rows*cols,) bool: the dots the prior puts inside the image, at least ``border_margin_px``
    from every edge (pixel centres run from 0 to W−1 and 0 to H−1)."""
    h, w = image_shape
    u, v = expected_centres[:, 0], expected_centres[:, 1]
    m = border_margin_px
    with np.errstate(invalid="ignore"):
        return (u >= m) & (u <= w - 1 - m) & (v >= m) & (v <= h - 1 - m)


def order_by_prior(points: np.ndarray, sel: np.ndarray, lattice: np.ndarray, plate: DotPlate,
                   expected_centres: np.ndarray, image_shape: tuple[int, int], *,
                   min_fraction: float = MIN_FRACTION) -> GridOrder:
    """Label the lattice points ``points[sel]`` (integer lattice coordinates ``lattice``, (K, 2))
    with the plate's dots, using the predicted dot positions ``expected_centres`` (rows*cols, 2)
    px. Returns a :class:`GridOrder` whose ``index`` is −1 for the dots not found."""
    n = plate.rows * plate.cols
    pitch = predicted_pitch_px(expected_centres)
    shape = tuple((lattice.max(axis=0) - lattice.min(axis=0) + 1).tolist())
    if not np.isfinite(pitch):
        return fail_order(plate, "partial view: no prediction of where the plate's dots are", shape)
    known = np.flatnonzero(np.all(np.isfinite(expected_centres), axis=1))
    d, j = cKDTree(expected_centres[known]).query(points[sel])
    voting = d <= VOTE_RADIUS * pitch
    if voting.sum() < 4:
        return fail_order(plate, f"partial view: {int(voting.sum())} of {len(sel)} lattice dots lie where the "
                                 "commanded axes put a plate dot (the prior or the plate is wrong)", shape)
    rc_voted = plate.row_col()[known[j[voting]]]
    best = (-1, None, None)
    for m in _SIGNED_PERMUTATIONS:
        offsets = rc_voted - lattice[voting] @ m.T
        uniq, counts = np.unique(offsets, axis=0, return_counts=True)
        k = int(np.argmax(counts))
        if counts[k] > best[0]:
            best = (int(counts[k]), m, uniq[k])
    agree, m, off = best
    if agree < MIN_AGREEMENT * voting.sum():
        return fail_order(plate, f"partial view: only {agree} of {int(voting.sum())} lattice dots agree on one "
                                 "labelling with where the commanded axes put the plate's dots", shape)
    rc = lattice @ m.T + off
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < plate.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < plate.cols)
    strays = int((~inside).sum())
    if strays >= max(2, (min(plate.rows, plate.cols) + 1) // 2):
        return fail_order(plate, f"extra dots: {strays} lattice-aligned dots beyond the {plate.rows}x{plate.cols} "
                                 "plate", shape)
    index = np.full(n, -1)
    index[rc[inside, 0] * plate.cols + rc[inside, 1]] = sel[inside]
    required = required_dots(expected_centres, image_shape, 0.5 * pitch)
    missing = np.flatnonzero(required & (index < 0))
    if len(missing):
        r, c = plate.row_col()[missing[0]]
        return fail_order(plate, f"missing dots: {len(missing)} dot(s) predicted inside the image not found, "
                                 f"first row {r} col {c}", shape)
    reason = too_few_dots(int((index >= 0).sum()), n, min_fraction)
    if reason:
        return fail_order(plate, reason, shape)
    return GridOrder(True, "", index, rotation_of(points, index, plate), False, shape)
