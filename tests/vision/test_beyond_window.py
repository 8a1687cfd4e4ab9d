"""The look one step beyond a complete window (tasks.vision.detection.beyond_window): a window of a larger
sheet is refused where no candidate search found the rest of it, clutter beyond a plate is not taken for it."""

from dataclasses import replace

import numpy as np
import pytest

from tasks.simulation.detector_stress import ISSUE_PLATE, errors_up_to_symmetry, random_fisheye_case, render_stress_case
from tasks.simulation.garden_stress import random_garden_case, render_garden_case
from tasks.vision.detection import detect_grid
from tasks.vision.detection.beyond_window import beyond_places, shape_stretch


@pytest.mark.parametrize(("rows", "cols"), [(3, 3), (2, 3)])
def test_a_window_of_a_larger_sheet_is_refused_where_no_search_found_the_rest(rows, cols):
    """Asked for a plate smaller than the sheet: through the fisheye the row of dots nearest the lens's
    axis is larger than the band that finds the rest, so no candidate search finds it and the window is
    complete with no stray beyond it. The code before labelled a 3x3 (2x3) window of the 4x3 sheet."""
    rng = np.random.default_rng(500)
    while (case := random_garden_case(rng, "fisheye-500", "fisheye")) is None:
        pass
    image, truth = render_garden_case(case)
    sheet = replace(ISSUE_PLATE, dark_dots=case.geometry.dark_dots)
    det = detect_grid(image, replace(sheet, rows=rows, cols=cols), "rrht")
    assert not det.ok and det.reason.startswith("extra dots"), det.reason
    whole = detect_grid(image, sheet, "rrht")  # the sheet asked for as it is: no dot beyond it
    assert whole.ok, whole.reason
    assert errors_up_to_symmetry(sheet, whole.centres, truth).max() < 0.25 * case.geometry.dot_px


def test_clutter_discs_beyond_a_fisheye_plate_are_not_its_dots():
    """Random fisheye draw 35 of seed 401: two light clutter discs one step beyond the plate's corner, of
    the dots' size and grey, one round where the dots are foreshortened and one half hidden by the plate's
    edge; without the shape test they refused the plate ("extra dots: 2 dots one step beyond")."""
    rng = np.random.default_rng(401)
    for i in range(36):
        case = random_fisheye_case(rng, f"random-{i}")
    image, truth = render_stress_case(case)
    plate = replace(ISSUE_PLATE, dark_dots=case.dark_dots)
    det = detect_grid(image, plate, "rrht")
    assert det.ok, det.reason
    assert errors_up_to_symmetry(plate, det.centres, truth).max() < 0.25 * case.dot_px


def test_shape_stretch():
    assert shape_stretch(np.array([2.0, 1.0, 0.3]), np.array([6.0, 3.0, 0.3])) == pytest.approx(1.0)  # any size
    assert shape_stretch(np.array([2.0, 1.0, 0.0]), np.array([1.0, 1.0, 0.0])) == pytest.approx(np.sqrt(2.0))
    assert shape_stretch(np.array([2.0, 1.0, 0.0]), np.array([2.0, 1.0, np.pi / 2])) == pytest.approx(2.0)
    assert shape_stretch(np.array([2.0, 1.0, 0.0]), np.array([2.0, 1.0, np.pi])) == pytest.approx(1.0)


def test_beyond_places_ring_the_window():
    places, edge, behind = beyond_places(4, 3)
    assert len(places) == 2 * (4 + 3)  # one beyond each edge dot, per side it lies on
    inside = (places[:, 0] >= 0) & (places[:, 0] < 4) & (places[:, 1] >= 0) & (places[:, 1] < 3)
    assert not inside.any()
    assert (np.abs(places - edge).sum(axis=1) == 1).all() and (np.abs(behind - edge).sum(axis=1) == 1).all()
    assert ((places - edge) == (edge - behind)).all()  # behind, edge and place in line
