"""Is the model uncertainty after compensation honest? Seed by seed, against the simulator's truth.

For each calibrated campaign ``<campaigns>/s<seed>`` (its lake under ``--results``: run
``bench/seed_panel.py`` first) the calibration and the propagation of its uncertainty are re-run
from the lake's poses (no images; about a minute per seed), and the true tip error after
compensation is set beside what the propagation states:

- ``true``: mean true tip position error after (µm), the ``verification`` table's truth rows;
  ``const``: the norm of its constant tool-frame vector c (the split of ``bench/seed_panel.py``);
- ``u``: the model uncertainty after (µm): the mean over the validation poses of √(E|Δtip|²),
  the ``verification`` table's ``model_uncertainty_position_um``; ``true/u``;
- ``σ1 σ2 σ3``: the standard deviations along the principal axes of Σ_c, the stated covariance of
  the constant tool-frame vector (:func:`tasks.identification.uncertainty.tool_frame_offset_covariance`);
- ``m2``: cᵀ Σ_c⁻¹ c, χ² with 3 degrees of freedom if the stated uncertainty is right, and its
  upper-tail ``p``;
- ``p_lo``, ``p_hi``: for a Gaussian error of exactly the stated covariance, the chance that its
  norm falls below u/3 (u would be "more than 3× the error") or above 2u (Monte Carlo);
- ``intr``: |c − G·Δθ|, what is left of c once the tip is corrected by the intrinsics' true error
  Δθ (truth − estimate, every camera; G the tip's linear response to the intrinsics, from the
  propagation's camera re-fits): the part of the error the intrinsics do not explain;
- ``m2_<camera>``: Δθᵀ Σ_θ⁻¹ Δθ over (f, cx, cy, k1, k2, p1, p2) of each camera's self-calibration,
  χ² with 7 degrees of freedom if its stated covariance
  (:func:`tasks.vision.intrinsics_uncertainty.intrinsics_covariance`) is right.

Below the table: the pooled mean of m2 / 3 (1 for an honest uncertainty), the pooled m2 per camera
/ 7, and the chance that a panel of these seeds with exactly honest uncertainties has every seed
within "true ≤ 2u and u ≤ 3 true" (the product of the seeds' 1 − p_lo − p_hi).

    python bench/tip_uncertainty.py --seeds 10 67 161 --campaigns C --results R
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats
from seed_panel import split_tip_error

from flows.calibrate import read_measured_campaign
from tasks.analysis.compensation import desired_tip_poses
from tasks.analysis.residuals import plates_of
from tasks.identification.calibration import calibrate
from tasks.identification.uncertainty import (
    propagate_uncertainty,
    tool_frame_offset_changes,
    tool_frame_offset_covariance,
)
from tasks.lake.store import read_table
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import AXIS_ORDER, CALIBRATION_STAGE
from tasks.vision.intrinsics_uncertainty import intrinsics_covariances, intrinsics_vector, pose_sensitivities

CHECKED_INTRINSICS = 7
"""f, cx, cy, k1, k2, p1, p2: the self-calibration holds k3 (tasks.vision.pipeline.FIX_K3)."""


def true_intrinsics_error(truth_camera: dict, camera: CameraModel) -> np.ndarray:
    """(8,) truth − estimate of θ (tasks.vision.intrinsics_uncertainty.INTRINSIC_PARAMETERS);
    truth_camera: the camera's entry of truth.json."""
    true = CameraModel(**{**truth_camera, "distortion": tuple(truth_camera["distortion"])})
    return intrinsics_vector(true) - intrinsics_vector(camera)


def gaussian_ratio_tails(cov: np.ndarray, u: float, draws: int = 200_000, seed: int = 0) -> tuple[float, float]:
    """(P(|e| < u/3), P(|e| > 2u)) for e ~ N(0, cov) (3, 3), u in the same unit as √cov."""
    w = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
    e2 = (np.random.default_rng(seed).standard_normal((draws, 3)) ** 2 * w).sum(axis=1)
    return float(np.mean(e2 < (u / 3) ** 2)), float(np.mean(e2 > (2 * u) ** 2))


