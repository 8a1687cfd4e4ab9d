"""bench/bench_stress.py: a mirrored labelling is told from the grid's own symmetry."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import bench_stress as bench

from tasks.simulation.detector_stress import ISSUE_PLATE


def test_a_labelling_with_rows_or_columns_alone_flipped_is_mirrored():
    plate = ISSUE_PLATE
    truth = plate.dot_centres_mm()[:, :2] * 10.0 + 300.0  # a fronto-parallel view, px
    grid = truth.reshape(plate.rows, plate.cols, 2)
    assert not bench.mirrored(plate, truth, truth)
    assert not bench.mirrored(plate, grid[::-1, ::-1].reshape(-1, 2), truth)  # half a turn: the grid's symmetry
    assert bench.mirrored(plate, grid[::-1].reshape(-1, 2), truth)
    assert bench.mirrored(plate, grid[:, ::-1].reshape(-1, 2), truth)
