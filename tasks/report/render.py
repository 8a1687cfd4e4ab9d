"""Assemble and write the calibration report (science only, no Prefect).

SYNOPSIS::

    from tasks.report import ReportData, write_report
    paths = write_report(Path("reports/demo/20261121T101500-ab12cd"), ReportData(...))
    paths["markdown"], paths["html"], paths["figures"]

The report follows the seed's §5.2: a summary, Table 3 (camera self-calibration), Table 4
(detectors), Table 5 (kinematic formulations), Fig. 10 and Fig. 11 (PDGE), Table 6 (PIGE),
Fig. 12 (single-direction errors before calibration), Fig. 13 with the before/after table,
then the caller's extra sections and figures and the provenance. The Markdown is the source;
the HTML is converted from it with markdown-it-py (CommonMark + tables, raw HTML escaped) and
every ``figures/<stem>.png`` image is embedded as a base64 data URI, so index.html stands alone.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from tasks.report import figures as F
from tasks.report import tables as T
from tasks.report.data import ReportData, write_report_data
from tasks.report.publish import publish_report
from tasks.simulation.truth_stats import SEED_AFTER, SEED_BEFORE

if TYPE_CHECKING:
    from matplotlib.figure import Figure

NOT_AVAILABLE = "Not available for this run."
STEM = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
PDGE_REQUIRED = ("axis", "position", *T.TRANSLATION, *T.ROTATION)
PIGE_REQUIRED = ("name", "value", "uncertainty", "identifiable")
VERIFICATION_REQUIRED = ("pose", "phase", "source", "position_um", "orientation_arcsec")
CAMERA_REQUIRED = ("camera", "trial", "status", "rms_px")
FORMULATION_REQUIRED = ("formulation", "mean_single_run_ms", "total_300_ms", "position_error_norm_um",
                        "orientation_error_norm_arcsec")


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


def _missing(df: pd.DataFrame | None, required) -> list[str]:
    return [c for c in required if df is None or c not in df.columns]


def check_inputs(data: ReportData) -> None:
    """Raise ValueError naming the missing columns of a required frame (pdge, pige, verification)
    and TypeError for a non-DataFrame; extra figure stems must be file-name safe and unique."""
    for name, required in (("pdge", PDGE_REQUIRED), ("pige", PIGE_REQUIRED), ("verification", VERIFICATION_REQUIRED)):
        df = getattr(data, name)
        if not isinstance(df, pd.DataFrame):
            raise TypeError(f"ReportData.{name} must be a pandas DataFrame, not {type(df).__name__}")
        if miss := _missing(df, required):
            raise ValueError(f"ReportData.{name} lacks the column(s) {', '.join(miss)}")
    stems = [s for s, _ in data.extra_figures]
    bad = [s for s in stems if not STEM.match(str(s)) or str(s).startswith(("fig10_", "fig11_", "fig12_", "fig13_"))]
    if bad or len(set(stems)) != len(stems):
        raise ValueError(f"extra figure stems must be unique file-name stems not starting with fig10_…fig13_: {stems}")


# --------------------------------------------------------------------------------------------
# Sections (each returns Markdown; figures are saved as they are drawn)
# --------------------------------------------------------------------------------------------


class _FigureSink:
    """Saves figures into ``folder`` as ``<stem>.png`` (150 dpi) and returns their Markdown."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.stems: list[str] = []

    def add(self, stem: str, fig: Figure, caption: str, own: bool = True) -> str:
        F.save_png(fig, self.folder / f"{stem}.png")
        if own:
            fig.clear()  # release the artists now; the Figure has no pyplot reference to close
        self.stems.append(stem)
        return f"![{caption}](figures/{stem}.png)\n\n*{caption}*"


def _mean_of(table: pd.DataFrame, source: str, quantity: str, phase: str) -> float:
    sel = table[(table["source"] == source) & (table["quantity"] == quantity) & (table["statistic"] == "mean")]
    return float(sel[phase].iloc[0]) if len(sel) else float("nan")


def _arrow(table: pd.DataFrame, source: str, quantity: str, unit: str) -> str:
    before, after = _mean_of(table, source, quantity, "before"), _mean_of(table, source, quantity, "after")
    rate = T.improvement_rate(before, after)
    tail = "" if T.is_missing(rate) else (f" ({T.fmt(rate, 1)} % better)" if rate >= 0 else
                                          f" ({T.fmt(-rate, 1)} % worse)")
    return f"{T.fmt_unit(before, unit)} → {T.fmt_unit(after, unit)} {T.UNIT_LABEL[unit]}{tail}"


