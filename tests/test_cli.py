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


def test_simulate_refuses_a_bad_effect_before_doing_anything(tmp_path):
    result = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--effect", "pitch_cyclic:axis=Q"])
    assert result.exit_code != 0
    assert "must be one of" in result.output
    assert not (tmp_path / "x").exists()


def test_ingest_of_a_missing_campaign_fails_fast_with_the_folder_named(tmp_path):
    result = runner.invoke(app, ["ingest", str(tmp_path / "nope")])
    assert result.exit_code == 2
    assert "nope" in result.output and "does not exist" in result.output
