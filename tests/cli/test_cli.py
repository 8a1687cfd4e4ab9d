"""The command line, without Prefect: catalogue, truth statistics, and refused bad input."""

from typer.testing import CliRunner

from fivecal.cli import app

runner = CliRunner()


def test_effects_lists_the_catalogue():
    result = runner.invoke(app, ["effects"])
    assert result.exit_code == 0
    assert "pitch_cyclic:" in result.output and "period_mm [mm]" in result.output


def test_truth_stats_prints_the_seed_comparison():
    result = runner.invoke(app, ["truth-stats", "--poses", "50"])
    assert result.exit_code == 0
    assert "position_mean_um" in result.output and "59.90" in result.output


def test_truth_stats_with_an_effect_changes_the_numbers():
    base = runner.invoke(app, ["truth-stats", "--poses", "20"]).output
    more = runner.invoke(app, ["truth-stats", "--poses", "20", "--effect", "tool_offset:dx_um=200"]).output
    assert base != more


def test_truth_stats_says_how_far_a_context_effect_moves_the_tip():
    """Each validation pose in its campaign context: an 8 µm backlash moves every tip by 4 µm."""
    result = runner.invoke(app, ["truth-stats", "--poses", "10", "--effect", "backlash:axis=Z,amount_um=8"])
    assert result.exit_code == 0
    assert "The effects move the tip by 4.00 µm on average (max 4.00)" in result.output


def test_simulate_refuses_a_missing_effect_module_before_doing_anything(tmp_path):
    # a wide terminal: the error box would otherwise wrap the long temporary path inside the file name
    result = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--effect-module", str(tmp_path / "nope.py")],
                           env={"COLUMNS": "1000"})
    assert result.exit_code != 0
    assert "nope.py" in result.output
    assert not (tmp_path / "x").exists()


def test_simulate_refuses_a_bad_effect_before_doing_anything(tmp_path):
    result = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--effect", "pitch_cyclic:axis=Q"])
    assert result.exit_code != 0
    assert "must be one of" in result.output
    assert not (tmp_path / "x").exists()


def test_ingest_of_a_missing_campaign_fails_fast_with_the_folder_named(tmp_path):
    result = runner.invoke(app, ["ingest", str(tmp_path / "nope")])
    assert result.exit_code == 2
    assert "nope" in result.output and "does not exist" in result.output


def test_detect_prints_ordered_centres_that_match_the_truth(tiny_campaign):
    import json

    import numpy as np
    import pandas as pd

    manifest = pd.read_csv(tiny_campaign / "manifest.csv")
    row = manifest[(manifest.camera == "camera1") & (manifest.stage == "pige")].iloc[0]
    result = runner.invoke(app, ["detect", str(tiny_campaign / row.path), "--pitch-mm", "9", "--row-pitch-mm", "6",
                                 "--diameter-mm", "2.5", "--json"])
    assert result.exit_code == 0, result.output
    found = json.loads(result.output)
    assert found["ok"] and len(found["dots"]) == 49 and found["centres"] == "ellipse"
    assert not any(d["shadowed"] for d in found["dots"])  # no cast shadow on a campaign view
    uv = np.array([[d["corrected_u_px"], d["corrected_v_px"]] for d in found["dots"]])
    ellipse = np.array([[d["ellipse_u_px"], d["ellipse_v_px"]] for d in found["dots"]])
    assert np.array_equal(np.array([[d["u_px"], d["v_px"]] for d in found["dots"]]), ellipse)  # the default
    truth = pd.read_parquet(tiny_campaign / "truth" / "dots.parquet")
    true_uv = truth[truth.image_id == row.image_id][["u_px", "v_px"]].to_numpy()
    # labels may differ by a symmetry of the grid without a rotation prior: compare as sets
    nearest = np.min(np.linalg.norm(true_uv[:, None] - uv[None], axis=-1), axis=1)
    assert nearest.max() < 0.15  # px, at 768×512 (4× binned): where the dots' centres project
    assert 0 < np.abs(ellipse - uv).max() < 0.1  # the perspective bias of the ellipse centres, small here

    corrected = runner.invoke(app, ["detect", str(tiny_campaign / row.path), "--pitch-mm", "9", "--row-pitch-mm",
                                    "6", "--diameter-mm", "2.5", "--json", "--centres", "corrected"])
    dots = json.loads(corrected.output)["dots"]
    assert np.array_equal(np.array([[d["u_px"], d["v_px"]] for d in dots]), uv)


def test_detect_names_an_unreadable_image(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png")
    result = runner.invoke(app, ["detect", str(bad)])
    assert result.exit_code == 2 and "broken.png" in result.output


def test_calibrate_refuses_both_an_existing_and_a_local_dask_cluster(tmp_path):
    result = runner.invoke(app, ["calibrate", str(tmp_path), "--dask-address", "tcp://127.0.0.1:8786",
                                 "--dask-workers", "2"])
    assert result.exit_code == 2
    assert "not both" in result.output


def test_calibrate_refuses_an_unknown_orientation_objective_before_any_work(tmp_path):
    result = runner.invoke(app, ["calibrate", str(tmp_path), "--orientation", "tool"])
    assert result.exit_code == 2
    assert "full, tool-axis" in result.output


def test_calibrate_refuses_fewer_than_one_verification_image_per_pose_before_any_work(tmp_path):
    result = runner.invoke(app, ["calibrate", str(tmp_path), "--verification-repeats", "0"])
    assert result.exit_code == 2
    assert "--verification-repeats" in result.output
