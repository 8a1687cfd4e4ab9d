"""A plate beside a larger lattice of clutter (tasks.vision.detection.grid.order_beside)."""

from __future__ import annotations

import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.grid import order_grid

PLATE = DotPlate(4, 3, 2.0, 1.0)  # pitch 2 diameters
STEP, SIZE = 20.0, 10.0  # px


def clutter() -> np.ndarray:
    """(30, 2) px: a 4 × 8 lattice of blobs of the dots' size and spacing with two holes, at
    (1, 2) and (2, 5), so that no 4 × 3 or 3 × 4 window of it is complete (a block of lettering)."""
    r, c = np.meshgrid(np.arange(4), np.arange(8), indexing="ij")
    keep = ~(((r == 1) & (c == 2)) | ((r == 2) & (c == 5)))
    return np.column_stack([50.0 + STEP * c[keep], 40.0 + STEP * r[keep]])


def plate_dots() -> np.ndarray:
    """(12, 2) px: the plate's dots, row-major, 200 px to the right of the clutter."""
    r, c = np.meshgrid(np.arange(4), np.arange(3), indexing="ij")
    return np.column_stack([400.0 + STEP * c.ravel(), 60.0 + STEP * r.ravel()])


def test_the_plate_beside_a_larger_lattice_of_clutter_is_ordered():
    """Growth starts from the seeds nearest the middle of those with four neighbours, most of them in
    the clutter, and keeps the largest lattice: the clutter's, with no complete window. The code
    before refused ("missing dots: 8x4 lattice of 30 dots"); the points beside that lattice are
    ordered too, and hold the plate."""
    points = np.vstack([clutter(), plate_dots()])
    order = order_grid(points, PLATE, sizes=np.full(len(points), SIZE), image_shape=(300, 600))
    assert order.ok, order.reason
    assert sorted(order.index.tolist()) == list(range(30, 42))  # the plate's dots, none of the clutter
    labelled = points[order.index].reshape(4, 3, 2)
    steps = np.linalg.norm(np.diff(labelled, axis=1), axis=2), np.linalg.norm(np.diff(labelled, axis=0), axis=2)
    assert all(np.allclose(s, STEP) for s in steps)  # neighbours by label are neighbours on the plate


def test_clutter_alone_is_refused_with_its_own_reason():
    """Without the plate nothing beside the clutter fills a window: the clutter's refusal stands."""
    points = clutter()
    order = order_grid(points, PLATE, sizes=np.full(len(points), SIZE), image_shape=(300, 600))
    assert not order.ok
    assert order.reason.startswith("missing dots: 8x4 lattice of 30 dots"), order.reason
