"""Report pages for "where the model fails" and "watch the error fall" (science only, no Prefect).

SYNOPSIS
    >>> from tasks.report.residual_figures import residual_report
    >>> sections, figures = residual_report(residuals, dot_residuals, ladder, cameras=cameras)
    >>> data.extra_sections += sections; data.extra_figures += figures      # ReportData

What each page shows (docs/residuals.md):

- ``residual_trends_<camera>``: the pose residual (camera-frame components, µm and arcsec) against each
  variable that varies for the camera (axis commands, time, temperature, plate position in the image):
  binned means with a simultaneous 95 % band (:func:`tasks.analysis.residuals.binned_mean`). A panel whose band
  leaves zero somewhere has a red title: structure, not noise.
- ``residual_approach_<camera>``: the same against the approach direction of each axis (−1, 0, +1).
- ``residual_field_<camera>``: the per-dot reprojection residual over the image, averaged on a grid
  (arrows, scaled; colour = length in px).
- ``model_ladder``: each refit's validation error and whitened RMS (train, cross-validated) beside
  the measurement noise floor.
- tables (Markdown): the significant trends, the worst poses by whitened residual norm, the ladder.

Figures follow :mod:`tasks.report.figures`: Agg-canvas Figures (no pyplot), saved by the report.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from tasks.analysis.residual_trends import ALPHA, trend_tests
from tasks.analysis.residuals import (
    CAMERA_COMPONENTS,
    CATEGORICAL_VARIABLES,
    TREND_VARIABLES,
    binned_mean,
    worst_poses,
)
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import COMMAND_COLUMNS
from tasks.report.figures import mark_no_data, new_figure
from tasks.report.tables import fmt, fmt_g, md_table

# variable -> (scale applied to x for display, axis label)
VARIABLE_LABEL = {"X_mm": (1.0, "X (mm)"), "Y_mm": (1.0, "Y (mm)"), "Z_mm": (1.0, "Z (mm)"), "A_deg": (1.0, "A (deg)"),
                  "C_deg": (1.0, "C (deg)"), "time_s": (1 / 60, "time (min)"),
                  "temperature_c": (1.0, "temperature (°C)"), "u_mean_px": (1.0, "plate u in image (px)"),
                  "v_mean_px": (1.0, "plate v in image (px)"),
                  **{f"approach_{a}": (1.0, f"approach {a}") for a in ("X", "Y", "Z", "A", "C")}}
COMPONENT_LABEL = {c: f"{c.removeprefix('cam_').split('_')[0]} ({'µm' if c.endswith('_um') else 'arcsec'})"
                   for c in CAMERA_COMPONENTS}
_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


def _stem(text: str) -> str:
    return _SAFE.sub("-", str(text))


def _cameras_outside_fit(residuals: pd.DataFrame) -> list[str]:
    """Cameras none of whose images enter the constant-parameter fit (their residuals are taken against
    the model completed by their chain's constant poses: :func:`tasks.analysis.residuals.chain_constant_part`)."""
    fitted = residuals.groupby("camera")["used_in_fit"].any()
    return sorted(str(c) for c, f in fitted.items() if not f)


def _varying(g: pd.DataFrame, variables: Sequence[str]) -> list[str]:
    out = []
    for v in variables:
        x = g[v].to_numpy(dtype=float)
        if np.unique(x[np.isfinite(x)]).size >= 2:
            out.append(v)
    return out


def _grid_figure(nrows: int, ncols: int, panel_in: tuple[float, float] = (2.3, 1.7)) -> Figure:
    """A figure for an nrows × ncols grid of small panels with fixed margins (inches). The constrained
    layout of :func:`new_figure` is switched off: solving it for dozens of panels costs seconds per figure."""
    w, h = panel_in[0] * ncols + 0.3, panel_in[1] * nrows + 0.9
    fig = new_figure(w, h)
    fig.set_layout_engine(None)
    fig.subplots_adjust(left=0.75 / w, right=1 - 0.15 / w, bottom=0.35 / h, top=1 - 0.6 / h, wspace=0.35, hspace=0.35)
    return fig


def _band_panel(ax, bins: pd.DataFrame, scale: float, categorical: bool) -> None:
    """Binned means with their band; zero dashed; red title when the band leaves zero."""
    ax.axhline(0.0, color="k", lw=0.6, ls="--")
    if bins.empty:
        mark_no_data(ax)
        return
    x = bins["x"].to_numpy() * scale
    if categorical:
        ax.errorbar(x, bins["mean"], yerr=bins["half_width"], fmt="o", ms=4, capsize=3, color="C0")
        ax.set_xticks(x)
    else:
        ax.fill_between(x, bins["lo"], bins["hi"], color="C0", alpha=0.25, lw=0)
        ax.plot(x, bins["mean"], "o-", ms=2.5, lw=1.0, color="C0")
    hit = bins["excludes_zero"].to_numpy(dtype=bool)
    if hit.any():
        ax.plot(x[hit], bins["mean"].to_numpy()[hit], "o", ms=4, color="C3")
    ax.tick_params(labelsize=6)
    ax.locator_params(nbins=4)
    ax.grid(alpha=0.3)


def trend_figure(residuals: pd.DataFrame, camera: str, variables: Sequence[str] = TREND_VARIABLES,
                 components: Sequence[str] = CAMERA_COMPONENTS, n_bins: int = 10,
                 trends: pd.DataFrame | None = None) -> Figure:
    """Residual of ``camera`` against each variable (rows) for each component (columns): binned means
    (equal-count bins, or one per value for the approach directions) with the simultaneous 95 % band.
    Variables that do not vary for the camera are left out. Red points: bins whose band excludes zero.
    Red frame: the panel's trend test (``trends``, the ``residual_trends`` table) is significant; without
    it, some bin's band excludes zero."""
    flagged = (set() if trends is None else
               {(r.variable, r.component) for r in trends.itertuples(index=False)
                if r.camera == camera and r.significant})
    g = residuals[residuals["camera"].astype(str) == camera]
    rows = _varying(g, variables)
    fig = _grid_figure(max(len(rows), 1), len(components))
    grid = fig.subplots(max(len(rows), 1), len(components), squeeze=False)
    if not rows:
        mark_no_data(grid[0][0], "no variable varies")
    for r, var in enumerate(rows):
        scale, label = VARIABLE_LABEL.get(var, (1.0, var))
        categorical = var in CATEGORICAL_VARIABLES
        for c, comp in enumerate(components):
            ax = grid[r][c]
            bins = binned_mean(g[var], g[comp], n_bins, categorical=categorical)
            _band_panel(ax, bins, scale, categorical)
            if r == 0:
                ax.set_title(COMPONENT_LABEL.get(comp, comp), fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=7)
            hit = (var, comp) in flagged if trends is not None else bool(len(bins) and bins["excludes_zero"].any())
            if hit:
                for side in ax.spines.values():
                    side.set_edgecolor("C3")
    fig.suptitle(f"{camera}: pose residual (camera frame) against each variable — binned mean, simultaneous 95 % "
                 "band; red frame: the residual follows the variable (trend test at 5 %)", fontsize=9)
    return fig


def vector_field_figure(dot_residuals: pd.DataFrame, camera: str, image_size: tuple[int, int] | None = None,
                        cells: int = 16, min_count: int = 3) -> Figure:
    """Mean per-dot reprojection residual (du, dv px) on a grid of ``cells`` columns over the image of
    ``camera`` (rows in proportion). Arrows are scaled for visibility (the key gives the scale), coloured
    by length; cells with fewer than ``min_count`` dots are empty. image_size: (width, height) px (else the
    extent of the dots). Image axes: u right, v down."""
    d = dot_residuals[dot_residuals["camera"].astype(str) == camera]
    d = d[np.isfinite(d[["u_px", "v_px", "du_px", "dv_px"]].to_numpy(dtype=float)).all(axis=1)]
    fig = new_figure(8.0, 5.6)
    ax = fig.subplots()
    if d.empty:
        mark_no_data(ax)
        return fig
    u, v = d["u_px"].to_numpy(dtype=float), d["v_px"].to_numpy(dtype=float)
    w, h = image_size if image_size else (float(u.max()) + 1, float(v.max()) + 1)
    nx = cells
    ny = max(1, round(cells * h / w))
    ix = np.clip((u / w * nx).astype(int), 0, nx - 1)
    iy = np.clip((v / h * ny).astype(int), 0, ny - 1)
    cell = iy * nx + ix
    count = np.bincount(cell, minlength=nx * ny)
    mu = np.bincount(cell, d["du_px"].to_numpy(dtype=float), nx * ny) / np.maximum(count, 1)
    mv = np.bincount(cell, d["dv_px"].to_numpy(dtype=float), nx * ny) / np.maximum(count, 1)
    ok = count >= min_count
    cx = (np.arange(nx * ny) % nx + 0.5) * w / nx
    cy = (np.arange(nx * ny) // nx + 0.5) * h / ny
    length = np.hypot(mu, mv)
    ax.scatter(u, v, s=0.5, color="0.85", zorder=0)
    if ok.any():
        ref = float(np.quantile(length[ok], 0.9)) or 1e-3
        q = ax.quiver(cx[ok], cy[ok], mu[ok], mv[ok], length[ok], cmap="viridis", angles="xy", scale_units="xy",
                      scale=ref / (0.8 * w / nx), width=0.004, pivot="mid")
        ax.quiverkey(q, 0.8, -0.12, ref, f"arrow: {ref:.3g} px", labelpos="E", coordinates="axes",
                     fontproperties={"size": 8})
        fig.colorbar(q, ax=ax, label="mean residual length (px)")
    rms = float(np.sqrt(np.mean(d["du_px"].to_numpy(dtype=float) ** 2 + d["dv_px"].to_numpy(dtype=float) ** 2)))
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title(f"{camera}: reprojection residual (detected − projected) over the image\n{len(d)} dots from "
                 f"{d['image_id'].nunique()} images, RMS {rms:.3g} px; mean per cell of a {nx}×{ny} grid",
                 fontsize=9)
    return fig


def _added(prev: str, now: str) -> str:
    """The effects of ``now`` that ``prev`` lacks (and those it dropped), for a step's label."""
    a = {s for s in str(prev).split("; ") if s}
    b = {s for s in str(now).split("; ") if s}
    parts = [f"+{s.split(',')[0]}" for s in sorted(b - a)] + [f"−{s.split(',')[0]}" for s in sorted(a - b)]
    return " ".join(parts) or ("base" if not b else "refit")


def ladder_labels(ladder: pd.DataFrame) -> list[str]:
    """One label per step: its number and what it added to the previous step (family:first parameter)."""
    effects = ladder["effects"].astype(str).tolist()
    return [f"{int(s)}: {_added(effects[i - 1] if i else '', effects[i])}" for i, s in enumerate(ladder["step"])]


def ladder_figure(ladder: pd.DataFrame) -> Figure:
    """The model ladder: validation tip position (µm) and orientation (arcsec) discrepancy per step with
    the noise floor (dashed) beside the tip error after compensating with each step's model (VBM on the
    verification capture and, simulated, the truth), and the whitened RMS of the fit (train) and of
    held-out poses (cv) with the floor 1. Log scale when a panel spans more than a factor of 20."""
    fig = new_figure(13.0, 4.2)
    axes = fig.subplots(1, 3)
    if ladder is None or ladder.empty:
        for ax in axes:
            mark_no_data(ax)
        return fig
    ladder = ladder.sort_values("step")
    x = np.arange(len(ladder))
    labels = ladder_labels(ladder)
    panels = ((axes[0], (("validation_position_um", "validation (RMS)"),
                         ("compensated_vbm_position_um", "compensated tip, VBM (mean)"),
                         ("compensated_truth_position_um", "compensated tip, truth (mean)")),
               "noise_floor_position_um", "tip position error (µm)"),
              (axes[1], (("validation_orientation_arcsec", "validation (RMS)"),
                         ("compensated_vbm_orientation_arcsec", "compensated tip, VBM (mean)"),
                         ("compensated_truth_orientation_arcsec", "compensated tip, truth (mean)")),
               "noise_floor_orientation_arcsec", "tip orientation error (arcsec)"),
              (axes[2], (("train_rms", "train"), ("cv_rms", "cross-validated"), ("validation_rms", "validation")),
               None, "whitened residual RMS"))
    for ax, series, floor, ylabel in panels:
        values = []
        for (col, label), marker in zip(series, ("o-", "s-", "^-"), strict=False):
            if col not in ladder:  # a ladder from before the column existed
                continue
            y = pd.to_numeric(ladder[col], errors="coerce").to_numpy(dtype=float)
            if not np.isfinite(y).any():  # e.g. no truth for a lab's campaign
                continue
            values.append(y)
            ax.plot(x, y, marker, ms=5, label=label)
        f = (pd.to_numeric(ladder[floor], errors="coerce").to_numpy(dtype=float) if floor
             else np.ones(len(ladder)))
        ax.plot(x, f, "k--", lw=1, label="noise floor" if floor else "noise level (1)")
        allv = np.concatenate([*values, f])
        allv = allv[np.isfinite(allv) & (allv > 0)]
        if allv.size and allv.max() / allv.min() > 20:
            ax.set_yscale("log")
        ax.set_xticks(x)
        ax.set_xticklabels(labels, rotation=30, ha="right", fontsize=7)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Model ladder: error of each refit beside the measurement noise floor", fontsize=10)
    return fig


# --------------------------------------------------------------------------------------------
# Markdown
# --------------------------------------------------------------------------------------------


def worst_poses_markdown(residuals: pd.DataFrame, n: int = 10) -> str:
    """The ``n`` poses with the largest whitened residual norm, with their commands (mm, deg), time,
    and residual (plate frame µm / arcsec)."""
    w = worst_poses(residuals, n)
    if w.empty:
        return "No poses."
    headers = ["image", "camera", "stage", *COMMAND_COLUMNS, "time (s)", "‖W e‖", "‖v‖ (µm)", "‖ω‖ (arcsec)"]
    rows = [[r.image_id, r.camera, r.stage, *(fmt(getattr(r, c), 3) for c in COMMAND_COLUMNS), fmt(r.time_s, 0),
             fmt(r.white_norm, 1), fmt(r.position_um, 2), fmt(r.orientation_arcsec, 1)]
            for r in w.itertuples(index=False)]
    return md_table(headers, rows, "lll" + "r" * (len(headers) - 3))


def trends_markdown(trends: pd.DataFrame, limit: int = 15) -> str:
    """The significant trends of the ``residual_trends`` table, most significant first."""
    s = trends[trends["significant"]]
    if s.empty:
        return f"No residual component follows any variable at the {ALPHA:.0%} level."
    rows = [[r.camera, r.variable, r.component, r.bins, fmt_g(r.span, 3), fmt_g(r.statistic, 3),
             fmt_g(r.p_value, 2)] for r in s.head(limit).itertuples(index=False)]
    more = f"\n\n({len(s) - limit} more significant panels not listed.)" if len(s) > limit else ""
    return md_table(["camera", "variable", "component", "bins", "span", "F", "p"], rows) + more


def trends_story(trends: pd.DataFrame, accepted: Sequence[str] = ()) -> str:
    """What the trend tests say, in words, beside the diagnosis' verdict (``accepted``: the effects it
    accepted, in order): how many panels are flagged against what chance flags, and whether an
    accepted effect or nothing the diagnosis found stands behind them."""
    n, k = len(trends), int(trends["significant"].sum()) if len(trends) else 0
    if not n:
        return "No trend could be tested."
    chance = ALPHA * n
    head = (f"{k} of {n} panels ({k / n:.0%}) show a trend at the {ALPHA:.0%} level; chance alone flags about "
            f"{chance:.0f} ({ALPHA:.0%}).")
    top = trends[trends["significant"]].head(5)
    named = "; ".join(f"{r.camera} {r.component} against {r.variable} (span {r.span:.3g}, p {r.p_value:.1g})"
                      for r in top.itertuples(index=False))
    if accepted:
        return (head + " The diagnosis attributes the structure to " + ", ".join(accepted) + "; the model refitted "
                "with it is the next step of the ladder. The strongest flagged panels: " + named + ".")
    if k <= 2 * chance:
        return (head + " That is what a model that lacks nothing gives, and the diagnosis names no missing effect: "
                "the flagged panels are read as chance" + (f" (the strongest: {named})." if named else "."))
    return (head + " More than chance, and the diagnosis names no effect of its catalogue: structure that is "
            "flagged and unexplained. The strongest: " + named + ".")


def ladder_markdown(ladder: pd.DataFrame) -> str:
    """The ladder as a table (one row per step), effects with their fitted values."""
    rows = []
    for lbl, r in zip(ladder_labels(ladder), ladder.itertuples(index=False), strict=True):
        rows.append([lbl, getattr(r, "effect_specs", r.effects) or "—", r.n_params, fmt(r.train_rms, 3),
                     fmt(r.cv_rms, 3), fmt(r.validation_rms, 3), fmt(r.validation_position_um, 2),
                     fmt(r.noise_floor_position_um, 2), fmt(r.validation_orientation_arcsec, 1),
                     fmt(r.noise_floor_orientation_arcsec, 1), fmt(r.bic, 1),
                     fmt(getattr(r, "compensated_vbm_position_um", float("nan")), 2),
                     fmt(getattr(r, "compensated_truth_position_um", float("nan")), 2)])
    headers = ["step", "effects (fitted values)", "params", "train RMS", "cv RMS", "validation RMS",
               "validation (µm)", "floor (µm)", "validation (arcsec)", "floor (arcsec)", "BIC",
               "compensated VBM (µm)", "compensated truth (µm)"]
    return md_table(headers, rows, "ll" + "r" * 11)


def residual_report(residuals: pd.DataFrame, dot_residuals: pd.DataFrame | None = None,
                    ladder: pd.DataFrame | None = None, *, cameras: Mapping[str, CameraModel] | None = None,
                    n_worst: int = 10, n_bins: int = 10, trends: pd.DataFrame | None = None,
                    accepted: Sequence[str] = ()) -> tuple[list[tuple[str, str]], list[tuple[str, Figure]]]:
    """Sections (title, Markdown) and figures (stem, Figure) for ``ReportData.extra_sections`` /
    ``extra_figures``.

    residuals: the ``residuals`` table. dot_residuals: the ``dot_residuals`` table (vector fields; None
    skips them). ladder: the ``model_ladder`` table (None skips it). cameras: {camera: intrinsics} for the
    image size of the vector fields. trends: the ``residual_trends`` table (None: tested here without the
    model's shared uncertainty, :func:`tasks.analysis.residual_trends.trend_tests`). accepted: the effects the
    diagnosis accepted, for the section's account of the flagged panels (:func:`trends_story`). The
    figures appear under the report's "Additional figures" with their stems as captions; the sections
    name them.
    """
    sections: list[tuple[str, str]] = []
    figures: list[tuple[str, Figure]] = []
    outside = _cameras_outside_fit(residuals)
    summary = trend_tests(residuals, n_bins=n_bins) if trends is None else trends
    names = []
    for camera in sorted(residuals["camera"].astype(str).unique()):
        figures.append((f"residual_trends_{_stem(camera)}",
                        trend_figure(residuals, camera, TREND_VARIABLES, n_bins=n_bins, trends=summary)))
        figures.append((f"residual_approach_{_stem(camera)}",
                        trend_figure(residuals, camera, CATEGORICAL_VARIABLES, trends=summary)))
        names += [f"`residual_trends_{_stem(camera)}`", f"`residual_approach_{_stem(camera)}`"]
    body = [
        "The pose residual of each image, e = log(T_model⁻¹ T_measured) (eq. 20), against everything it could "
        "depend on. Components are shown in the camera frame (µm, arcsec), where an error of the machine's linear "
        "axes keeps one direction whatever C and A are. Each panel bins the images of one camera by one variable "
        "and draws the mean residual with a simultaneous 95 % band. A panel is framed red when its bin means differ "
        "from each other more than the images' scatter and the identified model's own uncertainty allow (χ² at the "
        f"{ALPHA:.0%} level, `residual_trends` table): the residual follows that variable. Figures: "
        + ", ".join(names) + ".",
        f"{len(residuals)} poses; {int(residuals['used_in_fit'].sum())} in the constant-parameter fit, the others "
        "held out of it (validation poses, sweeps of other cameras).",
    ]
    if outside:
        body.append(f"Camera(s) {', '.join(outside)} take no part in the constant-parameter fit, so no parameter "
                    "reaches the constant poses at the ends of their chain (camera mount, plate mount, and the gauge "
                    "the fit chose for the axes they see). Their residuals are taken against the model completed by "
                    "those 12 numbers, fitted to their own images: what is left is how they vary otherwise.")
    body.append("### Significant trends\n\n" + trends_story(summary, accepted) + "\n\n" + trends_markdown(summary))
    body.append(f"### Worst poses\n\nThe {n_worst} poses with the largest whitened residual norm ‖W e‖ (≈ √6 ≈ 2.4 "
                "for a pose at its measurement noise):\n\n" + worst_poses_markdown(residuals, n_worst))
    sections.append(("Residuals — where the model fails", "\n\n".join(body)))
    if dot_residuals is not None and not dot_residuals.empty:
        fields = []
        for camera in sorted(dot_residuals["camera"].astype(str).unique()):
            size = None
            if cameras and camera in cameras:
                size = (cameras[camera].width_px, cameras[camera].height_px)
            figures.append((f"residual_field_{_stem(camera)}", vector_field_figure(dot_residuals, camera, size)))
            fields.append(f"`residual_field_{_stem(camera)}`")
        r2 = (dot_residuals["du_px"].astype(float) ** 2 + dot_residuals["dv_px"].astype(float) ** 2)
        rms = np.sqrt(r2.groupby(dot_residuals["camera"].astype(str)).mean())
        sections.append(("Reprojection residuals over the image",
                         "Per detected dot: detected centre − projection of the plate dot through the measured pose "
                         "and the calibrated intrinsics (px), averaged on a grid over the image (" + ", ".join(fields)
                         + "). A pattern (radial, swirling, one-sided) is image-space error the camera model lacks; "
                         "noise averages out. RMS per camera: "
                         + ", ".join(f"{c} {v:.3g} px" for c, v in rms.items()) + "."))
    if ladder is not None and not ladder.empty:
        figures.append(("model_ladder", ladder_figure(ladder)))
        sections.append(("Model ladder — watch the error fall",
                         "One step per refit with a set of effects (`model_ladder` table; figure `model_ladder`). "
                         "Validation: RMS over the held-out validation poses of the tip position/orientation where "
                         "the measured plate pose puts it minus where the model puts it; floor: the same for a "
                         "perfect model, from the pose covariances (high: each pose's tilt noise reaches the tip "
                         "with the lever arm). Train / cv / validation RMS: whitened residual RMS of the fit, of "
                         "five-axis poses predicted by refits that did not see them and of the validation poses "
                         "(1 = measurement noise): the sensitive measures.\n\n" + ladder_markdown(ladder)))
    return sections, figures
