"""The calibrate flow end to end on a small simulated campaign (Prefect test harness): a re-run
re-uses every cached task, and adding an effect re-runs the fit and what follows it (the
uncertainty propagation included) but no image work of the campaign, and more images per
verification pose re-run only the capture."""

import shutil
from pathlib import Path

import pandas as pd
import pytest

from flows.calibrate import calibrate_campaign
from flows.reproduce import opencv_threads
from tasks.campaign.ingest import CampaignError
from tasks.lake.store import read_table


def test_rerun_is_served_from_the_cache_and_an_added_effect_refits_without_image_work(
        calibrated_campaign, prefect_harness, tmp_path):
    folder = tmp_path / "campaigns" / calibrated_campaign.campaign.name
    shutil.copytree(calibrated_campaign.campaign, folder, ignore=shutil.ignore_patterns("captures"))
    results, reports = str(tmp_path / "results"), str(tmp_path / "reports")
    with opencv_threads(1):
        first = calibrate_campaign(str(folder), results_root=results, reports_root=reports, run="first")
        again = calibrate_campaign(str(folder), results_root=results, reports_root=reports, run="again")
        single = read_table("verification", results, first["campaign_id"])  # before the next run replaces it
        effect = calibrate_campaign(str(folder), results_root=results, reports_root=reports, run="effect",
                                    effects=["backlash:axis=X,amount_um=0"])
    n_chunks = again["cached"]["measure"]["detect"]
    assert n_chunks > 0  # (the first run may already hit: detection is keyed on image content)
    assert again["cached"] == {"measure": {"detect": n_chunks, "calibrate": 1, "poses": 1}, "identify": True,
                               "propagate_uncertainty": True, "compensate": True, "capture": True,
                               "cross_validate": True, "diagnose": True}
    assert again["verification_means"] == first["verification_means"]
    # the added effect: images, detection, camera calibration and poses from the cache; the fit anew
    assert effect["cached"]["measure"] == {"detect": n_chunks, "calibrate": 1, "poses": 1}
    assert not effect["cached"]["identify"] and not effect["cached"]["cross_validate"]
    assert not effect["cached"]["diagnose"]
    assert effect["effects"] and effect["effects"][0].startswith("backlash:axis=X")
    # its uncertainty propagated as the plain fit's is (the lake holds the last run's partition)
    assert not effect["cached"]["propagate_uncertainty"]
    pige = read_table("pige", results, first["campaign_id"]).set_index("name")
    assert "backlash:amount_um" in pige.index
    assert pige[pige.identifiable][["uncertainty_noise", "uncertainty_camera"]].notna().all().all()
    ladder = read_table("model_ladder", results, first["campaign_id"]).sort_values("step")
    assert len(ladder) == 2 and ladder["n_params"].iloc[1] == ladder["n_params"].iloc[0] + 1

    # two images per verification pose: only the capture is new; its repeats are averaged
    with opencv_threads(1):
        repeated = calibrate_campaign(str(folder), results_root=results, reports_root=reports, run="repeats",
                                      verification_repeats=2)
    assert repeated["cached"] | {"capture": True} == again["cached"] and not repeated["cached"]["capture"]
    after = read_table("verification", results, first["campaign_id"]).query("phase == 'after' and source == 'vbm'")
    single_after = single.query("phase == 'after' and source == 'vbm'")
    assert set(after["repeats"]) == {2} and set(single_after["repeats"]) == {1}
    assert len(pd.read_csv(Path(repeated["capture"]) / "manifest.csv")) == 2 * len(after)
    floor_ratio = after["noise_floor_position_um"].mean() / single_after["noise_floor_position_um"].mean()
    assert 0.55 < floor_ratio < 0.85  # 1/√2, give or take each image's own noise estimate


def test_a_lab_campaign_is_asked_for_its_capture_and_verified_once_it_is_there(
        calibrated_campaign, prefect_harness, tmp_path):
    """Without truth, calibrate writes the capture request and no after rows; with the lab's
    capture in place (here: the simulated campaign's own capture, the same images at the same
    commands) it measures the after rows exactly as for the simulated campaign; an image taken at
    another command stops it, naming the manifest's row, with the lake left as it was."""
    lab = tmp_path / "campaigns" / calibrated_campaign.campaign.name
    shutil.copytree(calibrated_campaign.campaign, lab, ignore=shutil.ignore_patterns("captures", "truth"))
    results, reports = str(tmp_path / "results"), str(tmp_path / "reports")
    with opencv_threads(1):
        asked = calibrate_campaign(str(lab), results_root=results, reports_root=reports, run="asked")
    assert asked["capture_state"] == "requested"
    request = Path(asked["capture"])
    assert request.name == Path(calibrated_campaign.summary["capture"]).name  # same compensated commands
    plan = pd.read_csv(request / "capture_plan.csv")
    verification = read_table("verification", results, asked["campaign_id"])
    assert set(zip(verification.phase, verification.source, strict=True)) == {("before", "vbm")}
    assert len(plan) == len(verification)

    simulated = Path(calibrated_campaign.summary["capture"])  # the lab plays back the simulator's capture
    shutil.copytree(simulated / "images", request / "images")
    shutil.copy(simulated / "manifest.csv", request / "manifest.csv")
    with opencv_threads(1):
        measured = calibrate_campaign(str(lab), results_root=results, reports_root=reports, run="measured")
    assert measured["capture_state"] == "measured"
    mine = read_table("verification", results, asked["campaign_id"]).query("source == 'vbm'")
    reference = read_table("verification", calibrated_campaign.results, asked["campaign_id"]).query("source == 'vbm'")
    columns = ["image_id", "phase", "position_um", "orientation_arcsec", "repeats"]
    pd.testing.assert_frame_equal(mine[columns].reset_index(drop=True), reference[columns].reset_index(drop=True))

    manifest = pd.read_csv(request / "manifest.csv")
    manifest.loc[1, "Z_mm"] += 0.01
    manifest.to_csv(request / "manifest.csv", index=False)
    with opencv_threads(1), pytest.raises(CampaignError, match=r"manifest\.csv.*row 2 \(.*_v\): Z_mm"):
        calibrate_campaign(str(lab), results_root=results, reports_root=reports, run="moved")
    kept = read_table("verification", results, asked["campaign_id"]).query("source == 'vbm'")
    pd.testing.assert_frame_equal(kept[columns].reset_index(drop=True), mine[columns].reset_index(drop=True))
