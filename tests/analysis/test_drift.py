"""Drift science (tasks.analysis.drift) and the drift report (tasks.report.drift_report) on synthetic lake tables
with a known drift: exact values, which rule flags, the verdict, and the written report."""

import math

import numpy as np
import pandas as pd
import pytest

from tasks.analysis.drift import (
    PDGE_COMPONENTS,
    DriftTolerance,
    campaign_objectives,
    drift_table,
    sweep_statistics,
    verdict,
    verification_summary,
)
from tasks.report.drift_report import DriftReportData, write_drift_report

REF, LATER = "b-ref", "a-later"  # ids sort the other way round from their capture times


def images_table():
    return pd.DataFrame({"campaign_id": [REF, REF, LATER],
                         "timestamp": pd.to_datetime(["2026-01-05T08:00:03Z", "2026-01-05T08:00:00Z",
                                                      "2026-01-12T08:00:00Z"], utc=True)})


PIGE = [  # name, kind, unit, (ref value, u), (later value, u), later identifiable
    ("delta_AZ", "pige", "um", (10.0, 1.0), (22.0, 1.0), True),        # Δ 12 µm, z 8.49: abs+sig, flagged
    ("beta_AY", "pige", "arcsec", (30.0, 3.0), (36.0, 4.0), True),     # Δ 6″, z 1.2: within
    ("gamma_YX", "pige", "arcsec", (5.0, 0.1), (7.0, 0.1), True),      # Δ 2″ < 15″, z 14.1: sig only
    ("alpha_YZ", "pige", "arcsec", (0.0, 20.0), (30.0, 20.0), True),   # Δ 30″ > 15″, z 1.06: abs only
    ("delta_AY", "pige", "um", (3.0, 1.0), (99.0, 1.0), False),        # unidentifiable later: unavailable
    ("camera1.ez", "mount", "arcsec", (0.0, 1.0), (40.0, 1.0), True),  # a fixture moved: flagged, a note
]


def pige_table():
    rows = []
    for name, kind, unit, ref, later, ident in PIGE:
        for campaign, (value, u), ok in ((REF, ref, True), (LATER, later, ident)):
            rows.append({"campaign_id": campaign, "name": name, "kind": kind, "joint": "A", "unit": unit,
                         "value": value if ok else np.nan, "uncertainty": u if ok else np.nan, "identifiable": ok})
    return pd.DataFrame(rows)


def pdge_table(later_dz=(0.0, 4.0, 8.0)):
    """Axis X at 3 positions; dz: ref 0, 1, 2 µm, later ``later_dz``; every other component 0; all s = 0.3."""
    rows = []
    for campaign, dz in ((REF, (0.0, 1.0, 2.0)), (LATER, later_dz)):
        for i, position in enumerate((-1.0, 0.0, 1.0)):
            row = {"campaign_id": campaign, "axis": "X", "position": position}
            for c in PDGE_COMPONENTS:
                row[c] = dz[i] if c == "dz_um" else 0.0
                row[f"std_{c}"] = 0.3
            rows.append(row)
    return pd.DataFrame(rows)


def verification_table(after_um=4.0, after_arcsec=40.0, after_tool_arcsec=30.0):
    rows = []
    for campaign in (REF, LATER):
        for pose, scale in enumerate((0.5, 1.5)):
            rows.append({"campaign_id": campaign, "pose": pose, "phase": "before", "source": "vbm",
                         "position_um": 60.0 * scale, "orientation_arcsec": 160.0 * scale,
                         "tool_direction_arcsec": 60.0 * scale})
            rows.append({"campaign_id": campaign, "pose": pose, "phase": "after", "source": "vbm",
                         "position_um": after_um * scale, "orientation_arcsec": after_arcsec * scale,
                         "tool_direction_arcsec": after_tool_arcsec * scale})
    return pd.DataFrame(rows)


def compensation_table(later_labels=("tool-axis", "full (tool-axis leaves a stroke)")):
    """The reference compensated with ``full``; the later campaign's poses labelled ``later_labels``."""
    return pd.DataFrame({"campaign_id": [REF, REF, LATER, LATER], "image_id": ["v0", "v1", "v0", "v1"],
                         "orientation_objective": ["full", "full", *later_labels]})


@pytest.fixture
def drift():
    return drift_table(pige_table(), pdge_table(), images_table(), DriftTolerance())


def row(drift, campaign, quantity):
    sel = drift[(drift.campaign_id == campaign) & (drift.quantity == quantity)]
    assert len(sel) == 1
    return sel.iloc[0]


# --------------------------------------------------------------------------------------------
# PDGE statistics
# --------------------------------------------------------------------------------------------


