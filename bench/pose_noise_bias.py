"""Second-order bias of the calibration in the pose noise, by antithetic draws.

The pose-level panel (``bench/seed_panel.py --mode poses``) shows a bias of a few parameters over 16
noise draws. Here each draw n of the tests' pose covariance is calibrated twice, on poses moved by
n and by −n: the estimate's response that is linear in the noise cancels in the pair's mean, so

    bias = ((x(n) − t(n)) + (x(−n) − t(−n))) / 2,   linear part = ((x(n) − t(n)) − (x(−n) − t(−n))) / 2

with t the truth in each fit's gauge (the same calibration of the exact poses, as the ``pige``
table's truth). ``--hold-smoothing`` holds the PDGE smoothers' roughness λ at the first
calibration's for every extraction of the pair (and its truth), so a bias that stays is not
GCV's data-dependent choice. ``--noise-on camera1|camera2`` leaves the other camera's poses exact;
``--noise-part rotation|translation`` keeps only the tilts or only the translations of the noise;
``--sweep-repeats N`` takes N images at each sweep position (a bias of the per-position means would
fall as 1/N, one of each image's own would not).

    python bench/pose_noise_bias.py --pairs 1 [--hold-smoothing] [--noise-on camera2] [--noise-part rotation]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from seed_panel import POSE_COV, SMALL_PLAN

import tasks.identification.pige_identification as pige_identification
from tasks.core import se3
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import Measurements, planned_measurements
from tasks.identification.parameters import default_parameters
from tasks.machine.description import load_machine
from tasks.simulation.campaign_plan import plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors

REPORTED = ("beta_AY", "delta_AZ", "alpha_AZ", "delta_AY")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=1)
    ap.add_argument("--hold-smoothing", action="store_true")
    ap.add_argument("--noise-on", choices=("all", "camera1", "camera2"), default="all")
    ap.add_argument("--plan-seed", type=int, default=5)
    ap.add_argument("--noise-seed", type=int, default=100)
    ap.add_argument("--noise-part", choices=("all", "rotation", "translation"), default="all")
    ap.add_argument("--sweep-repeats", type=int, default=SMALL_PLAN.sweep_repeats)
    args = ap.parse_args()
    machine, truth = load_machine("prototype"), load_prototype_errors()
    plan, _ = plan_campaign(machine, replace(SMALL_PLAN, sweep_repeats=args.sweep_repeats), args.plan_seed)
    clean = pige_identification.synthetic_measurements(machine, truth, planned_measurements(plan, POSE_COV))
    specs = default_parameters()
    scale = np.array([s.scale for s in specs])
    index = [[s.name for s in specs].index(name) for name in REPORTED]
    L = np.linalg.cholesky(POSE_COV)
    held: dict = {}
    extract = pige_identification.extract_pdges

    def extract_held(machine, model, measurements, truth=None, smoothing=None):
        return extract(machine, model, measurements, truth, held.get("lam", smoothing))

    if args.hold_smoothing:
        pige_identification.extract_pdges = extract_held
    for pair in range(args.pairs):
        n = np.random.default_rng([args.noise_seed, pair]).normal(size=(len(clean), 6)) @ L.T
        if args.noise_on != "all":
            n[(clean.table.camera != args.noise_on).to_numpy()] = 0.0
        if args.noise_part != "all":
            n[:, 3:] = 0.0 if args.noise_part == "translation" else n[:, 3:]
            n[:, :3] = 0.0 if args.noise_part == "rotation" else n[:, :3]
        held.clear()
        errors = []
        for sign in (1.0, -1.0):
            noisy = Measurements(clean.table, clean.T @ se3.exp(sign * n), clean.cov, clean.context)
            result = calibrate(machine, noisy, truth)
            errors.append((result.pige.fit.x - result.truth_pige.fit.x) / scale)
            if args.hold_smoothing:
                held.setdefault("lam", result.pdge.smoothing)
        bias, linear = (errors[0] + errors[1]) / 2, (errors[0] - errors[1]) / 2
        print(f"pair {pair} (noise on {args.noise_on}, {args.noise_part}, {args.sweep_repeats} per sweep position"
              f"{', λ held' if args.hold_smoothing else ''}): bias "
              + ", ".join(f"{REPORTED[k]} {bias[i]:+.2f}" for k, i in enumerate(index))
              + " | linear part " + ", ".join(f"{REPORTED[k]} {linear[i]:+.2f}" for k, i in enumerate(index)),
              flush=True)


if __name__ == "__main__":
    main()
