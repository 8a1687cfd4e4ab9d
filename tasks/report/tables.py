"""The report's tables (science only, no Prefect): statistics as DataFrames and their Markdown.

Units follow the column names: µm (``_um``), arcsec (``_arcsec``), px, ms, %. Every ``format_*``
function returns a Markdown pipe table (str); every other public function returns a DataFrame.
Missing values print as "–".
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from tasks.core.units import UNIT_LABEL
from tasks.simulation.truth_stats import SEED_AFTER, SEED_BEFORE, SEED_PDGE_MEANS

DASH = "–"
UNIDENTIFIABLE = "unidentifiable"
SEED_IMPROVEMENT_PCT = {"position": 96.1, "orientation": 67.4}
"""The seed's published improvement rates (§5.2), as printed there."""
SEED_DIRECTION_STD = {"dx_um": 3.46, "dy_um": 3.26, "dz_um": 5.99,
                      "rx_arcsec": 83.07, "ry_arcsec": 66.28, "rz_arcsec": 2.90}
"""The seed's Fig. 12: standard deviation of each single-direction error before calibration (µm, arcsec)."""
SEED_DIRECTION_RANGE = {"dx_um": "0–70", "dy_um": "0–70", "dz_um": "0–70",
                        "rx_arcsec": "−360–0", "ry_arcsec": "−180–180", "rz_arcsec": "−360–360"}
"""The seed's Fig. 12 ranges as its prose states them (µm, arcsec)."""
QUANTITIES = (("position", "position_um", "um"), ("orientation", "orientation_arcsec", "arcsec"),
              ("tool direction", "tool_direction_arcsec", "arcsec"))
"""(quantity, verification column, unit); the seed publishes no tool-direction figures."""
STATISTICS = ("mean", "max", "std")
SOURCES = ("vbm", "truth")
SOURCE_LABEL = {"vbm": "VBM", "truth": "truth"}
DECIMALS = {"um": 2, "arcsec": 1}
TRANSLATION = ("dx_um", "dy_um", "dz_um")
ROTATION = ("ex_arcsec", "ey_arcsec", "ez_arcsec")
DIRECTIONS = ("dx_um", "dy_um", "dz_um", "rx_arcsec", "ry_arcsec", "rz_arcsec")
BEFORE_AFTER_COLUMNS = ("source", "quantity", "unit", "statistic", "n_before", "n_after", "before", "after",
                        "improvement_pct", "seed_before", "seed_after", "seed_improvement_pct",
                        "noise_floor_before", "noise_floor_after", "model_uncertainty_after",
                        "model_predicted_before", "model_predicted_after")


# --------------------------------------------------------------------------------------------
# Formatting helpers
# --------------------------------------------------------------------------------------------


def is_missing(v) -> bool:
    """True for None, NaN, ±inf and pandas' NA."""
    if v is None or v is pd.NA:
        return True
    try:
        return not math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def fmt(v, decimals: int = 2) -> str:
    """A number with fixed decimals, "–" when missing."""
    return DASH if is_missing(v) else f"{float(v):.{decimals}f}"


def fmt_g(v, digits: int = 4) -> str:
    """A number with ``digits`` significant digits (scientific notation when needed), "–" when missing."""
    return DASH if is_missing(v) else f"{float(v):.{digits}g}"


def fmt_unit(v, unit: str) -> str:
    """A number in µm (2 decimals) or arcsec (1 decimal); other units 4 significant digits."""
    return fmt(v, DECIMALS[unit]) if unit in DECIMALS else fmt_g(v)


def u_decimals(uncertainty) -> int | None:
    """Decimal places that show ``uncertainty`` with two significant digits (0…8); None when it is
    missing or not positive."""
    if is_missing(uncertainty) or float(uncertainty) <= 0:
        return None
    return min(max(0, 1 - math.floor(math.log10(float(uncertainty)))), 8)


def fmt_pm(value, uncertainty) -> str:
    """``value ± u`` with u rounded to two significant digits and the value to the same decimal
    place (GUM convention); the value alone (4 significant digits) when u is missing or zero."""
    if is_missing(value):
        return DASH
    decimals = u_decimals(uncertainty)
    if decimals is None:
        return f"{float(value):.4g} ± {DASH}"
    return f"{float(value):.{decimals}f} ± {float(uncertainty):.{decimals}f}"


