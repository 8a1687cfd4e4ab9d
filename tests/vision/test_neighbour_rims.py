"""The neighbours' blurred printed dots in the rim fits (tasks.vision.detection.neighbour_rims), against
supersampled blurred ellipses and the stress set's plain sheet (tasks.simulation.detector_stress: a 4 × 3
grid of dots at a pitch of 1.5 diameters on a sheet whose edge lies 3 mm beyond the outer dots' rims,
an extra blur σ on top of the lens's 0.6 px + σ), centres against the projected true centres up to the
grid's symmetry. Before the printed-dot model (b9e81c2) the neighbours were modelled from the blurred-step
fits' levels, which under a blur near the dots' radius predicted a third of their tails, and the sheet's
edge was not modelled: dark 13 px dots under σ = 3 px were 0.33 px off with the model and 0.20 px without."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from tasks.simulation.detector_stress import StressCase, errors_up_to_symmetry, render_stress_case
from tasks.vision.detection.framework import FrameworkParams, detect_rrht
from tasks.vision.detection.neighbour_rims import DotRims, disc_fill, ellipse_fill, tails_at_rims
from tasks.vision.detection.subpixel import SubpixelParams


@pytest.mark.parametrize(("a", "b", "sigma"), [(6.0, 4.0, 2.0), (5.0, 3.8, 3.0), (7.0, 5.4, 4.0)])
def test_ellipse_fill_matches_a_blurred_ellipse(a, b, sigma):
    s = 16  # an ellipse of level 1 drawn 16× supersampled, averaged to pixels (σ² 1/12) and blurred to σ
    big = np.zeros((100 * s, 100 * s), np.float32)
    cv2.ellipse(big, (50 * s + s // 2, 50 * s + s // 2), (int(a * s), int(b * s)), 0, 0, 360, 1.0, -1)
    image = cv2.GaussianBlur(cv2.resize(big, (100, 100), interpolation=cv2.INTER_AREA), (0, 0),
                             float(np.sqrt(sigma**2 - 1 / 12)))
    ang = np.linspace(0.0, np.pi / 2, 7)[:, None]
    rim = 1.0 / np.hypot(np.cos(ang) / a, np.sin(ang) / b)
    d = np.arange(6.0)[None, :]  # px outside the rim along the line from the centre
    x, y = (rim + d) * np.cos(ang), (rim + d) * np.sin(ang)
    grey = cv2.remap(image, (50 + x).astype(np.float32), (50 + y).astype(np.float32), cv2.INTER_LINEAR)
    assert np.abs(ellipse_fill(x, y, a, b, 0.0, sigma) - grey).max() < 0.035
    assert np.abs(disc_fill(rim + d, rim, sigma) - grey).max() > 0.04  # the disc of the rim's distance misses by more


def _plain(dot_px: float, blur_px: float, dark: bool) -> tuple[np.ndarray, np.ndarray, StressCase]:
    """The case ``bench/bench_stress.py --blur-sweep DOT --blurs BLUR --tilts 0`` renders."""
    case = StressCase("blur-sweep", 640, 480, dot_px, tilt_deg=0.0, tilt_azimuth_deg=37.0, spin_deg=20.0,
                      dark_dots=dark, gradient=0.0, vignetting=0.0, seed=1000, defocus_px=blur_px)
    image, truth = render_stress_case(case)
    return image, truth, case


def _median_error(image, truth, case, **subpixel) -> float:
    plate = replace(case.plate, dark_dots=case.dark_dots)
    det = detect_rrht(image, plate, params=FrameworkParams(subpixel=SubpixelParams(**subpixel)))
    assert det.ok, det.reason
    return float(np.median(errors_up_to_symmetry(plate, det.centres, truth)))


@pytest.mark.parametrize(("dot_px", "blur_px", "dark", "median_px"), [
    (13.0, 3.0, True, 0.1),  # 0.33 px with the step fits' levels as the model (b9e81c2), 0.20 px without a model
    (10.0, 2.0, True, 0.1),  # 0.16 px (b9e81c2), 0.21 px without
])
def test_blur_as_wide_as_the_gap_is_taken_out_of_the_centres(dot_px, blur_px, dark, median_px):
    image, truth, case = _plain(dot_px, blur_px, dark)
    assert _median_error(image, truth, case) < median_px


def test_the_sheets_edge_beyond_the_outer_dots_is_taken_out_too():
    # 16 px dark dots under σ = 3 px: the sheet's edge (a background 125 DN darker, 3 mm beyond the outer
    # dots' rims) moves the outer dots towards the grid's middle once the neighbours are taken out
    image, truth, case = _plain(16.0, 3.0, True)
    assert _median_error(image, truth, case, far_edges=False) > 0.18
    assert _median_error(image, truth, case) < 0.1


@pytest.mark.parametrize(("sigma", "tail"), [(0.8, 0.00621), (2.5, 0.21186)])
def test_tails_at_rims_is_the_blurred_rim_across_the_gap_between_the_ellipses(sigma, tail):
    # ellipses of semi-axes 5 × 3 px (major along u), neighbours 8 px apart along v: the rims are
    # 2 px apart on that line (their major semi-axes would overlap); the tail there is Φ(−2/σ)
    centres = np.array([[0.0, 0.0], [0.0, 8.0], [30.0, 0.0]])
    dots = DotRims(centres, np.tile([5.0, 3.0], (3, 1)), np.zeros(3), np.full(3, sigma), np.zeros(3), np.ones(3))
    assert tails_at_rims(dots, np.array([0])) == pytest.approx(tail, abs=1e-5)
