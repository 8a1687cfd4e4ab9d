"""The dispensing test's report: ``<reports>/<campaign_id>/<run>/dispensing/`` (report.md, index.html,
figures/). Science only, no Prefect."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from tasks.report.figures import new_figure, save_png
from tasks.report.publish import write_markdown_and_html

SEED_DX_MM, SEED_DY_MM = 0.04, -0.06  # §5.3: mean δx, δy of the seed's 50 dots
PHASE_ORDER = ("nominal", "compensated", "check")


def _phases(rows: pd.DataFrame) -> list[str]:
    return [p for p in PHASE_ORDER if (rows["phase"] == p).any()]


def offsets_figure(rows: pd.DataFrame):
    """δx/δy histograms and a δx–δy scatter per phase, the seed's means beside (µm)."""
    phases = _phases(rows)
    fig = new_figure(9.0, 2.6 * len(phases))
    for i, phase in enumerate(phases):
        g = rows[(rows["phase"] == phase) & rows["qualified"]]
        for j, (col, seed) in enumerate((("dx_um", SEED_DX_MM), ("dy_um", SEED_DY_MM))):
            ax = fig.add_subplot(len(phases), 3, 3 * i + j + 1)
            ax.hist(g[col].dropna(), bins=20, color="tab:blue")
            ax.axvline(seed * 1e3, color="tab:red", ls="--", label=f"seed mean {seed * 1e3:+.0f} µm")
            ax.set_title(f"{phase}: δ{col[1]} (µm)", fontsize=8)
            ax.legend(fontsize=6)
        ax = fig.add_subplot(len(phases), 3, 3 * i + 3)
        ax.scatter(g["dx_um"], g["dy_um"], s=6)
        ax.scatter([SEED_DX_MM * 1e3], [SEED_DY_MM * 1e3], marker="x", color="tab:red", label="seed's mean")
        ax.set_xlabel("δx (µm)", fontsize=7)
        ax.set_ylabel("δy (µm)", fontsize=7)
        ax.set_title(f"{phase}: dot − ring", fontsize=8)
        ax.legend(fontsize=6)
    return fig


def features_figure(rows: pd.DataFrame, config: dict):
    """Distributions of d (mm), C, NSD_r and CoV_I over every dot found, the thresholds drawn."""
    fig = new_figure(9.0, 2.2)
    limits = {"circularity": config.get("circularity_min"), "nsd_r": config.get("nsd_r_max"),
              "cov_i": config.get("cov_i_max")}
    for k, col in enumerate(("diameter_mm", "circularity", "nsd_r", "cov_i")):
        ax = fig.add_subplot(1, 4, k + 1)
        ax.hist(rows[col].dropna(), bins=25, color="tab:gray")
        if limits.get(col) is not None:
            ax.axvline(limits[col], color="tab:red", ls="--")
        ax.set_title(col, fontsize=8)
    return fig


def _table(df: pd.DataFrame, floatfmt: str = "{:.2f}") -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(map(str, cols)) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        cells = [floatfmt.format(v) if isinstance(v, float | np.floating) else str(v) for v in r]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def reason_kind(reason: str) -> str:
    """A row's reason without its numbers: 'area', 'CoV_I', '2+ dots in the ring', 'no dot', ..."""
    first = str(reason).split(";")[0].strip()
    if "dots in the ring" in first:
        return "2+ dots in the ring"
    return first.split(" ")[0] if first[:1].isupper() or first.split(" ")[0] in ("area", "circularity") else first


def counts_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Per phase: rings, qualified, defective, and the commonest reasons."""
    out = []
    for phase in _phases(rows):
        g = rows[rows["phase"] == phase]
        reasons = g.loc[~g["qualified"], "reason"].map(reason_kind)
        out.append({"phase": phase, "rings": len(g), "qualified": int(g["qualified"].sum()),
                    "defective": int((~g["qualified"]).sum()),
                    "reasons": ", ".join(f"{k.strip()} ×{v}" for k, v in reasons.value_counts().items()) or "—"})
    return pd.DataFrame(out)


def confusion_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Truth class × verdict (simulated campaigns)."""
    t = rows.assign(verdict=np.where(rows["qualified"], "qualified", "defective"))
    return pd.crosstab(t["truth_defect"], t["verdict"]).reset_index()