def test_sweep_statistics_exact_values():
    y, s = np.array([1.0, 2.0, 4.0]), np.array([0.1, 0.2, 0.2])
    st = sweep_statistics(y, s)
    assert st["mean"] == pytest.approx((7 / 3, 0.3 / 3), abs=1e-12)
    std = math.sqrt((42 / 9) / 2)
    u_std = math.sqrt(0.16 / 9 + 0.04 / 9 + 1.0 / 9) / (2 * std)
    assert st["std"] == pytest.approx((std, u_std), abs=1e-12)
    assert st["max"] == (4.0, 0.2)
    # the peak magnitude counts negative excursions; NaN positions are dropped
    assert sweep_statistics(np.array([1.0, -5.0, np.nan]), np.array([0.1, 0.4, 0.1]))["max"] == (5.0, 0.4)


def test_sweep_statistics_uncertainty_matches_monte_carlo():
    """The first-order uncertainty of mean, std and max against the scatter of re-measured sweeps."""
    rng = np.random.default_rng(7)
    y = np.array([0.0, 3.0, 5.0, 4.0, 1.0, -2.0])
    s = np.array([0.2, 0.3, 0.2, 0.4, 0.3, 0.2])
    draws = y + rng.standard_normal((20000, y.size)) * s
    mc = {"mean": draws.mean(axis=1).std(), "std": draws.std(axis=1, ddof=1).std(),
          "max": np.abs(draws).max(axis=1).std()}
    predicted = sweep_statistics(y, s)
    for name, spread in mc.items():
        assert predicted[name][1] == pytest.approx(spread, rel=0.05), name


# --------------------------------------------------------------------------------------------
# Flagging
# --------------------------------------------------------------------------------------------


def test_campaigns_ordered_by_first_timestamp_and_reference_is_earliest(drift):
    assert list(dict.fromkeys(drift.campaign_id)) == [REF, LATER]
    assert (drift.reference_campaign_id == REF).all()
    assert row(drift, REF, "delta_AZ").time == pd.Timestamp("2026-01-05T08:00:00Z")
    ref_rows = drift[drift.campaign_id == REF]
    assert (ref_rows.rule == "reference").all() and not ref_rows.flagged.any()
    assert (ref_rows.delta_from_reference == 0).all()


def test_known_pige_drift_is_flagged_with_exact_numbers(drift):
    r = row(drift, LATER, "delta_AZ")
    assert (r.value, r.uncertainty, r.unit, r.kind, r.table) == (22.0, 1.0, "um", "pige", "pige")
    assert r.delta_from_reference == 12.0
    assert r.combined_uncertainty == pytest.approx(math.sqrt(2), abs=1e-12)
    assert r.z == pytest.approx(12 / math.sqrt(2), abs=1e-12)
    assert r.rule == "abs+sig" and r.flagged


def test_change_within_tolerance_is_not_flagged(drift):
    r = row(drift, LATER, "beta_AY")
    assert r.delta_from_reference == 6.0
    assert r.combined_uncertainty == pytest.approx(5.0, abs=1e-12)
    assert r.z == pytest.approx(1.2, abs=1e-12)
    assert r.rule == "within" and not r.flagged


def test_default_policy_needs_both_tests(drift):
    sig_only, abs_only = row(drift, LATER, "gamma_YX"), row(drift, LATER, "alpha_YZ")
    assert sig_only.rule == "sig" and not sig_only.flagged  # significant but 2″ is below the 15″ tolerance
    assert abs_only.rule == "abs" and not abs_only.flagged  # 30″ but within 2 u_c = 56.6″
    either = drift_table(pige_table(), pdge_table(), images_table(), DriftTolerance(require="either"))
    assert row(either, LATER, "gamma_YX").flagged and row(either, LATER, "alpha_YZ").flagged
    assert not row(either, LATER, "beta_AY").flagged
    only_abs = drift_table(pige_table(), pdge_table(), images_table(), DriftTolerance(require="abs"))
    assert row(only_abs, LATER, "alpha_YZ").flagged and not row(only_abs, LATER, "gamma_YX").flagged


