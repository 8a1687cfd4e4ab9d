"""The dispensing test over a panel of simulated campaigns: is the tip closed, and is the model
uncertainty of the tip after the tip fit honest, seed by seed?

Reads each campaign's dispensing summary (``<reports>/<campaign_id>/<run>/dispensing/summary.json``,
the latest run), its ``verification`` table (the ``after`` and ``after_tip`` truth rows with their
``model_uncertainty_position_um``) and its ``dispense_inspection`` table, and prints per seed:

- ``true after``, ``const after``, ``u after``: the mean true tip position error after
  compensation, the norm of its constant tool-frame vector and the mean model uncertainty there
  (µm);
- ``true tip``: the mean true tip position error after the tip fit (the ``after_tip`` rows),
  ``const tip`` the norm of its constant tool-frame vector c (tip frame, the split of
  ``bench/seed_panel.py``), ``rest tip`` the mean norm of what varies from pose to pose and
  ``rest rms`` its rms, √(mean ‖e‖² − ‖c‖²);
- ``u tip``: the mean model uncertainty after the tip fit (tasks.dispensing.tip_uncertainty); split
  like the true error, ``u const`` √tr Σ_c (Σ_c the stated covariance of the constant tool-frame
  part) and ``u rest`` √(mean u² − tr Σ_c); and by source (the rms over the poses of each one's
  expected error: ``u cam`` the intrinsics, ``u noise`` the pose noise through the PDGEs and the
  fit, ``u fit`` the tip fit's dot noise);
- ``true/u``, and ``ok``: whether "true ≤ 2u and u ≤ 3 × true" holds (issue 32);
- ``ms``: mean over the poses of ‖e‖² / mean of u², 1 for an honest uncertainty (pose by pose the
  expected squared norm is u²);
- ``m2``: cᵀ Σ_c⁻¹ c: χ² on 3 degrees of freedom if Σ_c is right;
- the tip offset found, its tool-axis uncertainty, and the dots' measured − true offsets.

Then the median and the worst seed, and the pooled checks: Σ‖e‖² / Σu² over every pose of every
seed, Σ m2 against χ² on 3n degrees of freedom, and the same ratio of squares for each part
(the constant: Σ‖c‖² / Σ tr Σ_c; what varies: Σ rest rms² / Σ u rest²).

    .venv/bin/python bench/dispense_panel.py --campaigns C --results R --reports P CAMPAIGN_ID...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats
from seed_panel import split_tip_error

from tasks.analysis.compensation import desired_tip_poses
from tasks.campaign.ingest import load_campaign_metadata
from tasks.lake.store import read_table
from tasks.machine.description import AXIS_ORDER
from tasks.vision.pipeline import nominal_machine


def verification_rows(campaign: Path, campaign_id: str, results: Path, phase: str) -> tuple[np.ndarray, pd.DataFrame]:
    """(R (N, 3, 3) the desired tip orientations, the truth rows of ``phase``) in the order of the
    compensation table."""
    ver = read_table("verification", results, campaign_id)
    rows = ver[(ver.phase == phase) & (ver.source == "truth")].set_index("image_id")
    comp = read_table("compensation", results, campaign_id).set_index("image_id").loc[rows.index]
    machine = nominal_machine(load_campaign_metadata(campaign))
    return desired_tip_poses(machine, comp[list(AXIS_ORDER)].to_numpy(float))[:, :3, :3], rows


def panel_row(campaign: Path, results: Path, reports: Path) -> tuple[dict, np.ndarray, np.ndarray] | None:
    """(the seed's row, ‖e‖² (N,) and u² (N,) after the tip fit) of one campaign; None without a
    dispensing run."""
    campaign_id = load_campaign_metadata(campaign)["campaign_id"]
    runs = sorted((reports / campaign_id).glob("*/dispensing/summary.json"))
    if not runs:
        return None
    s = json.loads(runs[-1].read_text())
    t = s["truth"]
    _, after = verification_rows(campaign, campaign_id, results, "after")
    R, tip = verification_rows(campaign, campaign_id, results, "after_tip")
    d = tip[["dx_um", "dy_um", "dz_um"]].to_numpy(float)
    true, const, rest = split_tip_error(d, R)
    e2 = (d**2).sum(axis=1)
    u = tip["model_uncertainty_position_um"].to_numpy(float)
    c = np.asarray(t["constant_after_tip_um"])
    cov_c = np.asarray(s["after_tip_constant_covariance_um2"])
    m2 = float(c @ np.linalg.solve(cov_c, c))
    parts = s["model_uncertainty_after_tip_parts_um"]
    rows = read_table("dispense_inspection", results, campaign_id)
    good = rows[rows["qualified"]]
    ex, ey = good["dx_um"] - good["truth_dx_um"], good["dy_um"] - good["truth_dy_um"]
    row = {"campaign": campaign_id,
           "true after": float(after["position_um"].mean()),
           "const after": float(np.linalg.norm(t["constant_before_um"])),
           "u after": float(after["model_uncertainty_position_um"].mean()),
           "true tip": true, "const tip": const, "rest tip": rest, "u tip": float(u.mean()),
           "rest rms": float(np.sqrt(max(e2.mean() - c @ c, 0.0))),
           "u const": float(np.sqrt(np.trace(cov_c))),
           "u rest": float(np.sqrt(max(np.mean(u**2) - np.trace(cov_c), 0.0))),
           "u cam": parts["camera"], "u noise": parts["noise"], "u fit": parts["tip_fit"],
           "true/u": true / float(u.mean()), "ok": bool(true <= 2 * u.mean() and u.mean() <= 3 * true),
           "ms": float(e2.mean() / np.mean(u**2)), "m2": m2,
           "tip x": s["tip_offset_um"][0], "tip y": s["tip_offset_um"][1], "tip z": s["tip_offset_um"][2],
           "u z": s["tip_offset_uncertainty_um"][2],
           "meas−true x": float(ex.mean()), "meas−true y": float(ey.mean()),
           "rms meas−true": float(np.sqrt(np.mean(np.concatenate([ex, ey]) ** 2))),
           "fit dots": s["tip_fit_dots"], "qualified": f"{len(good)}/{len(rows)}"}
    return row, e2, u**2


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--campaigns", type=Path, required=True, help="folder of the campaign folders")
    p.add_argument("--results", type=Path, required=True)
    p.add_argument("--reports", type=Path, required=True)
    p.add_argument("campaigns_ids", nargs="+", metavar="CAMPAIGN", help="campaign folder names under --campaigns")
    a = p.parse_args()
    found = [r for c in a.campaigns_ids if (r := panel_row(a.campaigns / c, a.results, a.reports)) is not None]
    df = pd.DataFrame([r for r, _, _ in found])
    e2 = np.concatenate([e for _, e, _ in found])
    u2 = np.concatenate([u for _, _, u in found])
    with pd.option_context("display.width", 300, "display.max_columns", 40):
        print(df.round(2).to_string(index=False))
        num = df.select_dtypes("number")
        print("\nmedian:\n" + num.median().round(2).to_string())
        worst = df.loc[np.log(df["true/u"]).abs().idxmax()]
        print(f"\nworst seed (true/u farthest from 1 in ratio): {worst['campaign']}, true/u {worst['true/u']:.2f}; "
              f"true/u {df['true/u'].min():.2f}–{df['true/u'].max():.2f}; "
              f"'true ≤ 2u and u ≤ 3 true' on {int(df['ok'].sum())} of {len(df)} seeds")
        n = len(df)
        print(f"pooled Σ‖e‖²/Σu² over {len(e2)} poses: {e2.sum() / u2.sum():.2f}; "
              f"Σ m2 {df['m2'].sum():.1f} on {3 * n} dof (/3n {df['m2'].sum() / (3 * n):.2f}, "
              f"P(below) {stats.chi2.cdf(df['m2'].sum(), 3 * n):.2f})")
        rest_u2 = (df["u rest"] ** 2).sum()
        print(f"which part: Σ‖c‖²/Σ tr Σ_c {(df['const tip'] ** 2).sum() / (df['u const'] ** 2).sum():.2f} "
              f"(the constant), Σ rest rms²/Σ u rest² {(df['rest rms'] ** 2).sum() / rest_u2:.2f} (what varies)")
        largest = df.loc[df["const tip"].idxmax(), "campaign"]
        print(f"max const after the tip fit {df['const tip'].max():.2f} µm ({largest}), "
              f"max |mean meas−true| {df[['meas−true x', 'meas−true y']].abs().max().max():.2f} µm")


if __name__ == "__main__":
    main()
