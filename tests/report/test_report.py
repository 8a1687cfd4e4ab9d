"""The calibration report (tasks.report): tables, figures, Markdown/HTML output, atomic replace.

Small synthetic frames with the documented schemas; no Prefect, no campaign.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tasks.report import ReportData, before_after_table, write_report
from tasks.report.render import NOT_AVAILABLE
from tasks.report.tables import fmt_pm
from tasks.vision.detector_comparison import SUMMARY_COLUMNS

AXES = {"X": "mm", "Y": "mm", "Z": "mm", "A": "deg", "C": "deg"}
COMPONENTS = ("dx_um", "dy_um", "dz_um", "ex_arcsec", "ey_arcsec", "ez_arcsec")
SECRET = 987.654  # the value of an unidentifiable parameter: must never be printed


def make_pdge(n: int = 8, seed: int = 0) -> pd.DataFrame:
    """n sweep positions per axis: smooth truth, fit = truth + small bias, measured = truth + noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for k, (axis, unit) in enumerate(AXES.items()):
        for pos in np.linspace(-5, 5, n):
            row = {"axis": axis, "position": float(pos), "position_unit": unit, "n_images": 5}
            for j, c in enumerate(COMPONENTS):
                scale = 10.0 if c.endswith("_um") else 100.0
                truth = scale * math.sin(0.3 * pos + j + k)
                row[c] = truth + rng.normal(0, 0.05 * scale)
                row[f"std_{c}"] = 0.05 * scale
                row[f"fit_{c}"] = truth + 0.01 * scale
                row[f"truth_{c}"] = truth
            rows.append(row)
    df = pd.DataFrame(rows)
    df["translation_um"] = np.linalg.norm(df[["dx_um", "dy_um", "dz_um"]].to_numpy(), axis=1)
    df["rotation_arcsec"] = np.linalg.norm(df[["ex_arcsec", "ey_arcsec", "ez_arcsec"]].to_numpy(), axis=1)
    return df


def make_pige() -> pd.DataFrame:
    return pd.DataFrame([
        {"name": "delta_x_A", "kind": "pige", "joint": "A", "unit": "um", "value": 12.34, "uncertainty": 0.42,
         "identifiable": True, "note": "", "truth": 12.0, "truth_nominal": 11.5},
        {"name": "alpha_C", "kind": "pige", "joint": "C", "unit": "arcsec", "value": -30.0, "uncertainty": 2.0,
         "identifiable": True, "note": "", "truth": -31.0, "truth_nominal": -31.0},
        {"name": "delta_z_C", "kind": "pige", "joint": "C", "unit": "um", "value": SECRET, "uncertainty": np.nan,
         "identifiable": False, "note": "absorbed by the camera mount", "truth": np.nan, "truth_nominal": 5.0},
        {"name": "mount_tx", "kind": "mount", "joint": "camera1", "unit": "um", "value": 34.0, "uncertainty": 1.5,
         "identifiable": True, "note": "hand-eye", "truth": 33.0, "truth_nominal": np.nan},
    ])


def make_verification(pos: dict, ori: dict, sources=("vbm", "truth"), floors: bool = True) -> pd.DataFrame:
    """pos/ori: {phase: list of error norms} (µm, arcsec); truth = vbm − 0.1; components from the norms."""
    rows = []
    for source in sources:
        offset = 0.0 if source == "vbm" else 0.1
        for phase in pos:
            for i, (p, o) in enumerate(zip(pos[phase], ori[phase], strict=True)):
                p, o = p - offset, o - offset
                row = {"image_id": f"{phase}-{i}", "pose": i, "phase": phase, "source": source,
                       "position_um": p, "orientation_arcsec": o,
                       "dx_um": p * 0.6, "dy_um": p * 0.0, "dz_um": p * 0.8,
                       "rx_arcsec": -o * 0.8, "ry_arcsec": o * 0.6, "rz_arcsec": 0.0}
                if floors:
                    row |= {"noise_floor_position_um": 0.5, "noise_floor_orientation_arcsec": 3.0}
                rows.append(row)
    return pd.DataFrame(rows)


