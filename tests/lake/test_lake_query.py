"""fivecal query: SQL over every table of the lake, across campaigns; docs/queries.md run for real."""

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from fivecal.cli import app
from tasks.lake.query import LakeQueryError, format_result, run_query, table_folders
from tasks.lake.store import read_table, write_partition

runner = CliRunner()
QUERIES_DOC = Path(__file__).resolve().parents[2] / "docs" / "queries.md"
DOC_QUERIES = re.findall(r"```sql\n(.*?)```", QUERIES_DOC.read_text(), flags=re.S)


def pige_rows(values):
    return pd.DataFrame({"name": ["delta_AZ", "beta_AY"], "kind": "pige", "joint": "A", "unit": ["um", "arcsec"],
                         "value": values, "uncertainty": [0.5, 2.0], "identifiable": True, "note": "",
                         "truth": np.nan, "truth_nominal": np.nan})


@pytest.fixture
def two_campaigns(tmp_path):
    root = tmp_path / "results"
    write_partition("pige", "20260105", pige_rows([1.0, 10.0]), {}, root)
    write_partition("pige", "w02", pige_rows([1.5, 30.0]), {}, root)
    return root


def test_a_query_spans_every_campaign_and_keeps_numeric_ids_as_text(two_campaigns):
    df = run_query("select campaign_id, name, value from pige order by name, campaign_id", two_campaigns)
    assert df.campaign_id.tolist() == ["20260105", "w02", "20260105", "w02"]
    assert df.value.tolist() == [10.0, 30.0, 1.0, 1.5]
    drift = run_query("select name, max(value) - min(value) as moved from pige group by name order by name",
                      two_campaigns)
    assert drift.moved.tolist() == [20.0, 0.5]


def test_the_cli_prints_table_csv_and_json(two_campaigns):
    sql = "select campaign_id, name, value from pige where name = 'beta_AY' order by campaign_id"
    table = runner.invoke(app, ["query", "--results", str(two_campaigns), sql])
    assert table.exit_code == 0, table.output
    assert table.output.split("\n")[0].split() == ["campaign_id", "name", "value"]
    assert re.search(r"20260105\s+beta_AY\s+10\.0\n\s+w02\s+beta_AY\s+30\.0", table.output)
    csv = runner.invoke(app, ["query", "--results", str(two_campaigns), "--format", "csv", sql])
    assert csv.output.splitlines() == ["campaign_id,name,value", "20260105,beta_AY,10.0", "w02,beta_AY,30.0"]
    js = runner.invoke(app, ["query", "--results", str(two_campaigns), "--format", "json", sql])
    assert json.loads(js.output) == [{"campaign_id": "20260105", "name": "beta_AY", "value": 10.0},
                                     {"campaign_id": "w02", "name": "beta_AY", "value": 30.0}]


def test_the_root_comes_from_the_environment(two_campaigns, monkeypatch):
    monkeypatch.setenv("FIVECAL_RESULTS_DIR", str(two_campaigns))
    result = runner.invoke(app, ["query", "--format", "csv", "select count(*) as n from pige"])
    assert result.exit_code == 0 and result.output.split() == ["n", "4"]


@pytest.mark.parametrize("sql, expected", [
    ("select * from nope", r"(?s)Table with name nope does not exist.*\ntables in the lake at .*: pige, "
                           r"lake_partitions"),
    ("selec 1", r"Parser Error: syntax error"),
    ("select no_such_column from pige", r"Binder Error"),
])
def test_bad_sql_prints_a_clear_message_and_exits_2(two_campaigns, sql, expected):
    with pytest.raises(LakeQueryError, match=expected):
        run_query(sql, two_campaigns)
    result = runner.invoke(app, ["query", "--results", str(two_campaigns), sql])
    assert result.exit_code == 2 and result.output.startswith("error: ") and re.search(expected, result.output)


def test_a_bad_format_exits_2(two_campaigns):
    result = runner.invoke(app, ["query", "--results", str(two_campaigns), "--format", "xml", "select 1"])
    assert result.exit_code == 2 and "choose one of table, csv, json" in result.output


def test_an_empty_or_missing_lake_has_no_tables_but_still_runs_sql(tmp_path):
    assert table_folders(tmp_path / "none") == {}
    assert run_query("select 41 + 1 as x", tmp_path / "none").x.tolist() == [42]
    assert run_query("select * from lake_partitions", tmp_path / "none").empty
    with pytest.raises(LakeQueryError, match=r"tables in the lake at .*: lake_partitions$"):
        run_query("select * from pige", tmp_path / "none")


def test_hidden_folders_and_stray_names_are_not_tables(two_campaigns):
    (two_campaigns / ".staging" / "pige.x.pid1.00000000.abc").mkdir(parents=True)
    shutil.copy(two_campaigns / "pige" / "campaign_id=w02" / "part-0.parquet",
                two_campaigns / ".staging" / "pige.x.pid1.00000000.abc" / "part-0.parquet")
    assert set(table_folders(two_campaigns)) == {"pige"}
    assert run_query("select count(*) as n from pige", two_campaigns).n.tolist() == [4]


