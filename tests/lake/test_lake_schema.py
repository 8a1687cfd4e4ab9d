"""The lake as a contract: every table's files match tasks/lake/schema.py and carry schema_version and
provenance; the doc is generated from the registry."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from tasks.lake import schema as lake_schema
from tasks.lake.schema import TABLES, schema_problems
from tasks.lake.store import partition_path, read_provenance, read_table, write_partition

DOC = Path(__file__).resolve().parents[2] / "docs" / "results-schema.md"
CALIBRATE_TABLES = ("pdge", "pige", "compensation", "verification", "formulations")
RESIDUAL_TABLES = ("residuals", "dot_residuals", "model_ladder")
MEASURE_TABLES = ("dots", "camera_calibration", "poses")
# the input hash each writer records (docs/results-schema.md, "Provenance")
INPUT_HASH = {"images": "input_sha256", "detector_comparison": "input_sha256",
              **dict.fromkeys(MEASURE_TABLES + CALIBRATE_TABLES + RESIDUAL_TABLES, "images_content_sha256")}


# --------------------------------------------------------------------------------------------
# The registry and its doc
# --------------------------------------------------------------------------------------------


def test_registry_has_every_table_of_today():
    # others may be added (one entry each): the tables the pipeline writes today must be there
    assert {"images", "dots", "camera_calibration", "poses", "detector_comparison", *CALIBRATE_TABLES,
            *RESIDUAL_TABLES} <= set(TABLES)
    for t in TABLES.values():
        assert t.version >= 1 and t.keys[0] == "campaign_id" and t.row and t.writer
        assert all(c.meaning for c in t.columns), t.name


def test_the_doc_is_generated_from_the_registry():
    assert lake_schema.doc_is_current(DOC), "run: python -m tasks.lake.schema --write docs/results-schema.md"
    text = DOC.read_text()
    for t in TABLES.values():
        assert f"### `{t.name}` (schema version {t.version})" in text
        assert all(f"| `{c.name}` | {c.dtype} |" in text for c in t.columns)


def test_check_command_fails_on_a_stale_doc(tmp_path):
    stale = tmp_path / "results-schema.md"
    stale.write_text(DOC.read_text().replace("| `value` | float64 |", "| `value` | int64 |"))
    run = subprocess.run([sys.executable, "-m", "tasks.lake.schema", "--check", str(stale)],
                         capture_output=True, text=True, cwd=DOC.parents[1])
    assert run.returncode == 1 and "differ" in run.stderr
    subprocess.run([sys.executable, "-m", "tasks.lake.schema", "--write", str(stale)], check=True, cwd=DOC.parents[1])
    assert lake_schema.doc_is_current(stale)


def test_a_bad_column_entry_is_refused():
    with pytest.raises(ValueError, match="dtype 'float'"):
        lake_schema.Column("x", "float")
    with pytest.raises(ValueError, match="frame 'moon'"):
        lake_schema.Column("x", "float64", frame="moon")


# --------------------------------------------------------------------------------------------
# write_partition: schema version, conformed dtypes
# --------------------------------------------------------------------------------------------


def test_write_partition_stamps_schema_version_and_table_over_the_provenance(tmp_path):
    df = pd.DataFrame({"formulation": ["a"], "mean_single_run_ms": [1.0], "total_300_ms": [2.0],
                       "position_error_norm_um": [0.0], "orientation_error_norm_arcsec": [0.0], "note": [""]})
    write_partition("formulations", "c1", df, {"fivecal_version": "9", "table": "wrong", "schema_version": 99},
                    tmp_path)
    prov = read_provenance("formulations", "c1", tmp_path)
    assert prov == {"fivecal_version": "9", "table": "formulations", "campaign_id": "c1",
                    "schema_version": TABLES["formulations"].version}
    assert schema_problems("formulations", pq.read_schema(partition_path("formulations", "c1", tmp_path)
                                                          / "part-0.parquet")) == []
    write_partition("not_registered", "c1", df, {}, tmp_path)
    assert read_provenance("not_registered", "c1", tmp_path)["schema_version"] is None


def test_integer_columns_with_missing_values_are_written_as_int64(tmp_path):
    poses = pd.DataFrame({"image_id": ["a", "b"], "n_points": [49.0, np.nan], "message": [None, None]})
    path = write_partition("poses", "c1", poses, {}, tmp_path)
    schema = pq.read_schema(path)
    assert lake_schema.arrow_dtype(schema.field("n_points").type) == "int64"
    assert lake_schema.arrow_dtype(schema.field("message").type) == "string"
    back = read_table("poses", tmp_path)
    assert back.n_points.tolist()[0] == 49 and back.n_points.isna().tolist() == [False, True]
    with pytest.raises(ValueError, match=r"poses\.n_points: non-integer value 2\.5 in row 1"):
        write_partition("poses", "c1", poses.assign(n_points=[1.0, 2.5]), {}, tmp_path)
    assert read_table("poses", tmp_path).n_points.tolist()[0] == 49  # the failed write changed nothing


def test_schema_problems_names_missing_extra_and_retyped_columns(tmp_path):
    df = pd.DataFrame({"formulation": ["a"], "mean_single_run_ms": [1], "extra": [1.0]})
    path = write_partition("unregistered_probe", "c1", df, {}, tmp_path)
    problems = schema_problems("formulations", pq.read_schema(path))
    assert "formulations: column mean_single_run_ms is int64 in the file, float64 in the registry" in problems
    assert "formulations: column extra (float64) is not in the registry" in problems
    assert "formulations: column note (string) missing from the file" in problems
    assert schema_problems("nope", pq.read_schema(path)) == ["table 'nope' is not in the registry "
                                                             "(tasks/lake/schema.py)"]


# --------------------------------------------------------------------------------------------
# Every table as the pipeline writes it
# --------------------------------------------------------------------------------------------


def _write_residual_tables(campaign: Path, root: Path) -> None:
    """The residuals, dot_residuals and model_ladder partitions of ``campaign``, written by their science
    functions from its lake, for as long as flows/calibrate.py does not write them itself."""
    import fivecal
    from tasks.analysis.model_ladder import append_step, ladder_step
    from tasks.analysis.residuals import dot_residual_table, plates_of, pose_residual_table
    from tasks.campaign.ingest import load_campaign_metadata
    from tasks.identification.calibration import calibrate
    from tasks.identification.measurements import assemble_measurements
    from tasks.vision.detector_comparison import intrinsics_from_table
    from tasks.vision.pipeline import content_key, nominal_machine

    metadata = load_campaign_metadata(campaign)
    campaign_id = metadata["campaign_id"]
    images, poses, dots = (read_table(t, root, campaign_id) for t in ("images", "poses", "dots"))
    machine, meas = nominal_machine(metadata), assemble_measurements(images, poses)
    result = calibrate(machine, meas)
    cameras = intrinsics_from_table(read_table("camera_calibration", root, campaign_id), metadata)
    prov = {"fivecal_version": fivecal.__version__,
            "images_content_sha256": content_key(images[["image_id", "content_sha256"]])}
    if not (root / "residuals").exists():
        write_partition("residuals", campaign_id, pose_residual_table(machine, result.model, meas, dots), prov, root)
    if not (root / "dot_residuals").exists():
        write_partition("dot_residuals", campaign_id, dot_residual_table(dots, meas, cameras, plates_of(machine)),
                        prov, root)
    if not (root / "model_ladder").exists():
        append_step(campaign_id, ladder_step(machine, result.model, result.pige.fit, meas), prov, root)


@pytest.fixture(scope="module")
def lake(calibrated_campaign, tmp_path_factory):
    """The calibrated campaign's lake plus a detector_comparison partition (written into a copy), and the
    residual tables where the calibrate flow has not written them."""
    from tasks.vision.detector_comparison import run_comparison

    root = tmp_path_factory.mktemp("lake") / "results"
    shutil.copytree(calibrated_campaign.results, root)
    run_comparison(calibrated_campaign.campaign, root, detectors=("rrht",), max_images_per_camera=1)
    if not all((root / t).exists() for t in RESIDUAL_TABLES):
        _write_residual_tables(calibrated_campaign.campaign, root)
    return root


# tables another flow writes, and the test that checks their files against the registry
CHECKED_ELSEWHERE = {"drift": "tests/flows/test_flows_recalibrate.py",
                     "dispense_inspection": "tests/flows/test_flows_dispense.py",
                     **dict.fromkeys(("dispense_areas", "dispense_paths", "dispense_beads"),
                                     "tests/dispense_job/test_dispense_job.py")}
LAKE_TABLES = sorted(set(TABLES) - set(CHECKED_ELSEWHERE))


def test_every_registered_table_is_checked_by_some_test():
    for table, test in CHECKED_ELSEWHERE.items():
        assert "partition_problems(\"" + table in (DOC.parents[1] / test).read_text(), (table, test)


@pytest.mark.parametrize("table", LAKE_TABLES)
def test_written_table_matches_the_registry_and_carries_version_and_provenance(lake, calibrated_campaign, table):
    campaign_id = calibrated_campaign.summary["campaign_id"]
    path = partition_path(table, campaign_id, lake) / "part-0.parquet"
    assert path.exists(), f"{table}: not written by ingest, measure, calibrate or compare-detectors"
    assert lake_schema.partition_problems(table, path) == []
    prov = read_provenance(table, campaign_id, lake)
    assert prov["campaign_id"] == campaign_id and prov["fivecal_version"]
    if table in INPUT_HASH:
        assert len(prov[INPUT_HASH[table]]) == 64
    rows = read_table(table, lake, campaign_id)
    keys = list(TABLES[table].keys)
    assert len(rows) > 0
    assert not rows[keys].isna().any().any(), f"{table}: null key"
    assert not rows.duplicated(keys).any(), f"{table}: keys {keys} do not identify a row"


def test_every_table_the_pipeline_writes_is_registered(lake):
    written = {d.name for d in lake.iterdir() if not d.name.startswith(".")}
    assert written <= set(TABLES), f"tables without a registry entry: {sorted(written - set(TABLES))}"
    assert {"images", *MEASURE_TABLES, *CALIBRATE_TABLES, "detector_comparison"} <= written


def test_partition_problems_checks_the_metadata_too(tmp_path):
    df = pd.DataFrame({"formulation": ["a"], "mean_single_run_ms": [1.0], "total_300_ms": [2.0],
                       "position_error_norm_um": [0.0], "orientation_error_norm_arcsec": [0.0], "note": [""]})
    path = write_partition("formulations", "c1", df, {}, tmp_path)
    assert lake_schema.partition_problems("formulations", path) == []
    moved = tmp_path / "copy.parquet"
    shutil.copy(path, moved)
    table = pq.read_table(moved)
    pq.write_table(table.replace_schema_metadata({b"fivecal": b'{"table": "formulations", "schema_version": 0}'}),
                   moved)
    assert lake_schema.partition_problems("formulations", moved) == [
        f"{moved}: schema_version 0 in the file, {TABLES['formulations'].version} in the registry"]