def truth_agreement(rows: pd.DataFrame) -> pd.DataFrame:
    """Per phase, over qualified dots: mean and rms of measured − true offsets (µm)."""
    out = []
    for phase in _phases(rows):
        g = rows[(rows["phase"] == phase) & rows["qualified"]]
        ex, ey = g["dx_um"] - g["truth_dx_um"], g["dy_um"] - g["truth_dy_um"]
        out.append({"phase": phase, "dots": len(g), "mean δx error (µm)": ex.mean(), "mean δy error (µm)": ey.mean(),
                    "rms δx error (µm)": float(np.sqrt((ex ** 2).mean())),
                    "rms δy error (µm)": float(np.sqrt((ey ** 2).mean()))})
    return pd.DataFrame(out)


def before_after_table(verification: pd.DataFrame) -> pd.DataFrame:
    """Mean tip errors per phase and source, after_tip included, beside the mean model uncertainty
    of the position at that phase's commands (after_tip: with the tip fit's constant replaced,
    tasks.dispensing.tip_uncertainty)."""
    order = {"before": 0, "after": 1, "after_tip": 2}
    columns = ["position_um", "model_uncertainty_position_um", "orientation_arcsec", "tool_direction_arcsec"]
    g = (verification.reindex(columns=["phase", "source", *columns]).groupby(["phase", "source"])[columns]
         .mean().reset_index())
    return g.sort_values(["phase", "source"], key=lambda s: s.map(order) if s.name == "phase" else s)


def write_dispensing_report(out_dir: Path, rows: pd.DataFrame, verification: pd.DataFrame, fit, summary: dict,
                            simulated: bool, config: dict | None = None) -> Path:
    """Write report.md, index.html and figures/ into ``out_dir``; returns index.html's path."""
    out_dir = Path(out_dir)
    (out_dir / "figures").mkdir(parents=True, exist_ok=True)
    for stem, fig in (("offsets", offsets_figure(rows)), ("features", features_figure(rows, config or {}))):
        save_png(fig, out_dir / "figures" / f"{stem}.png")
    tip = "\n".join(f"| {axis} | {v:+.2f} | {u:.2f} |" for axis, v, u in
                    zip("xyz", fit.offset_um, fit.uncertainty_um, strict=True))
    md = [f"# Dispensing test: {summary['campaign_id']}", "",
          "Dots dispensed in ring targets (§4.3, §5.3), inspected by §4.3, their offsets from the rings fitting the "
          "tip's constant offset in the tool frame (docs/dispensing-test.md).", "",
          "## The tip offset found", "",
          f"From {fit.dots} qualified dots of the nominal and compensated phases; dot residual rms "
          f"{fit.residual_rms_um:.2f} µm. "
          "Added to the model's tool_offset effect (tip frame: x, y across the tool, z along it).", "",
          "| tip axis | offset (µm) | u (µm) |", "|---|---:|---:|", tip, "",
          f"Fitted beside it, not folded in: a tool-axis error growing as sin A, {fit.tilt_um:+.2f} ± "
          f"{fit.tilt_uncertainty_um:.2f} µm per unit sin A (docs/dispensing-test.md).", "",
          "Model uncertainty of the tip position after the tip fit, mean over the validation poses "
          "compensated with it: "
          f"{summary.get('model_uncertainty_after_tip_um', float('nan')):.2f} µm (the calibration's propagated "
          "uncertainty, its constant tool-frame part replaced by what this fit leaves; "
          "tasks/dispensing/tip_uncertainty.py).", "",
          "## Dot offsets", "", "![dot offsets](figures/offsets.png)", "",
          "## Pass / defect counts", "", _table(counts_table(rows)), "",
          "## Dot features", "", "![features](figures/features.png)", ""]
    if simulated:
        md += ["## Against the truth", "", "Classification (truth class × verdict):", "",
               _table(confusion_table(rows)), "", "Measured − true dot offsets (qualified dots):", "",
               _table(truth_agreement(rows)), ""]
        t = summary.get("truth", {})
        if t:
            md += ["True constant tool-frame tip error over the validation poses (µm, tip frame x, y, z):", "",
                   f"- after compensation: {', '.join(f'{v:+.2f}' for v in t['constant_before_um'])} "
                   f"(norm {np.linalg.norm(t['constant_before_um']):.2f})",
                   f"- after the tip fit: {', '.join(f'{v:+.2f}' for v in t['constant_after_tip_um'])} "
                   f"(norm {np.linalg.norm(t['constant_after_tip_um']):.2f})", ""]
    md += ["## Before / after (validation poses)", "", _table(before_after_table(verification)), ""]
    return write_markdown_and_html(out_dir, "\n".join(md), f"Dispensing test {summary['campaign_id']}")["html"]
