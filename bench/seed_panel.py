"""A panel of clean seeds: does the calibration hold on every campaign, not only the demo's?

Two modes.

``images`` (default): for each seed, the campaign ``<campaigns>/s<seed>`` is simulated if it is not
there yet (``fivecal simulate --size SIZE --seed N``) and calibrated if its results root has no
``verification`` table for it yet (``fivecal calibrate``, Prefect's cache serving what is unchanged);
then the lake tables are read and one row per seed printed, the median and the worst seed below.
Already-simulated campaigns (e.g. a shared read-only panel) are only read: pass ``--campaigns`` to
them and ``--results``/``--reports`` to folders of your own.

    python bench/seed_panel.py --seeds 10 67 161 --campaigns /work/panel/small --results R --reports P

``profiles``: the PDGE columns alone, from the campaigns' measured poses: each seed is simulated
and measured (``fivecal measure``) if its results root has no ``poses`` table for it yet, then the
calibration is run in-process on the lake's poses (the ``identify`` step of ``fivecal calibrate``,
the same function on the same poses, without the uncertainty propagation, verification and report
that follow it): one row per seed with every component's RMS(fit − truth) of the X and Y profiles
beside the per-axis worst.

    python bench/seed_panel.py --mode profiles --seeds 497 639 --campaigns C --results R

``poses``: no images. The tests' small plan (50-position sweeps, 150 five-axis and 30 validation
poses) with the prototype's frozen errors as truth; ``--draws`` noise draws of the pose covariance
(tests/identification/test_identification.py's) are calibrated and the scatter of every parameter set beside the
uncertainty the calibration states (the propagated one of the first ``--propagate`` draws, as the
``pige`` table gives it; the LM's beside it), the bias and RMS of (est − truth)/u against the truth
in each fit's gauge (the same calibration of the exact poses, as the ``pige`` table's ``truth``),
with σ² per draw and the tip error of the identified model against the truth on the validation
poses (what compensation would leave).

    python bench/seed_panel.py --mode poses --draws 16

Columns (images mode), over the validation poses after compensation, true = against the simulator:
- ``true``: mean true tip position error (µm); ``const``: the norm of its mean in the tool frame
  (a constant tool-frame vector: a tip offset a dispensing test would remove); ``vary``: mean norm of
  what is left (the pose-varying part);
- ``vbm``: mean error as the vision system measures it (µm); ``u_model``: mean model uncertainty
  of the compensated tip (µm);
- ``z_rms``, ``in2u``: the 11 PIGEs' RMS of |est − truth|/u and the share within 2u;
- ``pdge X…C``: per axis the larger RMS(fit − truth) over the translations (µm) / rotations (″);
- ``σ²``: the constant-parameter fit's residual variance factor; ``flagged``: the share of residual
  trend panels called significant (the ``residual_trends`` table when present).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.analysis.compensation import desired_tip_poses
from tasks.analysis.residuals import trend_summary
from tasks.core import se3
from tasks.core.units import ARCSEC, UM
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.parameters import default_parameters
from tasks.identification.pdge_extraction import COMPONENT_COLUMNS
from tasks.identification.pige_identification import synthetic_measurements
from tasks.identification.uncertainty import propagate_uncertainty
from tasks.lake.store import read_table
from tasks.machine.description import AXIS_ORDER, load_machine
from tasks.machine.kinematics import forward
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors

POSE_COV = np.diag([0.2e-3**2] * 2 + [4e-3**2] + [(70 * ARCSEC) ** 2] * 2 + [(3 * ARCSEC) ** 2])
"""The tests' per-pose covariance (mm, rad): 0.2 µm lateral, 4 µm depth, 70″ tilts, 3″ about the normal."""
SMALL_PLAN = CampaignPlan(sweep_positions=50, sweep_repeats=1, pige_poses=150, validation_poses=30,
                          calibration_trials=1, images_per_trial=1)


# ---------------------------------------------------------------------------------------------
# tip errors split into a constant tool-frame vector and the rest
# ---------------------------------------------------------------------------------------------

