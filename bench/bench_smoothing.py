"""PDGE smoothing: fivecal's closed-form GCV (tasks/identification/smoothing.py) against scipy's
``make_smoothing_spline`` with its own GCV, side by side on the same data.

One call smooths the six error-motion components of one sweep (50 positions, as the demo's), as
the PDGE extraction does per axis and per alternation round. Prints the best-of wall times, their
ratio and the largest relative difference of the fitted values.

    python bench/bench_smoothing.py [--repeats 5] [--positions 50]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.interpolate import make_smoothing_spline
from timing import best_of

from tasks.identification.smoothing import smooth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--positions", type=int, default=50)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    x = np.linspace(-300.0, 300.0, args.positions)  # mm, a linear axis' sweep
    w = np.full(x.size, 5.0)  # five repeats per position
    Y = np.column_stack([1e-3 * np.sin(x / (80.0 + 20 * k)) + 2e-4 * rng.standard_normal(x.size) for k in range(6)])

    def scipy_gcv() -> np.ndarray:
        return np.column_stack([make_smoothing_spline(x, Y[:, k], w=w / w.mean())(x) for k in range(6)])

    t_scipy, ref = best_of(scipy_gcv, args.repeats)
    t_ours, (ours, _) = best_of(lambda: smooth(x, Y, w), args.repeats)
    print(f"{args.positions} positions × 6 components, best of {args.repeats}")
    print(f"  scipy make_smoothing_spline (GCV): {1e3 * t_scipy:8.1f} ms   (baseline)")
    print(f"  fivecal smooth (closed-form GCV):  {1e3 * t_ours:8.1f} ms   ratio {t_ours / t_scipy:.3f}")
    print(f"  largest relative difference of the fitted values: {np.abs(ours - ref).max() / np.abs(ref).max():.1e}")


if __name__ == "__main__":
    main()