HAND = make_verification({"before": [1.0, 2.0, 3.0, 4.0], "after": [0.5, 1.0, 1.0, 1.5]},
                         {"before": [10.0, 20.0, 30.0, 40.0], "after": [5.0, 5.0, 5.0, 5.0]})
LIGHT = make_verification({"before": [1.0, 2.0]}, {"before": [3.0, 4.0]}, sources=("vbm",), floors=False)


def make_camera_calibration() -> pd.DataFrame:
    rows = []
    for cam in ("camera1", "camera2"):
        for trial in ("0", "1", "2", "joint"):
            rows.append({"campaign_id": "c1", "camera": cam, "trial": trial,
                         "status": "failed" if (cam, trial) == ("camera2", "2") else "ok", "message": "",
                         "n_images": 15, "n_points": 1500, "rms_px": 0.01 + 0.001 * len(rows), "sigma_px": 0.01,
                         "fx_px": 5000.0, "fy_px": 5000.0, "cx_px": 384.0, "cy_px": 256.0, "k1": -0.1, "k2": 0.2,
                         "p1": 0.001, "p2": -0.001, "k3": 0.35, "std_fx_px": 1.2, "std_fy_px": 1.2,
                         "std_cx_px": 0.3, "std_cy_px": 0.3, "std_k1": 0.01, "std_k2": 0.1, "std_p1": 1e-4,
                         "std_p2": 1e-4, "std_k3": 0.5})
    return pd.DataFrame(rows)


def make_detectors() -> pd.DataFrame:
    rows = []
    for det in ("rrht", "blob"):
        for cam in ("camera1", "all"):
            rows.append({c: 1.0 for c in SUMMARY_COLUMNS} | {"detector": det, "camera": cam, "n_images": 20})
    return pd.DataFrame(rows)


def make_formulations() -> pd.DataFrame:
    return pd.DataFrame([
        {"formulation": "local POE (this work)", "mean_single_run_ms": 0.0026, "total_300_ms": 0.78,
         "position_error_norm_um": 1e-9, "orientation_error_norm_arcsec": 2e-7, "note": "reference"},
        {"formulation": "D-H", "mean_single_run_ms": 0.01, "total_300_ms": 3.0,
         "position_error_norm_um": 0.5, "orientation_error_norm_arcsec": 1.0, "note": ""},
    ])


def full_data(**kw) -> ReportData:
    base = dict(campaign_id="c1", run="20261121T101500-ab12cd", pdge=make_pdge(), pige=make_pige(),
                verification=HAND, camera_calibration=make_camera_calibration(),
                detector_comparison=make_detectors(), formulations=make_formulations(),
                identifiability=["delta_z_C is indistinguishable from the camera mount's tz."],
                provenance={"fivecal_version": "0.1.0", "inputs": {"poses": "sha256:abc"}}, simulated=True)
    return ReportData(**(base | kw))


@pytest.fixture(scope="module")
def full_report(tmp_path_factory) -> dict[str, Path]:
    return write_report(tmp_path_factory.mktemp("rep") / "c1" / "run1", full_data())


# --------------------------------------------------------------------------------------------
# before_after_table
# --------------------------------------------------------------------------------------------


def _row(table: pd.DataFrame, source: str, quantity: str, stat: str) -> pd.Series:
    sel = table[(table["source"] == source) & (table["quantity"] == quantity) & (table["statistic"] == stat)]
    assert len(sel) == 1
    return sel.iloc[0]