def test_a_test_that_cannot_be_made_leaves_the_other_to_decide():
    """An effect parameter in its own unit has no absolute tolerance; a missing uncertainty allows no
    significance test."""
    rows = pd.DataFrame([
        {"campaign_id": c, "name": "pitch_cyclic:amplitude", "kind": "effect", "unit": "ppm", "value": v,
         "uncertainty": 0.5, "identifiable": True} for c, v in ((REF, 1.0), (LATER, 4.0))] + [
        {"campaign_id": c, "name": "delta_CX", "kind": "pige", "unit": "um", "value": v, "uncertainty": np.nan,
         "identifiable": True} for c, v in ((REF, 0.0), (LATER, 9.0))])
    d = drift_table(rows, pdge_table().iloc[:0], images_table(), DriftTolerance())
    effect, pige = row(d, LATER, "pitch_cyclic:amplitude"), row(d, LATER, "delta_CX")
    assert (effect.rule, effect.flagged, effect.z) == ("sig (no tolerance)", True, pytest.approx(3 / math.sqrt(0.5)))
    assert (pige.rule, pige.flagged) == ("abs (u unknown)", True) and np.isnan(pige.z)
    strict = drift_table(rows, pdge_table().iloc[:0], images_table(), DriftTolerance(require="abs"))
    assert not row(strict, LATER, "pitch_cyclic:amplitude").flagged and row(strict, LATER, "delta_CX").flagged
    both_missing = rows.assign(uncertainty=np.nan)
    d = drift_table(both_missing, pdge_table().iloc[:0], images_table(), DriftTolerance())
    r = row(d, LATER, "pitch_cyclic:amplitude")
    assert (r.rule, r.flagged) == ("within (no tolerance, u unknown)", False)


def test_unidentifiable_is_unavailable_not_flagged(drift):
    r = row(drift, LATER, "delta_AY")
    assert np.isnan(r.value) and np.isnan(r.delta_from_reference)
    assert r.rule == "unavailable" and not r.flagged


def test_pdge_statistics_drift(drift):
    ref_mean, later_mean = row(drift, REF, "X.dz.mean"), row(drift, LATER, "X.dz.mean")
    assert (ref_mean.value, later_mean.value) == pytest.approx((1.0, 4.0), abs=1e-12)
    assert later_mean.uncertainty == pytest.approx(math.sqrt(3 * 0.09) / 3, abs=1e-12)
    assert later_mean.rule == "sig" and not later_mean.flagged  # Δ 3 µm < 5 µm
    peak = row(drift, LATER, "X.dz.max")
    assert (peak.value, peak.uncertainty, peak.delta_from_reference) == pytest.approx((8.0, 0.3, 6.0), abs=1e-12)
    assert peak.combined_uncertainty == pytest.approx(0.3 * math.sqrt(2), abs=1e-12)
    assert peak.rule == "abs+sig" and peak.flagged
    spread = row(drift, LATER, "X.dz.std")
    assert (spread.value, spread.uncertainty) == pytest.approx((4.0, 0.3 / math.sqrt(2)), abs=1e-12)
    assert spread.rule == "sig" and not spread.flagged  # Δ 3 µm
    assert row(drift, LATER, "X.dx.mean").rule == "within"
    assert set(drift[drift.table == "pdge"].quantity) == {f"X.{c}.{s}" for c in ("dx", "dy", "dz", "ex", "ey", "ez")
                                                         for s in ("mean", "std", "max")}


def test_pdge_within_tolerance_not_flagged():
    d = drift_table(pige_table(), pdge_table(later_dz=(0.0, 1.5, 3.0)), images_table(), DriftTolerance())
    assert not d[d.table == "pdge"].flagged.any()


def test_explicit_reference_and_errors():
    d = drift_table(pige_table(), pdge_table(), images_table(), DriftTolerance(), reference=LATER)
    assert row(d, REF, "delta_AZ").delta_from_reference == -12.0
    assert row(d, LATER, "delta_AZ").rule == "reference"
    with pytest.raises(ValueError, match="reference campaign 'nope'"):
        drift_table(pige_table(), pdge_table(), images_table(), DriftTolerance(), reference="nope")
    with pytest.raises(ValueError, match="lacks the column"):
        drift_table(pige_table().drop(columns="uncertainty"), pdge_table(), images_table(), DriftTolerance())
    with pytest.raises(ValueError, match="require"):
        DriftTolerance(require="sometimes")


# --------------------------------------------------------------------------------------------
# Verdict
# --------------------------------------------------------------------------------------------


def test_verdict_recompensate_on_flagged_pige(drift):
    v = verdict(drift, verification_summary(verification_table()), DriftTolerance())
    assert v.needs_recompensation and (v.latest_campaign_id, v.reference_campaign_id) == (LATER, REF)
    text = v.text()
    assert "Recompensate" in text and "delta_AZ +12.00 µm (z = 8.5)" in text and "X.dz.max" in text
    assert "camera1.ez" in text and "check the fixtures" in text  # a note, not a reason
    assert not any("camera1.ez" in r for r in v.reasons)
    assert "4.00 µm and 40.0 arcsec" in text and ": within." in text


def test_verdict_no_drift_small_error_means_no_recompensation():
    quiet = pige_table()
    quiet = quiet[quiet.name.isin(["beta_AY"])]
    d = drift_table(quiet, pdge_table(later_dz=(0.0, 1.5, 3.0)), images_table(), DriftTolerance())
    v = verdict(d, verification_summary(verification_table()), DriftTolerance())
    assert not v.needs_recompensation
    assert "No recompensation needed" in v.text() and "No PIGE or PDGE quantity moved" in v.text()


