"""Benchmark: the detectors on real photographs of a 4 × 3 dot grid, against an image-based truth.

    .venv/bin/python bench/real_photo_truth.py --out DIR NAME=PHOTO...     # once: images + truth
    .venv/bin/python bench/bench_real_photos.py DIR [--repeat 3] [--debug OUT] [--invert]

DIR holds ``NAME.png`` (a photograph of a large dot grid cut down to a rows × cols block, the
block's own pixels) and ``NAME.json`` (its truth), written by ``bench/real_photo_truth.py``
(see there: the truth is the centre of an ellipse through each dot's visible rim, as fitted by
hand; a second estimator, the intensity centroid, and a map of the surrounding dots judge it).
With ``--invert`` every image is inverted (255 − grey) and the plate's dots are light: the same
dots in the other polarity.

The detectors of bench/bench_stress.py run in the same process on the same images, interleaved
over the repeats (median wall time kept). Scoring:

* rrht: **found** when it says so and every dot lies within a quarter of the dot size of the
  true centre of the dot its label names, up to the grid's symmetry (no rotation prior is given,
  as with ``fivecal detect``); **wrong** when it says so and that fails (a wrong labelling);
* OpenCV and the baselines order the grid their own way: found when each true dot has exactly
  one detected centre within a quarter of the dot size (labels not compared), else wrong.

The centre error of a found grid is the distance to the truth (rim ellipse with flat levels); the
median distances to the two other estimators of real_photo_truth.py (intensity centroid, rim
ellipse with sloped levels) are printed beside it: where they differ, the dots' images are not
uniformly dark and their centre is defined no better than that. Per detector:
found / refused / wrong, the median over the photographs of the per-photograph median error, the
worst dot, and the median time; then per regime of the hidden set that a variant imitates
(its name: ``640x480`` distant, ``fisheye``, ``3024x4032`` large) the grids found and the median
error against the rim ellipse refitted on the image as delivered (``rim_in_image_px``: through the
lens the distorted dot's ellipse, as a hand fit on it), for RRHT's centres and its ellipse centres.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_stress import DETECTORS as STRESS_DETECTORS
from bench_stress import run as run_stress
from bench_stress import score

from tasks.machine.plate import DotPlate
from tasks.vision.detection import detect_grid
from tasks.vision.detection.debug_image import draw_detection

DETECTORS = (*STRESS_DETECTORS, "rrht ellipse")
"""The stress bench's detectors, and RRHT's ellipse centres (before the perspective-bias correction,
``GridDetection.ellipse_centres``, as ``fivecal detect --json`` also prints them)."""


def run(name: str, image: np.ndarray, plate: DotPlate) -> np.ndarray | None:
    """One detector's centres (rows*cols, 2) px, or None when it finds no grid."""
    if name == "rrht ellipse":
        det = detect_grid(image, plate, "rrht")
        return det.ellipse_centres if det.ok else None
    return run_stress(name, image, plate)


def regime(name: str) -> str:
    """The hidden set's regime a variant of ``real_photo_truth.py`` imitates, from its name."""
    if "fisheye" in name:
        return "fisheye"
    if "3024x4032" in name:
        return "large"
    if "640x480" in name:
        return "distant"
    return "other"


