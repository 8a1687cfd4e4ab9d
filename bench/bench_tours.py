"""Tour planning of the dispensing job: time and quality of the exact, heuristic and baseline tours.

Run as ``python bench/bench_tours.py [--seeds 20] [--large-seeds 5]``. Points are drawn uniformly on a 300 × 300 mm
tray with home at its corner (0, 0). Every table is measured in this process, the nearest-neighbour
tour of the same points being the baseline of the length ratios. Times are wall times of warm calls
(the compiled loops are loaded once before timing) on whatever else the machine is running; the
tables also give the process's CPU time, which other jobs on the machine do not inflate.

1. exact tours for 10…60 points: time (median and worst over seeds), proven optimal, length / NN;
2. 500 points, uniform and in a tray's pockets: time, the gap to the lower bound (the larger of
   Held–Karp's and the LP bound with subtour and blossom cuts), length / NN, the paper's annealing;
3. the paper's Table 9 points: every method's length and time, and the travel time of the tour plus
   the beads against the paper's Tables 4 and 8.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tasks.dispense_job import paper_points as paper
from tasks.dispense_job.bead_path import bead_path, bead_time_s
from tasks.dispense_job.tour_bound import distance_matrix, held_karp_bound
from tasks.dispense_job.tour_exact import plan_tour, tour_path_mm
from tasks.dispense_job.travel_time import travel_time_s

TRAY_MM = 300.0
# The paper quotes its travel speed (3.5 mm/s, §4.3) but no acceleration; 50 mm/s² is assumed (at
# 3.5 mm/s the ramps take 0.07 s and change the times by well under 1 %).
SPEED_MM_S = (3.5, 3.5)
ACCEL_MM_S2 = (50.0, 50.0)


def _points(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, TRAY_MM, (n, 2))


def _tray(seed: int, rows: int = 20, cols: int = 25, pitch_mm: float = 12.0, play_mm: float = 3.0) -> np.ndarray:
    """Boards in the pockets of a rows × cols tray, each off its pocket's centre by up to ±play_mm per
    axis (the paper's boards lie loosely in a tray)."""
    gy, gx = np.mgrid[0:rows, 0:cols]
    pockets = 10.0 + pitch_mm * np.column_stack([gx.ravel(), gy.ravel()])
    return pockets + np.random.default_rng(seed).uniform(-play_mm, play_mm, pockets.shape)


def exact_table(seeds: list[int]) -> None:
    print("1. exact tours (proven optimum), uniform points on a 300 mm tray, home at (0, 0)")
    print(f"{'points':>6} {'median s':>9} {'worst s':>8} {'cpu median':>10} {'cpu worst':>9} {'proven':>7} "
          f"{'opt/NN median':>14} {'opt/NN worst':>13}")
    for n in (10, 20, 30, 40, 50, 60):
        times, cpus, proven, ratios = [], [], [], []
        for seed in seeds:
            pts = _points(n, seed)
            cpu = time.process_time()
            tour = plan_tour(pts, seed=seed)
            cpus.append(time.process_time() - cpu)
            nearest = plan_tour(pts, method="nearest")
            times.append(tour.seconds)
            proven.append(tour.proven_optimal)
            ratios.append(tour.length_mm / nearest.length_mm)
        print(f"{n:>6} {np.median(times):>9.3f} {max(times):>8.3f} {np.median(cpus):>10.3f} {max(cpus):>9.3f} "
              f"{sum(proven):>3}/{len(proven):<3} "
              f"{np.median(ratios):>14.3f} {max(ratios):>13.3f}")


def large_table(seeds: list[int]) -> None:
    print("\n2. 500 points: iterated local search + tour merging, gap to the lower bound (Held–Karp, LP with cuts)")
    layouts = {
        "uniform": lambda seed: _points(500, seed),
        "tray 25x20, ±3 mm": _tray,
    }
    for layout, make in layouts.items():
        print(f"{layout}:")
        print(f"{'seed':>5} {'s':>6} {'cpu s':>6} {'length mm':>10} {'bound mm':>10} {'gap %':>6} {'HK gap %':>8} "
              f"{'ILS/NN':>7} {'SA/NN':>6} {'SA s':>5}")
        gaps, times = [], []
        for seed in seeds:
            pts = make(seed)
            cpu = time.process_time()
            tour = plan_tour(pts, seed=seed)
            cpu = time.process_time() - cpu
            nearest = plan_tour(pts, method="nearest")
            annealed = plan_tour(pts, method="annealing", seed=seed)
            # the Held–Karp bound alone (the plan's bound is the larger of it and the LP bound with cuts)
            held_karp = held_karp_bound(distance_matrix(np.vstack([(0.0, 0.0), pts])), tour.length_mm).bound_mm
            gaps.append(100 * tour.gap)
            times.append(tour.seconds)
            print(f"{seed:>5} {tour.seconds:>6.2f} {cpu:>6.2f} {tour.length_mm:>10.1f} {tour.lower_bound_mm:>10.1f} "
                  f"{100 * tour.gap:>6.2f} {100 * (tour.length_mm / held_karp - 1):>8.2f} "
                  f"{tour.length_mm / nearest.length_mm:>7.3f} "
                  f"{annealed.length_mm / nearest.length_mm:>6.3f} {annealed.seconds:>5.2f}")
        print(f"gap median {np.median(gaps):.2f} %, worst {max(gaps):.2f} %; time median {np.median(times):.2f} s, "
              f"worst {max(times):.2f} s")


def paper_table() -> None:
    pts, home = paper.TABLE9_MACHINE_MM, paper.HOME_MM
    print("\n3. the paper's Table 9 points (20 boards, machine mm), home (0, 0)")
    beads = sum(bead_time_s(bead_path(c, a, (4.0, 2.0))) for c, a in zip(pts, paper.TABLE9_ANGLE_DEG, strict=True))
    print(f"{'method':>17} {'length mm':>10} {'/ optimal':>10} {'bound mm':>9} {'proven':>7} {'plan s':>7} "
          f"{'travel s':>9} {'+ beads s':>10}")
    rows = {}
    for method in ("optimal", "annealing", "nearest", "given_order", "return_to_origin"):
        tour = plan_tour(pts, home, method, seed=0)
        rows[method] = tour
        travel = travel_time_s(tour_path_mm(pts, tour, home), SPEED_MM_S, ACCEL_MM_S2)
        rows[method + "_time"] = travel + beads
        print(f"{method:>17} {tour.length_mm:>10.1f} {tour.length_mm / rows['optimal'].length_mm:>10.3f} "
              f"{tour.lower_bound_mm:>9.1f} {tour.proven_optimal!s:>7} {tour.seconds:>7.3f} {travel:>9.1f} "
              f"{travel + beads:>10.1f}")
    print(f"beads: 20 strokes at 0.9 mm/s take {beads:.1f} s in all; travel at {SPEED_MM_S[0]} mm/s, "
          f"{ACCEL_MM_S2[0]} mm/s² per axis")
    for base in ("given_order", "return_to_origin"):
        cut = 1 - rows["optimal"].length_mm / rows[base].length_mm
        saved = 1 - rows["optimal_time"] / rows[base + "_time"]
        print(f"optimal against {base}: {100 * cut:.1f} % shorter, {100 * saved:.1f} % of the time saved")
    paper_cut = 1 - paper.ANNEALED_20_MM / paper.CONVENTIONAL_20_MM
    print(f"paper (another 20-board placement): {paper.CONVENTIONAL_20_MM} -> {paper.ANNEALED_20_MM} mm, "
          f"{100 * paper_cut:.1f} % shorter; Table 4 group means {paper.TABLE4_GROUPS_MM.tolist()} mm; "
          f"Table 8 time saved {100 * paper.TABLE8_IMPROVEMENT.min():.1f}–{100 * paper.TABLE8_IMPROVEMENT.max():.1f} % "
          f"(group 1: {100 * paper.TABLE8_IMPROVEMENT[0]:.1f} %); planning {paper.TABLE9_PLANNING_S} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20, help="random layouts per size of the exact table")
    parser.add_argument("--large-seeds", type=int, default=5, help="random layouts of each 500-point layout")
    args = parser.parse_args()
    plan_tour(_points(12, 99), seed=0)  # load the compiled loops before timing
    for method in ("annealing", "nearest"):
        plan_tour(_points(12, 99), method=method)
    exact_table(list(range(args.seeds)))
    large_table(list(range(args.large_seeds)))
    paper_table()


if __name__ == "__main__":
    main()
