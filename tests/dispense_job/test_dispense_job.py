"""The dispensing job (issue 34): boards, location, pixel maps, program, the flow on a simulated tray.
The tours, travel time and bead path are tested in tests/dispense_job/test_dispense_job_tours.py."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from tasks.dispense_job.bead_path import bead_path
from tasks.dispense_job.boards import TraySpec, render_tray
from tasks.dispense_job.camera_view import camera_image
from tasks.dispense_job.locate import locate, sobel_edges
from tasks.dispense_job.pixel_map import (
    PAPER_TABLE2_MM,
    PAPER_TABLE2_PX,
    commands_at,
    fit_planar_map,
    pixels_to_workpiece,
)
from tasks.dispense_job.program import Motion, program_rows, program_time_s
from tasks.dispense_job.recognition import match_found_boards, score_tray
from tasks.dispense_job.tour_exact import plan_tour
from tasks.dispense_job.travel_time import travel_time_s
from tasks.dispensing.tip import landing_points


def test_every_intact_board_is_found_to_10_um_and_every_defective_one_rejected_for_its_defect():
    spec = TraySpec(rows=2, cols=3, image_px=(1400, 1000), defect_rate=0.5)
    scored = []
    for seed in (1, 2, 3):
        image, truth, _ = render_tray(spec, seed)
        scored.append(score_tray(locate(image, mm_per_px=spec.mm_per_px), truth, spec))
    import pandas as pd

    df = pd.concat(scored, ignore_index=True)
    assert {"", "broken_edge", "missing_component"} <= set(df.defect)
    assert df.correct.all(), df[~df.correct][["board_id", "defect", "reason"]]
    intact = df[df.defect == ""]
    assert intact.ok.all()
    assert intact.centre_error_mm.max() <= 0.01
    # the paper's rectangle alone (its centre on the edge pixels' grid) is the baseline the refinement beats
    assert intact.centre_error_mm.max() < intact.paper_centre_error_mm.max()
    assert np.abs(intact.angle_error_deg).max() < 0.5
    assert np.allclose(intact.width_mm, 2.0, atol=0.05) and np.allclose(intact.length_mm, 4.0, atol=0.1)


def test_a_blobs_sobel_edges_are_the_exact_half_maximum_threshold_of_its_gradient():
    rng = np.random.default_rng(1)
    for _ in range(50):
        h, w = (int(n) for n in rng.integers(20, 120, 2))
        mask = np.zeros((h, w), np.uint8)
        box = ((float(rng.uniform(5, w - 5)), float(rng.uniform(5, h - 5))),
               (float(rng.uniform(4, w)), float(rng.uniform(4, h))), float(rng.uniform(0, 180)))
        cv2.ellipse(mask, box, 255, -1)
        f = mask.astype(np.float64)
        magnitude = np.hypot(cv2.Sobel(f, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(f, cv2.CV_64F, 0, 1, ksize=3))
        assert np.array_equal(sobel_edges(mask), magnitude > 0.5 * magnitude.max())


def test_a_blank_tray_has_no_board():
    spec = TraySpec(rows=2, cols=2, image_px=(1000, 1000))
    image, truth, _ = render_tray(spec, 4, boards=0)
    found = locate(image, mm_per_px=spec.mm_per_px)
    assert truth.empty and found.boards == []


def test_locate_command_prints_the_areas_and_writes_an_overlay(tmp_path):
    import cv2
    from typer.testing import CliRunner

    from fivecal.cli import app

    spec = TraySpec(rows=1, cols=2, image_px=(1000, 600), defect_rate=0.0)
    image, truth, _ = render_tray(spec, 8)
    path, overlay = tmp_path / "tray.png", tmp_path / "overlay.png"
    cv2.imwrite(str(path), image[..., ::-1])
    result = CliRunner().invoke(app, ["locate", str(path), "--overlay", str(overlay)])
    assert result.exit_code == 0, result.output
    assert result.output.count("accepted") == 2 and cv2.imread(str(overlay)).shape == image.shape
    printed = np.array([[float(w) for w in line.split()[1:3]] for line in result.output.splitlines()
                        if line.endswith("accepted")])
    true_uv = truth[["area_u_px", "area_v_px"]].to_numpy(float)
    assert all(np.min(np.linalg.norm(true_uv - p, axis=1)) < 0.1 for p in printed)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((300, 400, 3), 25, np.uint8))
    assert "no board found" in CliRunner().invoke(app, ["locate", str(blank)]).output
    bad = CliRunner().invoke(app, ["locate", str(tmp_path / "missing.png")])
    assert bad.exit_code == 2 and "missing.png: not a readable image" in bad.output


def test_the_paper_table2_planar_map_reproduces_its_table9_conversions():
    m = fit_planar_map(PAPER_TABLE2_PX, PAPER_TABLE2_MM)
    table9_px = np.array([[629.28, 713.64], [1999.52, 1128.5], [1108.04, 1598.28], [264.48, 1550.5],
                          [2186.52, 579.12], [1374.84, 1903.8], [2031.04, 2197.92], [642.96, 2008.68],
                          [948.48, 2058.84], [2243.52, 2496.6], [1051.08, 2421.36], [836.76, 446.88],
                          [1942.56, 2118.13], [978.12, 1459.2], [585.96, 1146.84], [565.44, 937.08],
                          [2268.6, 884.64], [563.16, 1422.72], [2154.6, 1561.9], [886.92, 1694.06]])
    table9_mm = np.array([[27.6, 31.3], [87.7, 49.5], [48.6, 70.1], [11.6, 68.0], [95.9, 25.4], [60.3, 83.5],
                          [88.8, 96.4], [28.2, 88.1], [41.6, 90.3], [98.4, 109.5], [46.1, 106.2], [36.7, 19.6],
                          [85.2, 92.9], [42.9, 64.1], [25.7, 50.3], [24.8, 41.1], [99.5, 38.8], [24.7, 62.4],
                          [94.5, 68.5], [38.9, 74.3]])
    # Table 2's five pairs have whole millimetres; its affine fit gives all twenty of Table 9's conversions
    # (made with the paper's full camera model) to 0.25 mm per axis, 0.18 mm on average
    err = np.abs(m.apply(table9_px) - table9_mm)
    assert err.max() < 0.3 and np.hypot(*err.T).mean() < 0.2
    assert 0.0437 < m.matrix[0, 0] < 0.0439  # mm per pixel
    with pytest.raises(ValueError, match="one line"):
        fit_planar_map([[0, 0], [1, 1], [2, 2]], [[0, 0], [1, 1], [2, 2]])


def test_the_calibrated_map_sends_the_needle_onto_the_true_areas(machine, errors):
    """Through the true camera and model, as a perfect calibration would, the needle is sent onto the areas
    to a few µm, nearer than through the nominal machine (camera 1 rides on Z with the needle: the
    machine's errors move both, and only what differs between them is left)."""
    from tasks.dispense_job.boards import board_truth, paint_tray, place_boards
    from tasks.dispense_job.tray_io import SURFACE_Z_MM
    from tasks.dispensing.workpiece import imaging_commands

    spec = TraySpec(rows=2, cols=3, defect_rate=0.0)
    placed = place_boards(spec, np.random.default_rng([5, 34]))
    imaging = imaging_commands(machine, np.zeros((1, 2)), np.array([SURFACE_Z_MM]))[0]
    cam = machine.cameras["camera1"]
    view = camera_image(paint_tray(spec, placed).astype(np.float32), spec, machine, errors, cam, imaging, SURFACE_Z_MM)
    found = locate(np.clip(np.rint(view), 0, 255).astype(np.uint8), mm_per_px=0.045)
    uv = np.array([[b.area.rect.u, b.area.rect.v] for b in found.boards if b.ok])
    assert len(uv) == len(placed)
    truth = board_truth(spec, placed)[["area_x_mm", "area_y_mm"]].to_numpy(float)
    miss = {}
    for name, model in (("true", errors), ("nominal", None)):
        xy = pixels_to_workpiece(machine, model, cam, imaging, uv, SURFACE_Z_MM)
        landed = landing_points(machine, errors, commands_at(machine, model, xy, SURFACE_Z_MM, 0.2))
        miss[name] = np.array([np.min(np.linalg.norm(truth - p, axis=1)) for p in landed])
    assert miss["true"].max() <= 0.005
    assert np.median(miss["true"]) < np.median(miss["nominal"])


def test_the_program_visits_every_board_once_and_times_travel_and_glue_apart():
    beads = [np.array([[0, 0, 0, 0, 0], [1, 0, 0, 0, 0]], float), np.array([[10, 0, 0, 0, 0], [10, 2, 0, 0, 0]], float)]
    motion = Motion(travel_mm_s=2.0, bead_mm_s=1.0, lift_mm=1.0)
    prog = program_rows(np.array([-1, 1, 0, 1, -1]), ["a", "b"], beads, np.zeros(5), motion)
    assert prog.board_id.tolist() == ["", "b", "b", "b", "b", "a", "a", "a", "a", ""]
    assert prog.dispense.sum() == 2
    back = program_rows(np.array([1, 0]), ["a", "b"], beads, np.zeros(5), motion, home_between=True)
    assert back.move.tolist().count("home") == 2 and back.move.iloc[5] == "home"  # after b, and at the end

    def dist(path, speed, accel):
        return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum() / speed[0])

    travel, glue = program_time_s(prog, motion, dist)
    assert glue == pytest.approx(2.0 / 1.0 + 1.0 / 1.0)
    # home → above b (10, 0, 1) → down → up at (10, 2, 1) → above a → down; up at (1, 0, 1) → home
    legs = np.hypot(10, 1) + 1 + 1 + np.hypot(10, 2) + 1 + 1 + np.hypot(1, 1)
    assert travel == pytest.approx(legs / 2.0)