def test_format_result_truncates_long_tables_only():
    df = pd.DataFrame({"i": range(7)})
    text = format_result(df, "table", max_rows=5)
    assert text.splitlines()[-1].startswith("… 2 more rows (7 in all") and " 4" in text and " 5\n" not in text
    assert len(format_result(df, "csv").splitlines()) == 8 and len(format_result(df, "table", 0).splitlines()) == 8
    assert format_result(None) == "(no result)"


# --------------------------------------------------------------------------------------------
# docs/queries.md against a calibrated campaign and a second one
# --------------------------------------------------------------------------------------------

SECOND = "calibrated-w2"


@pytest.fixture(scope="module")
def lake_of_two(calibrated_campaign, tmp_path_factory):
    """The calibrated campaign's lake plus campaign SECOND, a week later: every PIGE moved by +1,
    X's εz fit by +0.5″ everywhere, errors after compensation doubled, one image missing and one
    grid not found."""
    root = tmp_path_factory.mktemp("two") / "results"
    shutil.copytree(calibrated_campaign.results, root)
    first = calibrated_campaign.summary["campaign_id"]

    def copy(table, change):
        df = read_table(table, root, first).drop(columns="campaign_id")
        write_partition(table, SECOND, change(df), {"fivecal_version": "test"}, root)

    def images(df):
        df = df.assign(timestamp=df["timestamp"] + pd.Timedelta(days=7))
        df.loc[0, ["status", "message"]] = ["missing_file", "manifest row 1 (images/x.png): file missing"]
        return df

    def poses(df):
        df.loc[1, ["status", "message"]] = ["no_grid", "images/y.png: no grid"]
        return df

    def verification(df):
        after = df["phase"] == "after"
        return df.assign(position_um=np.where(after, 2 * df["position_um"], df["position_um"]))

    copy("images", images)
    copy("poses", poses)
    copy("pige", lambda df: df.assign(value=df["value"] + 1.0))
    copy("pdge", lambda df: df.assign(fit_ez_arcsec=df["fit_ez_arcsec"] + np.where(df["axis"] == "X", 0.5, 0.0)))
    copy("verification", verification)
    return root, first


def test_every_query_of_the_doc_runs_on_two_campaigns(lake_of_two):
    root, first = lake_of_two
    assert len(DOC_QUERIES) >= 6
    for sql in DOC_QUERIES:
        df = run_query(sql, root)
        assert df is not None and len(df) > 0, sql
        assert {first, SECOND} <= set(df["campaign_id"]) or "status <> 'ok'" in sql, sql


def doc_query(heading, index=0):
    """The ``index``-th sql block after the heading that starts with ``heading``."""
    text = QUERIES_DOC.read_text()
    return re.findall(r"```sql\n(.*?)```", text[text.index("## " + heading):], flags=re.S)[index]


def test_pige_trend_gives_each_change_and_its_z(lake_of_two):
    root, first = lake_of_two
    df = run_query(doc_query("How has each PIGE moved"), root)
    later = df[(df.campaign_id == SECOND) & df.identifiable.astype(bool)]
    assert len(later) > 0 and later.change.to_numpy() == pytest.approx(1.0)
    assert later.change_z.to_numpy() == pytest.approx(1.0 / (np.sqrt(2) * later.uncertainty.to_numpy()))
    assert df[df.campaign_id == first].change.isna().all()  # the first campaign has no previous one
    assert (df.groupby("name").started.apply(lambda s: s.is_monotonic_increasing)).all()


def test_pdge_drift_and_worst_poses_and_failures(lake_of_two):
    root, first = lake_of_two
    drift = run_query(doc_query("How has a PDGE drifted"), root)
    assert drift.campaign_id.tolist() == [first, SECOND]
    pointwise = run_query(doc_query("How has a PDGE drifted", 1), root)
    assert pointwise[pointwise.campaign_id == SECOND].change_arcsec.to_numpy() == pytest.approx(0.5)

    worst = run_query(doc_query("Which validation poses are worst"), root)
    assert worst.after_um.is_monotonic_decreasing and worst.campaign_id.iloc[0] == SECOND
    failed = run_query(doc_query("Which images failed"), root)
    assert failed[["campaign_id", "status", "n"]].values.tolist() == [[SECOND, "missing_file", 1]]
    no_pose = run_query(doc_query("Which images failed", 1), root)
    assert no_pose[["campaign_id", "status"]].values.tolist() == [[SECOND, "no_grid"]]


def test_lake_partitions_shows_schema_and_fivecal_versions(lake_of_two):
    root, first = lake_of_two
    df = run_query(doc_query("What wrote each partition"), root)
    pige = df[df["table"] == "pige"].set_index("campaign_id")
    assert pige.loc[SECOND, "fivecal_version"] == "test" and pige.loc[SECOND, "schema_version"] == 2
    assert pige.loc[first, "num_rows"] == len(read_table("pige", root, first))


# --------------------------------------------------------------------------------------------
# read-only, confined to the lake, memory-limited, streamed