def test_verdict_recompensate_on_poor_compensation_alone():
    quiet = pige_table()
    quiet = quiet[quiet.name.isin(["beta_AY"])]
    d = drift_table(quiet, pdge_table(later_dz=(0.0, 1.5, 3.0)), images_table(), DriftTolerance())
    summary = verification_summary(verification_table(after_um=30.0))
    after = summary[(summary.campaign_id == LATER) & (summary.phase == "after")].iloc[0]
    assert (after.n, after.position_um) == (2, 30.0)
    assert after.position_sem_um == pytest.approx(15.0, abs=1e-12)  # 15 and 45 µm: std 21.2, /√2
    v = verdict(d, summary, DriftTolerance())
    assert v.needs_recompensation and len(v.reasons) == 1 and "past the threshold" in v.reasons[0]


def test_campaign_objective_is_the_one_asked_for_fallbacks_included():
    objectives = campaign_objectives(compensation_table())
    assert objectives.to_dict() == {REF: "full", LATER: "tool-axis"}
    every_pose_fell_back = compensation_table(("full (tool-axis did not converge)",) * 2)
    assert campaign_objectives(every_pose_fell_back)[LATER] == "tool-axis"
    written_before_the_column = compensation_table().drop(columns="orientation_objective")
    assert set(campaign_objectives(written_before_the_column)) == {"full"}
    assert campaign_objectives(pd.DataFrame()).empty


def test_tool_axis_campaign_is_judged_on_its_tool_direction():
    quiet = pige_table()
    quiet = quiet[quiet.name.isin(["beta_AY"])]
    d = drift_table(quiet, pdge_table(later_dz=(0.0, 1.5, 3.0)), images_table(), DriftTolerance())
    # the whole rotation after a tool-axis compensation is large (the spin is left free), its tool direction small
    verification = verification_table(after_arcsec=1600.0, after_tool_arcsec=12.0)
    summary = verification_summary(verification, compensation_table())
    after = summary[summary.phase == "after"].set_index("campaign_id")
    assert after.loc[LATER, ["orientation_objective", "objective_orientation_arcsec", "tool_direction_arcsec"]
                     ].tolist() == ["tool-axis", 12.0, 12.0]
    assert after.loc[LATER, "objective_orientation_sem_arcsec"] == pytest.approx(6.0)  # 6 and 18″: std 8.49, /√2
    assert after.loc[REF, ["orientation_objective", "objective_orientation_arcsec"]].tolist() == ["full", 1600.0]
    v = verdict(d, summary, DriftTolerance())
    assert not v.needs_recompensation
    assert "12.0 arcsec of tool direction (compensated for the tool axis" in v.text() and ": within." in v.text()
    # without the compensation table every campaign counts as full: 1600″ of whole rotation is past 100″
    v_full = verdict(d, verification_summary(verification), DriftTolerance())
    assert v_full.needs_recompensation and "1600.0 arcsec of orientation" in v_full.reasons[0]
    # a tool-axis campaign without tool-direction figures cannot pass as within
    no_column = verification_summary(verification.drop(columns="tool_direction_arcsec"), compensation_table())
    v_unknown = verdict(d, no_column, DriftTolerance())
    assert v_unknown.needs_recompensation and "no figure of tool direction" in v_unknown.reasons[0]


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def test_drift_report_written_whole_and_self_contained(drift, tmp_path):
    tol = DriftTolerance()
    summary = verification_summary(verification_table())
    data = DriftReportData("run1", drift, summary, tol, verdict(drift, summary, tol), {"reference": REF})
    out = tmp_path / "drift" / "run1"
    paths = write_drift_report(out, data)
    md = paths["markdown"].read_text()
    assert {p.name for p in paths["figures"].iterdir()} == {"pige_trend.png", "pdge_X_trend.png",
                                                           "verification_trend.png"}
    assert "Recompensate the machine" in md and f"`{REF}` (reference)" in md
    assert "| `a-later` | delta_AZ | pige | 22.0 ± 1.0 | 10.0 ± 1.0 | 12.00 µm | 8.5 | abs+sig |" in md
    assert "22.0 ± 1.0 ⚑" in md and "7.00 ± 0.10 |" in md  # flagged and unflagged trend cells
    html = paths["html"].read_text()
    assert html.count("data:image/png;base64,") == 3 and 'src="figures/' not in html
    write_drift_report(out, data)  # a re-run replaces the report whole
    assert sorted(p.name for p in out.parent.iterdir()) == ["run1"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError):
        write_drift_report(tmp_path / "other", data)
