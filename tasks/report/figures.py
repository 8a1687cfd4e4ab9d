"""The report's figures (the seed's Figs. 10–13) as matplotlib Figures (science only, no Prefect).

Every figure is a :class:`matplotlib.figure.Figure` drawn on its own Agg canvas: no pyplot, so
no global figure registry and no GUI backend, whatever the process's default backend is. The
caller saves it (:func:`save_png`, 150 dpi) and drops it. Units: µm and arcsec as in the column
names; positions in command units (mm or deg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from tasks.core.units import UNIT_LABEL
from tasks.report.tables import (
    DIRECTIONS,
    ROTATION,
    SEED_DIRECTION_STD,
    SOURCE_LABEL,
    TRANSLATION,
    axes_in,
    column,
    translation_rotation,
)
from tasks.simulation.truth_stats import SEED_AFTER, SEED_BEFORE, SEED_PDGE_MEANS

DPI = 150
COLOURS = ("C0", "C1", "C2")
SYMBOL = {"dx_um": "δx", "dy_um": "δy", "dz_um": "δz", "ex_arcsec": "εx", "ey_arcsec": "εy", "ez_arcsec": "εz"}


def new_figure(width_in: float, height_in: float) -> Figure:
    """A Figure on its own Agg canvas (no pyplot state)."""
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: Path, dpi: int = DPI) -> Path:
    """Write ``fig`` as PNG at ``dpi`` (deterministic: no timestamp metadata). Returns ``path``."""
    fig.savefig(path, dpi=dpi, format="png", metadata={"Software": None})
    return path


def mark_no_data(ax, text: str = "no data") -> None:
    """Write ``text`` in grey at the centre of an empty panel ``ax``."""
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="grey")


# --------------------------------------------------------------------------------------------
# Fig. 10: PDGE against position
# --------------------------------------------------------------------------------------------


def _pdge_panel(ax, g: pd.DataFrame, cols: tuple[str, ...], simulated: bool) -> None:
    """Measured (±1 standard error), fitted and (dashed) true error motions of three components."""
    x = column(g, "position").to_numpy()
    for c, colour in zip(cols, COLOURS, strict=True):
        y, s = column(g, c).to_numpy(), column(g, f"std_{c}").to_numpy()
        ax.errorbar(x, y, yerr=np.where(np.isfinite(s), s, 0.0), fmt="o", ms=3, capsize=2, lw=0.8, color=colour,
                    label=f"{SYMBOL[c]} measured ±1 s.e.")
        fit = column(g, f"fit_{c}").to_numpy()
        if np.isfinite(fit).any():
            ax.plot(x, fit, "-", lw=1.2, color=colour, label=f"{SYMBOL[c]} fit")
        truth = column(g, f"truth_{c}").to_numpy()
        if simulated and np.isfinite(truth).any():
            ax.plot(x, truth, "--", lw=1.2, color=colour, alpha=0.8, label=f"{SYMBOL[c]} truth")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: never hides a point


def fig10_pdge(pdge: pd.DataFrame, axis: str, simulated: bool) -> Figure:
    """Fig. 10 for one axis: translational (µm) and rotational (arcsec) PDGE against the axis
    position, measured points with ±1 standard-error bars, the fitted model as a line and, when
    simulated, the truth dashed."""
    g = pdge[pdge["axis"].astype(str) == axis].sort_values("position")
    unit = str(g["position_unit"].iloc[0]) if "position_unit" in g.columns and len(g) else ""
    fig = new_figure(10.0, 6.5)
    top, bottom = fig.subplots(2, 1, sharex=True)
    _pdge_panel(top, g, TRANSLATION, simulated)
    _pdge_panel(bottom, g, ROTATION, simulated)
    top.set_ylabel("translational error (µm)")
    top.set_title("translational PDGE δx, δy, δz")
    bottom.set_ylabel("rotational error (arcsec)")
    bottom.set_title("rotational PDGE εx, εy, εz")
    bottom.set_xlabel(f"{axis} position ({UNIT_LABEL.get(unit, unit)})")
    fig.suptitle(f"Fig. 10 (seed): PDGE measurement results, {axis} axis")
    return fig


# --------------------------------------------------------------------------------------------
# Fig. 11: PDGE magnitude histograms
# --------------------------------------------------------------------------------------------


def _histogram_with_normal(ax, values: np.ndarray, unit: str, seed_mean: float) -> None:
    """Histogram (counts) of the finite values, the scipy.stats.norm.fit curve scaled to counts,
    the mean as a vertical line and the seed's Fig. 11 mean in the legend."""
    from scipy import stats

    v = values[np.isfinite(values)]
    label = UNIT_LABEL[unit]
    if v.size == 0:
        mark_no_data(ax)
        return
    counts, edges, _ = ax.hist(v, bins=min(15, max(5, v.size // 3)), color="C0", alpha=0.6, label="measured")
    mu, sigma = stats.norm.fit(v)
    if sigma > 0:
        x = np.linspace(min(edges[0], mu - 3 * sigma), max(edges[-1], mu + 3 * sigma), 200)
        width = float(np.diff(edges).mean())
        ax.plot(x, stats.norm.pdf(x, mu, sigma) * v.size * width, "C3-", lw=1.5,
                label=f"normal fit μ = {mu:.3g}, σ = {sigma:.3g} {label}")
    ax.axvline(float(v.mean()), color="k", lw=1.2, label=f"mean {v.mean():.3g} {label}")
    ax.legend(handles=[*ax.get_legend_handles_labels()[0],
                       Line2D([], [], ls="none", label=f"seed Fig. 11 mean {seed_mean:.3g} {label}")],
              fontsize=7, loc="upper right", framealpha=0.85)
    ax.set_ylim(0, 1.8 * max(float(counts.max()), 1.0))  # headroom for the legend
    ax.set_ylabel("count")
    ax.grid(alpha=0.3)


def fig11_histograms(pdge: pd.DataFrame) -> Figure:
    """Fig. 11: per axis (rows), histograms of the measured translational (µm) and rotational
    (arcsec) PDGE magnitudes over the sweep, with a fitted normal curve, the mean and the seed's
    Fig. 11 mean."""
    axes = axes_in(pdge)
    fig = new_figure(10.0, 2.4 * max(1, len(axes)) + 0.6)
    grid = fig.subplots(max(1, len(axes)), 2, squeeze=False)
    for row, axis in zip(grid, axes, strict=False):
        t, r = translation_rotation(pdge[pdge["axis"].astype(str) == axis])
        seed_t, seed_r = SEED_PDGE_MEANS.get(axis, (np.nan, np.nan))
        _histogram_with_normal(row[0], t, "um", seed_t)
        _histogram_with_normal(row[1], r, "arcsec", seed_r)
        row[0].set_xlabel(f"{axis} axis: translational PDGE ‖(δx, δy, δz)‖ (µm)")
        row[1].set_xlabel(f"{axis} axis: rotational PDGE ‖(εx, εy, εz)‖ (arcsec)")
    if not axes:
        for ax in grid[0]:
            mark_no_data(ax)
    fig.suptitle("Fig. 11 (seed): distributions of the PDGE magnitudes with fitted normal curves")
    return fig


# --------------------------------------------------------------------------------------------
# Fig. 12: single-direction errors before calibration
# --------------------------------------------------------------------------------------------


def fig12_single_direction(verification: pd.DataFrame) -> Figure:
    """Fig. 12: VBM-measured position (dx, dy, dz µm) and orientation (rx, ry, rz arcsec) errors of
    the tip before calibration against the validation pose index; the legend gives each
    direction's standard deviation (ddof = 1) beside the seed's."""
    v = verification
    g = v[(v["source"].astype(str) == "vbm") & (v["phase"].astype(str) == "before")].sort_values("pose")
    fig = new_figure(11.0, 6.5)
    panels = fig.subplots(2, 1, sharex=True)
    for ax, cols, unit in ((panels[0], DIRECTIONS[:3], "um"), (panels[1], DIRECTIONS[3:], "arcsec")):
        if g.empty:
            mark_no_data(ax)
        for c, colour in zip(cols, COLOURS, strict=True):
            y = column(g, c)
            if g.empty or not y.notna().any():
                continue
            sd = float(y.std(ddof=1)) if y.notna().sum() > 1 else 0.0
            ax.plot(column(g, "pose"), y, "o-", ms=3, lw=0.8, color=colour,
                    label=f"{c[:2]}: σ = {sd:.2f} {UNIT_LABEL[unit]} (seed {SEED_DIRECTION_STD[c]:.2f})")
        ax.set_ylabel(f"{'position' if unit == 'um' else 'orientation'} error ({UNIT_LABEL[unit]})")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    panels[1].set_xlabel("validation pose index")
    fig.suptitle("Fig. 12 (seed): single-direction X/Y/Z errors before calibration (VBM)")
    return fig


# --------------------------------------------------------------------------------------------
# Fig. 13: before / after histograms
# --------------------------------------------------------------------------------------------

_PANELS = (("position_um", "before", "um"), ("position_um", "after", "um"),
           ("orientation_arcsec", "before", "arcsec"), ("orientation_arcsec", "after", "arcsec"))


def _phase_histogram(ax, values: pd.Series, col: str, phase: str, unit: str) -> None:
    """Histogram of one quantity in one phase with its mean as a vertical line and the seed's mean
    in the legend (not drawn: it may lie far outside this run's range)."""
    v = values.to_numpy(dtype=float)
    v = v[np.isfinite(v)]
    quantity = col.rsplit("_", 1)[0]
    seed = (SEED_BEFORE if phase == "before" else SEED_AFTER)[f"{quantity}_mean_{unit}"]
    label = UNIT_LABEL[unit]
    ax.set_xlabel(f"{quantity} error {phase} ({label})")
    ax.set_ylabel("poses")
    if v.size == 0:
        mark_no_data(ax)
        return
    counts, _, _ = ax.hist(v, bins=min(15, max(5, v.size // 3)), color="C0" if phase == "before" else "C2",
                           alpha=0.7)
    ax.axvline(float(v.mean()), color="k", lw=1.2, label=f"mean {v.mean():.3g} {label}")
    ax.legend(handles=[*ax.get_legend_handles_labels()[0],
                       Line2D([], [], ls="none", label=f"seed mean {seed:.3g} {label}")],
              fontsize=7, loc="upper right", framealpha=0.85)
    ax.set_ylim(0, 1.5 * max(float(counts.max()), 1.0))
    ax.grid(alpha=0.3)


def fig13_before_after(verification: pd.DataFrame, simulated: bool) -> Figure:
    """Fig. 13: histograms of the tip position (µm) and orientation (arcsec) error norms before and
    after compensation; first row VBM, second row the simulator's truth when simulated."""
    sources = ["vbm", "truth"] if simulated and (verification["source"].astype(str) == "truth").any() else ["vbm"]
    fig = new_figure(15.0, 3.2 * len(sources) + 0.6)
    grid = fig.subplots(len(sources), 4, squeeze=False)
    for row, source in zip(grid, sources, strict=True):
        s = verification[verification["source"].astype(str) == source]
        for ax, (col, phase, unit) in zip(row, _PANELS, strict=True):
            _phase_histogram(ax, column(s[s["phase"].astype(str) == phase], col), col, phase, unit)
            ax.set_title(f"{SOURCE_LABEL[source]}: {col.rsplit('_', 1)[0]} {phase}", fontsize=9)
    fig.suptitle("Fig. 13 (seed): position and orientation error before and after calibration")
    return fig
