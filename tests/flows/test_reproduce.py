"""fivecal reproduce: the report records its numbers and parameters; a re-run with a refreshed cache
reproduces them; tampered numbers and changed inputs are reported."""

import json
import re
import shutil

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

import fivecal
from fivecal.cli import app
from flows import reproduce as R
from tasks.core.version import code_fingerprint
from tasks.lake.schema import PARTITION, TABLES
from tasks.lake.store import read_table
from tasks.report.data import REPORT_TABLES

runner = CliRunner()


def report_dir(calibrated):
    return calibrated.reports / calibrated.summary["campaign_id"] / "fixture"


# --------------------------------------------------------------------------------------------
# Comparison rules (no Prefect)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("a, b, expected", [
    (1.0, 1.0, True), (1.0, 1.0 + 5e-10, True), (1.0, 1.0 + 2e-9, False), (-3e5, -3e5 * (1 + 1e-10), True),
    (np.nan, np.nan, True), (np.nan, 0.0, False), (0.0, 1e-300, False), (None, np.nan, True), (pd.NA, pd.NA, True),
    (pd.NA, 3, False), (3, 3, True), (3, 4, False), ("a", "a", True), ("a", "b", False), (True, False, False),
])
def test_same(a, b, expected):
    assert R.same(a, b) is expected


def pige(values, names=("delta_AZ", "beta_AY", "C.dz0")):
    return pd.DataFrame({"name": list(names), "unit": "um", "value": values, "identifiable": True})


def test_rows_are_matched_by_key_and_every_difference_is_named():
    rec = pige([1.0, np.nan, 3.0])
    rep = pige([1.0, np.nan, 3.5], names=("delta_AZ", "beta_AY", "C.ez0"))[::-1]  # other order, one row renamed
    c = R.compare_frames("pige", rec, rep)
    got = {(d.key, d.column, d.recorded, d.reproduced) for d in c.differences}
    assert got == {("name=C.dz0", "(row)", "present", "missing"), ("name=C.ez0", "(row)", "absent", "present")}
    assert c.numbers == 2 and c.texts == 4  # value × 2 common rows; unit, identifiable × 2
    c = R.compare_frames("pige", rec, rec.assign(value=[1.0, 2.0, 3.0]).drop(columns="unit"))
    assert [(d.key, d.column) for d in c.differences] == [("(every row)", "unit"), ("name=beta_AY", "value")]


def test_timings_are_not_compared_and_unkeyed_tables_match_by_position():
    f = pd.DataFrame({"formulation": ["a", "b"], "total_300_ms": [1.0, 2.0], "position_error_norm_um": [0.0, 5.0]})
    c = R.compare_frames("formulations", f, f.assign(total_300_ms=[9.0, 9.0]))
    assert c.differences == [] and c.not_compared == ["formulations.total_300_ms (timing)"] and c.numbers == 2
    dup = pd.DataFrame({"name": ["x", "x"], "value": [1.0, 2.0]})
    c = R.compare_frames("pige", dup, dup.assign(value=[1.0, 2.5]))
    assert [d.key for d in c.differences] == ["row 1"] and "matched by position" in c.notes[0]


def test_format_names_table_key_column_and_both_values():
    c = R.Comparison(numbers=10, differences=[R.Difference("pige", "name=delta_AZ", "value", 1.5, 1.5000001)])
    text = R.format_comparison(c)
    assert "pige: 1 difference(s)\n  name=delta_AZ  value: recorded 1.5, reproduced 1.5000001 (rel. diff 6.7e-08)" \
        in text
    assert R.format_comparison(R.Comparison(numbers=7, texts=2)).endswith("all 7 numbers reproduced (and 2 text "
                                                                          "values and flags)")


def test_cached_steps_reads_flags_counts_and_subflows():
    summary = {"measure": {"detect": 0, "calibrate": 1, "poses": 0}, "identify": False, "capture": True}
    assert R.cached_steps(summary) == ["measure.calibrate", "capture"]
    assert R.cached_steps({"measure": {"detect": 0}, "identify": False}) == []


def test_a_folder_without_recorded_data_exits_2(tmp_path):
    (tmp_path / "report.md").write_text("# old report")
    result = runner.invoke(app, ["reproduce", str(tmp_path)])
    assert result.exit_code == 2 and f"error: {tmp_path}/data/parameters.json: missing" in result.output


# --------------------------------------------------------------------------------------------
# What the report records
# --------------------------------------------------------------------------------------------


