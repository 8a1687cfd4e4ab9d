"""PIGE identification (LM of eq. 22) over the 300 five-axis poses: wall time against the 2 s goal.

Baseline, run side by side in this process: one forward-kinematics pass over the same poses (the
unit the fit is made of), so the ratio says how many passes a fit costs. Also timed: the fit the
calibration really runs, over camera 1's sweeps and five-axis poses (about 1300 images).

Poses are exact (the simulator's truth) plus Gaussian noise at the demo's per-image precision;
the PDGE profiles are extracted from the noise-free sweeps first (not timed).

    python bench/bench_identification.py [--repeats 3]
"""

from __future__ import annotations

import argparse

import numpy as np
from timing import best_of

from tasks.core import se3
from tasks.core.units import ARCSEC
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.pdge_extraction import extract_pdges
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    identify_pige,
    synthetic_measurements,
)
from tasks.machine.description import load_machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors

GOAL_S = 2.0
COV = np.diag([0.25e-3**2] * 2 + [4e-3**2] + [(70 * ARCSEC) ** 2] * 2 + [(3 * ARCSEC) ** 2])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    machine, truth = load_machine("prototype"), load_prototype_errors()
    plan, _ = plan_campaign(machine, CampaignPlan(), 0)
    clean = synthetic_measurements(machine, truth, planned_measurements(plan, COV))
    noise = np.random.default_rng(1).normal(size=(len(clean), 6)) @ np.linalg.cholesky(COV).T
    noisy = Measurements(clean.table, clean.T @ se3.exp(noise), clean.cov, clean.context)
    base = ErrorModel(pdge=extract_pdges(machine, ErrorModel(), clean).profiles)
    five_axis = noisy.stage("pige", camera=IDENTIFICATION_CAMERA)
    full = noisy.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)

    t_fk, _ = best_of(lambda: forward(machine, five_axis.commands, base, five_axis.context), 20)
    t_300, fit = best_of(lambda: identify_pige(machine, base, five_axis), args.repeats)
    t_full, fit_full = best_of(lambda: identify_pige(machine, base, full), args.repeats)
    print(f"{'':34s}{'time':>10s}{'ratio':>10s}")
    print(f"{'baseline: one FK pass, 300 poses':34s}{t_fk * 1e3:8.2f}ms{1.0:10.1f}")
    print(f"{'LM fit, 300 five-axis poses':34s}{t_300:9.2f}s{t_300 / t_fk:10.0f}   goal {GOAL_S:.1f} s, "
          f"{fit.fit.iterations} iterations, {int(fit.fit.identifiable.sum())}/{fit.fit.x.size} identifiable")
    print(f"{f'LM fit, {len(full)} images (calibrate)':34s}{t_full:9.2f}s{t_full / t_fk:10.0f}   "
          f"{fit_full.fit.iterations} iterations, {int(fit_full.fit.identifiable.sum())}/{fit_full.fit.x.size} "
          "identifiable")


if __name__ == "__main__":
    main()