def split_tip_error(d_workpiece_um: np.ndarray, R_tool: np.ndarray) -> tuple[float, float, float]:
    """(mean ‖d‖, ‖constant tool-frame vector‖, mean ‖d − constant‖) in µm.

    d_workpiece_um: (N, 3) tip position errors in the workpiece frame (µm). R_tool: (N, 3, 3) the
    desired tip orientations (tool frame -> workpiece frame). The constant is the mean of the errors
    expressed in the tool frame: the best single tip offset."""
    d_tool = np.einsum("nji,nj->ni", R_tool, d_workpiece_um)
    const = d_tool.mean(axis=0)
    return (float(np.linalg.norm(d_workpiece_um, axis=1).mean()), float(np.linalg.norm(const)),
            float(np.linalg.norm(d_tool - const, axis=1).mean()))


def pdge_errors(pdge: pd.DataFrame) -> dict[str, tuple[float, float]]:
    """{axis: (RMS(fit − truth) of the worst translation (µm), of the worst rotation (″))} over the
    positions of the ``pdge`` table."""
    out = {}
    for axis, g in pdge.groupby("axis"):
        rms = {c: float(np.sqrt(np.nanmean((g[f"fit_{c}"] - g[f"truth_{c}"]) ** 2))) for c in COMPONENT_COLUMNS}
        out[str(axis)] = (max(rms[c] for c in COMPONENT_COLUMNS[:3]), max(rms[c] for c in COMPONENT_COLUMNS[3:]))
    return out


def pige_check(pige: pd.DataFrame) -> tuple[float, float]:
    """(RMS of |value − truth|/uncertainty, share within 2u) over the identifiable PIGEs."""
    p = pige[(pige["kind"] == "pige") & pige["identifiable"]]
    z = ((p["value"] - p["truth"]) / p["uncertainty"]).to_numpy(dtype=float)
    z = z[np.isfinite(z)]
    return (float(np.sqrt(np.mean(z**2))), float(np.mean(np.abs(z) <= 2.0))) if z.size else (np.nan, np.nan)


# ---------------------------------------------------------------------------------------------
# images mode
# ---------------------------------------------------------------------------------------------

def _fivecal(*args: str, log: Path) -> None:
    with open(log, "a") as out:
        rc = subprocess.call([sys.executable, "-c", "from fivecal.cli import app; app()", *args], stdout=out,
                             stderr=subprocess.STDOUT)
    if rc:
        raise RuntimeError(f"fivecal {' '.join(args)} failed (exit {rc}); see {log}")


def _has(table: str, root: Path, campaign_id: str) -> bool:
    try:
        return not read_table(table, root, campaign_id).empty
    except (FileNotFoundError, OSError, ValueError):
        return False


def seed_row(machine, campaign: Path, root: Path) -> dict:
    """The panel's columns for one calibrated campaign (its lake under ``root``)."""
    campaign_id = json.loads((campaign / "campaign.json").read_text())["campaign_id"]
    ver = read_table("verification", root, campaign_id)
    comp = read_table("compensation", root, campaign_id).set_index("image_id")
    after = ver[(ver.phase == "after") & (ver.source == "truth")].set_index("image_id")
    commands = comp.loc[after.index, list(AXIS_ORDER)].to_numpy(dtype=float)
    R = desired_tip_poses(machine, commands)[:, :3, :3]
    true, const, vary = split_tip_error(after[["dx_um", "dy_um", "dz_um"]].to_numpy(dtype=float), R)
    vbm = ver[(ver.phase == "after") & (ver.source == "vbm")]
    z_rms, in2u = pige_check(read_table("pige", root, campaign_id))
    ladder = read_table("model_ladder", root, campaign_id).sort_values("step").iloc[0]
    sigma2 = float(ladder.train_rms**2 * ladder.n_residuals / max(ladder.n_residuals - ladder.n_params, 1))
    if _has("residual_trends", root, campaign_id):
        trends = read_table("residual_trends", root, campaign_id)
    else:
        trends = trend_summary(read_table("residuals", root, campaign_id))
    row = {"campaign": campaign.name, "true": true, "const": const, "vary": vary,
           "vbm": float(vbm.position_um.mean()), "u_model": float(after.model_uncertainty_position_um.mean()),
           "z_rms": z_rms, "in2u": in2u, "sigma2": sigma2, "flagged": float(trends["significant"].mean())}
    for axis, (um, arcsec) in pdge_errors(read_table("pdge", root, campaign_id)).items():
        row[f"pdge_{axis}_um"], row[f"pdge_{axis}_arcsec"] = um, arcsec
    return row


