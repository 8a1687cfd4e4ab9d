"""Trend plots of the drift report (science only, no Prefect; no pyplot state).

Each figure is a :class:`matplotlib.figure.Figure` from :func:`tasks.report.figures.new_figure`,
saved by the caller with :func:`tasks.report.figures.save_png`. The x axis is the campaign's rank
in capture order (1 = earliest; the report's campaign table maps ranks to campaign ids and
times). Values in µm or arcsec as the quantity's unit; error bars are ±1 standard uncertainty.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from tasks.analysis.drift import PDGE_COMPONENTS, PDGE_STATISTICS, DriftTolerance
from tasks.core.units import UNIT_LABEL
from tasks.report.figures import mark_no_data, new_figure


def campaign_ranks(drift: pd.DataFrame) -> dict[str, int]:
    """{campaign_id: 1-based rank in capture order} (the drift table is in capture order)."""
    return {c: i + 1 for i, c in enumerate(dict.fromkeys(drift["campaign_id"].astype(str)))}


def _trend_panel(ax, rows: pd.DataFrame, ranks: dict[str, int], tolerance: DriftTolerance, title: str,
                 colour: str = "C0", label: str | None = None, band: bool = True) -> None:
    """One quantity over the campaigns: value ±u, the reference value dashed (with its ±tolerance
    band when ``band``), flagged campaigns as red crosses."""
    rows = rows[np.isfinite(rows["value"].to_numpy(dtype=float))]
    ax.set_title(title, fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    if rows.empty:
        if band:
            mark_no_data(ax, "not identified")
        return
    x = rows["campaign_id"].map(ranks).to_numpy(dtype=float)
    y = rows["value"].to_numpy(dtype=float)
    u = np.nan_to_num(rows["uncertainty"].to_numpy(dtype=float))
    ax.errorbar(x, y, yerr=u, fmt="o-", ms=3, lw=0.8, capsize=2, color=colour, label=label)
    ref = rows[rows["rule"] == "reference"]
    if len(ref):
        r = float(ref["value"].iloc[0])
        ax.axhline(r, color=colour if not band else "grey", lw=0.8, ls="--")
        tol = tolerance.absolute(str(ref["unit"].iloc[0]))
        if band and np.isfinite(tol):
            ax.axhspan(r - tol, r + tol, color="grey", alpha=0.15, lw=0)
    flagged = rows[rows["flagged"].astype(bool)]
    if len(flagged):
        ax.plot(flagged["campaign_id"].map(ranks), flagged["value"], "x", color="C3", ms=8, mew=2)
    ax.set_xticks(sorted(set(ranks.values())))


def _grid(n: int, ncols: int, width_in: float = 2.6, height_in: float = 2.0):
    nrows = max(1, -(-n // ncols))
    fig = new_figure(width_in * ncols, height_in * nrows + 0.6)
    return fig, fig.subplots(nrows, ncols, squeeze=False).ravel()


def pige_trend(drift: pd.DataFrame, tolerance: DriftTolerance, ncols: int = 4) -> Figure:
    """Every ``pige`` table quantity over the campaigns (one panel each)."""
    rows = drift[drift["table"] == "pige"]
    names = list(dict.fromkeys(rows["quantity"]))
    ranks = campaign_ranks(drift)
    fig, axes = _grid(max(len(names), 1), ncols)
    for ax, name in zip(axes, names, strict=False):
        g = rows[rows["quantity"] == name]
        _trend_panel(ax, g, ranks, tolerance, f"{name} ({UNIT_LABEL.get(g['unit'].iloc[0], g['unit'].iloc[0])})")
    for ax in axes[len(names):]:
        ax.set_axis_off()
    fig.suptitle("PIGE and fitted constants against campaign (±1u; dashed: reference, band: ±tolerance; "
                 "×: flagged)", fontsize=9)
    return fig


def pdge_trend(drift: pd.DataFrame, axis: str, tolerance: DriftTolerance) -> Figure:
    """The PDGE statistics of one axis over the campaigns: one panel per component with its mean,
    std and max |·| (dashed: the reference campaign's values)."""
    ranks = campaign_ranks(drift)
    fig, axes = _grid(len(PDGE_COMPONENTS), 3, 3.2, 2.3)
    for ax, (component, unit) in zip(axes, PDGE_COMPONENTS.values(), strict=True):
        for stat, colour in zip(PDGE_STATISTICS, ("C0", "C1", "C2"), strict=True):
            _trend_panel(ax, drift[drift["quantity"] == f"{axis}.{component}.{stat}"], ranks, tolerance,
                         f"{component} ({UNIT_LABEL[unit]})", colour, stat, band=False)
        ax.legend(fontsize=6, loc="upper left")
    fig.suptitle(f"PDGE statistics of the {axis} axis against campaign (±1u; dashed: reference; ×: flagged)",
                 fontsize=9)
    return fig


def verification_trend(summary: pd.DataFrame, ranks: dict[str, int], tolerance: DriftTolerance) -> Figure:
    """Mean tip position (µm) and orientation (arcsec) error over the validation poses per campaign,
    before and after compensation (VBM; truth dashed when simulated), ±1 standard error of the mean,
    with the recompensation thresholds. The orientation is the one each campaign's compensation aims
    at (``objective_orientation_arcsec``: the whole rotation, or the tool direction under tool-axis)."""
    fig = new_figure(9.0, 3.4)
    axes = fig.subplots(1, 2)
    s = summary[summary["campaign_id"].astype(str).isin(ranks)]
    for ax, (col, sem, unit, limit) in zip(axes, (
            ("position_um", "position_sem_um", "um", tolerance.after_position_um),
            ("objective_orientation_arcsec", "objective_orientation_sem_arcsec", "arcsec",
             tolerance.after_orientation_arcsec)),
            strict=True):
        if s.empty:
            mark_no_data(ax)
        for (phase, source), g in s.groupby(["phase", "source"]):
            g = g.assign(rank=g["campaign_id"].map(ranks)).sort_values("rank")
            ax.errorbar(g["rank"], g[col], yerr=np.nan_to_num(g[sem].to_numpy(dtype=float)), capsize=2, ms=4,
                        fmt=("o" if phase == "after" else "s") + ("-" if source == "vbm" else "--"),
                        label=f"{phase}, {source}")
        ax.axhline(limit, color="C3", lw=1, label=f"threshold {limit:g} {UNIT_LABEL[unit]}")
        ax.set_xticks(sorted(ranks.values()))
        ax.set_xlabel("campaign (capture order)")
        ax.set_ylabel(f"mean {'position' if unit == 'um' else 'orientation'} error ({UNIT_LABEL[unit]})")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return fig
