"""The measure flow end to end (ingest, detection, self-calibration, poses) through Prefect's harness."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tasks.core import se3
from tasks.lake.store import read_table
from tasks.simulation.campaign_plan import CampaignPlan
from tasks.simulation.simulate import write_campaign

pytestmark = pytest.mark.flow

PLAN = CampaignPlan(calibration_trials=2, images_per_trial=5, sweep_positions=2, sweep_repeats=1, pige_poses=3,
                    validation_poses=1)


def poses_as_matrices(df, suffix=""):
    T = np.zeros((len(df), 4, 4))
    T[:, 3, 3] = 1.0
    for i in range(3):
        for j in range(4):
            T[:, i, j] = df[f"T{i}{j}{suffix}"]
    return T


def test_measure_finds_every_grid_calibrates_and_caches(prefect_harness, tmp_path):
    from flows.measure import measure_campaign

    folder = write_campaign(tmp_path / "m1", "m1", seed=4, size="small", plan=PLAN)
    results = tmp_path / "results"
    first = measure_campaign(str(folder), str(results))
    n = len(pd.read_csv(folder / "manifest.csv"))
    assert first["n_images"] == n and first["n_detected"] == n and first["n_poses"] == n
    assert first["cached"] == {"detect": 0, "calibrate": 0, "poses": 0}

    cal = read_table("camera_calibration", results, "m1")
    truth = json.loads((folder / "truth" / "truth.json").read_text())["cameras"]
    for camera, t in truth.items():
        joint = cal[(cal.camera == camera) & (cal.trial == "joint")].iloc[0]
        f_true = t["focal_length_mm"] / t["pixel_size_mm"]
        assert abs(joint.fx_px - f_true) / f_true < 0.002  # 10 views of 768×512 images
        assert joint.rms_px < 0.05

    # machine poses: the grid labels follow the commanded axes, so rotations agree with the truth
    poses = read_table("poses", results, "m1").merge(pd.read_parquet(folder / "truth" / "images.parquet"),
                                                       on=["image_id", "camera"], suffixes=("", "_t"))
    manifest = pd.read_csv(folder / "manifest.csv")
    machine_views = poses[poses.image_id.isin(manifest.image_id[manifest.stage != "camera_calibration"])]
    err = se3.inverse(poses_as_matrices(machine_views, "_t")) @ poses_as_matrices(machine_views)
    assert np.degrees(se3.rotation_angle(err[:, :3, :3])).max() < 0.2

    before = read_table("poses", results, "m1")
    second = measure_campaign(str(folder), str(results))
    n_chunks = -(-n // 32)
    assert second["cached"] == {"detect": n_chunks, "calibrate": 1, "poses": 1}
    pd.testing.assert_frame_equal(read_table("poses", results, "m1"), before)


def test_calibrate_on_a_campaign_without_a_validation_pose_ends_in_one_line_and_writes_no_calibrate_table(
        prefect_harness, campaign_copy, tmp_path):
    from typer.testing import CliRunner

    from fivecal.cli import app

    campaign = campaign_copy("noval")
    manifest = pd.read_csv(campaign / "manifest.csv", dtype=str)
    for path in manifest.loc[manifest.stage == "validation", "path"]:  # 1 of 18: ingest accepts the campaign
        (campaign / path).unlink()
    root = tmp_path / "results"
    result = CliRunner().invoke(app, ["calibrate", str(campaign), "--results", str(root), "--reports",
                                      str(tmp_path / "reports")])
    assert result.exit_code == 2, result.output
    assert "no validation image of camera1 gave a pose" in result.output and "Traceback" not in result.output
    assert len(read_table("poses", root, "noval")) == len(manifest) - 1  # measure's step went through
    assert not any((root / t).exists() for t in ("pdge", "pige", "compensation", "verification", "diagnosis"))


def test_plates_that_are_not_the_ones_photographed_refuse_the_campaign_naming_them(
        prefect_harness, campaign_copy, tmp_path, capsys):
    """campaign.json says plate a and target a have 6 rows; the images show 7: no grid is found on
    them, and the campaign is refused (exit 2) with each plate's count, the earlier tables kept."""
    from typer.testing import CliRunner

    from fivecal.cli import _print_table3, app
    from flows.measure import measure_campaign

    campaign = campaign_copy("wrongrows")
    root = tmp_path / "results"
    good = measure_campaign(str(campaign), str(root))
    # too few calibration views in this tiny campaign: said in words, not as NaN intrinsics
    _print_table3(Path(good["tables"]["camera_calibration"]), campaign)
    printed = capsys.readouterr().out
    assert "camera1: NOT CALIBRATED (no ok trial)" in printed and "nan" not in printed
    before = read_table("dots", root, "wrongrows")

    meta = json.loads((campaign / "campaign.json").read_text())
    for plate in ("plate_a", "target_a"):
        meta["plates"][plate]["rows"] = 6
    (campaign / "campaign.json").write_text(json.dumps(meta))
    bad = CliRunner().invoke(app, ["measure", str(campaign), "--results", str(root)])
    assert bad.exit_code == 2, bad.output
    assert "error: " in bad.output and "no dot grid found in 14 of 18 images" in bad.output
    assert "plate_a (6×7 dots at 11 mm): 0 of 12" in bad.output
    assert "target_b (7×7 dots at 2.5 mm): 2 of 2" in bad.output
    pd.testing.assert_frame_equal(read_table("dots", root, "wrongrows"), before)
