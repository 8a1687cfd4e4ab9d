"""bench/bench_detector_sets.py: scoring and the summary table on two rendered stress images."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import bench_detector_sets as bench

from tasks.simulation.detector_stress import STRESS_CASES, render_stress_case

DETECTORS = tuple(d for d in bench.DETECTORS if d != "rrht ellipse")


def scored(item: bench.Image) -> dict[str, tuple[str, float | None]]:
    return bench.score_image(item, bench.detect_all(item, DETECTORS)[0])


def test_a_render_and_blank_paper_give_each_detectors_counts_and_a_table_row():
    case = next(c for c in STRESS_CASES if c.name == "distant-8px")
    image, truth = render_stress_case(case)
    plate = replace(case.plate, dark_dots=case.dark_dots)
    render = bench.Image("distant-8px", image, plate, truth, truth, case.dot_px)
    blank = bench.Image("blank", np.full_like(image, 200), plate, truth, truth, case.dot_px)
    rows = [scored(render), scored(blank)]
    cells = bench.summarise(rows, DETECTORS)

    assert rows[0]["rrht"][0] == "found" and rows[0]["rrht"][1] < 0.05  # measured 0.016 px
    assert cells["rrht"].startswith("1 / 1 / 0, 0.0")
    assert cells["cv2"] == "0 / 2 / 0"  # findCirclesGrid without clustering finds no 4 × 3 grid
    assert rows[0]["cv2+clustering"][0] == "found"

    # The same answers against a truth a third of a dot off: found grids become wrong ones.
    off = replace(render, truth=truth + 0.3 * case.dot_px, error_truth=truth + 0.3 * case.dot_px)
    moved = scored(off)
    assert moved["rrht"] == ("wrong", None) and moved["cv2+clustering"] == ("wrong", None)

    text = bench.table([(bench.ImageSet("stress", "two images", lambda: []), 2, cells, [0.010, 0.030])])
    row = text.splitlines()[2]
    assert row.startswith("| stress (2) | 1 / 1 / 0, 0.0") and row.endswith("| 20 / 30 |")
    assert row.split(" | ")[2] == "–"  # no ellipse-centre column where the truth is not a hand fit
