"""Benchmark: RRHT on 12 MP photographs over the issue's envelope, this code against a baseline in the same process.

    .venv/bin/python bench/bench_12mp.py                        # 36 envelope renders against main, 3 repeats
    .venv/bin/python bench/bench_12mp.py --baseline 556755d     # against another commit
    .venv/bin/python bench/bench_12mp.py --stress               # also the stress set's 12 MP cases
    .venv/bin/python bench/bench_12mp.py --sizes 8,400 --tilts 50 --repeat 5
    .venv/bin/python bench/bench_12mp.py --sizes none --photos DIR [--photos DIR ...]   # large photographs only
    .venv/bin/python bench/bench_12mp.py --sizes none --photos DIR --only p03 --threads 1 --repeat 9

Images: ``tasks.simulation.detector_stress`` renders of a 4 × 3 sheet of Ø 4 mm dots in a 3024 × 4032
colour JPEG (80), the envelope of ``bench/bench_stress.py --envelope`` at 12 MP: each dot size
(``--sizes``, px) × tilt (``--tilts``, deg, azimuth 37°, spin 20°) × polarity, 30 clutter items, paper
texture, a shadow edge to 0.5, light gradient 0.8, vignetting 0.3, seed 1000; with ``--stress`` also
the stress set's 3024 × 4032 cases (phone-12mp, phone-garden, …); with ``--photos DIR`` (repeatable) also
the photographs of at least ``--min-mp`` megapixels (default 8) in each folder written by
``bench/real_photo_truth.py`` (their truth the rim ellipse of the image as delivered, a hand fit; refused
ones count too: a refusal must be as fast as a find). ``--sizes none`` leaves the envelope out. Each image
is rendered (read) once and held in memory while it is timed.

Baseline: the ``tasks`` package of ``--baseline`` (a git ref, default ``main``) is extracted with
``git archive`` into a temporary folder and imported a second time under the same names (its modules
kept apart from this code's), so both ``detect_grid`` run in this process on the same arrays. Each
is called once per image untimed (compiled kernels loaded; a fresh extract compiles the baseline's
numba kernels, about a minute), then ``--repeat`` times interleaved, the one going first alternating;
medians of the wall time (``time.perf_counter``) and of the process's CPU time (``time.process_time``,
every thread) are kept. The host's 1-minute load average is printed before and after: the wall
times count the waits for a core when other jobs run, and the CPU times the threads that spin while
they wait; ``--threads 1`` runs OpenCV and both codes' kernels on the calling thread, whose CPU time
compares the codes on a busy host.

Prints per image: found / refused for each code, their wall and CPU ms, the ratios baseline / this,
the median and worst centre error against the renderer's truth (px, up to the grid's symmetry), and
whether the two codes give the same verdict, reason and centres (bits); then the worst and median
times and the cases over 0.5 s of wall time.
"""

from __future__ import annotations

import argparse
import importlib
import itertools
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_photos import photographs

from tasks.machine.plate import DotPlate
from tasks.simulation.detector_stress import STRESS_CASES, StressCase, errors_up_to_symmetry, render_stress_case
from tasks.vision.detection import detect_grid
from tasks.vision.detection.parallel import set_kernel_threads

ROOT = Path(__file__).resolve().parents[1]
GOAL_S = 0.5