def test_a_tray_without_its_sidecar_or_beyond_the_travel_is_refused_with_a_message(tmp_path, machine, errors):
    import cv2

    from tasks.dispense_job.tray_io import read_tray
    from tasks.dispense_job.tray_job import Calibration, Planners, run_tray

    spec = TraySpec(rows=1, cols=2, defect_rate=0.0)
    image, _, _ = render_tray(spec, 6)
    path = tmp_path / "far.png"
    cv2.imwrite(str(path), image[..., ::-1])
    with pytest.raises(ValueError, match=r"far\.png.*sidecar far\.json"):
        read_tray(path)
    # the tray seen 1 m along X: its boards are far outside the 600 mm stroke
    path.with_suffix(".json").write_text(json.dumps({"imaging_command": [1000, 0, 19.8, 0, 0], "surface_z_mm": 19.8,
                                                     "mm_per_px": 0.045}))
    tray = read_tray(path)
    planners = Planners(plan_tour, travel_time_s, bead_path)
    cal = Calibration("x", machine, errors, machine.cameras["camera1"])
    with pytest.raises(ValueError, match=r"larger than the machine's travel.*outside the travel"):
        run_tray(tray, locate(tray.read_rgb(), mm_per_px=0.045), cal, planners, ("compensated",))
    blank, _, _ = render_tray(spec, 6, boards=0)
    cv2.imwrite(str(path), blank[..., ::-1])
    with pytest.raises(ValueError, match=r"far\.png: no board found"):
        run_tray(tray, locate(tray.read_rgb(), mm_per_px=0.045), cal, planners, ("compensated",))



