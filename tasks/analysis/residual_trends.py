"""Does a residual follow a variable? One test per camera × variable × component, at a stated level.

SYNOPSIS
    >>> shared = shared_deviations(machine, result.model, propagated, measurements)   # (M, N, 6)
    >>> tests = trend_tests(residuals, shared)          # the `residual_trends` lake table
    >>> tests.significant.mean()                        # ≈ ALPHA on a campaign that lacks nothing

The question a panel of the residual figures asks is whether the residual *varies with* the
variable, so the test is on the differences between the bins' means, not on the means against zero:
a constant offset (a camera-frame rotation the fit leaves in the validation poses, say) follows no
variable and is not a trend. With b the K bin means and d = b − b̄ (b̄ their mean weighted by the
inverse of Σ), the statistic is dᵀ Σ⁺ d / (K − 1), Σ the covariance of the bin means, referred to
an F distribution with Welch's correction for variances estimated from each bin's own images
(Welch 1951, the one-way analysis of unequal variances; on 612 pure-noise panels 8.0 % were flagged
at 5 % without it, 6.9 % with it: tests/analysis/test_residuals.py):

    Σ = diag(s²_k / n_k) + Σ_shared

- s²_k / n_k: the scatter of the images within each bin (their own noise, whatever its size);
- Σ_shared: what the images of a campaign share, which the scatter within a bin cannot show: the
  identified model's own error. Every image's predicted pose comes from the same model; where the
  model is off (a PDGE profile that follows its sweep's noise, a constant known to ±u) the residuals
  of all images at that axis position move together. :func:`shared_deviations` takes it from the
  re-fitted models of the uncertainty propagation (:mod:`tasks.identification.uncertainty`: the
  camera intrinsics' directions at 1σ, the noise draws' spread): each re-fit changes every image's
  residual by the change of its predicted pose, and the bins' means of those changes span Σ_shared.

A panel is ``significant`` when p < ALPHA (5 %): on a campaign that lacks no effect, about one panel
in twenty. The tests are not corrected for their number: the share of flagged panels is the measure
(docs/residuals.md), and a missing effect flags the panels its signature reaches, not one.
Units: the residual's (µm, arcsec); variables in their own units.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats

from tasks.analysis.residuals import (
    CAMERA_COMPONENTS,
    CATEGORICAL_VARIABLES,
    TO_FILE_UNITS,
    TREND_VARIABLES,
    chain_constant_part,
)
from tasks.identification.measurements import Measurements
from tasks.identification.pige_identification import IDENTIFICATION_CAMERA, pose_residuals
from tasks.machine.description import CALIBRATION_STAGE, Machine
from tasks.machine.error_model import ErrorModel

ALPHA = 0.05
"""Level of each panel's test."""
TREND_COLUMNS = ("camera", "variable", "component", "bins", "span", "statistic", "p_value", "significant")
MIN_COUNT = 3


def bin_codes(x: np.ndarray, n_bins: int, categorical: bool) -> np.ndarray:
    """(N,) bin index of each x (−1 for a non-finite x): one bin per value (categorical) or up to
    ``n_bins`` equal-count bins (quantiles; tied values share a bin), as
    :func:`tasks.analysis.residuals.binned_mean` bins."""
    x = np.asarray(x, dtype=float)
    codes = np.full(x.size, -1)
    good = np.isfinite(x)
    if not good.any():
        return codes
    if categorical:
        codes[good] = np.unique(x[good], return_inverse=True)[1]
    else:
        edges = np.unique(np.quantile(x[good], np.linspace(0.0, 1.0, max(1, n_bins) + 1)))
        codes[good] = np.clip(np.searchsorted(edges, x[good], side="right") - 1, 0, max(len(edges) - 2, 0))
    return codes


