"""The drift report across campaigns: Markdown, self-contained HTML and PNG trend plots.

Science only (no Prefect). SYNOPSIS::

    from tasks.analysis.drift import DriftTolerance, drift_table, verification_summary, verdict
    from tasks.report.drift_report import DriftReportData, write_drift_report
    tol = DriftTolerance()
    drift = drift_table(pige, pdge, images, tol)
    summary = verification_summary(verification, compensation)
    paths = write_drift_report(Path("reports/drift/20260112T020000Z"),
                               DriftReportData("20260112T020000Z", drift, summary, tol, verdict(drift, summary, tol)))
    paths["markdown"], paths["html"], paths["figures"]

Sections: the verdict, the campaigns in capture order, how a quantity is flagged, the flagged
quantities, PIGE trends (figure and table), PDGE trends per axis, the verification error after
compensation, provenance. The Markdown is the source; the HTML comes from
:func:`tasks.report.publish.markdown_to_html` with every figure embedded, so index.html stands
alone. Tables show the last :data:`TABLE_CAMPAIGNS` campaigns; the figures show all of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from tasks.analysis.drift import DriftTolerance, Verdict
from tasks.core.units import UNIT_LABEL
from tasks.report import drift_figures
from tasks.report.figures import save_png
from tasks.report.publish import publish_report
from tasks.report.render import provenance_section
from tasks.report.tables import fmt, fmt_pm, fmt_unit, md_table

TABLE_CAMPAIGNS = 8
FLAG = "⚑"


@dataclass
class DriftReportData:
    """Everything the drift report shows: the drift table (:func:`tasks.analysis.drift.flag_drift`), the
    verification summary (:func:`tasks.analysis.drift.verification_summary`), the tolerance used, the
    verdict and a provenance dict."""

    run: str
    drift: pd.DataFrame
    verification: pd.DataFrame
    tolerance: DriftTolerance
    verdict: Verdict
    provenance: dict = field(default_factory=dict)


def _campaigns(data: DriftReportData) -> list[str]:
    return list(drift_figures.campaign_ranks(data.drift))


def campaigns_section(data: DriftReportData) -> str:
    """One row per campaign in capture order: rank, id, time, identified PIGEs, flags, mean
    VBM tip error after compensation (the orientation its compensation aims at) and the objective."""
    d, v = data.drift, data.verification
    rows = []
    for rank, campaign in enumerate(_campaigns(data), start=1):
        g = d[d["campaign_id"] == campaign]
        pige = g[g["table"] == "pige"]
        after = v[(v["campaign_id"] == campaign) & (v["phase"] == "after") & (v["source"] == "vbm")]
        time = g["time"].iloc[0]
        rows.append([rank, f"`{campaign}`" + (" (reference)" if (g["rule"] == "reference").any() else ""),
                     "–" if pd.isna(time) else time.strftime("%Y-%m-%d %H:%M"),
                     f"{int(pige['value'].notna().sum())} / {len(pige)}",
                     int((g["flagged"] & (g["table"] == "pige")).sum()),
                     int((g["flagged"] & (g["table"] == "pdge")).sum()),
                     fmt(after["position_um"].iloc[0], 2) if len(after) else "–",
                     fmt(after["objective_orientation_arcsec"].iloc[0], 1) if len(after) else "–",
                     after["orientation_objective"].iloc[0] if len(after) else "–"])
    return "## Campaigns\n\nIn capture order (first image timestamp, UTC); the rank is the x axis of the plots.\n\n" + \
        md_table(["#", "Campaign", "Captured (UTC)", "PIGEs identified", "PIGE flags", "PDGE flags",
                  "After comp. position (µm)", "After comp. orientation (arcsec)", "Objective"], rows,
                 "rlrrrrrrl")


def rules_section(tol: DriftTolerance) -> str:
    """The tolerances and the flagging policy in words."""
    policy = {"both": "both tests are exceeded (when the uncertainty is unknown, the absolute test alone)",
              "abs": "the absolute test is exceeded", "sig": "the significance test is exceeded",
              "either": "either test is exceeded"}[tol.require]
    return ("## How a quantity is flagged\n\n"
            "Each quantity is compared with the same quantity of the reference campaign: Δ = value − reference, "
            "combined standard uncertainty u_c = √(u² + u_ref²).\n\n"
            f"- **Absolute test:** |Δ| > {tol.abs_um:g} µm (translations) or {tol.abs_arcsec:g} arcsec (rotations).\n"
            f"- **Significance test:** |Δ| > k·u_c with k = {tol.k:g}.\n"
            f"- **Flagged** when {policy}. The `rule` column of the `drift` table names the tests a change "
            "exceeds (`abs+sig`, `abs`, `sig`, `within`; `unavailable` when a value is missing).\n"
            f"- **Recompensation** when the latest campaign has a flagged PIGE/constant/squareness parameter or "
            f"PDGE statistic, or its mean tip error after compensation (VBM) exceeds {tol.after_position_um:g} µm "
            f"or {tol.after_orientation_arcsec:g} arcsec of the orientation its compensation aims at (the whole "
            "rotation, or the tool direction for a campaign compensated with `--orientation tool-axis`).\n\n"
            "PDGE statistics over each axis' sweep: mean, std (ddof = 1) and max |·| of the measured error "
            "motion, uncertainties propagated from the per-position standard errors (see docs/recalibration.md).")


def _pm(value, unc, unit: str) -> str:
    return fmt_pm(value, unc) if pd.notna(unc) else fmt_unit(value, unit)


def flagged_section(data: DriftReportData) -> str:
    """Every flagged quantity of every campaign: value ±u, reference ±u, Δ, z and the rule."""
    d = data.drift
    flagged = d[d["flagged"].astype(bool)]
    head = "## Flagged quantities\n\n"
    if flagged.empty:
        return head + "None: no quantity moved past tolerance."
    ref = d[d["rule"] == "reference"].set_index("quantity")
    rows = [[f"`{r.campaign_id}`", r.quantity, r.kind, _pm(r.value, r.uncertainty, r.unit),
             _pm(ref["value"].get(r.quantity), ref["uncertainty"].get(r.quantity), r.unit),
             f"{fmt_unit(r.delta_from_reference, r.unit)} {UNIT_LABEL.get(r.unit, r.unit)}", fmt(r.z, 1), r.rule]
            for r in flagged.itertuples()]
    return head + md_table(["Campaign", "Quantity", "Kind", "Value ± u", "Reference ± u", "Δ", "z", "Rule"], rows,
                           "lllrrrrl")


def _trend_table(data: DriftReportData, rows: pd.DataFrame) -> str:
    """Quantities (rows) × the last campaigns (columns), ``value ± u`` with ⚑ on flagged cells."""
    campaigns = _campaigns(data)[-TABLE_CAMPAIGNS:]
    rows = rows[rows["campaign_id"].isin(campaigns)]
    body = []
    for name, g in rows.groupby("quantity", sort=False):
        unit = str(g["unit"].iloc[0])
        cells = g.set_index("campaign_id")
        line = [f"{name} ({UNIT_LABEL.get(unit, unit)})"]
        for c in campaigns:
            if c not in cells.index:
                line.append("–")
                continue
            r = cells.loc[c]
            line.append(_pm(r["value"], r["uncertainty"], unit) + (f" {FLAG}" if bool(r["flagged"]) else ""))
        body.append(line)
    ranks = drift_figures.campaign_ranks(data.drift)
    return md_table(["Quantity", *[f"#{ranks[c]} {c}" for c in campaigns]], body)


def pige_section(data: DriftReportData, figures: Path) -> str:
    head = "## PIGE trends\n\n"
    rows = data.drift[data.drift["table"] == "pige"]
    if rows.empty:
        return head + "No PIGE results."
    return "\n\n".join([head + f"Identified value ± standard uncertainty per campaign ({FLAG}: flagged; – : "
                        "unidentifiable).", _figure(figures, "pige_trend", drift_figures.pige_trend(
                            data.drift, data.tolerance), "PIGE trends"), _trend_table(data, rows)])


def pdge_section(data: DriftReportData, figures: Path) -> str:
    head = "## PDGE trends\n\n"
    rows = data.drift[data.drift["table"] == "pdge"]
    if rows.empty:
        return head + "No PDGE results."
    parts = [head + f"Mean, std and max |·| of each measured error motion over the axis' sweep ({FLAG}: flagged)."]
    for axis in dict.fromkeys(rows["quantity"].str.split(".").str[0]):
        axis_rows = rows[rows["quantity"].str.startswith(f"{axis}.")]
        parts += [f"### {axis} axis", _figure(figures, f"pdge_{axis}_trend",
                                              drift_figures.pdge_trend(data.drift, axis, data.tolerance),
                                              f"PDGE statistics of the {axis} axis"), _trend_table(data, axis_rows)]
    return "\n\n".join(parts)


def verification_section(data: DriftReportData, figures: Path) -> str:
    head = "## Tip error before and after compensation\n\n"
    v = data.verification
    if v.empty:
        return head + "No verification results."
    ranks = drift_figures.campaign_ranks(data.drift)
    rows = [[f"#{ranks.get(r.campaign_id, '?')} `{r.campaign_id}`", r.orientation_objective, r.phase, r.source, r.n,
             fmt_pm(r.position_um, r.position_sem_um), fmt_pm(r.orientation_arcsec, r.orientation_sem_arcsec),
             fmt_pm(r.tool_direction_arcsec, r.tool_direction_sem_arcsec)]
            for r in v.assign(rank=v["campaign_id"].map(ranks)).sort_values(["rank", "phase", "source"],
                                                                            ascending=[True, False, False])
            .itertuples()]
    text = ("Mean over the validation poses ± standard error of the mean. The orientation threshold is "
            "applied to the orientation each campaign's compensation aims at (objective `full`: the whole "
            "rotation; `tool-axis`: the tool direction), and the figure plots that one.")
    return "\n\n".join([head + text,
                        _figure(figures, "verification_trend",
                                drift_figures.verification_trend(v, ranks, data.tolerance),
                                "Mean tip error per campaign"),
                        md_table(["Campaign", "Objective", "Phase", "Source", "Poses", "Position (µm)",
                                  "Orientation (arcsec)", "Tool direction (arcsec)"], rows, "llllrrrr")])


def _figure(folder: Path, stem: str, fig, caption: str) -> str:
    save_png(fig, folder / f"{stem}.png")
    fig.clear()
    return f"![{caption}](figures/{stem}.png)\n\n*{caption}*"


def build_markdown(data: DriftReportData, figures: Path) -> str:
    """The whole drift report as Markdown; figures are written into ``figures`` on the way."""
    sections = [f"# Drift report — run {data.run}", "## Verdict\n\n" + data.verdict.text(),
                campaigns_section(data), rules_section(data.tolerance), flagged_section(data),
                pige_section(data, figures), pdge_section(data, figures), verification_section(data, figures),
                provenance_section(data)]
    return "\n\n".join(sections) + "\n"


def write_drift_report(out_dir: Path, data: DriftReportData) -> dict[str, Path]:
    """Write ``out_dir/report.md``, a self-contained ``out_dir/index.html`` and ``out_dir/figures/*.png``.

    Atomic (:func:`tasks.report.publish.publish_report`): ``out_dir`` is absent, the previous report
    or the whole new one. Returns {"markdown", "html", "figures"} paths.
    """
    return publish_report(out_dir, f"fivecal drift report — {data.run}", lambda figures: build_markdown(data, figures))