def test_before_after_table_hand_checked():
    t = before_after_table(HAND)
    assert list(t["source"].unique()) == ["vbm", "truth"]
    mean = _row(t, "vbm", "position", "mean")
    assert mean["before"] == pytest.approx(2.5) and mean["after"] == pytest.approx(1.0)
    assert mean["improvement_pct"] == pytest.approx(60.0)
    assert mean["n_before"] == 4 and mean["n_after"] == 4
    assert mean["seed_before"] == 59.9 and mean["seed_after"] == 1.80 and mean["seed_improvement_pct"] == 96.1
    assert mean["noise_floor_before"] == pytest.approx(0.5)
    assert _row(t, "vbm", "position", "max")["before"] == pytest.approx(4.0)
    assert _row(t, "vbm", "position", "std")["before"] == pytest.approx(math.sqrt(5 / 3))
    assert math.isnan(_row(t, "vbm", "position", "std")["improvement_pct"])
    ori = _row(t, "vbm", "orientation", "mean")
    assert ori["before"] == pytest.approx(25.0) and ori["after"] == pytest.approx(5.0)
    assert ori["improvement_pct"] == pytest.approx(80.0) and ori["seed_improvement_pct"] == 67.4
    assert _row(t, "vbm", "orientation", "std")["after"] == pytest.approx(0.0)
    assert _row(t, "vbm", "orientation", "max")["seed_before"] == 331.0
    assert _row(t, "truth", "position", "mean")["before"] == pytest.approx(2.4)


def test_before_after_table_before_only_and_nan():
    v = make_verification({"before": [1.0, np.nan, 3.0]}, {"before": [1.0, 2.0, 3.0]}, sources=("vbm",),
                          floors=False)
    t = before_after_table(v)
    mean = _row(t, "vbm", "position", "mean")
    assert mean["before"] == pytest.approx(2.0) and mean["n_before"] == 2
    assert mean["n_after"] == 0 and math.isnan(mean["after"]) and math.isnan(mean["improvement_pct"])
    assert math.isnan(mean["noise_floor_before"])
    assert set(t["source"]) == {"vbm"}


def test_tool_direction_rows_follow_their_column_and_have_no_seed_figure():
    """The tool direction is |(rx, ry)| of make_verification's rows: the whole orientation here."""
    v = HAND.assign(tool_direction_arcsec=np.hypot(HAND["rx_arcsec"], HAND["ry_arcsec"]),
                    noise_floor_tool_direction_arcsec=2.0)
    t = before_after_table(v)
    tool = _row(t, "vbm", "tool direction", "mean")
    assert tool["before"] == pytest.approx(25.0) and tool["after"] == pytest.approx(5.0)
    assert tool["improvement_pct"] == pytest.approx(80.0) and tool["noise_floor_after"] == pytest.approx(2.0)
    assert math.isnan(tool["seed_after"]) and math.isnan(tool["seed_improvement_pct"])
    assert len(t) == len(before_after_table(HAND)) * 3 // 2  # a third quantity; none without its column


def test_model_predicted_columns_give_the_mean_rows_beside_the_measurement():
    """The identified model's own prediction per phase: its mean over the poses on the mean rows of
    both sources, NaN elsewhere, and two headed columns in the Markdown only when it is given."""
    from tasks.report.tables import format_before_after

    v = HAND.assign(model_predicted_position_um=np.where(HAND["phase"] == "before", 2.0, 0.0),
                    model_predicted_orientation_arcsec=np.where(HAND["phase"] == "before", 24.0, 4.5))
    t = before_after_table(v)
    for source in ("vbm", "truth"):
        ori = _row(t, source, "orientation", "mean")
        assert ori["model_predicted_before"] == pytest.approx(24.0)
        assert ori["model_predicted_after"] == pytest.approx(4.5)
    assert _row(t, "vbm", "position", "mean")["model_predicted_after"] == pytest.approx(0.0)
    assert math.isnan(_row(t, "vbm", "orientation", "max")["model_predicted_after"])
    assert "| Model predicts before | Model predicts after |" in format_before_after(t)
    assert "Model predicts" not in format_before_after(before_after_table(HAND))