def test_the_report_records_the_lake_numbers_and_the_parameters(calibrated_campaign):
    folder = report_dir(calibrated_campaign)
    recorded = R.load_report(folder)
    campaign_id = calibrated_campaign.summary["campaign_id"]
    assert set(recorded.tables) == set(REPORT_TABLES)
    for name, df in recorded.tables.items():
        lake = read_table(name, calibrated_campaign.results, campaign_id).drop(columns=PARTITION)
        pd.testing.assert_frame_equal(df, lake, check_dtype=False)
        meta = json.loads(pq.read_schema(folder / "data" / f"{name}.parquet").metadata[b"fivecal"])
        assert meta["schema_version"] == TABLES[name].version
    p = recorded.parameters
    assert p["campaign_id"] == campaign_id and p["run"] == "fixture" and p["simulated"] is True
    assert p["provenance"]["campaign"] == str(calibrated_campaign.campaign.resolve())
    assert p["provenance"]["detector"] == "rrht" and p["provenance"]["fivecal_version"] == fivecal.__version__
    assert set(p["campaign_files_sha256"]) == {"campaign.json", "manifest.csv"}
    assert re.fullmatch("[0-9a-f]{64}", p["code_sha256"])  # the tree may be edited meanwhile: see below
    assert p["environment"]["opencv_threads"] >= 1 and p["environment"]["numpy"] == np.__version__
    images = read_table("images", calibrated_campaign.results, campaign_id)
    assert recorded.inputs.content_sha256.tolist() == images.content_sha256.tolist()