def load_baseline(ref: str, folder: Path, kernel_threads: int | None = None):
    """``detect_grid`` of the ``tasks`` package at git ref ``ref`` (extracted into ``folder``), imported
    beside this code's: this code's ``tasks`` modules are set aside while the baseline's load, then
    put back, so each keeps its own. ``kernel_threads``: the baseline's compiled kernels' threads
    (``parallel.set_kernel_threads``; None: its default)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "tasks"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    ours = {k: v for k, v in sys.modules.items() if k == "tasks" or k.startswith("tasks.")}
    for k in ours:
        del sys.modules[k]
    sys.path.insert(0, str(folder))
    try:
        fn = importlib.import_module("tasks.vision.detection").detect_grid
        if kernel_threads is not None:
            importlib.import_module("tasks.vision.detection.parallel").set_kernel_threads(kernel_threads)
    finally:
        sys.path.remove(str(folder))
        for k in [k for k in sys.modules if k == "tasks" or k.startswith("tasks.")]:
            del sys.modules[k]
        sys.modules.update(ours)
    return fn


def envelope_cases(sizes: list[float], tilts: list[float]) -> list[StressCase]:
    """The 12 MP envelope of ``bench_stress.py --envelope`` (same scene parameters)."""
    return [StressCase(f"{d:g}px-{t:g}deg-{'dark' if dark else 'light'}", 3024, 4032, d, tilt_deg=t,
                       tilt_azimuth_deg=37.0, spin_deg=20.0, dark_dots=dark, clutter=30, texture=True, shadow=0.5,
                       gradient=0.8, vignetting=0.3, colour=True, jpeg=80, seed=1000)
            for d in sizes for t in tilts for dark in (True, False)]


def rendered(cases: list[StressCase]) -> Iterator[tuple[str, np.ndarray, DotPlate, np.ndarray]]:
    """(name, image, plate, truth px) of each render, one at a time."""
    for case in cases:
        image, truth = render_stress_case(case)
        yield case.name, image, replace(case.plate, dark_dots=case.dark_dots), truth


def large_photographs(folders: list[Path], min_mp: float) -> Iterator[tuple[str, np.ndarray, DotPlate, np.ndarray]]:
    """(folder/name, image, plate, truth px: the image's rim ellipses) of each photograph in ``folders`` of at
    least ``min_mp`` megapixels, one at a time."""
    for folder in folders:
        for jpath, image, plate, _, _, others in photographs(folder):
            if image.size >= min_mp * 1e6:
                yield f"{folder.name}/{jpath.stem}", image, plate, others["image rim"]


def timed(fn, image, plate):
    t0, c0 = time.perf_counter(), time.process_time()
    det = fn(image, plate, "rrht")
    return det, time.perf_counter() - t0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="main", help="git ref of the baseline code (default main)")
    ap.add_argument("--sizes", default="8,12,16,50,150,400", help="dot diameters, px")
    ap.add_argument("--tilts", default="0,30,50", help="tilts, deg")
    ap.add_argument("--stress", action="store_true", help="also the stress set's 3024 x 4032 cases")
    ap.add_argument("--photos", type=Path, action="append", default=[],
                    help="a folder of bench/real_photo_truth.py's photographs (repeatable)")
    ap.add_argument("--min-mp", type=float, default=8.0, help="with --photos: the photographs of at least this "
                                                                "many megapixels (default 8)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default="", help="only the images whose name contains this")
    ap.add_argument("--threads", type=int, default=None,
                    help="OpenCV's threads and both codes' kernel threads (default: theirs; 1: CPU time "
                         "without threads waiting for a core on a busy host)")
    args = ap.parse_args()
    if args.threads is not None:
        cv2.setNumThreads(args.threads)
        set_kernel_threads(args.threads)
    cases = [] if args.sizes == "none" else envelope_cases([float(x) for x in args.sizes.split(",")],
                                                           [float(x) for x in args.tilts.split(",")])
    if args.stress:
        cases += [c for c in STRESS_CASES if (c.width, c.height) == (3024, 4032)]
    cases = [c for c in cases if args.only in c.name]
    images = itertools.chain(rendered(cases), (i for i in large_photographs(args.photos, args.min_mp)
                                                if args.only in i[0]))
    tmp = tempfile.TemporaryDirectory(prefix="bench12mp-")
    codes = {"base": load_baseline(args.baseline, Path(tmp.name), args.threads), "this": detect_grid}
    photos = f", photographs of {args.min_mp:g} MP and more in {', '.join(map(str, args.photos))}" * bool(args.photos)
    threads = f"; {args.threads} thread(s)" if args.threads is not None else ""
    print(f"baseline {args.baseline}, {len(cases)} renders 3024x4032{photos}, {args.repeat} repeats{threads}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    print(f"{'case':34s} {'base: found wall/cpu ms':>25s} {'this: found wall/cpu ms':>25s} {'ratio wall/cpu':>15s} "
          f"{'error med/worst px, base | this':>33s} same")
    rows = []
    for n, (name, image, plate, truth) in enumerate(images):
        out = {k: fn(image, plate, "rrht") for k, fn in codes.items()}  # untimed: kernels loaded, caches warm
        wall: dict[str, list[float]] = {k: [] for k in codes}
        cpu: dict[str, list[float]] = {k: [] for k in codes}
        for r in range(args.repeat):
            for k in (list(codes) if (n + r) % 2 == 0 else list(codes)[::-1]):
                out[k], w, c = timed(codes[k], image, plate)
                wall[k].append(w)
                cpu[k].append(c)
        row = {"case": name}
        for k in codes:
            row[k + "_ok"] = bool(out[k].ok)
            row[k + "_wall"], row[k + "_cpu"] = statistics.median(wall[k]), statistics.median(cpu[k])
            e = errors_up_to_symmetry(plate, out[k].centres, truth) if out[k].ok else None
            row[k + "_err"] = (float(np.median(e)), float(e.max())) if e is not None else None
        same = (out["base"].ok == out["this"].ok and out["base"].reason == out["this"].reason
                and np.array_equal(out["base"].centres, out["this"].centres, equal_nan=True))
        row["same"] = same
        rows.append(row)

        def err(k, row=row):
            return "refused" if row[k + "_err"] is None else f"{row[k + '_err'][0]:.4f}/{row[k + '_err'][1]:.4f}"

        print(f"{name:34s} {'found' if row['base_ok'] else 'REFUSED':>7s} {1e3 * row['base_wall']:7.0f} "
              f"{1e3 * row['base_cpu']:7.0f}    {'found' if row['this_ok'] else 'REFUSED':>7s} "
              f"{1e3 * row['this_wall']:7.0f} {1e3 * row['this_cpu']:7.0f}   "
              f"{row['base_wall'] / row['this_wall']:5.2f}x {row['base_cpu'] / row['this_cpu']:5.2f}x   "
              f"{err('base'):>15s} | {err('this'):15s} {'yes' if same else 'NO'}", flush=True)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    for k, name in (("base", f"baseline {args.baseline}"), ("this", "this code")):
        w = [r[k + "_wall"] for r in rows]
        c = [r[k + "_cpu"] for r in rows]
        over = [r["case"] for r in rows if r[k + "_wall"] >= GOAL_S]
        print(f"{name:22s} found {sum(r[k + '_ok'] for r in rows)}/{len(rows)}; "
              f"wall median {1e3 * statistics.median(w):.0f} ms, worst {1e3 * max(w):.0f} ms; "
              f"CPU median {1e3 * statistics.median(c):.0f} ms, worst {1e3 * max(c):.0f} ms; "
              f"{len(over)} over {GOAL_S} s wall{': ' + ', '.join(over) if over else ''}")
    print(f"verdict, reason and centres (bits) the same in {sum(r['same'] for r in rows)} of {len(rows)} images; "
          "ratio baseline / this, "
          f"median over images: wall {statistics.median(r['base_wall'] / r['this_wall'] for r in rows):.2f}x, "
          f"CPU {statistics.median(r['base_cpu'] / r['this_cpu'] for r in rows):.2f}x")


if __name__ == "__main__":
    main()
