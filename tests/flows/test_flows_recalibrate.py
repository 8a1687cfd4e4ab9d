"""Scheduled recalibration through Prefect's harness: each dropped campaign is calibrated exactly
once over repeated ticks, the drift report covers every campaign, and a failed or claimed
campaign is left for a later tick."""

import asyncio
from pathlib import Path

import pandas as pd
import pytest
from prefect import flow

import flows.recalibrate as recalibrate
from tasks.campaign.recalibration_ledger import Ledger
from tasks.lake.schema import partition_problems
from tasks.lake.store import read_table
from tasks.simulation.campaign_plan import CampaignPlan
from tasks.simulation.simulate import write_campaign

pytestmark = pytest.mark.flow

# the smallest plan with which calibrate completes (2 sweep positions, 3 PIGE and 1 validation pose)
PLAN = CampaignPlan(calibration_trials=1, images_per_trial=4, sweep_positions=2, sweep_repeats=1, pige_poses=3,
                    validation_poses=1)


def drop_campaign(watch, campaign_id, seed, days_later):
    """Write a small simulated campaign in a hidden folder, its capture ``days_later`` than the
    simulator's epoch, then rename it into view (how docs/recalibration.md asks a lab to drop one)."""
    staging = watch / f".{campaign_id}.partial"
    write_campaign(staging, campaign_id, seed=seed, size="small", plan=PLAN)
    manifest = pd.read_csv(staging / "manifest.csv", dtype=str, keep_default_na=False)
    stamps = pd.to_datetime(manifest["timestamp"], utc=True) + pd.Timedelta(days=days_later)
    manifest["timestamp"] = stamps.dt.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    manifest.to_csv(staging / "manifest.csv", index=False)
    staging.rename(watch / campaign_id)
    return watch / campaign_id