def summary_section(data: ReportData, ba: pd.DataFrame) -> str:
    """The opening summary: campaign, run, data origin and the before → after mean errors."""
    lines = [f"- **Campaign:** `{data.campaign_id}`", f"- **Run:** `{data.run}`",
             f"- **Data:** {'simulated (virtual machine; truth available)' if data.simulated else 'measured'}"]
    sources = [s for s in T.SOURCES if s in set(ba["source"])]
    for s in sources:
        label = "VBM" if s == "vbm" else "truth (simulator)"
        lines.append(f"- **Mean position error, {label}:** {_arrow(ba, s, 'position', 'um')}")
        lines.append(f"- **Mean orientation error, {label}:** {_arrow(ba, s, 'orientation', 'arcsec')}")
        if (ba["quantity"] == "tool direction").any():
            lines.append(f"- **Mean tool-direction error, {label}:** {_arrow(ba, s, 'tool direction', 'arcsec')}")
    if not sources:
        lines.append(f"- **Before/after errors:** {NOT_AVAILABLE}")
    sb, sa = SEED_BEFORE, SEED_AFTER
    lines.append(f"- **The seed (§5.2):** {sb['position_mean_um']:.2f} → {sa['position_mean_um']:.2f} µm "
                 f"and {sb['orientation_mean_arcsec']:.1f} → {sa['orientation_mean_arcsec']:.1f} arcsec "
                 f"(published rates {T.SEED_IMPROVEMENT_PCT['position']:.1f} % and "
                 f"{T.SEED_IMPROVEMENT_PCT['orientation']:.1f} %)")
    return "## Summary\n\n" + "\n".join(lines)


def camera_section(data: ReportData) -> str:
    """Table 3 (trial RMS per camera, mean, std), the joint intrinsics and the distortion check."""
    head = "## Table 3 — Camera self-calibration\n\n"
    df = T.for_campaign(data.camera_calibration, data.campaign_id)
    if df is None or df.empty or _missing(df, CAMERA_REQUIRED):
        return head + NOT_AVAILABLE
    trials = df[df["trial"].astype(str) != "joint"]
    if trials.duplicated(["trial", "camera"]).any():
        return head + f"{NOT_AVAILABLE} (the camera_calibration table has duplicate trial rows)"
    parts = [head + "Reprojection RMS (px) of each self-calibration trial; mean and std over the ok trials.\n\n"
             + (T.format_table3(df) if not trials.empty else NOT_AVAILABLE)]
    if (joint := T.format_joint_intrinsics(df)) is not None:
        parts.append("Joint best estimate per camera (value ± OpenCV's standard deviation):\n\n" + joint)
    if (check := T.distortion_check(df)) is not None:
        parts.append(check)
    return "\n\n".join(parts)


def detector_section(data: ReportData) -> str:
    """Table 4 with ``tasks.vision.detector_comparison.format_table4``."""
    from tasks.vision.detector_comparison import SUMMARY_COLUMNS, format_table4

    head = "## Table 4 — Target detection with PnP\n\n"
    df = T.for_campaign(data.detector_comparison, data.campaign_id)
    if df is None or df.empty or _missing(df, SUMMARY_COLUMNS):
        return head + NOT_AVAILABLE
    return head + ("Runtime, detection rate, centre and pose errors per detector (bold: all cameras pooled); "
                   "see docs/detector-comparison.md.\n\n" + format_table4(df))


def formulation_section(data: ReportData) -> str:
    """Table 5: kinematic formulations compared."""
    head = "## Table 5 — Kinematic modelling formulations\n\n"
    df = data.formulations
    if df is None or df.empty or _missing(df, FORMULATION_REQUIRED):
        return head + NOT_AVAILABLE
    return head + ("Mean single-run time, total time to build 300 sets of error matrices, and the error norms "
                   "of each formulation.\n\n" + T.format_table5(df))


def pdge_section(data: ReportData, sink: _FigureSink) -> str:
    """Fig. 10 (one figure per axis), its quality table, Fig. 11 and the magnitude table."""
    head10 = "## Fig. 10 — PDGE measurement\n\n"
    head11 = "## Fig. 11 — PDGE distributions\n\n"
    axes = T.axes_in(data.pdge)
    if not axes:
        return head10 + NOT_AVAILABLE + "\n\n" + head11 + NOT_AVAILABLE
    parts = [head10 + "Error motions of each axis against its position: points are the mean over the repeats "
             "with ±1 standard error, the line is the fitted smooth model"
             + (", the dashed line the simulator's truth in the same gauge." if data.simulated else ".")]
    for axis in axes:
        parts.append(sink.add(f"fig10_pdge_{axis}", F.fig10_pdge(data.pdge, axis, data.simulated),
                              f"Fig. 10 — PDGE of the {axis} axis"))
    parts.append("Measurement quality per axis (s.e. = standard error of a measured point; z = (measured − "
                 "reference)/s.e.):\n\n" + T.format_pdge_quality(T.pdge_quality(data.pdge), data.simulated))
    parts.append(head11 + "Histograms of the translational and rotational PDGE magnitudes over each sweep with "
                 "the maximum-likelihood normal fit; the seed's Fig. 11 means beside.")
    parts.append(sink.add("fig11_pdge_histograms", F.fig11_histograms(data.pdge),
                          "Fig. 11 — PDGE magnitude histograms"))
    parts.append(T.format_pdge_magnitudes(T.pdge_magnitudes(data.pdge), data.simulated))
    return "\n\n".join(parts)


