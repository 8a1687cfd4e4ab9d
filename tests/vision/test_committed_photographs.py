"""The RRHT detector on real public photographs committed with the tests (tests/photos/README.md).

Two webcam photographs of robot_cal_tools' 10 × 10 dot target (Apache-2.0; a sheet taped to
cardboard on a carpet, cables and a trolley around it, the paper overexposed so that the 7–8 px dots
are lighter inside than at their rim), committed as the grey window around the target. Each was
cut down by ``bench/real_photo_truth.py`` to a 4 × 3 block (the other dots and the big fiducial
inpainted) and brought into the hidden acceptance set's regimes: as photographed, 640 × 480 with
15 px dots, 320 × 360 through a fisheye with 30 px dots (committed as made: the lens is the bench's),
3024 × 4032 with 150 px dots. The test remakes the others from the window and the recorded
inpainting. Truth: the centre of the ellipse through each dot's visible rim (no detector of ours).
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
from tests.vision.test_real_photographs import remake

FOLDER = Path(__file__).resolve().parents[1] / "photos" / "robot_cal_tools"
TRUTHS = sorted(FOLDER.glob("test_set_10x10_*.json"))
MEDIAN_BOUND_PX = {"photographed": 0.08, "distant": 0.16, "fisheye": 0.42, "large": 0.6}
"""Median error over the 12 dots allowed per regime (measured 0.037–0.048, 0.059–0.106, 0.094–0.283 and
0.337–0.398 px over both photographs and polarities, tests/photos/README.md)."""


def regime(truth: dict) -> str:
    """The hidden set's regime the variant imitates."""
    variant = truth["variant"]
    return ("fisheye" if variant.endswith("fisheye") else "large" if variant.endswith("3024x4032")
            else "distant" if variant.endswith("640x480") else "photographed")


def image_of(truth_file: Path, truth: dict) -> np.ndarray:
    """The image bench/real_photo_truth.py wrote for ``truth``, made again from the committed window."""
    if regime(truth) == "fisheye":
        return cv2.imread(str(truth_file.with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
    photo = truth["source"].rsplit("/", 1)[1].removesuffix(".png")
    window = cv2.imread(str(FOLDER / f"test_set_10x10_{photo}_window.png"), cv2.IMREAD_GRAYSCALE)
    return remake(window, {**truth, "crop_xywh": [0, 0, window.shape[1], window.shape[0]]})


@pytest.mark.parametrize("dark", [True, False], ids=["dark dots", "light dots"])
@pytest.mark.parametrize("truth_file", TRUTHS, ids=[p.stem for p in TRUTHS])
def test_the_block_is_found_and_labelled(truth_file, dark):
    """Found without a rotation prior, as ``fivecal detect``; labelled right up to the grid's
    symmetry (every dot within a quarter of its size of the true centre its label names, a wrong
    label being a pitch, two dot sizes, off); median error within the regime's bound. The light dots
    are the same photograph inverted: the code before refused the 640 × 480 view of photograph 0 so
    ("missing dots: 6x3 lattice of 13 dots, at most 8 of 12 in a 4x3 window": a larger lattice of the
    lettering beside the target taken for the plate's, grid.order_beside)."""
    truth = json.loads(truth_file.read_text())
    img = image_of(truth_file, truth)
    plate = DotPlate(truth["rows"], truth["cols"], truth["pitch_over_diameter"], 1.0, dark_dots=dark)
    det = detect_grid(img if dark else 255 - img, plate, "rrht")
    assert det.ok, det.reason
    err = errors_up_to_symmetry(plate, det.centres, np.array(truth["truth_px"]))
    assert err.max() < 0.25 * truth["dot_diameter_px"]
    assert np.median(err) < MEDIAN_BOUND_PX[regime(truth)], np.median(err)
