"""The check of a labelled window against its own lattice (tasks.vision.detection.lattice_check)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from tasks.machine.plate import DotPlate
from tasks.simulation.detector_stress import STRESS_CASES
from tasks.simulation.render import true_dot_centres
from tasks.vision.detection.grid import order_grid
from tasks.vision.detection.lattice_check import MAX_CELL_MISFIT, cell_misfits, check_window, plate_like_strays


def fisheye_grid() -> np.ndarray:
    """(4, 3, 2) px: the true dot centres of the fisheye stress case (k1 −0.35, 25° of tilt, off axis)."""
    case = next(c for c in STRESS_CASES if c.name == "fisheye")
    return true_dot_centres(case.camera(), case.plate, case.pose()).reshape(4, 3, 2)


def test_true_grids_close_every_cell():
    """Perspective and a strong fisheye bend every cell of a small window alike: the true grid of
    the fisheye stress case stays far below the limit, a fronto-parallel one is exact."""
    assert cell_misfits(fisheye_grid()).max() < 0.5 * MAX_CELL_MISFIT
    r, c = np.meshgrid(np.arange(4.0), np.arange(3.0), indexing="ij")
    assert cell_misfits(np.stack([30 * c + 5, 30 * r + 7], axis=-1)).max() < 1e-12


def test_a_stray_that_took_a_dots_place_is_replaced_or_refused():
    """A corner dot taken by a stray blob 0.45 of a step off: with the true dot among the candidates
    the window is mended (that dot is labelled instead), without it the window is refused with the
    cell named; a clean window is returned unchanged."""
    grid = fisheye_grid()
    pts = grid.reshape(-1, 2)
    step = np.linalg.norm(grid[0, 2] - grid[0, 1])
    stray = grid[0, 2] + 0.45 * step * np.array([0.6, 0.8])
    sizes = np.full(14, 30.0)
    window = np.arange(12).reshape(4, 3)
    with_stray = np.vstack([pts, stray, [900.0, 900.0]])  # the last: a far-away blob, never taken

    same, why = check_window(with_stray, sizes, window)
    assert why == "" and (same == window).all()

    took = window.copy()
    took[0, 2] = 12  # the stray holds the corner, the true dot 2 is left out
    mended, why = check_window(with_stray, sizes, took)
    assert why == "" and (mended == window).all()

    without_true = with_stray.copy()
    without_true[2] = [-900.0, -900.0]
    _, why = check_window(without_true, sizes, took)
    assert why.startswith("irregular lattice: a 2x2 cell of dots (window rows 0-1, columns 1-2)")


def test_a_replacement_must_have_the_dots_size():
    """The true dot's candidate of twice the stray's size is not a replacement: refused instead."""
    grid = fisheye_grid()
    stray = grid[0, 2] + 0.45 * np.linalg.norm(grid[0, 2] - grid[0, 1]) * np.array([0.6, 0.8])
    pts = np.vstack([grid.reshape(-1, 2), stray])
    sizes = np.full(13, 30.0)
    sizes[2] = 60.0
    took = np.arange(12).reshape(4, 3)
    took[0, 2] = 12
    _, why = check_window(pts, sizes, took)
    assert why.startswith("irregular lattice")


def _five_by_three_plate_without_one_dot() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (14, 2), sizes (14,), levels (14, 2)): a 5 × 3 plate through the fisheye stress case's
    lens with dot (0, 0) unseen, so that as a 4 × 3 plate it has one complete window (rows 1–4) and
    two plate dots beyond it (row 0)."""
    case = next(c for c in STRESS_CASES if c.name == "fisheye")
    plate = replace(case.plate, rows=5)
    pts = true_dot_centres(case.camera(), plate, case.pose())[1:]
    return pts, np.full(14, 30.0), np.tile([60.0, 200.0], (14, 1))


def test_plate_dots_beyond_the_window_are_refused_as_extra_dots():
    """A bigger plate than asked for continues the window's lattice, size and grey levels: its dots
    beyond the window count, and the view is refused (a 4 × 3 label of a 5 × 3 plate would be wrong)."""
    pts, sizes, levels = _five_by_three_plate_without_one_dot()
    plate = DotPlate(4, 3, 6.0, 4.0)
    for lv in (None, levels):
        order = order_grid(pts, plate, sizes=sizes, levels=lv)
        assert not order.ok and order.reason.startswith("extra dots: 2 lattice-aligned dots beyond the 4x3 window")


def test_clutter_beyond_the_window_is_not_an_extra_dot():
    """The same two points beyond the window as clutter: of another grey level inside (half the dots'
    contrast lighter) or of 0.7× the size, or off the place the window's lattice carries on to by 0.4
    of a step: not plate dots, so the window is labelled, every dot right up to the grid's symmetry."""
    pts, sizes, levels = _five_by_three_plate_without_one_dot()
    plate = DotPlate(4, 3, 6.0, 4.0)
    lattice = np.vstack([[-1, 0, 1], np.arange(2, 14).reshape(4, 3)])
    window = (4, 3, 1, 0)
    assert plate_like_strays(pts, sizes, levels, lattice, window).all()
    lighter, smaller, moved = levels.copy(), sizes.copy(), pts.copy()
    lighter[:2, 0] += 0.5 * 140.0
    smaller[:2] *= 0.7
    moved[:2] += 0.4 * np.linalg.norm(pts[2] - pts[5]) * np.array([0.6, 0.8])
    assert not plate_like_strays(moved, sizes, levels, lattice, window).any()
    true = np.arange(2, 14).reshape(4, 3)
    for s, lv in ((sizes, lighter), (smaller, levels)):
        assert not plate_like_strays(pts, s, lv, lattice, window).any()
        order = order_grid(pts, plate, sizes=s, levels=lv)
        assert order.ok, order.reason
        got = order.index.reshape(4, 3)
        assert any((got == t).all() for t in (true, true[::-1], true[:, ::-1], true[::-1, ::-1]))