def lake_files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize("sql, expected", [
    ("copy (select 'evil2' as campaign_id, 1 as x) to '{root}/pige' (format parquet, partition_by (campaign_id))",
     "COPY statements are not allowed: fivecal query is read-only"),
    ("copy pige to '{outside}/stolen.csv'", "COPY statements are not allowed"),
    ("attach '{outside}/new.duckdb' as other", "ATTACH statements are not allowed"),
    ("attach ':memory:' as other", "ATTACH statements are not allowed"),
    ("install httpfs", "statements are not allowed"),
    ("load httpfs", "statements are not allowed"),
    ("set enable_external_access = true", "SET statements are not allowed"),
    ("pragma memory_limit = '100GB'", "SET statements are not allowed"),
    ("pragma version", "PRAGMA statements are not allowed"),
    ("create table t as select 1", "CREATE statements are not allowed"),
    ("select 1; select 2", "give one SQL statement per query (got 2)"),
    ("select * from read_csv('/etc/passwd')", "Permission Error"),
    ("select * from read_text('/etc/hostname')", "Permission Error"),
    ("select * from glob('/etc/*')", "Permission Error"),
    ("select * from read_text('{outside}/secret.txt')", "Permission Error"),
    ("select * from query('copy (select 1) to ''{outside}/x.csv''')", "Error"),
])
def test_the_query_is_read_only_and_confined_to_the_lake(two_campaigns, tmp_path, sql, expected):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("secret")
    before, outside_before = lake_files(two_campaigns), lake_files(outside)
    sql = sql.format(root=two_campaigns, outside=outside)
    result = runner.invoke(app, ["query", "--results", str(two_campaigns), sql])
    assert result.exit_code == 2 and result.output.startswith("error: "), result.output
    assert expected in result.output and "Traceback" not in result.output
    assert "secret" not in result.output.replace("secret.txt", "")
    assert lake_files(two_campaigns) == before and lake_files(outside) == outside_before
    assert run_query("select distinct campaign_id from pige order by 1", two_campaigns).campaign_id.tolist() == [
        "20260105", "w02"]


def test_the_lake_itself_stays_readable_and_the_error_says_how_to_open_a_full_session(two_campaigns):
    files = run_query("select file from glob('" + str(two_campaigns.resolve()) + "/**/*.parquet')", two_campaigns)
    assert len(files) == 2
    result = runner.invoke(app, ["query", "--results", str(two_campaigns), "select * from read_csv('/etc/passwd')"])
    assert "docs/queries.md" in result.output


def test_max_rows_costs_what_it_prints(two_campaigns):
    start = time.monotonic()
    result = runner.invoke(app, ["query", "--results", str(two_campaigns), "--max-rows", "3",
                                 "select * from range(300000000)"])
    elapsed = time.monotonic() - start
    assert result.exit_code == 0, result.output
    assert [line.strip() for line in result.output.split("\n")[:4]] == ["range", "0", "1", "2"]
    assert "more rows not shown (the first 3 above" in result.output
    assert elapsed < 20, elapsed  # 3e8 rows would take minutes and GBs to load before printing


def test_a_query_over_its_memory_limit_is_a_clear_error_exit_2(two_campaigns):
    result = runner.invoke(app, ["query", "--results", str(two_campaigns), "--memory-limit", "64MB",
                                 "select count(distinct range::varchar) from range(30000000)"])
    assert result.exit_code == 2 and result.output.startswith("error: "), result.output
    assert "Out of Memory" in result.output and "Traceback" not in result.output


def test_csv_and_json_stream_every_row(two_campaigns):
    csv = runner.invoke(app, ["query", "--results", str(two_campaigns), "--format", "csv",
                              "select range as i from range(25000)"])
    assert csv.output.splitlines() == ["i", *map(str, range(25000))]  # three batches of 10 000
    js = runner.invoke(app, ["query", "--results", str(two_campaigns), "--format", "json",
                             "select range as i from range(25000)"])
    assert json.loads(js.output) == [{"i": i} for i in range(25000)]
    empty = runner.invoke(app, ["query", "--results", str(two_campaigns), "--format", "json",
                                "select 1 as i where false"])
    assert json.loads(empty.output) == []


@pytest.mark.parametrize("link_at", ["pige/campaign_id=stolen", "pige/campaign_id=w02/secret.txt", "secrets"])
def test_a_lake_holding_a_symbolic_link_is_refused_naming_the_link(two_campaigns, tmp_path, link_at):
    """DuckDB confines a query by the path's text: a link inside the lake would lead out of it."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("secret")
    (two_campaigns / link_at).symlink_to(outside / "secret.txt" if link_at.endswith(".txt") else outside)
    result = runner.invoke(app, ["query", "--results", str(two_campaigns),
                                 f"select * from read_text('{two_campaigns.resolve()}/{link_at}/secret.txt')"])
    assert result.exit_code == 2 and "symbolic link" in result.output and link_at.split("/")[-1] in result.output
    assert "secret" not in result.output.replace("secret.txt", "").replace("secrets", "")
    (two_campaigns / link_at).unlink()
    assert run_query("select count(*) as n from pige", two_campaigns).n.tolist() == [4]