def test_the_code_fingerprint_follows_every_code_and_json_file(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub" / "__pycache__").mkdir(parents=True)
    (pkg / "a.py").write_text("x = 1\n")
    (pkg / "sub" / "m.json").write_text("{}")
    first = code_fingerprint({"pkg": pkg})
    (pkg / "sub" / "__pycache__" / "a.cpython-311.pyc").write_bytes(b"\0")
    (pkg / "notes.txt").write_text("not code")
    assert code_fingerprint({"pkg": pkg}) == first
    (pkg / "sub" / "m.json").write_text('{"k": 1}')
    assert code_fingerprint({"pkg": pkg}) != first
    assert re.fullmatch("[0-9a-f]{64}", code_fingerprint())


def test_changed_inputs_are_named_and_nothing_is_rerun(calibrated_campaign, tmp_path):
    campaign = tmp_path / "campaign"
    shutil.copytree(calibrated_campaign.campaign, campaign, ignore=shutil.ignore_patterns("captures"))
    inputs = R.load_report(report_dir(calibrated_campaign)).inputs
    first, second = inputs.path.iloc[0], inputs.path.iloc[1]
    (campaign / first).write_bytes((campaign / first).read_bytes() + b"\0")
    (campaign / second).unlink()
    with open(campaign / "manifest.csv", "a") as f:
        f.write("\n")
    result = runner.invoke(app, ["reproduce", str(report_dir(calibrated_campaign)), "--campaign", str(campaign)])
    assert result.exit_code == 1, result.output
    assert "the campaign's inputs differ from the report's; not re-running" in result.output
    assert re.search(rf"{campaign}/manifest.csv: content changed \(sha256 \w{{12}}… → \w{{12}}…\)", result.output)
    assert f"{campaign / first} (manifest row 1): content changed" in result.output
    assert f"{campaign / second} (manifest row 2): missing or unreadable" in result.output
    assert "re-running" not in result.output.replace("not re-running", "")


# --------------------------------------------------------------------------------------------
# The re-run
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reproduction(calibrated_campaign, prefect_harness, tmp_path_factory):
    """fivecal reproduce on the fixture's report, on a copy of its campaign (the re-run renders the
    verification capture again into the campaign folder); the re-run's output kept in work/."""
    tmp = tmp_path_factory.mktemp("reproduce")
    campaign = tmp / "campaign"
    shutil.copytree(calibrated_campaign.campaign, campaign)
    work = tmp / "work"
    result = runner.invoke(app, ["reproduce", str(report_dir(calibrated_campaign)), "--campaign", str(campaign),
                                 "--workdir", str(work)])
    return result, work / "reports" / calibrated_campaign.summary["campaign_id"] / R.RUN_NAME


def expected_numbers(recorded):
    n = 0
    for name, df in recorded.tables.items():
        keys = set(TABLES[name].keys)
        cols = [c.name for c in TABLES[name].columns if c.reproducible and c.name not in keys
                and c.dtype in ("int64", "float64")]
        n += len(df) * len(cols)
    return n


def test_the_calibrated_campaign_reproduces(reproduction, calibrated_campaign):
    result, reproduced = reproduction
    assert result.exit_code == 0, result.output
    assert "hash as recorded" in result.output
    assert "re-running calibrate with Prefect's cache refreshed" in result.output
    n = expected_numbers(R.load_report(report_dir(calibrated_campaign)))
    assert f"all {n} numbers reproduced" in result.output and n > 500
    assert "formulations.total_300_ms (timing)" in result.output
    assert (reproduced / "index.html").is_file() and (reproduced / "data" / "pige.parquet").is_file()


def test_tampered_numbers_are_printed_with_table_key_column_and_values(calibrated_campaign, tmp_path, monkeypatch):
    """The recorded data of a copy of the report is altered. The re-run is replaced by the original report
    (what an exact reproduction gives, as the test above shows), so this checks what is compared and printed
    without a second calibration."""
    report = tmp_path / "report"
    shutil.copytree(report_dir(calibrated_campaign), report)
    data = report / "data"
    pige = pd.read_parquet(data / "pige.parquet")
    i = int(np.flatnonzero(pige.identifiable)[0])
    name, value = pige.name.iloc[i], float(pige.value.iloc[i])
    pige.loc[i, "value"] = value * (1 + 1e-6)
    pige.to_parquet(data / "pige.parquet")
    verification = pd.read_parquet(data / "verification.parquet")
    dropped = verification.iloc[0]
    verification.iloc[1:].to_parquet(data / "verification.parquet")
    compensation = pd.read_parquet(data / "compensation.parquet")
    compensation.loc[0, "X_compensated"] = compensation.loc[0, "X_compensated"] + 1e-7  # 0.1 µm
    compensation.to_parquet(data / "compensation.parquet")

    original = report_dir(calibrated_campaign)
    monkeypatch.setattr(R, "rerun", lambda recorded, work, campaign=None: (original, {}))
    result = runner.invoke(app, ["reproduce", str(report)])
    assert result.exit_code == 1, result.output
    out = result.output
    assert f"pige: 1 difference(s)\n  name={name}  value: recorded {value * (1 + 1e-6)!r}, reproduced {value!r}" in out
    assert (f"verification: 1 difference(s)\n  phase={dropped.phase}, source={dropped.source}, "
            f"image_id={dropped.image_id}  (row): recorded absent, reproduced present") in out
    assert f"compensation: 1 difference(s)\n  image_id={compensation.image_id.iloc[0]}  X_compensated: " in out
    assert re.search(r"\n3 difference\(s\) among \d+ numbers", out)


# --------------------------------------------------------------------------------------------
# Why calibration must run OpenCV on one thread
# --------------------------------------------------------------------------------------------


def self_calibrations(calibrated, calibrate, threads, n=4):
    from tasks.campaign.ingest import load_campaign_metadata

    campaign_id = calibrated.summary["campaign_id"]
    dots = read_table("dots", calibrated.results, campaign_id).drop(columns=PARTITION)
    images = read_table("images", calibrated.results, campaign_id)
    metadata = load_campaign_metadata(calibrated.campaign)
    with R.opencv_threads(threads):
        return [calibrate(dots, images, metadata)[0] for _ in range(n)]


def test_the_calibration_step_is_bitwise_repeatable_with_two_opencv_threads(calibrated_campaign):
    """The measure flow's calibration task pins OpenCV and BLAS to one thread: same numbers at any setting.
    (OpenCV's multi-threaded calibrateCameraExtended differs by ~1e-6 px from call to call, which the
    identification amplifies to 1e-4 relative: tasks.steps.vision.one_numeric_thread.)"""
    from tasks.steps.vision import calibrate

    runs = self_calibrations(calibrated_campaign, calibrate.fn, 2, n=6)
    for t in runs[1:]:
        pd.testing.assert_frame_equal(t, runs[0], check_exact=True)


def test_the_rerun_takes_the_recorded_model_and_compensation_options(tmp_path):
    """An --add-effect, --orientation tool-axis, --verification-repeats 5 report re-runs as such; an
    older report without these keys re-runs as the plain fit with the default objective and one
    image per verification pose."""
    provenance = {"campaign": "c", "effects": ["backlash:axis=X,amount_um=0,amount_arcsec=0"],
                  "effect_modules": ["my_effects"], "orientation_objective": "tool-axis", "verification_repeats": 5}
    recorded = R.Recorded(tmp_path, {"provenance": provenance}, {}, None)
    assert recorded.calibrate_options == {"effects": provenance["effects"], "effect_modules": ["my_effects"],
                                          "orientation": "tool-axis", "verification_repeats": 5}
    old = R.Recorded(tmp_path, {"provenance": {"campaign": "c"}}, {}, None)
    assert old.calibrate_options == {"effects": [], "effect_modules": [], "orientation": "full",
                                     "verification_repeats": 1}