def test_summary_says_worse_when_after_exceeds_before_and_the_objective_is_counted():
    """Under the tool-axis objective the whole orientation error grows: the summary says "worse"
    instead of a negative "better", and the before/after section counts the poses per objective."""
    from tasks.report.render import before_after_section, summary_section

    v = make_verification({"before": [1.0, 2.0], "after": [0.5, 0.5]}, {"before": [10.0, 20.0], "after": [30.0, 30.0]},
                          sources=("vbm",))
    compensation = pd.DataFrame({"image_id": ["a", "b"], "orientation_objective": ["tool-axis", "full (…)"]})
    data = full_data(verification=v, compensation=compensation)
    ba = before_after_table(v)
    summary = summary_section(data, ba)
    assert "15.0 → 30.0 arcsec (100.0 % worse)" in summary and "1.50 → 0.50 µm (66.7 % better)" in summary

    class NoFigures:
        def add(self, *args, **kwargs):
            return ""

    section = before_after_section(data, ba, NoFigures())
    assert "(validation poses): tool-axis 1, full (…) 1." in section
    assert "Images per validation pose" not in section  # a table written before the repeats column

    repeated = v.assign(repeats=np.where(v["phase"] == "before", 1, 5))
    section = before_after_section(full_data(verification=repeated, compensation=compensation), ba, NoFigures())
    assert "Images per validation pose in the VBM figures: before 1, after 5." in section


def test_fmt_pm_rounds_to_two_significant_digits_of_u():
    assert fmt_pm(12.3456, 0.42) == "12.35 ± 0.42"
    assert fmt_pm(1234.5, 37.0) == "1234 ± 37" or fmt_pm(1234.5, 37.0) == "1235 ± 37"
    assert fmt_pm(np.nan, 1.0) == "–"


# --------------------------------------------------------------------------------------------
# write_report
# --------------------------------------------------------------------------------------------


def test_files_exist_and_html_is_self_contained(full_report):
    from PIL import Image

    md, html, figs = full_report["markdown"], full_report["html"], full_report["figures"]
    assert md.is_file() and html.is_file() and figs.is_dir()
    stems = sorted(p.stem for p in figs.glob("*.png"))
    assert stems == sorted([*(f"fig10_pdge_{a}" for a in AXES), "fig11_pdge_histograms",
                            "fig12_single_direction_before", "fig13_before_after"])
    with Image.open(figs / "fig11_pdge_histograms.png") as im:
        assert round(im.info["dpi"][0]) == 150
    text = html.read_text(encoding="utf-8")
    assert text.count("data:image/png;base64,") == len(stems)
    assert 'src="figures/' not in text and "<style>" in text and "<table>" in text
    assert not list(md.parent.parent.glob(".run1.tmp-*"))  # no staging left behind


def test_markdown_has_every_table_and_the_seed_figures(full_report):
    md = full_report["markdown"].read_text(encoding="utf-8")
    assert md.startswith("# Calibration report — campaign c1, run 20261121T101500-ab12cd")
    assert md.index("## Summary") < md.index("## Table 3")
    for header in ("## Table 3 — Camera self-calibration", "## Table 4 — Target detection with PnP",
                   "## Table 5 — Kinematic modelling formulations", "## Table 6 — Identified PIGEs",
                   "## Fig. 10", "## Fig. 11", "## Fig. 12", "## Fig. 13", "### Before/after statistics",
                   "## Provenance", "| Trial | camera1: RMS (px) | camera2: RMS (px) |", "| Detector |",
                   "| Formulation |", "| Parameter |", "| Source | Quantity | Statistic |"):
        assert header in md, header
    for seed in ("59.90", "1.80", "72.70", "4.90", "160.0", "52.9", "331.0", "140.0", "96.1", "67.4",
                 "3.46", "83.07", "40.20", "253.0"):
        assert seed in md, seed
    assert NOT_AVAILABLE not in md
    assert "2.50 → 1.00 µm (60.0 % better)" in md  # summary, VBM
    assert "2.40 → 0.90 µm" in md  # summary, truth
    assert '"fivecal_version": "0.1.0"' in md
    assert "| joint |" not in md.split("## Table 3")[1].split("Joint best estimate")[0]
    assert "(failed)" in md
    assert "delta_z_C is indistinguishable" in md
    assert "VBM against truth" in md