def escape_cell(text) -> str:
    """Cell text safe inside a Markdown pipe table (pipes escaped, line breaks flattened)."""
    return str(text).replace("\\", "\\\\").replace("|", "\\|").replace("\r", " ").replace("\n", " ")


def md_table(headers: Sequence[str], rows: Sequence[Sequence], align: str | None = None) -> str:
    """A Markdown pipe table. ``align``: one character per column, "l" or "r" (default: first
    column left, the others right). Cells are converted with ``str`` and escaped."""
    align = align or "l" + "r" * (len(headers) - 1)
    sep = ["---:" if a == "r" else "---" for a in align]
    lines = ["| " + " | ".join(escape_cell(h) for h in headers) + " |", "|" + "|".join(sep) + "|"]
    lines += ["| " + " | ".join(escape_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def for_campaign(df: pd.DataFrame | None, campaign_id: str) -> pd.DataFrame | None:
    """Rows of ``campaign_id`` when the frame has a ``campaign_id`` column (lake tables read for
    every campaign); the frame unchanged otherwise; None for None."""
    if df is None or "campaign_id" not in df.columns:
        return df
    return df[df["campaign_id"].astype(str) == str(campaign_id)]


def column(df: pd.DataFrame, name: str) -> pd.Series:
    """Column ``name`` as floats, or NaN everywhere when the frame lacks it."""
    if name in df.columns:
        return pd.to_numeric(df[name], errors="coerce").astype(float)
    return pd.Series(np.nan, index=df.index, dtype=float)


# --------------------------------------------------------------------------------------------
# Before / after compensation (Fig. 13)
# --------------------------------------------------------------------------------------------


def _stats(values: pd.Series) -> dict[str, float]:
    """n, mean, max, std (ddof = 1; 0 for a single value) of the finite values, as in
    ``tasks.simulation.truth_stats.summarise``."""
    v = values.to_numpy(dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0, "mean": np.nan, "max": np.nan, "std": np.nan}
    return {"n": int(v.size), "mean": float(v.mean()), "max": float(v.max()),
            "std": float(v.std(ddof=1)) if v.size > 1 else 0.0}


def improvement_rate(before: float, after: float) -> float:
    """Improvement rate 100·(1 − after/before) (%), NaN when either is missing or before is 0."""
    if is_missing(before) or is_missing(after) or before == 0:
        return np.nan
    return 100.0 * (1.0 - after / before)


def _phase(verification: pd.DataFrame, source: str, phase: str) -> pd.DataFrame:
    v = verification
    return v[(v["source"].astype(str) == source) & (v["phase"].astype(str) == phase)]


def before_after_table(verification: pd.DataFrame) -> pd.DataFrame:
    """Before/after statistics of the tip error over the validation poses, beside the seed's.

    verification: the report's verification frame (columns source, phase, position_um,
    orientation_arcsec; optional tool_direction_arcsec and noise_floor_<quantity column>).
    Returns one row per source present ("vbm", then "truth"), quantity ("position" in µm,
    "orientation" and, when the frame has its column, "tool direction" in arcsec) and statistic
    ("mean", "max", "std" with ddof = 1), columns
    :data:`BEFORE_AFTER_COLUMNS`: n_before/n_after (poses with a finite value), before, after,
    improvement_pct = 100·(1 − after/before) on the mean rows only (NaN on max/std rows),
    seed_before/seed_after (SEED_BEFORE/SEED_AFTER, same unit; NaN for the tool direction),
    seed_improvement_pct (the seed's published 96.1 / 67.4 % on the mean rows), noise_floor_before/after
    (mean over the poses of the expected error norm from measurement noise alone; on the VBM mean rows
    only, NaN when not given),
    model_uncertainty_after (mean expected error norm after compensation from the identified model's
    uncertainty; on the mean rows, NaN when not given), model_predicted_before/after (mean error norm
    the identified model itself predicts at the phase's commands, column model_predicted_<quantity
    column>; on the mean rows, NaN when not given).
    """
    rows = []
    present = set(verification["source"].astype(str)) if "source" in verification.columns else set()
    for source in [s for s in SOURCES if s in present]:
        for quantity, col, unit in QUANTITIES:
            if col not in verification.columns:
                continue
            phases = {p: _phase(verification, source, p) for p in ("before", "after")}
            stats = {p: _stats(column(f, col)) for p, f in phases.items()}
            floor = {p: _stats(column(f, f"noise_floor_{col}"))["mean"] if source == "vbm" else np.nan
                     for p, f in phases.items()}
            expected = _stats(column(phases["after"], f"model_uncertainty_{col}"))["mean"]
            predicted = {p: _stats(column(f, f"model_predicted_{col}"))["mean"] for p, f in phases.items()}
            for stat in STATISTICS:
                key = f"{quantity}_{stat}_{unit}"
                mean_row = stat == "mean"
                rows.append({
                    "source": source, "quantity": quantity, "unit": unit, "statistic": stat,
                    "n_before": stats["before"]["n"], "n_after": stats["after"]["n"],
                    "before": stats["before"][stat], "after": stats["after"][stat],
                    "improvement_pct": (improvement_rate(stats["before"][stat], stats["after"][stat])
                                        if mean_row else np.nan),
                    "seed_before": SEED_BEFORE.get(key, np.nan), "seed_after": SEED_AFTER.get(key, np.nan),
                    "seed_improvement_pct": SEED_IMPROVEMENT_PCT.get(quantity, np.nan) if mean_row else np.nan,
                    "noise_floor_before": floor["before"] if mean_row else np.nan,
                    "noise_floor_after": floor["after"] if mean_row else np.nan,
                    "model_uncertainty_after": expected if mean_row else np.nan,
                    "model_predicted_before": predicted["before"] if mean_row else np.nan,
                    "model_predicted_after": predicted["after"] if mean_row else np.nan,
                })
    return pd.DataFrame(rows, columns=list(BEFORE_AFTER_COLUMNS))


def format_before_after(table: pd.DataFrame) -> str:
    """:func:`before_after_table` as Markdown (noise-floor columns only when any is given)."""
    floors = bool(table[["noise_floor_before", "noise_floor_after"]].notna().any().any())
    headers = ["Source", "Quantity", "Statistic", "n before / after", "Before", "After", "Improvement (%)",
               "Seed before", "Seed after", "Seed improvement (%)"]
    if floors:
        headers += ["Noise floor before", "Noise floor after"]
    expected = bool(table["model_uncertainty_after"].notna().any())
    if expected:
        headers += ["Model uncertainty after"]
    predicted = bool(table[["model_predicted_before", "model_predicted_after"]].notna().any().any())
    if predicted:
        headers += ["Model predicts before", "Model predicts after"]
    rows = []
    for r in table.itertuples(index=False):
        row = [SOURCE_LABEL.get(r.source, r.source), f"{r.quantity} ({UNIT_LABEL[r.unit]})", r.statistic,
               f"{r.n_before} / {r.n_after}", fmt_unit(r.before, r.unit), fmt_unit(r.after, r.unit),
               fmt(r.improvement_pct, 1), fmt_unit(r.seed_before, r.unit), fmt_unit(r.seed_after, r.unit),
               fmt(r.seed_improvement_pct, 1)]
        if floors:
            row += [fmt_unit(r.noise_floor_before, r.unit), fmt_unit(r.noise_floor_after, r.unit)]
        if expected:
            row += [fmt_unit(r.model_uncertainty_after, r.unit)]
        if predicted:
            row += [fmt_unit(r.model_predicted_before, r.unit), fmt_unit(r.model_predicted_after, r.unit)]
        rows.append(row)
    return md_table(headers, rows, "lll" + "r" * (len(headers) - 3))


def seed_rate_note() -> str:
    """A sentence: the seed's published rates against the rates its own published means give."""
    pos = improvement_rate(SEED_BEFORE["position_mean_um"], SEED_AFTER["position_mean_um"])
    ori = improvement_rate(SEED_BEFORE["orientation_mean_arcsec"], SEED_AFTER["orientation_mean_arcsec"])
    return (f"The seed's published improvement rates ({SEED_IMPROVEMENT_PCT['position']:.1f} % position, "
            f"{SEED_IMPROVEMENT_PCT['orientation']:.1f} % orientation) do not follow exactly from its own "
            f"published means: 1 − {SEED_AFTER['position_mean_um']:.2f}/{SEED_BEFORE['position_mean_um']:.1f} "
            f"= {pos:.1f} % and 1 − {SEED_AFTER['orientation_mean_arcsec']:.1f}/"
            f"{SEED_BEFORE['orientation_mean_arcsec']:.0f} = {ori:.1f} %. This report computes the rate as "
            "1 − after/before of the means.")


def vbm_vs_truth(verification: pd.DataFrame) -> pd.DataFrame:
    """How far the VBM measurement of each validation pose is from the simulator's truth.

    Pairs "vbm" and "truth" rows by (pose, phase). Returns one row per phase with n (pairs),
    position_rms_um = sqrt(mean ‖(dx, dy, dz)_vbm − (dx, dy, dz)_truth‖²) (µm),
    orientation_rms_arcsec, the same for (rx, ry, rz) (arcsec), and the mean noise floors
    (µm, arcsec; NaN when not given). Empty when either source or a component column is missing.
    """
    cols = ["phase", "n", "position_rms_um", "orientation_rms_arcsec", "noise_floor_position_um",
            "noise_floor_orientation_arcsec"]
    needed = {"pose", "phase", "source", *DIRECTIONS}
    if not needed <= set(verification.columns):
        return pd.DataFrame(columns=cols)
    vbm = verification[verification["source"].astype(str) == "vbm"]
    truth = verification[verification["source"].astype(str) == "truth"]
    pairs = vbm.merge(truth[["pose", "phase", *DIRECTIONS]], on=["pose", "phase"], suffixes=("", "_truth"))
    rows = []
    for phase in ("before", "after"):
        p = pairs[pairs["phase"].astype(str) == phase]
        if p.empty:
            continue
        d = np.stack([column(p, c) - column(p, f"{c}_truth") for c in DIRECTIONS], axis=1)
        rows.append({"phase": phase, "n": len(p),
                     "position_rms_um": float(np.sqrt(np.nanmean(np.sum(d[:, :3] ** 2, axis=1)))),
                     "orientation_rms_arcsec": float(np.sqrt(np.nanmean(np.sum(d[:, 3:] ** 2, axis=1)))),
                     "noise_floor_position_um": float(column(p, "noise_floor_position_um").mean()),
                     "noise_floor_orientation_arcsec": float(column(p, "noise_floor_orientation_arcsec").mean())})
    return pd.DataFrame(rows, columns=cols)


def format_vbm_vs_truth(table: pd.DataFrame) -> str:
    """:func:`vbm_vs_truth` as Markdown."""
    rows = [[r.phase, r.n, fmt(r.position_rms_um, 2), fmt(r.orientation_rms_arcsec, 1),
             fmt(r.noise_floor_position_um, 2), fmt(r.noise_floor_orientation_arcsec, 1)]
            for r in table.itertuples(index=False)]
    return md_table(["Phase", "Poses", "RMS ‖VBM − truth‖ position (µm)", "RMS ‖VBM − truth‖ orientation (arcsec)",
                     "Mean noise floor position (µm)", "Mean noise floor orientation (arcsec)"], rows)


# --------------------------------------------------------------------------------------------
# Single-direction errors before calibration (Fig. 12)
# --------------------------------------------------------------------------------------------


def direction_stats(verification: pd.DataFrame, phase: str = "before") -> pd.DataFrame:
    """Per source and direction (dx/dy/dz µm, rx/ry/rz arcsec) of one phase: n, mean, std (ddof = 1),
    min, max, and the seed's Fig. 12 std and range (before calibration only)."""
    rows = []
    present = set(verification["source"].astype(str)) if "source" in verification.columns else set()
    for source in [s for s in SOURCES if s in present]:
        f = _phase(verification, source, phase)
        for c in DIRECTIONS:
            v = column(f, c).dropna()
            s = _stats(v)
            rows.append({"source": source, "direction": c, "unit": c.rsplit("_", 1)[1], "n": s["n"],
                         "mean": s["mean"], "std": s["std"], "min": float(v.min()) if len(v) else np.nan,
                         "max": s["max"], "seed_std": SEED_DIRECTION_STD[c] if phase == "before" else np.nan,
                         "seed_range": SEED_DIRECTION_RANGE[c] if phase == "before" else ""})
    return pd.DataFrame(rows, columns=["source", "direction", "unit", "n", "mean", "std", "min", "max", "seed_std",
                                       "seed_range"])


def format_direction_stats(table: pd.DataFrame) -> str:
    """:func:`direction_stats` as Markdown."""
    rows = [[SOURCE_LABEL.get(r.source, r.source), r.direction.rsplit("_", 1)[0], UNIT_LABEL[r.unit], r.n,
             fmt_unit(r.mean, r.unit), fmt_unit(r.std, r.unit), fmt_unit(r.min, r.unit), fmt_unit(r.max, r.unit),
             fmt(r.seed_std, 2), r.seed_range or DASH]
            for r in table.itertuples(index=False)]
    return md_table(["Source", "Direction", "Unit", "Poses", "Mean", "Std", "Min", "Max", "Seed std", "Seed range"],
                    rows, "llll" + "r" * 6)


# --------------------------------------------------------------------------------------------
# PDGE (Figs. 10 and 11)
# --------------------------------------------------------------------------------------------


def axes_in(pdge: pd.DataFrame) -> list[str]:
    """Axes of the pdge frame, in the machine's order (X, Y, Z, A, C) then any others."""
    present = list(dict.fromkeys(pdge["axis"].astype(str))) if "axis" in pdge.columns else []
    return [a for a in SEED_PDGE_MEANS if a in present] + [a for a in present if a not in SEED_PDGE_MEANS]


def norms(df: pd.DataFrame, cols: Sequence[str]) -> np.ndarray:
    """Row-wise Euclidean norm of three columns (NaN where any is missing)."""
    return np.sqrt(sum(column(df, c).to_numpy() ** 2 for c in cols))


def translation_rotation(pdge: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """(translation_um, rotation_arcsec) per row: the given norm columns, else the norms of the
    measured 3-vectors."""
    t = column(pdge, "translation_um").to_numpy() if "translation_um" in pdge.columns else norms(pdge, TRANSLATION)
    r = column(pdge, "rotation_arcsec").to_numpy() if "rotation_arcsec" in pdge.columns else norms(pdge, ROTATION)
    return t, r


def _normal_fit(values: np.ndarray) -> tuple[float, float]:
    """(μ, σ) of scipy.stats.norm.fit (maximum likelihood) on the finite values; NaN if none."""
    from scipy import stats

    v = values[np.isfinite(values)]
    if v.size == 0:
        return np.nan, np.nan
    mu, sigma = stats.norm.fit(v)
    return float(mu), float(sigma)


def pdge_magnitudes(pdge: pd.DataFrame) -> pd.DataFrame:
    """Fig. 11 statistics per axis: positions, mean of the measured translational (µm) and
    rotational (arcsec) PDGE magnitude, the normal fit (μ, σ), the truth's mean magnitude
    (norm of the truth 3-vectors; NaN when not simulated) and the seed's Fig. 11 mean."""
    rows = []
    for axis in axes_in(pdge):
        g = pdge[pdge["axis"].astype(str) == axis]
        t, r = translation_rotation(g)
        (tmu, tsd), (rmu, rsd) = _normal_fit(t), _normal_fit(r)
        seed = SEED_PDGE_MEANS.get(axis, (np.nan, np.nan))
        rows.append({"axis": axis, "n": len(g),
                     "translation_mean_um": float(np.nanmean(t)) if np.isfinite(t).any() else np.nan,
                     "translation_fit_mu_um": tmu, "translation_fit_sigma_um": tsd,
                     "translation_truth_mean_um": _nanmean(norms(g, [f"truth_{c}" for c in TRANSLATION])),
                     "seed_translation_mean_um": seed[0],
                     "rotation_mean_arcsec": float(np.nanmean(r)) if np.isfinite(r).any() else np.nan,
                     "rotation_fit_mu_arcsec": rmu, "rotation_fit_sigma_arcsec": rsd,
                     "rotation_truth_mean_arcsec": _nanmean(norms(g, [f"truth_{c}" for c in ROTATION])),
                     "seed_rotation_mean_arcsec": seed[1]})
    return pd.DataFrame(rows)


def _nanmean(v: np.ndarray) -> float:
    v = np.asarray(v, dtype=float)
    return float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else np.nan


def format_pdge_magnitudes(table: pd.DataFrame, simulated: bool) -> str:
    """:func:`pdge_magnitudes` as Markdown (truth columns when simulated)."""
    headers = ["Axis", "Positions", "Transl. mean (µm)", "Normal fit μ ± σ (µm)"]
    headers += ["Truth transl. mean (µm)"] if simulated else []
    headers += ["Seed Fig. 11 (µm)", "Rot. mean (arcsec)", "Normal fit μ ± σ (arcsec)"]
    headers += ["Truth rot. mean (arcsec)"] if simulated else []
    headers += ["Seed Fig. 11 (arcsec)"]
    rows = []
    for r in table.itertuples(index=False):
        row = [r.axis, r.n, fmt(r.translation_mean_um, 2),
               f"{fmt(r.translation_fit_mu_um, 2)} ± {fmt(r.translation_fit_sigma_um, 2)}"]
        row += [fmt(r.translation_truth_mean_um, 2)] if simulated else []
        row += [fmt(r.seed_translation_mean_um, 2), fmt(r.rotation_mean_arcsec, 1),
                f"{fmt(r.rotation_fit_mu_arcsec, 1)} ± {fmt(r.rotation_fit_sigma_arcsec, 1)}"]
        row += [fmt(r.rotation_truth_mean_arcsec, 1)] if simulated else []
        row += [fmt(r.seed_rotation_mean_arcsec, 1)]
        rows.append(row)
    return md_table(headers, rows)


def _rms_norm(df: pd.DataFrame, cols: Sequence[str], ref: str) -> float:
    """sqrt(mean over rows of ‖c − ref_c‖²) over the three columns (rows with all six finite)."""
    d = np.stack([column(df, c).to_numpy() - column(df, f"{ref}_{c}").to_numpy() for c in cols], axis=1)
    ok = np.isfinite(d).all(axis=1)
    return float(np.sqrt(np.mean(np.sum(d[ok] ** 2, axis=1)))) if ok.any() else np.nan


def _mean_z2(df: pd.DataFrame, cols: Sequence[str], ref: str) -> float:
    """Mean of ((c − ref_c)/std_c)² over components and rows with a positive finite std_c."""
    z = np.concatenate([(column(df, c) - column(df, f"{ref}_{c}")).to_numpy() / column(df, f"std_{c}").to_numpy()
                        for c in cols])
    s = np.concatenate([column(df, f"std_{c}").to_numpy() for c in cols])
    ok = np.isfinite(z) & (s > 0)
    return float(np.mean(z[ok] ** 2)) if ok.any() else np.nan


def pdge_quality(pdge: pd.DataFrame) -> pd.DataFrame:
    """Fig. 10 measurement quality per axis.

    n (positions), images_mean (mean n_images per position), se_translation_um /
    se_rotation_arcsec (RMS of the standard errors std_c over components and positions),
    fit_rms_* and truth_rms_* (sqrt of the mean squared norm of the measured − fitted and measured
    − truth 3-vectors, µm / arcsec), fit_z2 / truth_z2 (mean of ((measured − reference)/std)²
    over the six components: ≈ 1 when the standard errors are honest and the reference is right;
    below 1 against the fit, which has absorbed some noise).
    """
    rows = []
    for axis in axes_in(pdge):
        g = pdge[pdge["axis"].astype(str) == axis]
        se_t = np.concatenate([column(g, f"std_{c}").to_numpy() for c in TRANSLATION])
        se_r = np.concatenate([column(g, f"std_{c}").to_numpy() for c in ROTATION])
        rows.append({"axis": axis, "n": len(g), "images_mean": float(column(g, "n_images").mean()),
                     "se_translation_um": _rms(se_t), "se_rotation_arcsec": _rms(se_r),
                     "fit_rms_um": _rms_norm(g, TRANSLATION, "fit"), "fit_rms_arcsec": _rms_norm(g, ROTATION, "fit"),
                     "truth_rms_um": _rms_norm(g, TRANSLATION, "truth"),
                     "truth_rms_arcsec": _rms_norm(g, ROTATION, "truth"),
                     "fit_z2": _mean_z2(g, (*TRANSLATION, *ROTATION), "fit"),
                     "truth_z2": _mean_z2(g, (*TRANSLATION, *ROTATION), "truth")})
    return pd.DataFrame(rows)


def _rms(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else np.nan


def format_pdge_quality(table: pd.DataFrame, simulated: bool) -> str:
    """:func:`pdge_quality` as Markdown (truth columns when simulated)."""
    headers = ["Axis", "Positions", "Images / position", "RMS s.e. transl. (µm)", "RMS s.e. rot. (arcsec)",
               "RMS meas − fit transl. (µm)", "RMS meas − fit rot. (arcsec)", "Mean z² vs fit"]
    if simulated:
        headers += ["RMS meas − truth transl. (µm)", "RMS meas − truth rot. (arcsec)", "Mean z² vs truth"]
    rows = []
    for r in table.itertuples(index=False):
        row = [r.axis, r.n, fmt(r.images_mean, 1), fmt(r.se_translation_um, 3), fmt(r.se_rotation_arcsec, 2),
               fmt(r.fit_rms_um, 3), fmt(r.fit_rms_arcsec, 2), fmt(r.fit_z2, 2)]
        if simulated:
            row += [fmt(r.truth_rms_um, 3), fmt(r.truth_rms_arcsec, 2), fmt(r.truth_z2, 2)]
        rows.append(row)
    return md_table(headers, rows)


# --------------------------------------------------------------------------------------------
# PIGE identification (Table 6)
# --------------------------------------------------------------------------------------------

KIND_ORDER = {"pige": 0, "mount": 1, "constant": 2}


def _identifiable(r: dict) -> bool:
    """A parameter counts as identified only when flagged identifiable and its value is finite."""
    flag = r.get("identifiable", True)
    return bool(flag) and not is_missing(flag) and not is_missing(r.get("value"))


def pige_rows(pige: pd.DataFrame) -> list[dict]:
    """The PIGE frame's records ordered by kind (pige, mount, constant, other), input order within."""
    recs = pige.to_dict("records")
    return sorted(recs, key=lambda r: KIND_ORDER.get(str(r.get("kind", "")), len(KIND_ORDER)))


def deviation_over_u(r: dict) -> float:
    """|value − truth| / uncertainty (truth in the identification's gauge), NaN when any is missing."""
    if not _identifiable(r) or is_missing(r.get("truth")) or is_missing(r.get("uncertainty")):
        return np.nan
    u = float(r["uncertainty"])
    return abs(float(r["value"]) - float(r["truth"])) / u if u > 0 else np.nan


def _like_estimate(v, decimals: int | None) -> str:
    """A truth value with the estimate's decimal places (4 significant digits without them)."""
    return fmt_g(v) if decimals is None else fmt(v, decimals)


UNCERTAINTY_PARTS = {"uncertainty_fit": "u fit", "uncertainty_noise": "u noise", "uncertainty_camera": "u camera"}
"""The parts of a propagated uncertainty (the pige table's columns) and their Table 6 headers."""


def format_pige(pige: pd.DataFrame, simulated: bool) -> str:
    """Table 6 as Markdown: estimate ± standard uncertainty, unit, truth (identification gauge and
    the simulator's raw PIGE) and |value − truth|/u when simulated. Unidentifiable parameters show
    the word "unidentifiable" in place of every estimate-derived cell, never a number."""
    parts = [c for c in UNCERTAINTY_PARTS if c in pige.columns and pige[c].notna().any()]
    headers = ["Parameter", "Kind", "Joint", "Estimate ± u", "Unit", *(UNCERTAINTY_PARTS[c] for c in parts)]
    if simulated:
        headers += ["Truth (identification gauge)", "Truth (simulator PIGE)", "abs(est − truth)/u"]
    headers += ["Note"]
    rows = []
    for r in pige_rows(pige):
        unit = str(r.get("unit", ""))
        ident = _identifiable(r)
        row = [r.get("name", ""), r.get("kind", ""), r.get("joint", ""),
               fmt_pm(r["value"], r.get("uncertainty")) if ident else UNIDENTIFIABLE, UNIT_LABEL.get(unit, unit)]
        d = u_decimals(r.get("uncertainty")) if ident else None
        row += [_like_estimate(r.get(c), u_decimals(r.get(c))) if ident else DASH for c in parts]
        if simulated:
            row += [_like_estimate(r.get("truth"), d), _like_estimate(r.get("truth_nominal"), d),
                    fmt(deviation_over_u(r), 2) if ident else DASH]
        note = r.get("note", "")
        row += [DASH if is_missing(note) or note == "" else note]
        rows.append(row)
    return md_table(headers, rows, "llll" + "l" + "r" * len(parts) + ("rrr" if simulated else "") + "l")


def pige_coverage(pige: pd.DataFrame) -> dict[str, float]:
    """Calibration of the stated uncertainties against the truth: n (identifiable parameters with
    a truth and uncertainty), within_1u / within_2u (fractions with |value − truth| ≤ 1u / 2u;
    0.68 / 0.95 expected for honest Gaussian uncertainties), rms_z (≈ 1 expected),
    n_unidentifiable."""
    recs = pige.to_dict("records")
    z = np.array([deviation_over_u(r) for r in recs], dtype=float)
    z = z[np.isfinite(z)]
    return {"n": int(z.size), "within_1u": float(np.mean(z <= 1)) if z.size else np.nan,
            "within_2u": float(np.mean(z <= 2)) if z.size else np.nan,
            "rms_z": float(np.sqrt(np.mean(z ** 2))) if z.size else np.nan,
            "n_unidentifiable": sum(not _identifiable(r) for r in recs)}


# --------------------------------------------------------------------------------------------
# Camera calibration (Table 3), detectors (Table 4), formulations (Table 5)
# --------------------------------------------------------------------------------------------

CAMERA_COLUMNS = {"camera", "trial", "status", "rms_px"}
DISTORTION = ("k1", "k2", "p1", "p2", "k3")


def format_table3(camera_calibration: pd.DataFrame) -> str:
    """The seed's Table 3 (``tasks.vision.camera_calibration.table3`` of the trial rows, the ``joint``
    rows left out): reprojection RMS (px) per trial and camera, then mean and std over ok trials."""
    from tasks.vision.camera_calibration import table3

    trials = camera_calibration[camera_calibration["trial"].astype(str) != "joint"]
    wide = table3(trials)
    cams = [str(c) for c in wide.columns]
    status = {(str(r["trial"]), str(r["camera"])): str(r["status"]) for r in trials.to_dict("records")}
    rows = []
    for trial, values in wide.iterrows():
        cells = []
        for cam, v in zip(cams, values, strict=True):
            failed = status.get((str(trial), cam), "ok") != "ok"
            cells.append(f"{fmt(v, 4)} ({status[(str(trial), cam)]})" if failed else fmt(v, 4))
        rows.append([trial, *cells])
    return md_table(["Trial", *[f"{c}: RMS (px)" for c in cams]], rows)


def format_joint_intrinsics(camera_calibration: pd.DataFrame) -> str | None:
    """The ``joint`` rows (best estimate per camera): images, RMS (px), intrinsics ± std; None
    without joint rows."""
    joint = camera_calibration[camera_calibration["trial"].astype(str) == "joint"]
    if joint.empty:
        return None
    names = ("fx_px", "fy_px", "cx_px", "cy_px", *DISTORTION)
    rows = [[r.get("camera"), r.get("status"), r.get("n_images", DASH), fmt(r.get("rms_px"), 4),
             *[fmt_pm(r.get(n), r.get(f"std_{n}")) for n in names]] for r in joint.to_dict("records")]
    return md_table(["Camera", "Status", "Images", "RMS (px)", "fx (px)", "fy (px)", "cx (px)", "cy (px)",
                     *DISTORTION], rows, "ll" + "r" * (len(names) + 2))


def distortion_check(camera_calibration: pd.DataFrame, limit: float = 0.4) -> str | None:
    """A sentence per camera: the largest |k1|, |k2|, |p1|, |p2|, |k3| over ok trials against the
    seed's bound (all five below 0.4). None without the distortion columns."""
    if not set(DISTORTION) <= set(camera_calibration.columns):
        return None
    ok = camera_calibration[(camera_calibration["status"].astype(str) == "ok")
                            & (camera_calibration["trial"].astype(str) != "joint")]
    parts = []
    for cam, g in ok.groupby("camera", sort=True):
        worst = g[list(DISTORTION)].abs().max()
        name = str(worst.idxmax())
        parts.append(f"{cam}: max |{name}| = {worst.max():.3f} ({'below' if worst.max() < limit else 'NOT below'} "
                     f"{limit})")
    if not parts:
        return None
    return "Largest distortion coefficient over the ok trials — " + "; ".join(parts) + \
        f". The seed: all five below {limit} in every trial."


def format_table5(formulations: pd.DataFrame) -> str:
    """The seed's Table 5 (formulation comparison) as Markdown: ms and error norms (µm, arcsec)."""
    rows = [[r.get("formulation", ""), fmt_g(r.get("mean_single_run_ms")), fmt_g(r.get("total_300_ms")),
             fmt_g(r.get("position_error_norm_um")), fmt_g(r.get("orientation_error_norm_arcsec")),
             DASH if is_missing(r.get("note")) or r.get("note") == "" else r.get("note")]
            for r in formulations.to_dict("records")]
    return md_table(["Formulation", "Mean single run (ms)", "Total, 300 sets (ms)", "Position error norm (µm)",
                     "Orientation error norm (arcsec)", "Note"], rows, "lrrrrl")