def seed_check(campaign: Path, root: Path) -> dict:
    """The columns of the module docstring for one calibrated campaign."""
    c = read_measured_campaign(campaign, str(root))
    truth_cameras = json.loads((campaign / "truth" / "truth.json").read_text())["cameras"]
    result = calibrate(c.machine, c.measurements, c.truth)
    covs = intrinsics_covariances(c.dots, c.images, c.cameras, plates_of(c.machine, CALIBRATION_STAGE),
                                  plates_of(c.machine), c.machine.linear_axes)
    sens = pose_sensitivities(c.dots, c.measurements.table["image_id"].tolist(), c.measurements.T, c.cameras,
                              plates_of(c.machine), c.measurements.table["camera"].tolist())
    prop = propagate_uncertainty(c.machine, result, c.measurements, sens, covs)

    ver = read_table("verification", root, c.campaign_id)
    after = ver[(ver.phase == "after") & (ver.source == "truth")].set_index("image_id")
    comp = read_table("compensation", root, c.campaign_id).set_index("image_id").loc[after.index]
    compensated = comp[[f"{a}_compensated" for a in AXIS_ORDER]].to_numpy(float)
    R = desired_tip_poses(c.machine, comp[list(AXIS_ORDER)].to_numpy(float))[:, :3, :3]
    d = after[["dx_um", "dy_um", "dz_um"]].to_numpy(float)
    true, _, _ = split_tip_error(d, R)
    const = np.einsum("nji,nj->ni", R, d).mean(axis=0)
    u = float(after.model_uncertainty_position_um.mean())
    cov = tool_frame_offset_covariance(c.machine, result.model, prop, compensated, R)
    m2 = float(const @ np.linalg.solve(cov, const))
    p_lo, p_hi = gaussian_ratio_tails(cov, u)

    # the tip's linear response to each camera's intrinsics, from its re-fits at 1σ along the
    # eigen-directions of its covariance (propagate_uncertainty's order)
    explained, row = np.zeros(3), {}
    models = iter(prop.camera_models)
    for cam, cov_theta in covs.items():
        if not np.all(np.isfinite(cov_theta)):
            continue
        w, V = np.linalg.eigh(cov_theta)
        C = tool_frame_offset_changes(c.machine, result.model, [next(models) for _ in range(w.size)],
                                      compensated, R).T  # (3, 8)
        G = C @ np.diag(1.0 / np.sqrt(np.clip(w, 1e-300, None))) @ V.T
        dtheta = true_intrinsics_error(truth_cameras[cam], c.cameras[cam])
        explained += G @ dtheta
        k = CHECKED_INTRINSICS
        row[f"m2_{cam}"] = float(dtheta[:k] @ np.linalg.solve(cov_theta[:k, :k], dtheta[:k]))
    sig = np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0.0, None))
    return {"true": true, "const": float(np.linalg.norm(const)), "u": u, "true/u": true / u,
            "σ1": sig[0], "σ2": sig[1], "σ3": sig[2], "m2": m2, "p": float(stats.chi2.sf(m2, 3)),
            "p_lo": p_lo, "p_hi": p_hi, "intr": float(np.linalg.norm(const - explained)), **row}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 67, 161, 262, 497, 519, 619, 639, 848, 957])
    ap.add_argument("--campaigns", required=True, help="folder of the s<seed> campaigns")
    ap.add_argument("--results", required=True, help="their results lake (calibrated)")
    ap.add_argument("--csv", help="also write the table here")
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        rows.append({"seed": seed, **seed_check(Path(args.campaigns) / f"s{seed}", Path(args.results))})
        print(pd.DataFrame(rows[-1:]).to_string(index=False, float_format=lambda v: f"{v:.2f}"), flush=True)
    table = pd.DataFrame(rows)
    pd.set_option("display.width", 250)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    n = len(table)
    print(f"pooled m2/3 {table.m2.mean() / 3:.2f} (χ² {table.m2.sum():.1f} on {3 * n} dof: "
          f"lower tail {stats.chi2.cdf(table.m2.sum(), 3 * n):.3f}, upper {stats.chi2.sf(table.m2.sum(), 3 * n):.3f})")
    for col in [c for c in table.columns if c.startswith("m2_")]:
        s = table[col].sum()
        dof = CHECKED_INTRINSICS * n
        print(f"{col}: pooled /7 {s / dof:.2f} (upper tail {stats.chi2.sf(s, dof):.3f})")
    every = float(np.prod(1.0 - table.p_lo - table.p_hi))
    print(f"worst true/u {table['true/u'].max():.2f}, smallest {table['true/u'].min():.2f}; "
          f"chance that every seed meets 'true ≤ 2u and u ≤ 3 true' with exact uncertainties: {every:.2f}")
    if args.csv:
        table.to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