def calibrate_runs(folder) -> list[str]:
    """States of the Prefect flow runs of ``calibrate-campaign`` on ``folder``."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowFilter, FlowFilterName
    from prefect.client.schemas.sorting import FlowRunSort

    async def read():
        async with get_client() as client:
            return await client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=["calibrate-campaign"])),
                                               sort=FlowRunSort.START_TIME_ASC, limit=200)

    return [r.state_name for r in asyncio.run(read()) if r.parameters.get("campaign") == str(folder)]


def tick(watch, results, reports, **kw):
    return recalibrate.recalibrate_new_campaigns(str(watch), str(results), str(reports), settle_seconds=0, **kw)


def test_each_dropped_campaign_is_calibrated_exactly_once(prefect_harness, tmp_path):
    watch, results, reports = tmp_path / "watch", tmp_path / "results", tmp_path / "reports"
    watch.mkdir()
    (watch / "broken").mkdir()
    (watch / "broken" / "campaign.json").write_text("{not json")
    (watch / "broken" / "manifest.csv").write_text("image_id\n")
    w1 = drop_campaign(watch, "w1", seed=1, days_later=0)

    waiting = recalibrate.recalibrate_new_campaigns(str(watch), str(results), str(reports), settle_seconds=3600)
    assert waiting["calibrated"] == [] and waiting["waiting"] == [str(w1)] and waiting["drift"] is None

    first = tick(watch, results, reports)
    assert first["calibrated"] == ["w1"]
    assert [(s["folder"], "not valid JSON" in s["reason"]) for s in first["skipped"]] == [(str(watch / "broken"),
                                                                                             True)]
    assert first["drift"]["campaigns"] == ["w1"]

    w2 = drop_campaign(watch, "w2", seed=2, days_later=7)
    second = tick(watch, results, reports, orientation="tool-axis")  # the lab switched objectives
    assert (second["calibrated"], second["already_calibrated"]) == (["w2"], ["w1"])
    third = tick(watch, results, reports)
    assert (third["calibrated"], sorted(third["already_calibrated"]), third["drift"]) == ([], ["w1", "w2"], None)

    # exactly once, by Prefect's records and by the ledger
    assert calibrate_runs(w1) == ["Completed"] and calibrate_runs(w2) == ["Completed"]
    assert sorted(r["campaign_id"] for r in Ledger.under(results).records()) == ["w1", "w2"]

    # the second tick's drift report covers both campaigns, w1 (captured first) the reference
    drift = read_table("drift", results)
    drift_files = sorted((results / "drift").rglob("*.parquet"))
    assert drift_files and all(partition_problems("drift", f) == [] for f in drift_files)  # the lake contract
    assert set(drift.campaign_id) == {"w1", "w2"} and (drift.reference_campaign_id == "w1").all()
    times = drift.groupby("campaign_id")["time"].first()
    assert times["w2"] - times["w1"] == pd.Timedelta(days=7)
    assert set(drift[drift.campaign_id == "w1"].rule) == {"reference"}
    n_pige = len(read_table("pige", results, "w2"))
    assert (drift.groupby("campaign_id").size() == n_pige + 5 * 6 * 3).all()  # PIGEs + 5 axes × 6 × 3 stats
    markdown = open(second["drift"]["markdown"]).read()
    assert "| 1 | `w1` (reference) |" in markdown and "| 2 | `w2` |" in markdown
    # w2 was compensated for the tool axis (a pose that fell back says so): judged on its tool direction
    assert set(read_table("compensation", results, "w1").orientation_objective) == {"full"}
    assert not (read_table("compensation", results, "w2").orientation_objective == "full").any()
    assert "of tool direction (compensated for the tool axis" in second["drift"]["verdict"]
    assert markdown.count("| tool-axis |") == 5  # the campaigns row and w2's four verification rows
    assert markdown.count("](figures/") == 7  # PIGE, 5 PDGE axes, verification
    assert second["drift"]["report"].startswith(str(reports / "drift"))


@flow(name="fake-calibrate")
def lab_calibrate(campaign, results_root=None, detector="rrht", reports_root="reports", run=None,
                  orientation="full", verification_repeats=1):
    """calibrate_campaign's contract for a lab's campaign (the real one: test_flows_calibrate.py):
    the capture requested until its manifest is there, then measured."""
    capture = Path(campaign) / "captures" / "compensated-0123"
    state = "measured" if (capture / "manifest.csv").is_file() else "requested"
    capture.mkdir(parents=True, exist_ok=True)
    (capture / "capture_plan.csv").write_text("image_id\nv0_v\n")
    return {"report": f"{campaign}/report.html", "capture": str(capture), "capture_state": state}


def test_a_lab_campaign_is_verified_on_the_tick_after_its_capture_arrives(prefect_harness, tmp_path, monkeypatch,
                                                                         campaign_copy):
    """A campaign calibrated with its verification capture requested waits for it over the ticks;
    the first tick after the lab wrote it (and left it alone for the settle time) calibrates the
    same input again, and then nothing is left to do."""
    watch, results, reports = tmp_path / "watch", tmp_path / "results", tmp_path / "reports"
    watch.mkdir()
    campaign_copy("lab1").rename(watch / "lab1")
    monkeypatch.setattr(recalibrate, "calibrate_campaign", lab_calibrate)

    first = tick(watch, results, reports)
    assert first["calibrated"] == ["lab1"] and first["awaiting_capture"] == ["lab1"]
    (record,) = Ledger.under(results).records()
    assert record["capture_state"] == "requested"
    assert tick(watch, results, reports)["calibrated"] == []

    (Path(record["capture"]) / "manifest.csv").write_text("image_id\n")  # the lab's capture arrives
    settling = recalibrate.recalibrate_new_campaigns(str(watch), str(results), str(reports), settle_seconds=3600)
    assert (settling["calibrated"], settling["awaiting_capture"]) == ([], ["lab1"])  # still being written?
    measured = tick(watch, results, reports)
    assert (measured["calibrated"], measured["awaiting_capture"], measured["already_calibrated"]) == (
        ["lab1"], [], [])
    assert [r["capture_state"] for r in Ledger.under(results).records()] == ["measured"]
    again = tick(watch, results, reports)
    assert (again["calibrated"], again["already_calibrated"]) == ([], ["lab1"])


@flow(name="fake-calibrate")
def failing_calibrate(campaign, results_root=None, detector="rrht", reports_root="reports", run=None,
                      orientation="full", verification_repeats=1):
    raise RuntimeError(f"simulated crash on {campaign}")


@flow(name="fake-calibrate")
def passing_calibrate(campaign, results_root=None, detector="rrht", reports_root="reports", run=None,
                      orientation="full", verification_repeats=1):
    return {"report": f"{campaign}/report.html"}


def test_failed_or_claimed_campaign_is_left_for_the_next_tick(prefect_harness, tmp_path, monkeypatch, campaign_copy):
    watch, results, reports = tmp_path / "watch", tmp_path / "results", tmp_path / "reports"
    watch.mkdir()
    campaign_copy("f1").rename(watch / "f1")
    monkeypatch.setattr(recalibrate, "calibrate_campaign", failing_calibrate)
    state = recalibrate.recalibrate_new_campaigns(str(watch), str(results), str(reports), settle_seconds=0,
                                                  return_state=True)
    assert state.is_failed() and "calibration failed for f1" in state.message
    assert Ledger.under(results).records() == []

    monkeypatch.setattr(recalibrate, "calibrate_campaign", passing_calibrate)
    with Ledger.under(results).claim("f1") as mine:  # another run is calibrating f1 right now
        assert mine
        busy = tick(watch, results, reports)
    assert busy["calibrated"] == [] and Ledger.under(results).records() == []

    done = tick(watch, results, reports)
    assert done["calibrated"] == ["f1"] and done["drift"]["campaigns"] == []  # nothing in the lake: empty report
    assert [r["report"] for r in Ledger.under(results).records()] == [f"{watch / 'f1'}/report.html"]
    assert tick(watch, results, reports)["calibrated"] == []


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def test_tolerance_option_parsing():
    import typer

    from fivecal.recalibrate_cli import parse_tolerance

    tol = parse_tolerance(["abs_um=3", "k=3", "require=either"])
    assert (tol.abs_um, tol.abs_arcsec, tol.k, tol.require) == (3.0, 15.0, 3.0, "either")
    for bad, message in (("abs_mm=3", "KEY one of"), ("k=x", "not a number"), ("require=maybe", "require"),
                         ("abs_um=-1", "positive")):
        with pytest.raises(typer.BadParameter, match=message):
            parse_tolerance([bad])


def test_recalibrate_command_runs_one_tick(prefect_harness, tmp_path):
    from typer.testing import CliRunner

    from fivecal.cli import app

    watch = tmp_path / "watch"
    watch.mkdir()
    args = ["recalibrate", "--watch", str(watch), "--results", str(tmp_path / "results"), "--reports",
            str(tmp_path / "reports")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "calibrated now: none" in result.output and "drift report: not written" in result.output
    result = CliRunner().invoke(app, [*args, "--always-report", "--tolerance", "abs_um=2"])
    assert result.exit_code == 0, result.output
    assert "**No verdict:** no calibrated campaign" in result.output
    assert len(list((tmp_path / "reports" / "drift").glob("*/index.html"))) == 1


def test_serve_recalibration_serves_the_flow_on_its_cron(prefect_harness, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from fivecal.cli import app

    calls = []
    monkeypatch.setattr(recalibrate.recalibrate_new_campaigns, "serve", lambda **kw: calls.append(kw))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "watch").mkdir()
    result = CliRunner().invoke(app, ["serve-recalibration", "--watch", "watch", "--cron", "0 2 * * *", "--results",
                                      "res", "--tolerance", "abs_arcsec=20", "--timezone", "Europe/Zurich",
                                      "--orientation", "tool-axis", "--verification-repeats", "3"])
    assert result.exit_code == 0, result.output
    (kw,) = calls
    assert (kw["name"], kw["limit"], kw["schedules"][0].cron, kw["schedules"][0].timezone) == (
        "scheduled-recalibration", 1, "0 2 * * *", "Europe/Zurich")
    p = kw["parameters"]
    assert (p["watch_dir"], p["results_root"], p["reports_root"]) == (
        str(tmp_path / "watch"), str(tmp_path / "res"), str(tmp_path / "reports"))  # absolute: runs start elsewhere
    assert p["tolerance"]["abs_arcsec"] == 20.0 and p["orientation"] == "tool-axis" and p["verification_repeats"] == 3
    assert recalibrate.recalibrate_new_campaigns.validate_parameters(p)
    unknown = CliRunner().invoke(app, ["serve-recalibration", "--watch", "watch", "--cron", "0 2 * * *",
                                       "--orientation", "spin"])
    assert unknown.exit_code == 2 and "full, tool-axis" in " ".join(unknown.output.replace("│", " ").split())
    bad = CliRunner().invoke(app, ["serve-recalibration", "--watch", "watch", "--cron", "61 2 * * *"])
    assert bad.exit_code == 2 and "not a valid cron schedule" in " ".join(bad.output.replace("│", " ").split())


def test_serve_recalibration_refuses_the_temporary_server(tmp_path):
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    (tmp_path / "watch").mkdir()
    run = subprocess.run([sys.executable, "-m", "fivecal.cli", "serve-recalibration", "--watch",
                          str(tmp_path / "watch"), "--cron", "0 2 * * *"], env=env, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2 and "temporary server cannot run schedules" in run.stderr
