"""Which coarse search band finds a grid of small dots in a large frame (tasks.vision.detection.framework).

The frame is the envelope's scene of ``bench/bench_12mp.py`` (clutter, paper texture, shadow, colour
JPEG) at 1200 × 1600: its first band starts above 8 px, so the half-resolution band of 12 px up and
the full-resolution band of 6–16 px are searched after it.
"""

from dataclasses import replace

import numpy as np
import pytest

from tasks.simulation.detector_stress import StressCase, errors_up_to_symmetry, render_stress_case
from tasks.vision.detection.framework import (
    SMALL_DOT_PX,
    BandSearch,
    FrameworkParams,
    detect_rrht,
    search_bands,
    small_dot_grid,
)
from tasks.vision.detection.preprocess import check_image


def _frame(dot_px: float, tilt_deg: float = 0.0):
    case = StressCase(f"frame-{dot_px:g}px", 1200, 1600, dot_px, tilt_deg=tilt_deg, tilt_azimuth_deg=37.0,
                      spin_deg=20.0, clutter=30, texture=True, shadow=0.5, gradient=0.8, vignetting=0.3,
                      colour=True, jpeg=80, seed=1000)
    image, truth = render_stress_case(case)
    return check_image(image), truth, replace(case.plate, dark_dots=case.dark_dots)


def _small_dot_pair(image, plate):
    p = FrameworkParams()
    bands = search_bands(image.shape, plate, None, p.coarse_target_diameter_px, p.coarse_width_px)
    assert len(bands) == 4 and bands[2][0] == 2 and bands[3][:2] == (1, SMALL_DOT_PX)
    return [BandSearch(image, plate, *b, p, {}, {"expected_rotation_deg": None, "mirrored": False,
                                                   "expected_centres_px": None}) for b in bands[2:]]


@pytest.fixture(scope="module")
def small_dots():
    return _frame(8.0)


def test_small_dots_are_taken_from_the_full_resolution_band_before_the_half_resolution_contours(small_dots):
    image, truth, plate = small_dots
    half, full = _small_dot_pair(image, plate)
    assert not half.hough_is_final()  # the 12 px band's circles give no grid
    found = small_dot_grid(half, full)
    assert found is not None and found.ok and found.factor == 1
    d = 2.0 * np.sqrt(np.prod(found.circles.axes[found.order.index], axis=1))
    assert 6.0 < np.median(d) < half.d_min  # the dots' size, below the half-resolution band's
    det = detect_rrht(image, plate)
    assert det.ok
    assert np.median(errors_up_to_symmetry(plate, det.centres, truth)) < 0.1


def test_a_grid_at_the_half_resolution_bands_size_is_not_taken_from_the_finer_band(small_dots):
    image, _, plate = small_dots
    half, full = _small_dot_pair(image, plate)
    # a band starting at 7 px would hold these 8 px dots: its own contours are searched first
    holding = BandSearch(image, plate, 2, 7.0, half.d_max, half.p, {}, half.kw)
    assert not holding.hough_is_final()
    assert small_dot_grid(holding, full) is None


def test_dots_the_half_resolution_band_finds_are_unaffected():
    image, truth, plate = _frame(16.0)
    half, full = _small_dot_pair(image, plate)
    assert half.hough_is_final()  # its circles give the grid: the band goes on as before
    assert small_dot_grid(half, full) is None
    det = detect_rrht(image, plate)
    assert det.ok and np.median(errors_up_to_symmetry(plate, det.centres, truth)) < 0.1