def shared_deviations(machine: Machine, model: ErrorModel, propagated, measurements: Measurements) -> np.ndarray:
    """(M, N, 6) deviations of every image's camera-frame residual (µm, arcsec) that the model's own
    uncertainty makes, shared by all images: Σ_m D_m D_mᵀ is their covariance. One per camera
    direction of the propagation (its change at 1σ) and one per noise draw (centred, over √(n − 1)).

    propagated: a :class:`tasks.identification.uncertainty.PropagatedUncertainty` of ``model``.
    measurements: the campaign's; rows as in the ``residuals`` table (calibration views left out).
    Cameras outside the constant fit are taken, as the table takes them, against their chain's
    constant poses (:func:`tasks.analysis.residuals.chain_constant_part`)."""
    from tasks.identification.pige_identification import whitening

    keep = (measurements.table["stage"] != CALIBRATION_STAGE).to_numpy()
    m = measurements.select(keep)
    R = m.T[:, :3, :3]
    W = whitening(m.cov)
    cams = m.table["camera"].to_numpy()

    def residual(mod: ErrorModel) -> np.ndarray:
        e = pose_residuals(machine, mod, m)
        for camera in np.unique(cams[cams != IDENTIFICATION_CAMERA]):
            rows = cams == camera
            e[rows] -= chain_constant_part(m.T[rows], e[rows], W[rows])
        cam = np.concatenate([np.einsum("nij,nj->ni", R, e[:, :3]), np.einsum("nij,nj->ni", R, e[:, 3:])], axis=1)
        return cam * TO_FILE_UNITS

    ref = residual(model)
    out = [residual(mod) - ref for mod in propagated.camera_models]
    noise = [residual(mod) - ref for mod in propagated.noise_models]
    if len(noise) >= 2:
        noise = np.array(noise)
        out += list((noise - noise.mean(axis=0)) / np.sqrt(len(noise) - 1))
    return np.array(out).reshape(len(out), len(ref), 6)


def panel_test(x: np.ndarray, y: np.ndarray, n_bins: int = 10, categorical: bool = False,
               shared: np.ndarray | None = None) -> dict | None:
    """The test of one panel (module docstring). x, y: (N,). shared: (M, N) the shared deviations of
    y (None: none). Returns bins, span (max − min of the bin means), statistic (Welch's F), p_value; None
    when fewer than two bins hold MIN_COUNT points."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    good = np.isfinite(x) & np.isfinite(y)
    codes = bin_codes(np.where(good, x, np.nan), n_bins, categorical)
    labels, counts = np.unique(codes[codes >= 0], return_counts=True)
    labels = labels[counts >= MIN_COUNT]
    if labels.size < 2:
        return None
    member = codes[None, :] == labels[:, None]  # (K, N)
    n = member.sum(axis=1)
    means = (member * np.nan_to_num(y)).sum(axis=1) / n
    var = np.array([np.var(y[row], ddof=1) for row in member])
    cov = np.diag(var / n)
    if shared is not None and len(shared):
        S = (np.nan_to_num(shared) @ member.T) / n  # (M, K): each deviation's bin means
        cov = cov + S.T @ S
    inv = np.linalg.pinv(cov)
    one = np.ones(labels.size)
    centre = (one @ inv @ means) / (one @ inv @ one)
    d = means - centre
    k = labels.size
    # Welch's correction for variances estimated from the bins' own images (eq. of Welch 1951)
    w = n / np.maximum(var, 1e-300)
    a = float(np.sum((1.0 - w / w.sum()) ** 2 / (n - 1)))
    f = float(d @ inv @ d) / (k - 1) / (1.0 + 2.0 * (k - 2) * a / (k**2 - 1))
    dof2 = (k**2 - 1) / (3.0 * a) if a > 0 else np.inf
    return {"bins": int(k), "span": float(means.max() - means.min()), "statistic": f,
            "p_value": float(stats.f.sf(f, k - 1, dof2))}


def trend_tests(residuals: pd.DataFrame, shared: np.ndarray | None = None, n_bins: int = 10,
                components: Sequence[str] = CAMERA_COMPONENTS,
                variables: Sequence[str] = TREND_VARIABLES + CATEGORICAL_VARIABLES,
                alpha: float = ALPHA) -> pd.DataFrame:
    """The ``residual_trends`` table: one row per camera × variable × component whose variable
    varies for the camera (:data:`TREND_COLUMNS`; ``campaign_id`` is added by the writer).

    residuals: the ``residuals`` table. shared: (M, N, 6) :func:`shared_deviations` in the rows'
    order, components in :data:`tasks.analysis.residuals.CAMERA_COMPONENTS` order (None: the scatter within the
    bins alone). Sorted by p-value."""
    rows = []
    comp_index = {c: i for i, c in enumerate(CAMERA_COMPONENTS)}
    cams = residuals["camera"].astype(str).to_numpy()
    for camera in sorted(set(cams)):
        sel = cams == camera
        g = residuals[sel]
        for var in variables:
            x = g[var].to_numpy(dtype=float)
            if np.unique(x[np.isfinite(x)]).size < 2:
                continue
            for comp in components:
                sh = None if shared is None or comp not in comp_index else shared[:, sel, comp_index[comp]]
                t = panel_test(x, g[comp].to_numpy(dtype=float), n_bins, var in CATEGORICAL_VARIABLES, sh)
                if t is None:
                    continue
                rows.append({"camera": camera, "variable": var, "component": comp, **t,
                             "significant": bool(t["p_value"] < alpha)})
    out = pd.DataFrame(rows, columns=list(TREND_COLUMNS))
    return out.sort_values("p_value", kind="stable").reset_index(drop=True)