def pige_section(data: ReportData) -> str:
    """Table 6 (PIGE ± standard uncertainty), the uncertainty coverage check and the identifiability notes."""
    head = "## Table 6 — Identified PIGEs\n\n"
    parts = []
    if data.pige.empty:
        parts.append(head + NOT_AVAILABLE)
    else:
        propagated = "uncertainty_camera" in data.pige and data.pige["uncertainty_camera"].notna().any()
        parts.append(head + "Estimates with their standard uncertainty (k = 1)"
                     + (", u = √(u noise² + u camera²): u noise carries the pose noise through the PDGE "
                        "extraction and the fit (bootstrap), u camera the error of the cameras' self-calibrated "
                        "intrinsics, common to every pose; u fit is the Levenberg–Marquardt covariance alone, "
                        "which holds the PDGE profiles and the intrinsics exact" if propagated else "")
                     + ("; truth in the identification's gauge and the simulator's raw PIGE; abs(est − truth)/u "
                        "should be below 2 for about 95 % of the parameters." if data.simulated else ".")
                     + "\n\n" + T.format_pige(data.pige, data.simulated))
        cov = T.pige_coverage(data.pige)
        if data.simulated and cov["n"]:
            parts.append(f"Uncertainty check over {cov['n']} identified parameters with a truth: "
                         f"{100 * cov['within_1u']:.0f} % within 1u (68 % expected), "
                         f"{100 * cov['within_2u']:.0f} % within 2u (95 % expected), RMS of "
                         f"abs(est − truth)/u = {cov['rms_z']:.2f} (1 expected).")
        if cov["n_unidentifiable"]:
            parts.append(f"{cov['n_unidentifiable']} parameter(s) unidentifiable from this campaign.")
    ident = "### Identifiability\n\n" + ("\n".join(f"- {s}" for s in data.identifiability)
                                        if data.identifiability else "No unidentifiable directions reported.")
    parts.append(ident)
    return "\n\n".join(parts)


def direction_section(data: ReportData, sink: _FigureSink) -> str:
    """Fig. 12 and the per-direction statistics before calibration."""
    head = "## Fig. 12 — Single-direction errors before calibration\n\n"
    v = data.verification
    before = v[(v["phase"].astype(str) == "before") & (v["source"].astype(str) == "vbm")]
    if before.empty or _missing(v, T.DIRECTIONS):
        return head + NOT_AVAILABLE
    stats = T.direction_stats(v, "before")
    return "\n\n".join([
        head + "Tip position (µm) and orientation (arcsec) error components before calibration, as the VBM "
        "measures them, against the validation pose index; the seed's standard deviations beside.",
        sink.add("fig12_single_direction_before", F.fig12_single_direction(v),
                 "Fig. 12 — single-direction errors before calibration (VBM)"),
        T.format_direction_stats(stats)])


def before_after_section(data: ReportData, ba: pd.DataFrame, sink: _FigureSink) -> str:
    """Fig. 13, the before/after table beside the seed's figures and the VBM-against-truth check."""
    head = "## Fig. 13 — Before and after compensation\n\n"
    if ba.empty:
        return head + NOT_AVAILABLE
    parts = [head + "Histograms of the tip error norms over the validation poses before and after compensation"
             + (" (top: VBM, bottom: truth)." if data.simulated else " (VBM)."),
             sink.add("fig13_before_after", F.fig13_before_after(data.verification, data.simulated),
                      "Fig. 13 — position and orientation error before and after calibration"),
             "### Before/after statistics beside the seed\n\nmean/max/std over the validation poses (std with "
             "ddof = 1); improvement = 1 − after/before of the means"
             + ("; noise floor = mean expected error norm from measurement noise alone" if
                ba[["noise_floor_before", "noise_floor_after"]].notna().any().any() else "")
             + ("; model uncertainty after = mean expected tip error after compensation from the identified "
                "model's uncertainty alone (the PIGE table's u): how far compensation can be trusted to place the "
                "tip" if ba["model_uncertainty_after"].notna().any() else "")
             + ("; model predicts = mean tip error the identified model itself predicts at the phase's commands: "
                "before, how much of the measured error the model accounts for; after, what it says compensation "
                "leaves (A and C turn the tool about two directions only, so after a full compensation the "
                "orientation it predicts is the rotation about the third, which no command can make)"
                if ba[["model_predicted_before", "model_predicted_after"]].notna().any().any() else "") + "."
             + "\n\n" + T.format_before_after(ba),
             T.seed_rate_note()]
    if objective := _objective_note(data.compensation):
        parts.append(objective)
    if repeats := _repeats_note(data.verification):
        parts.append(repeats)
    if data.simulated and not (vt := T.vbm_vs_truth(data.verification)).empty:
        parts.append("### VBM against truth on the validation poses\n\nHow far the vision measurement of the "
                     "tip error is from the simulator's truth, pose by pose:\n\n" + T.format_vbm_vs_truth(vt))
    return "\n\n".join(parts)