@pytest.mark.flow
def test_dispense_job_flow_on_a_simulated_tray(calibrated_campaign, prefect_harness, tmp_path):
    """End to end: a 6-board simulated tray plus an unreadable image; the job goes on past the bad
    image, writes the tables, programs and report, and every compensated bead lies within the paper's
    ±0.5 mm. (The fixture's calibration is rough: how near compensation sends the needle is measured
    on properly calibrated campaigns, docs/dispense-job.md.)"""
    from flows.dispense_job import dispense_job
    from tasks.dispense_job.tray_io import simulate_tray
    from tasks.lake.schema import TABLES, partition_problems
    from tasks.lake.store import read_table

    tray = simulate_tray(tmp_path / "trays" / "t1.png", calibrated_campaign.campaign, seed=7, boards=6,
                         spec=TraySpec(defect_rate=0.0))
    broken = tmp_path / "trays" / "broken.png"
    broken.write_bytes(b"not a png")
    broken.with_suffix(".json").write_text(tray.with_suffix(".json").read_text())
    results = tmp_path / "results"
    import shutil

    shutil.copytree(calibrated_campaign.results, results)
    summary = dispense_job([str(tray), str(broken)], str(calibrated_campaign.campaign), str(results),
                           str(tmp_path / "reports"), "t", ("compensated", "nominal"))
    assert "not a readable image" in summary["trays"]["broken"]["error"]
    assert summary["trays"]["t1"] == {"boards": 6, "accepted": 6, "rejected": [], "recognised": 6, "true_boards": 6}
    areas = read_table("dispense_areas", results, summary["campaign_id"])
    assert (areas.true_defect == "none").all() and areas.recognised.all()
    assert set(areas.phase) == {"compensated", "nominal"} and areas.map_error_um.between(0, 500).all()
    paths = read_table("dispense_paths", results, summary["campaign_id"])
    assert set(paths.method) == {"optimal", "annealing", "nearest", "return_to_origin"} and (paths.points == 6).all()
    beads = read_table("dispense_beads", results, summary["campaign_id"])
    comp = beads[beads.phase == "compensated"]
    assert len(comp) == 6 and comp.found.all() and comp.true_within_tolerance.all()
    assert (Path(summary["report"])).read_text().count("## ") >= 4
    tables = summary["tables"]
    assert partition_problems("dispense_areas", Path(tables["dispense_areas"])) == []
    assert partition_problems("dispense_paths", Path(tables["dispense_paths"])) == []
    assert partition_problems("dispense_beads", Path(tables["dispense_beads"])) == []
    for table in ("dispense_areas", "dispense_paths", "dispense_beads"):
        rows, keys = read_table(table, results, summary["campaign_id"]), list(TABLES[table].keys[1:])
        assert not rows[keys].isna().any().any() and not rows.duplicated(keys).any(), table
    out = tmp_path / "reports" / summary["campaign_id"] / "t" / "dispense-job"
    assert (out / "program-t1-compensated.csv").is_file() and (out / "index.html").is_file()
    assert cv2.imread(str(out / "dispensed-t1-nominal.png")).shape[2] == 3
    assert not list(out.parent.glob(".dispense-job.tmp-*"))  # published whole: no staging folder left


