"""Benchmark: RRHT's centres under a cast shadow's straight edge across the dots (tasks.simulation.shadow_edge).

    .venv/bin/python bench/bench_shadow_sweep.py            # the sweep below, one line per dot size and polarity
    .venv/bin/python bench/bench_shadow_sweep.py --cases    # and one line per render
    .venv/bin/python bench/bench_shadow_sweep.py --no-uneven-dark-edge-fit  # SubpixelParams(uneven_dark_edge_fit=False)

Sweep: dark and light dots of 10, 14, 20, 30 and 40 px; the shadow at 0.35, 0.5 and 0.8 of the
light; its edge blurred by 0.5 px, 0.15 and 0.5 of a dot; the edge passing the grid's centre at
0, 0.4 and 0.8 of a dot radius (at 70° to the rows, so that it crosses several dots at various
distances from their centres); exposure 1 and 1.3 (lit light dots saturated). Per render
``detect_grid(image, plate, "rrht")`` (``detect_rrht``) with no prior; a grid counts as found when every dot is
within a quarter of the dot size of its own true centre (up to the grid's symmetry), wrong
otherwise. Errors (px) of the dots the edge crosses (within one radius of the centre) and of
the others: median and worst over the found grids.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tasks.simulation.detector_stress import errors_up_to_symmetry
from tasks.simulation.shadow_edge import ShadowEdgeCase, render_shadow_edge
from tasks.vision.detection.framework import FrameworkParams, detect_rrht
from tasks.vision.detection.subpixel import SubpixelParams

DOTS_PX = (10.0, 14.0, 20.0, 30.0, 40.0)
SHADOWS = (0.35, 0.5, 0.8)
EDGE_BLURS = ("0.5px", 0.15, 0.5)  # px, or × the dot size
OFFSETS = (0.0, 0.4, 0.8)
EXPOSURES = (1.0, 1.3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", action="store_true", help="print one line per render")
    ap.add_argument("--no-uneven-dark-edge-fit", action="store_true",
                    help="SubpixelParams(uneven_dark_edge_fit=False): no pixel edge fit on dark dots lit unevenly")
    args = ap.parse_args()
    params = FrameworkParams(subpixel=SubpixelParams(uneven_dark_edge_fit=not args.no_uneven_dark_edge_fit))
    print(f"{'dots':12s} {'found':>5s} {'refused':>7s} {'wrong':>5s}  "
          "crossed: median / worst px   others: median / worst px")
    for dark, dot in itertools.product((True, False), DOTS_PX):
        counts = {"found": 0, "refused": 0, "wrong": 0}
        crossed, others = [], []
        for seed, (shadow, blur, offset, exposure) in enumerate(itertools.product(SHADOWS, EDGE_BLURS, OFFSETS,
                                                                                  EXPOSURES)):
            blur_px = 0.5 if blur == "0.5px" else blur * dot
            case = ShadowEdgeCase(dot, dark_dots=dark, shadow=shadow, edge_blur_px=blur_px, edge_offset=offset,
                                  exposure=exposure, seed=seed)
            image, truth, to_edge = render_shadow_edge(case)
            plate = replace(case.plate, dark_dots=dark)
            det = detect_rrht(image, plate, params=params)
            if not det.ok:
                verdict, what = "refused", det.reason
            else:
                e = errors_up_to_symmetry(plate, det.centres, truth)
                verdict = "found" if e.max() < 0.25 * dot else "wrong"
                near = to_edge < 1.0
                worst_near = e[near].max() if near.any() else np.nan
                what = f"crossed worst {worst_near:.3f} px, others worst {e[~near].max():.3f} px"
                if verdict == "found":
                    crossed += list(e[near])
                    others += list(e[~near])
            counts[verdict] += 1
            if args.cases:
                print(f"  {'dark' if dark else 'light'} {dot:4.0f}px shadow {shadow:.2f} edge blur {blur_px:5.2f}px "
                      f"offset {offset:.1f} exposure {exposure:.1f}: {verdict} ({what})", flush=True)
        c, o = np.array(crossed), np.array(others)
        print(f"{'dark' if dark else 'light':5s} {dot:4.0f}px {counts['found']:5d} {counts['refused']:7d} "
              f"{counts['wrong']:5d}  {np.median(c) if len(c) else np.nan:14.3f} / {c.max() if len(c) else np.nan:.3f}"
              f"   {np.median(o) if len(o) else np.nan:17.3f} / {o.max() if len(o) else np.nan:.3f}", flush=True)


if __name__ == "__main__":
    main()