def _objective_note(compensation: pd.DataFrame | None) -> str:
    """What the compensation turned A and C for, counted over the validation poses ("" when unknown)."""
    if compensation is None or "orientation_objective" not in compensation.columns:
        return ""
    counts = compensation["orientation_objective"].astype(str).value_counts()
    return ("Orientation objective of the compensation (validation poses): "
            + ", ".join(f"{name} {n}" for name, n in counts.items())
            + ". 'full' turns A and C for the whole tip rotation, as the seed's orientation error counts it; "
            "'tool-axis' puts the tool direction right and leaves the rotation about the tool axis free, which "
            "five axes cannot fix along with it (docs/calibrate.md, step 6).")


def _repeats_note(verification: pd.DataFrame) -> str:
    """How many images the VBM rows average per pose, per phase ("" when the table does not say)."""
    if "repeats" not in verification.columns:
        return ""
    vbm = verification[verification["source"].astype(str) == "vbm"]
    per_phase = vbm.groupby(vbm["phase"].astype(str), sort=False)["repeats"].agg(["min", "max"])
    if per_phase.empty or per_phase.isna().any().any():
        return ""
    counts = ", ".join(f"{phase} {int(r['min'])}" + (f"–{int(r['max'])}" if r["max"] != r["min"] else "")
                       for phase, r in per_phase.iterrows())
    return (f"Images per validation pose in the VBM figures: {counts}. The repeats of a pose are averaged "
            "(passes over all the poses in turn), so its noise floor falls as 1/√n; a systematic error of "
            "the vision system, common to the repeats, does not.")


def extras_section(data: ReportData, sink: _FigureSink) -> str:
    """The caller's sections (verbatim Markdown) and figures."""
    parts = [f"## {title}\n\n{body.strip()}" for title, body in data.extra_sections]
    if data.extra_figures:
        figs = [sink.add(str(stem), fig, str(stem), own=False) for stem, fig in data.extra_figures]
        parts.append("## Additional figures\n\n" + "\n\n".join(figs))
    return "\n\n".join(parts)


def provenance_section(data: ReportData) -> str:
    """The provenance dict as pretty-printed JSON (keys sorted)."""
    text = json.dumps(data.provenance, indent=2, sort_keys=True, ensure_ascii=False, default=str)
    fence = "`" * max(3, 1 + max((len(m) for m in re.findall(r"`+", text)), default=0))
    return f"## Provenance\n\n{fence}json\n{text}\n{fence}"


def build_markdown(data: ReportData, figures_dir: Path) -> str:
    """The whole report as Markdown; figures are written into ``figures_dir`` on the way."""
    sink = _FigureSink(figures_dir)
    ba = T.before_after_table(data.verification)
    sections = [f"# Calibration report — campaign {data.campaign_id}, run {data.run}",
                summary_section(data, ba), camera_section(data), detector_section(data), formulation_section(data),
                pdge_section(data, sink), pige_section(data), direction_section(data, sink),
                before_after_section(data, ba, sink), extras_section(data, sink), provenance_section(data)]
    return "\n\n".join(s for s in sections if s) + "\n"


def write_report(out_dir: Path, data: ReportData) -> dict[str, Path]:
    """Write ``out_dir/report.md``, ``out_dir/index.html`` (self-contained: PNGs embedded as
    base64 data URIs, CSS inline), ``out_dir/figures/*.png`` (150 dpi) and ``out_dir/data/``
    (the numbers and parameters, for ``fivecal reproduce``: tasks/report/data.py).

    Atomic (:func:`tasks.report.publish.publish_report`): ``out_dir`` is either absent/the old
    report or the whole new one. Raises ValueError/TypeError for malformed required inputs (before
    anything is written) and FileExistsError when ``out_dir`` is a file or a non-empty folder that is
    not a report. Returns {"markdown": report.md, "html": index.html, "figures": the figures folder}.
    """
    check_inputs(data)
    return publish_report(out_dir, f"fivecal report — {data.campaign_id} / {data.run}",
                          lambda figures: build_markdown(data, figures),
                          write_data=lambda staging: write_report_data(staging, data))
