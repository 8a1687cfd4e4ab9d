"""The dispense-test flow on the calibrated fixture campaign: tables, report, truth agreement, cache,
and a calibration that added a user-written effect family."""

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from flows.dispense import dispense_test
from flows.reproduce import opencv_threads
from tasks.campaign.ingest import load_campaign_metadata
from tasks.dispensing.workpiece import Workpiece
from tasks.lake.schema import partition_problems
from tasks.lake.store import partition_path, read_provenance, read_table, write_partition
from tasks.machine.effects import EFFECTS

SMALL = Workpiece(rings=20)
USER_MODULE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "cross_backlash.py"
USER_EFFECT = "cross_backlash:axis=X,along=Y,amount_um=0"


def _as_if_calibrated_with_a_user_effect(results: Path, campaign_id: str) -> None:
    """The pige partition's provenance as ``calibrate --effect-module M --add-effect SPEC`` records it."""
    path = partition_path("pige", campaign_id, results) / "part-0.parquet"
    provenance = {k: v for k, v in read_provenance("pige", campaign_id, results).items()
                  if k not in ("table", "campaign_id", "schema_version")}
    provenance.update(effects=[USER_EFFECT], effect_modules=[str(USER_MODULE)])
    write_partition("pige", campaign_id, pd.read_parquet(path), provenance, results)


def test_dispense_test_writes_its_table_after_tip_rows_and_report(calibrated_campaign, prefect_harness, tmp_path):
    folder = tmp_path / "campaigns" / calibrated_campaign.campaign.name
    shutil.copytree(calibrated_campaign.campaign, folder, ignore=shutil.ignore_patterns("captures"))
    results = tmp_path / "results"
    shutil.copytree(calibrated_campaign.results, results)
    # the calibration added an effect of a user family: the flow imports the module it recorded
    _as_if_calibrated_with_a_user_effect(results, load_campaign_metadata(folder)["campaign_id"])
    catalogue = dict(EFFECTS)
    try:
        with opencv_threads(1):
            summary = dispense_test(str(folder), results_root=str(results), reports_root=str(tmp_path / "reports"),
                                    run="t", workpiece=SMALL)
    finally:
        EFFECTS.clear()
        EFFECTS.update(catalogue)
    campaign_id = summary["campaign_id"]
    assert summary["captures"] == {"dispense": "measured", "check": "measured"}
    path = partition_path("dispense_inspection", campaign_id, results) / "part-0.parquet"
    assert partition_problems("dispense_inspection", path) == []
    rows = read_table("dispense_inspection", results, campaign_id)
    assert rows.groupby("phase").size().to_dict() == {"nominal": 20, "compensated": 20, "check": 20}
    good = rows[rows["qualified"]]
    assert len(good) >= 0.8 * len(rows)
    assert (good["truth_defect"] == "none").all()  # nothing defective passes
    assert (rows.loc[~rows["qualified"], "reason"] != "").all()
    # the measured dot offsets are the true ones to a few µm (0.05 px at 45 µm/px is 2.3 µm)
    err = np.hypot(good["dx_um"] - good["truth_dx_um"], good["dy_um"] - good["truth_dy_um"])
    assert err.max() < 8.0 and np.sqrt(np.mean(err ** 2)) < 4.0
    ver = read_table("verification", results, campaign_id)
    tip = ver[ver["phase"] == "after_tip"]
    assert set(tip["source"]) == {"truth"} and len(tip) == len(ver[(ver.phase == "after") & (ver.source == "truth")])
    # the model uncertainty after the tip fit, beside the truth, and its mean in the summary
    assert (tip["model_uncertainty_position_um"] > 0).all()
    assert summary["model_uncertainty_after_tip_um"] == pytest.approx(tip["model_uncertainty_position_um"].mean())
    assert len(summary["tip_offset_um"]) == 3 and all(u > 0 for u in summary["tip_offset_uncertainty_um"])
    assert (tmp_path / "reports" / campaign_id / "t" / "dispensing" / "index.html").is_file()
    calibration = read_provenance("dispense_inspection", campaign_id, results)["calibration"]
    assert calibration["effects"] == [USER_EFFECT] and calibration["effect_modules"] == [str(USER_MODULE)]