def photographs(folder: Path, only: str = "", invert: bool = False):
    """Read ``folder``'s photographs (bench/real_photo_truth.py's output) whose name contains ``only``, in
    name order; ``invert``: every image inverted (255 − grey) and the plate's dots light. Yields (json path,
    grey image, plate, truth px, dot size px, the other estimators: {"centroid",
    "sloped", "image rim"} px; "image rim" is the rim ellipse of the image as delivered, as a hand fit on it)."""
    for jpath in sorted(p for p in folder.glob("*.json") if only in p.stem):
        t = json.loads(jpath.read_text())
        image = cv2.imread(str(jpath.with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(f"{jpath.with_suffix('.png')}: missing or unreadable (truth {jpath})")
        plate = DotPlate(t["rows"], t["cols"], t["pitch_over_diameter"], 1.0, dark_dots=not invert)
        if invert:
            image = 255 - image
        others = {"centroid": np.array(t["centroid_px"]), "sloped": np.array(t["rim_sloped_px"]),
                  "image rim": np.array(t.get("rim_in_image_px", t["truth_px"]))}
        yield jpath, image, plate, np.array(t["truth_px"]), t["dot_diameter_px"], others


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="written by bench/real_photo_truth.py")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default="", help="only photographs whose name contains this")
    ap.add_argument("--debug", type=Path, default=None, help="write rrht's debug drawings here")
    ap.add_argument("--detector", action="append", choices=DETECTORS,
                    help="only these detectors (repeatable; default all)")
    ap.add_argument("--invert", action="store_true", help="light dots: every image inverted (255 - grey)")
    args = ap.parse_args()
    detectors = tuple(d for d in DETECTORS if not args.detector or d in args.detector)
    rows, warm = [], False
    for jpath, image, plate, truth, dot_px, others in photographs(args.folder, args.only, invert=args.invert):
        if not warm:
            for d in detectors:
                run(d, image, plate)
            warm = True
        out, times = {}, {d: [] for d in detectors}
        for _ in range(args.repeat):
            for d in detectors:
                t0 = time.perf_counter()
                out[d] = run(d, image, plate)
                times[d].append(time.perf_counter() - t0)
        if args.debug:
            args.debug.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(args.debug / f"{jpath.stem}.png"), draw_detection(image, detect_grid(image, plate), plate))
        row = {"name": jpath.stem, "regime": regime(jpath.stem),
               "spread": {k: float(np.median(np.linalg.norm(truth - v, axis=1))) for k, v in others.items()}}
        line = f"{jpath.stem:44s} d {dot_px:5.1f}px truth-centroid {row['spread']['centroid']:.2f}"
        for d in detectors:
            verdict, e = score(d, out[d], plate, truth, dot_px)
            e_other = {k: score(d, out[d], plate, v, dot_px)[1] for k, v in others.items()}
            row[d] = (verdict, e, e_other, 1e3 * statistics.median(times[d]))
            line += f" | {d} {verdict[:5]}" + (f" {np.median(e):.2f}" if e is not None else "")
        rows.append(row)
        print(line, flush=True)
    if not rows:
        print(f"no NAME.json in {args.folder}")
        return
    spread = {k: statistics.median(r["spread"][k] for r in rows) for k in ("centroid", "sloped")}
    print(f"\n{len(rows)} photographs; median over them of the per-photo median distance from the truth (rim "
          f"ellipse, flat levels) to the intensity centroids {spread['centroid']:.3f} px, to the rim ellipses "
          f"with sloped levels {spread['sloped']:.3f} px")
    print(f"{'detector':15s} {'found':>6s} {'refused':>8s} {'wrong':>6s} {'median err px':>14s} "
          f"{'vs centroid':>12s} {'vs sloped rim':>14s} {'worst dot px':>13s} {'median ms':>10s}")
    for d in detectors:
        n = {v: sum(r[d][0] == v for r in rows) for v in ("found", "refused", "wrong")}
        errs = [r[d][1] for r in rows if r[d][1] is not None]

        def med(es):
            return statistics.median(float(np.median(e)) for e in es) if es else float("nan")

        other = {k: med([r[d][2][k] for r in rows if r[d][2][k] is not None]) for k in ("centroid", "sloped")}
        worst = max(float(e.max()) for e in errs) if errs else float("nan")
        print(f"{d:15s} {n['found']:6d} {n['refused']:8d} {n['wrong']:6d} {med(errs):14.3f} {other['centroid']:12.3f} "
              f"{other['sloped']:14.3f} {worst:13.3f} {statistics.median(r[d][3] for r in rows):10.1f}")
    print("\nper regime (found / images; median of the per-photo median error against the rim-ellipse "
          "truth of the image as delivered, 'image rim')")
    regimes = sorted({r["regime"] for r in rows})
    print(f"{'detector':15s} " + " ".join(f"{g:>22s}" for g in regimes))
    for d in detectors:
        cells = []
        for g in regimes:
            rg = [r for r in rows if r["regime"] == g]
            es = [r[d][2]["image rim"] for r in rg if r[d][0] == "found" and r[d][2]["image rim"] is not None]
            n_wrong = sum(r[d][0] == "wrong" for r in rg)
            err = statistics.median(float(np.median(e)) for e in es) if es else float("nan")
            cells.append(f"{len(es)}/{len(rg)}{f' ({n_wrong} wrong)' if n_wrong else ''} {err:.3f}")
        print(f"{d:15s} " + " ".join(f"{c:>22s}" for c in cells))
    for ref in (d for d in ("cv2+clustering", "cv2") if d in detectors and "rrht" in detectors):
        both = [r for r in rows if r["rrht"][1] is not None and r[ref][1] is not None]
        if both:
            sp = statistics.mean(r[ref][3] for r in both) / statistics.mean(r["rrht"][3] for r in both)
            print(f"on the {len(both)} photographs rrht and {ref} both found: {ref} time / rrht time {sp:.2f}x, "
                  f"median error rrht {statistics.median(float(np.median(r['rrht'][1])) for r in both):.3f} px, "
                  f"{ref} {statistics.median(float(np.median(r[ref][1])) for r in both):.3f} px")


if __name__ == "__main__":
    main()