def _simulated(args, seed: int, root: Path) -> tuple[Path, str, Path]:
    """The panel's campaign of ``seed`` (simulated first when absent): (folder, campaign_id, log file)."""
    campaign = Path(args.campaigns) / f"s{seed}"
    log = root / f"s{seed}.log"
    if not (campaign / "campaign.json").exists():
        _fivecal("simulate", str(campaign), "--seed", str(seed), "--size", args.size, log=log)
    return campaign, json.loads((campaign / "campaign.json").read_text())["campaign_id"], log


def run_images(args) -> pd.DataFrame:
    machine = load_machine("prototype")
    root, reports = Path(args.results), Path(args.reports)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        campaign, campaign_id, log = _simulated(args, seed, root)
        if not _has("verification", root, campaign_id):
            t0 = time.perf_counter()
            _fivecal("calibrate", str(campaign), "--results", str(root), "--reports", str(reports), log=log)
            print(f"s{seed}: calibrated in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
        rows.append({"seed": seed, **seed_row(machine, campaign, root)})
    return pd.DataFrame(rows)


def run_profiles(args) -> pd.DataFrame:
    """profiles mode (module docstring): one row per seed of PDGE errors against the truth."""
    from flows.calibrate import read_measured_campaign

    root = Path(args.results)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        campaign, campaign_id, log = _simulated(args, seed, root)
        if not _has("poses", root, campaign_id):
            _fivecal("measure", str(campaign), "--results", str(root), log=log)
        measured = read_measured_campaign(campaign, str(root))
        t0 = time.perf_counter()
        result = calibrate(measured.machine, measured.measurements, measured.truth)
        row = {"seed": seed, "campaign": campaign.name, "sigma2": result.pige.fit.sigma2,
               "seconds": time.perf_counter() - t0}
        for axis, (um, arcsec) in pdge_errors(result.pdge.table).items():
            row[f"pdge_{axis}_um"], row[f"pdge_{axis}_arcsec"] = um, arcsec
        table = result.pdge.table
        for axis in ("X", "Y"):
            g = table[table.axis == axis]
            for c in COMPONENT_COLUMNS[3:]:
                row[f"{axis}_{c.split('_')[0]}"] = float(np.sqrt(np.nanmean((g[f"fit_{c}"] - g[f"truth_{c}"]) ** 2)))
        rows.append(row)
        print(f"s{seed}: " + ", ".join(f"{k} {v:.2f}" for k, v in row.items() if k not in ("seed", "campaign")),
              file=sys.stderr, flush=True)
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------
# poses mode
# ---------------------------------------------------------------------------------------------

def run_poses(args) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-parameter scatter table, per-draw table) of ``args.draws`` noisy calibrations."""
    machine, truth = load_machine("prototype"), load_prototype_errors()
    plan, _ = plan_campaign(machine, SMALL_PLAN, args.plan_seed)
    clean = synthetic_measurements(machine, truth, planned_measurements(plan, POSE_COV))
    specs = default_parameters()
    scale = np.array([s.scale for s in specs])
    val = clean.stage("validation", camera="camera1")
    desired = desired_tip_poses(machine, val.commands)
    true_tip = forward(machine, val.commands, truth).tool_in_workpiece()
    L = np.linalg.cholesky(POSE_COV)
    values, truths, lm_u, stated, draws = [], [], [], [], []
    for d in range(args.draws):
        rng = np.random.default_rng([args.noise_seed, d])
        noisy = Measurements(clean.table, clean.T @ se3.exp(rng.normal(size=(len(clean), 6)) @ L.T), clean.cov,
                             clean.context)
        t0 = time.perf_counter()
        result = calibrate(machine, noisy, truth)
        seconds = time.perf_counter() - t0
        fit = result.pige.fit
        values.append(np.where(fit.identifiable, fit.x, np.nan) / scale)
        truths.append(result.truth_pige.fit.x / scale)  # the truth in this fit's gauge
        lm_u.append(fit.uncertainty / scale)
        if d < args.propagate:
            stated.append(propagate_uncertainty(machine, result, noisy).combined / scale)
        model_tip = forward(machine, val.commands, result.model).tool_in_workpiece()
        d_um = (true_tip[:, :3, 3] - model_tip[:, :3, 3]) / UM
        true, const, vary = split_tip_error(d_um, desired[:, :3, :3])
        draws.append({"draw": d, "sigma2": fit.sigma2, "identifiable": int(fit.identifiable.sum()),
                      "tip_um": true, "const_um": const, "vary_um": vary, "seconds": seconds})
        print(f"draw {d}: σ² {fit.sigma2:.2f}, {int(fit.identifiable.sum())}/{fit.x.size} identifiable, "
              f"tip {true:.2f} µm (vary {vary:.2f}), {seconds:.1f} s", file=sys.stderr, flush=True)
    values, truths, lm_u = np.array(values), np.array(truths), np.array(lm_u)
    u = np.nanmedian(np.array(stated), axis=0) if stated else np.nanmedian(lm_u, axis=0)
    sd = np.nanstd(values, axis=0, ddof=1)
    per_param = pd.DataFrame({"parameter": [s.name for s in specs], "unit": [s.unit for s in specs],
                              "scatter": sd, "stated_u": u, "lm_u": np.nanmedian(lm_u, axis=0),
                              "scatter_over_u": sd / u, "bias": np.nanmean(values - truths, axis=0),
                              "rms_z": np.sqrt(np.nanmean(((values - truths) / u) ** 2, axis=0))})
    return per_param, pd.DataFrame(draws)


# ---------------------------------------------------------------------------------------------

def _print_panel(table: pd.DataFrame) -> None:
    fmt = {c: "{:.2f}".format for c in table.columns if c not in ("seed", "campaign")}
    fmt.update({"flagged": "{:.0%}".format, "in2u": "{:.0%}".format})
    summary = pd.DataFrame([table.drop(columns=["campaign"]).median(numeric_only=True).rename("median")])
    worst = {c: (table[c].min() if c == "in2u" else table[c].max()) for c in table.columns
             if c not in ("seed", "campaign")}
    summary.loc["worst"] = pd.Series(worst)
    summary["seed"] = np.nan
    print(table.drop(columns=["campaign"]).to_string(index=False, formatters=fmt))
    print(summary.drop(columns=["seed"]).to_string(formatters=fmt))
    if "z_rms" in table:
        pooled = table[["z_rms"]].pow(2).mean().pow(0.5).iloc[0]
        print(f"pooled RMS |est − truth|/u over seeds (PIGEs): {pooled:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=("images", "profiles", "poses"), default="images")
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 67, 161, 262, 497, 519, 619, 639, 848, 957])
    ap.add_argument("--size", default="small")
    ap.add_argument("--campaigns", default="data/campaigns/panel", help="folder of the s<seed> campaigns")
    ap.add_argument("--results", default="data/results-panel")
    ap.add_argument("--reports", default="reports-panel")
    ap.add_argument("--draws", type=int, default=16, help="poses mode: noise draws")
    ap.add_argument("--propagate", type=int, default=1,
                    help="poses mode: draws whose propagated uncertainty is computed (the stated u is their median)")
    ap.add_argument("--plan-seed", type=int, default=5)
    ap.add_argument("--noise-seed", type=int, default=100)
    ap.add_argument("--csv", help="also write the table(s) here (poses mode: <csv> and <csv>.draws.csv)")
    args = ap.parse_args()
    pd.set_option("display.width", 250)
    if args.mode in ("images", "profiles"):
        table = run_images(args) if args.mode == "images" else run_profiles(args)
        _print_panel(table)
        if args.csv:
            table.to_csv(args.csv, index=False)
        return
    per_param, draws = run_poses(args)
    print(per_param.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print(draws.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    worst = per_param.scatter_over_u.max()
    pooled = np.sqrt(np.mean(per_param.rms_z**2))
    print(f"worst scatter / stated u: {worst:.2f} ({per_param.parameter[per_param.scatter_over_u.idxmax()]}); "
          f"σ² {draws.sigma2.min():.2f}–{draws.sigma2.max():.2f}; pooled RMS z {pooled:.2f}; "
          f"pose-varying tip error after: median {draws.vary_um.median():.2f}, worst {draws.vary_um.max():.2f} µm")
    if args.csv:
        per_param.to_csv(args.csv, index=False)
        draws.to_csv(f"{args.csv}.draws.csv", index=False)


if __name__ == "__main__":
    main()