def test_unidentifiable_pige_is_a_word_never_a_number(full_report):
    md = full_report["markdown"].read_text(encoding="utf-8")
    html = full_report["html"].read_text(encoding="utf-8")
    line = next(x for x in md.splitlines() if x.startswith("| delta_z_C |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[3] == "unidentifiable" and "absorbed by the camera mount" in cells[-1]
    assert "987" not in md and "987" not in re.sub(r"base64,[^\"]+", "", html)
    ident = next(x for x in md.splitlines() if x.startswith("| delta_x_A |"))
    assert "12.34 ± 0.42" in ident and "0.81" in ident  # |12.34 − 12|/0.42


def test_missing_optional_inputs_do_not_fail(tmp_path):
    data = ReportData(campaign_id="c2", run="r", pdge=make_pdge().iloc[0:0], pige=make_pige().iloc[0:0],
                      verification=LIGHT)
    paths = write_report(tmp_path / "out", data)
    md = paths["markdown"].read_text(encoding="utf-8")
    for header in ("## Table 3", "## Table 4", "## Table 5", "## Fig. 10", "## Fig. 11", "## Table 6"):
        assert f"{header}" in md and NOT_AVAILABLE in md.split(header)[1].split("\n## ")[0], header
    assert "Truth (identification gauge)" not in md and "VBM against truth" not in md
    assert "1.50 → – µm" in md  # no after phase
    assert sorted(p.stem for p in paths["figures"].glob("*.png")) == ["fig12_single_direction_before",
                                                                      "fig13_before_after"]


def test_lake_table_of_another_campaign_is_not_shown(tmp_path):
    md = write_report(tmp_path / "o", full_data(campaign_id="other", pdge=make_pdge().iloc[0:0]))["markdown"]
    text = md.read_text(encoding="utf-8")
    assert NOT_AVAILABLE in text.split("## Table 3")[1].split("\n## ")[0]


def test_rewrite_replaces_the_folder_whole(tmp_path):
    out = tmp_path / "reports" / "c1" / "run"
    small = dict(pdge=make_pdge().iloc[0:0], camera_calibration=None, detector_comparison=None, verification=LIGHT,
                 simulated=False)
    write_report(out, full_data(**small))
    (out / "stray.txt").write_text("old")
    (out / "figures" / "old.png").write_bytes(b"x")
    paths = write_report(out, full_data(run="second", **small))
    assert not (out / "stray.txt").exists() and not (out / "figures" / "old.png").exists()
    assert "run second" in paths["markdown"].read_text(encoding="utf-8")
    assert sorted(p.name for p in out.parent.iterdir()) == ["run"]


def test_refuses_to_replace_a_folder_that_is_not_a_report(tmp_path):
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "data.csv").write_text("1")
    with pytest.raises(FileExistsError):
        write_report(tmp_path / "precious", full_data())
    assert (tmp_path / "precious" / "data.csv").exists()


def test_malformed_required_input_fails_before_writing(tmp_path):
    with pytest.raises(ValueError, match="position_um"):
        write_report(tmp_path / "bad", full_data(verification=HAND.drop(columns="position_um")))
    assert not (tmp_path / "bad").exists() and not list(tmp_path.iterdir())


def test_extra_sections_and_figures(tmp_path):
    from tasks.report.figures import new_figure

    fig = new_figure(3, 2)
    fig.subplots().plot([0, 1], [0, 1])
    data = full_data(pdge=make_pdge().iloc[0:0], verification=LIGHT, simulated=False,
                     extra_sections=[("Squareness", "XY: **12″**")], extra_figures=[("residuals", fig)])
    paths = write_report(tmp_path / "x", data)
    md = paths["markdown"].read_text(encoding="utf-8")
    assert "## Squareness\n\nXY: **12″**" in md and "](figures/residuals.png)" in md
    assert (paths["figures"] / "residuals.png").is_file()
    assert "<strong>12″</strong>" in paths["html"].read_text(encoding="utf-8")
    with pytest.raises(ValueError, match="stems"):
        write_report(tmp_path / "y", full_data(extra_figures=[("../evil", fig)]))
