"""The verification capture a lab is asked for (tasks.campaign.capture_request), no Prefect: the request's
files, and the check that each captured image was taken at the command it was asked for."""

import json

import numpy as np
import pandas as pd
import pytest

from tasks.campaign.capture_request import (
    PLAN_FILE,
    capture_rows,
    check_capture_commands,
    has_capture,
    write_capture_request,
)
from tasks.campaign.folder import MANIFEST_COLUMNS
from tasks.campaign.ingest import CampaignError
from tasks.machine.description import COMMAND_COLUMNS

COMMANDS = np.array([[1.0, 2.0, 3.0, 10.0, 20.0], [-1.0, -2.0, -3.0, -10.0, 123.4567891]])


def _manifest(rows: pd.DataFrame) -> pd.DataFrame:
    """The lab's manifest for ``rows``: the same rows with a timestamp and a temperature."""
    m = rows.round(dict.fromkeys(COMMAND_COLUMNS, 6)).assign(timestamp="2026-02-01T08:00:00.000000Z",
                                                             temperature_c=20.0)
    return m[list(MANIFEST_COLUMNS)]


def test_the_request_lists_each_repeat_as_a_pass_over_the_poses(tiny_campaign, tmp_path):
    rows = capture_rows(["p0", "p1"], COMMANDS, "camera1", repeats=2)
    out = tmp_path / "captures" / "compensated-abc"
    plan = write_capture_request(tiny_campaign, out, rows)
    assert plan == out / PLAN_FILE and not has_capture(out)
    written = pd.read_csv(plan)
    assert written["image_id"].tolist() == ["p0_v", "p1_v", "p0_v1", "p1_v1"]
    assert written["path"].tolist()[:2] == ["images/camera1/p0_v.png", "images/camera1/p1_v.png"]
    assert written["repeat"].tolist() == [0, 0, 1, 1] and set(written["stage"]) == {"verification"}
    np.testing.assert_allclose(written[list(COMMAND_COLUMNS)], np.tile(COMMANDS, (2, 1)), atol=5e-7)
    campaign_id = json.loads((tiny_campaign / "campaign.json").read_text())["campaign_id"]
    assert json.loads((out / "campaign.json").read_text())["campaign_id"] == f"{campaign_id}-compensated-abc"


def test_images_taken_away_from_the_requested_commands_are_named_by_row(tmp_path):
    rows = capture_rows(["p0", "p1"], COMMANDS, "camera1", repeats=2)
    manifest = _manifest(rows)
    manifest.loc[0, "X_mm"] += 0.0005                     # within 1 µm: the controller's rounding
    manifest.loc[len(manifest)] = manifest.loc[3].copy()  # an image the request does not name: ignored
    manifest.loc[len(manifest) - 1, ["image_id", "Z_mm"]] = ["extra", 50.0]
    manifest.to_csv(tmp_path / "manifest.csv", index=False)
    assert has_capture(tmp_path)
    check_capture_commands(tmp_path, rows)

    manifest.loc[1, "C_deg"] += 2 / 3600                  # 2″ off
    manifest["Y_mm"] = manifest["Y_mm"].astype(object)
    manifest.loc[2, "Y_mm"] = "n/a"
    manifest.to_csv(tmp_path / "manifest.csv", index=False)
    with pytest.raises(CampaignError) as e:
        check_capture_commands(tmp_path, rows)
    message = str(e.value)
    assert str(tmp_path / "manifest.csv") in message
    assert "row 2 (p1_v): C_deg" in message and "row 3 (p0_v1): Y_mm 'n/a'" in message
    assert "row 1 " not in message and "extra" not in message
