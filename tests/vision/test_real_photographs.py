"""The RRHT detector on a real public photograph of printed dot grids (tests/photos/README.md).

The photograph (OpenCV's documentation, Apache-2.0, fetched from PyPI by ``make photos``) holds
two asymmetric circle grids. ``bench/real_photo_truth.py`` cut its black-on-white grid down to
one 4 × 3 block of the 45° square lattice its dots form, inpainting every other dot, and
recorded how (``tests/photos/dual_circles_left*.json``); the test remakes each image from the
photograph alone. Truth: the centre of the ellipse through each dot's visible rim, made by that
script without any detector of ours (it agrees with the dots' intensity centroids to 0.03 px
median: these dots are uniformly dark).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tasks.machine.plate import DotPlate
from tasks.simulation.detector_stress import errors_up_to_symmetry
from tasks.vision.detection import detect_grid

PHOTOS = Path(__file__).resolve().parents[1] / "photos"
PHOTO = PHOTOS / "cache" / "dualCircles.jpg"
TRUTHS = sorted(PHOTOS.glob("dual_circles_left*.json"))


@pytest.fixture(scope="module")
def photo() -> np.ndarray:
    if not PHOTO.exists():
        pytest.fail(f"{PHOTO} is missing: run `make photos` (tests/photos/fetch.py; `make test` does it first)")
    return cv2.cvtColor(cv2.imread(str(PHOTO), cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)


def remake(grey: np.ndarray, truth: dict) -> np.ndarray:
    """The image bench/real_photo_truth.py wrote for ``truth``: window, inpainting, resize, crop."""
    x, y, w, h = truth["crop_xywh"]
    img = grey[y:y + h, x:x + w].copy()
    mask = np.zeros(img.shape, np.uint8)
    for u, v, bw, bh, deg in truth["inpaint_ellipses"]:
        cv2.ellipse(mask, ((u, v), (bw, bh), deg), 255, -1)
    img = cv2.inpaint(img, mask, 5, cv2.INPAINT_TELEA)
    scale_txt, _, crop_txt = truth["variant"].partition(":")
    scale = float(scale_txt)
    if scale != 1:
        size = (round(img.shape[1] * scale), round(img.shape[0] * scale))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)
    if crop_txt:
        cw, ch = (int(s) for s in crop_txt.split("x"))
        x0, y0 = (int(s) for s in truth["window_origin"])
        img = img[y0:y0 + ch, x0:x0 + cw]
    return img


def prior(truth_px: np.ndarray) -> tuple[float, bool]:
    """(expected rotation deg, mirrored) from the true centres of dots (0, 0), (0, 1) and (1, 0)."""
    dx, dy = truth_px[1] - truth_px[0], truth_px[3] - truth_px[0]
    return float(np.degrees(np.arctan2(-dx[1], dx[0]))), bool(dx[0] * dy[1] - dx[1] * dy[0] > 0)


@pytest.mark.parametrize("truth_file", TRUTHS, ids=[p.stem for p in TRUTHS])
def test_the_block_is_found_and_labelled_on_the_photograph(photo, truth_file):
    truth = json.loads(truth_file.read_text())
    img = remake(photo, truth)
    true_px = np.array(truth["truth_px"])
    plate = DotPlate(truth["rows"], truth["cols"], truth["pitch_over_diameter"], 1.0)
    rotation, mirrored = prior(true_px)
    det = detect_grid(img, plate, "rrht", expected_rotation_deg=rotation, mirrored=mirrored)
    assert det.ok, det.reason
    err = np.linalg.norm(det.centres - true_px, axis=1)  # label by label: a wrong labelling is a pitch off
    assert err.max() < 0.25 * truth["dot_diameter_px"]
    assert np.median(err) < 0.08 and err.max() < 0.3  # measured 0.02–0.06 px and 0.05–0.15 px
    blind = detect_grid(img, plate, "rrht")  # as `fivecal detect` without --rotation-deg
    assert blind.ok, blind.reason
    np.testing.assert_allclose(errors_up_to_symmetry(plate, blind.centres, true_px), err, atol=1e-6)


def test_light_dots_on_the_inverted_photograph(photo):
    truth = json.loads((PHOTOS / "dual_circles_left.json").read_text())
    img = 255 - remake(photo, truth)
    plate = DotPlate(4, 3, truth["pitch_over_diameter"], 1.0, dark_dots=False)
    det = detect_grid(img, plate, "rrht")
    assert det.ok, det.reason
    err = errors_up_to_symmetry(plate, det.centres, np.array(truth["truth_px"]))
    assert np.median(err) < 0.08 and err.max() < 0.3


@pytest.mark.parametrize("dark", [True, False], ids=["dark dots", "light dots"])
def test_the_block_on_a_large_even_page_is_found(photo, dark):
    """The block's own pixels (a square around it, 2.2 block widths) set in a page six times as wide
    of the photograph's paper level with 1.5 DN of noise: the 12 dots are 0.3 % of the pixels, and
    the 1–99 % grey stretch spans the paper's noise alone (before: "missing dots", 11 of 12)."""
    truth = json.loads((PHOTOS / "dual_circles_left.json").read_text())
    img = remake(photo, truth)
    true_px = np.array(truth["truth_px"])
    centre = true_px.mean(axis=0).astype(int)
    half = int(1.1 * np.ptp(true_px, axis=0).max())
    x0, y0 = max(centre[0] - half, 0), max(centre[1] - half, 0)
    patch = img[y0:centre[1] + half, x0:centre[0] + half]
    h, w = 6 * patch.shape[0], 6 * patch.shape[1]
    page = np.random.default_rng(0).normal(float(np.median(patch)), 1.5, (h, w))
    oy, ox = (h - patch.shape[0]) // 2, (w - patch.shape[1]) // 2
    page[oy:oy + patch.shape[0], ox:ox + patch.shape[1]] = patch
    page = np.clip(np.rint(page), 0, 255).astype(np.uint8)
    plate = DotPlate(4, 3, truth["pitch_over_diameter"], 1.0, dark_dots=dark)
    det = detect_grid(page if dark else 255 - page, plate, "rrht")
    assert det.ok, det.reason
    err = errors_up_to_symmetry(plate, det.centres, true_px - [x0, y0] + [ox, oy])
    assert np.median(err) < 0.08 and err.max() < 0.3  # measured 0.029 px median


@pytest.mark.parametrize("window, dark, reason", [
    ((0, 400), True, "extra dots: 9x8 lattice holds 15 complete 4x3 windows"),  # the whole black-dot grid
    # the white-dot grid, a tape measure across it: the band reported is the one whose lattice fills a 4 x 3
    # window (the most plate-like), and the grid beyond it is as much of the plate (the code before reported
    # the largest lattice, "missing dots")
    ((400, 800), False, "extra dots: 7 lattice-aligned dots beyond the 4x3 window"),
])
def test_the_uncut_grids_are_refused_with_the_reason(photo, window, dark, reason):
    """Neither grid of the photograph is a 4 × 3 plate: a wrong labelling is worse than none."""
    det = detect_grid(photo[:, window[0]:window[1]], DotPlate(4, 3, 1.86, 1.0, dark_dots=dark), "rrht")
    assert not det.ok
    assert det.reason.startswith(reason), det.reason
