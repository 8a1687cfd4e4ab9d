"""The simulate flow end to end through Prefect's test harness, on a small campaign."""

import pandas as pd
import pytest

from tasks.simulation.campaign_plan import CampaignPlan

pytestmark = pytest.mark.flow


def test_simulate_flow_writes_a_complete_campaign_atomically(prefect_harness, tmp_path):
    from flows.simulate import simulate_campaign

    out = tmp_path / "c1"
    path = simulate_campaign(str(out), seed=3, size="small", effects=["scale:axis=X,ppm=30"], plan="small")
    assert path == str(out.resolve())
    manifest = pd.read_csv(out / "manifest.csv")
    p = CampaignPlan.small()
    c_positions = p.sweep_positions + 1 - p.sweep_positions % 2  # C: both stroke ends and home
    expected = 2 * p.calibration_trials * p.images_per_trial + (4 * p.sweep_positions + c_positions) * p.sweep_repeats \
        + p.pige_poses + p.validation_poses
    assert len(manifest) == expected
    assert all((out / rel).is_file() for rel in manifest.path)
    assert not any(x.name.endswith(".partial") for x in tmp_path.iterdir())
    truth = (out / "truth" / "truth.json").read_text()
    assert "scale:axis=X,ppm=30" in truth
    in_view = pd.read_parquet(out / "truth" / "images.parquet").set_index("image_id").in_view
    calibration = manifest.loc[manifest.stage == "camera_calibration", "image_id"]
    assert len(in_view) == expected and in_view.loc[calibration].all()  # plate a may leave the field elsewhere

    with pytest.raises(FileExistsError, match="already exists"):
        simulate_campaign(str(out), seed=3, size="small", plan="small")