def test_dispense_job_command_takes_the_user_effect_modules_to_the_flow(calibrated_campaign, tmp_path, monkeypatch):
    """``--effect-module``: a module that cannot be imported is a usage error naming the option, before
    anything runs; an importable one (the documented example family) reaches the flow (which hands it
    to flows/lake_calibration.py in place of the modules the calibration recorded)."""
    from typer.testing import CliRunner

    import flows.dispense_job
    from fivecal.cli import app
    from tasks.machine.effects import EFFECTS

    seen = {}

    def fake_flow(images, campaign, results, reports, run, phases, effect_modules=None):
        seen.update(images=images, effect_modules=effect_modules)
        return {"trays": {}, "beads": pd.DataFrame(), "tables": {}, "report": "r.md"}

    monkeypatch.setattr(flows.dispense_job, "dispense_job", fake_flow)
    tray = str(tmp_path / "t1.png")
    campaign = str(calibrated_campaign.campaign)
    runner = CliRunner()
    bad = runner.invoke(app, ["dispense-job", tray, "--campaign", campaign, "--effect-module",
                              str(tmp_path / "nope.py")])
    assert bad.exit_code == 2 and "--effect-module" in bad.output and seen == {}
    module = str(Path(__file__).resolve().parents[2] / "docs" / "examples" / "cross_backlash.py")
    catalogue = dict(EFFECTS)
    try:
        good = runner.invoke(app, ["dispense-job", tray, "--campaign", campaign, "--effect-module", module])
    finally:
        EFFECTS.clear()
        EFFECTS.update(catalogue)
    assert good.exit_code == 0, good.output
    assert seen == {"images": [tray], "effect_modules": [module]}


def test_found_boards_are_scored_against_the_true_ones_on_the_tray():
    """Four true boards (intact, broken edge, missing component, one never found) and four found ones
    (one far from every true board): each found board gets its true board's defect and whether its
    verdict is the one the truth asks for; the true board nobody found is returned."""
    truth = pd.DataFrame({"board_id": ["p0", "p1", "p2", "p3"], "board_x_mm": [0.0, 21.0, 42.0, 63.0],
                          "board_y_mm": [0.0, 0.0, 0.0, 21.0], "defect": ["", "broken_edge", "missing_component", ""]})
    found = np.array([[0.4, -0.3], [21.2, 0.1], [41.0, 1.5], [30.0, 30.0]])
    defects, correct, missed = match_found_boards(
        found, np.array([True, False, True, False]),
        ["", "broken edge (notch 0.9 mm)", "", "no dispensing area"], truth)
    assert defects == ["none", "broken_edge", "missing_component", "unmatched"]
    assert correct == [True, True, False, False]  # a board without its capacitor must not be accepted
    assert missed["board_id"].tolist() == ["p3"]
