"""Benchmark: the detectors on the renderer's stress set (tasks.simulation.detector_stress), same images, same process.

    .venv/bin/python bench/bench_stress.py                 # all cases, 3 timed repeats
    .venv/bin/python bench/bench_stress.py --seeds 3       # each case with 3 seeds (other noise, clutter)
    .venv/bin/python bench/bench_stress.py --case fisheye  # one case (repeatable)
    .venv/bin/python bench/bench_stress.py --random 200    # random cases: found / refused / wrongly labelled
    .venv/bin/python bench/bench_stress.py --random 80 --fisheye   # random fisheye frames (random_fisheye_case)
    .venv/bin/python bench/bench_stress.py --random 20 --garden phone   # garden photographs (garden_stress)
    .venv/bin/python bench/bench_stress.py --hand-fit      # centres against the truth and a hand-fit-like rim ellipse
    .venv/bin/python bench/bench_stress.py --envelope 8,12,20,50,150,400 --tilts 0,30,50   # the issue's envelope (RRHT)
    .venv/bin/python bench/bench_stress.py --blur-sweep 10,13,16 --blurs 1,2,3 --tilts 0,40   # neighbour model off / on
    .venv/bin/python bench/bench_stress.py --blur-sweep 10,13,16 --margin-mm 400   # … the sheet's edge out of reach

Each stress image (a 4 × 3 sheet of Ø 4 mm dots at a 6 mm pitch, rendered with lens distortion,
then paper texture, clutter, shadow, colour, JPEG and the conversion back to grey, as a user's
photograph) is rendered once and handed to every detector in turn, interleaved over the repeats;
the median wall time is kept. Detectors:

* rrht: ``detect_grid(image, plate, "rrht")`` (no hint, no rotation prior, as ``fivecal detect``);
* blob: our findCirclesGrid baseline (a SimpleBlobDetector tuned to the polarity and to dots of
  1/128…1/14 of the image side); hough: our HoughCircles baseline;
* cv2 / cv2+clustering: ``cv2.findCirclesGrid(image, (cols, rows), CALIB_CB_SYMMETRIC_GRID
  [| CALIB_CB_CLUSTERING])`` with OpenCV's default blob detector, the image inverted for light
  dots (what a user of OpenCV would run).

A grid counts as found when the detector says so and each true dot centre has exactly one
detected centre within a quarter of the dot size (labels are not compared: OpenCV's order is its
own); the centre error is that distance. Prints one row per image, then per detector the found
rate, the median and worst centre error, the median time, and the time and error ratios against
cv2.findCirclesGrid on the images both found.

``--random N`` draws N cases with :func:`tasks.simulation.detector_stress.random_case` (those whose dots are
not all wholly in view are skipped) and counts, for RRHT and findCirclesGrid with clustering, the
grids found and correctly labelled (RRHT: each dot within a quarter of its size of its own true
centre, up to the grid's symmetry, a mirrored labelling wrong; OpenCV: one-to-one as above), refused,
and found but wrong, and the worst dot's error over the grids found;
findCirclesGrid without clustering too. ``--garden REGIME`` draws garden photographs of a sheet on a
clipboard (:func:`tasks.simulation.garden_stress.random_garden_case`: phone, fisheye or distant).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tasks.machine.plate import DotPlate
from tasks.simulation.detector_stress import (
    ISSUE_PLATE,
    STRESS_CASES,
    StressCase,
    errors_up_to_symmetry,
    random_case,
    random_fisheye_case,
    render_stress_case,
)
from tasks.simulation.garden_stress import GARDEN_REGIMES, random_garden_case, render_garden_case
from tasks.vision.detection import detect_grid
from tasks.vision.detection.framework import FrameworkParams, detect_rrht
from tasks.vision.detection.subpixel import SubpixelParams

DETECTORS = ("rrht", "blob", "hough", "cv2", "cv2+clustering")


def run_opencv(image: np.ndarray, plate: DotPlate, clustering: bool) -> np.ndarray | None:
    """cv2.findCirclesGrid with OpenCV's default blob detector: (rows*cols, 2) px or None."""
    img = image if plate.dark_dots else cv2.bitwise_not(image)
    flags = cv2.CALIB_CB_SYMMETRIC_GRID | (cv2.CALIB_CB_CLUSTERING if clustering else 0)
    ok, c = cv2.findCirclesGrid(img, (plate.cols, plate.rows), flags=flags)
    return c.reshape(-1, 2).astype(float) if ok and c is not None else None


def run(name: str, image: np.ndarray, plate: DotPlate) -> np.ndarray | None:
    if name in ("cv2", "cv2+clustering"):
        return run_opencv(image, plate, name == "cv2+clustering")
    det = detect_grid(image, plate, name)
    return det.centres if det.ok else None


def match_errors(found: np.ndarray | None, truth: np.ndarray, dot_px: float) -> np.ndarray | None:
    """Distance (px) from each true centre to its detected one, or None unless one-to-one."""
    if found is None or len(found) != len(truth) or not np.isfinite(found).all():
        return None
    d, j = cKDTree(found).query(truth)
    if len(np.unique(j)) != len(truth) or d.max() > 0.25 * dot_px:
        return None
    return d


def score(detector: str, centres: np.ndarray | None, plate: DotPlate, truth: np.ndarray,
          dot_px: float) -> tuple[str, np.ndarray | None]:
    """("found" | "refused" | "wrong", per-dot errors px or None) of one detector's answer. RRHT
    (any name starting "rrht"): found when every dot lies within a quarter of the dot size of the true
    centre its label names, up to the grid's symmetry; the others order the grid their own way: found
    when one-to-one within a quarter of the dot size (:func:`match_errors`)."""
    if centres is None:
        return "refused", None
    if detector.startswith("rrht"):
        e = errors_up_to_symmetry(plate, centres, truth)
        return ("found", e) if e.max() < 0.25 * dot_px else ("wrong", None)
    e = match_errors(centres, truth, dot_px)
    return ("found", e) if e is not None else ("wrong", None)


def mirrored(plate: DotPlate, centres: np.ndarray, truth: np.ndarray) -> bool:
    """Whether a labelling (rows*cols, 2) px fits the truth better with its rows or its columns alone
    flipped than as it is or turned by half a turn: the wrong handedness, which
    :func:`errors_up_to_symmetry` accepts (on renders the truth has the plate's own handedness)."""
    g = centres.reshape(plate.rows, plate.cols, 2)
    proper = min(float(np.median(np.linalg.norm(c.reshape(-1, 2) - truth, axis=1))) for c in (g, g[::-1, ::-1]))
    return proper > float(np.median(errors_up_to_symmetry(plate, centres, truth)))


def stress_images(cases, seeds: int):
    """Render each named stress case with ``seeds`` seeds (case.seed, +100, +200 …). Yields (case, image,
    truth px, plate)."""
    for case in cases:
        for s in range(seeds):
            c = replace(case, seed=case.seed + 100 * s)
            image, truth = render_stress_case(c)
            yield c, image, truth, replace(c.plate, dark_dots=c.dark_dots)


def random_images(n: int, seed: int, fisheye: bool = False, garden: str | None = None):
    """Render ``n`` random draws (seed ``seed``): :func:`random_case`, :func:`random_fisheye_case` with
    ``fisheye``, or garden photographs of the regime ``garden``. Yields (geometry, image, truth px, plate,
    description) for the draws whose dots are all wholly in view; the others are skipped."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        if garden:
            case = random_garden_case(rng, f"{garden}-{i}", garden)
            if case is None:
                continue
            image, truth = render_garden_case(case)
            geometry, jpeg = case.geometry, case.jpeg
            what = f"margin {case.sheet_margin_mm:4.1f}mm shadow {case.shadow:.2f}"
        else:
            geometry = (random_fisheye_case if fisheye else random_case)(rng, f"random-{i}")
            if geometry is None:
                continue
            image, truth = render_stress_case(geometry)
            what, jpeg = f"blur {geometry.defocus_px:.0f}", geometry.jpeg
        what = (f"{geometry.width}x{geometry.height} dot {geometry.dot_px:5.1f}px tilt {geometry.tilt_deg:4.1f} "
                f"k1 {geometry.k1:+.2f} {what} jpeg {jpeg:2d} {'dark' if geometry.dark_dots else 'light'}")
        yield geometry, image, truth, replace(ISSUE_PLATE, dark_dots=geometry.dark_dots), what


def random_run(n: int, seed: int, fisheye: bool = False, garden: str | None = None) -> None:
    """Random stress cases (``garden``: garden photographs of that regime, garden_stress.random_garden_case):
    found / refused / wrong for RRHT and cv2.findCirclesGrid with and without clustering, same images."""
    detectors = ("rrht", "cv2+clustering", "cv2")
    counts = {d: {"found": 0, "refused": 0, "wrong": 0} for d in detectors}
    errs: dict[str, list[float]] = {d: [] for d in counts}
    worst: dict[str, list[float]] = {d: [] for d in counts}
    n_cases = 0
    for geometry, image, truth, plate, what in random_images(n, seed, fisheye, garden):
        n_cases += 1
        verdicts = []
        for d in counts:
            det = detect_grid(image, plate, "rrht") if d == "rrht" else None
            c = run(d, image, plate) if det is None else (det.centres if det.ok else None)
            verdict, e = score(d, c, plate, truth, geometry.dot_px)
            if d == "rrht" and verdict == "found" and mirrored(plate, c, truth):
                verdict, e = "wrong", None
            errs[d] += [float(np.median(e))] if e is not None else []
            worst[d] += [float(e.max())] if e is not None else []
            counts[d][verdict] += 1
            verdicts.append(f"{d} {verdict}" + (f" ({det.reason})" if det is not None and c is None else ""))
        print(f"{geometry.name:11s} {what}: " + ", ".join(verdicts), flush=True)
    print(f"\n{n_cases} random cases in view (of {n} drawn, seed {seed})")
    for d, c in counts.items():
        med = statistics.median(errs[d]) if errs[d] else float("nan")
        worst_dot = max(worst[d]) if worst[d] else float("nan")
        print(f"{d:15s} found {c['found']}, refused {c['refused']}, wrong {c['wrong']}; "
              f"median of the per-image median centre errors {med:.3f} px, worst dot {worst_dot:.3f} px")


def envelope_run(dot_sizes: list[float], tilts: list[float], size: str | None, defocus_px: float, k1: float) -> None:
    """RRHT on a grid of cases: each dot size (px) × tilt (deg) × polarity, with clutter, paper texture, a
    shadow edge, uneven light, colour and JPEG 80; images 640 × 480 below 20 px dots, 1280 × 960 below 100 px,
    3024 × 4032 above (or ``size`` "WxH"); extra blur σ ``defocus_px``; with ``k1`` ≠ 0 the fisheye-like lens
    (k2 0.1, f 0.55 × the longer side, the plate off its axis). Prints the verdict (found / refused / WRONG), the
    wall time and the median and worst centre error."""
    for d in dot_sizes:
        w, h = (3024, 4032) if d >= 100 else ((1280, 960) if d >= 20 else (640, 480))
        if size:
            w, h = (int(x) for x in size.split("x"))
        for tilt in tilts:
            for dark in (True, False):
                case = StressCase(f"envelope-{d:g}px-{tilt:g}deg", w, h, d, tilt_deg=tilt, tilt_azimuth_deg=37.0,
                                  spin_deg=20.0, dark_dots=dark, clutter=30, texture=True, shadow=0.5, gradient=0.8,
                                  vignetting=0.3, colour=True, jpeg=80, seed=1000, defocus_px=defocus_px, k1=k1,
                                  k2=0.1 if k1 else 0.0, focal_px=0.55 * max(w, h) if k1 else 0.0,
                                  offset=(0.2, -0.15) if k1 else (0.0, 0.0))
                image, truth = render_stress_case(case)
                plate = replace(case.plate, dark_dots=dark)
                t0 = time.perf_counter()
                det = detect_grid(image, plate, "rrht")
                ms = 1e3 * (time.perf_counter() - t0)
                if det.ok:
                    e = errors_up_to_symmetry(plate, det.centres, truth)
                    verdict = "found" if e.max() < 0.25 * d else "WRONG"
                    what = f"median {np.median(e):.3f} px, worst {e.max():.3f} px"
                else:
                    verdict, what = "refused", det.reason
                print(f"{case.name:22s} {w}x{h} {'dark ' if dark else 'light'} blur {defocus_px:g} k1 {k1:+.2f} "
                      f"{verdict:7s} {ms:6.0f} ms  {what}", flush=True)


def blur_sweep_run(dot_sizes: list[float], blurs: list[float], tilts: list[float], scene: bool,
                   margin_mm: float | None = None) -> None:
    """RRHT's centre error (median / worst px against the true centres, up to the grid's symmetry) with
    the rim fits' neighbour model off and on (``SubpixelParams.neighbour_iterations`` 0 and its
    default), same image, on 640 × 480 renders of each dot size (px) × extra blur σ (px) × tilt (deg)
    × polarity: a plain sheet (even light), or with ``scene`` the envelope's (clutter, paper texture, a
    shadow edge, uneven light, colour, JPEG 80); ``margin_mm``: the sheet's margin beyond the outer dots'
    centres (the stress plate's 5 mm by default; 400 puts its edge out of the rays' reach)."""
    on = SubpixelParams().neighbour_iterations
    for d in dot_sizes:
        for blur in blurs:
            for tilt in tilts:
                for dark in (True, False):
                    extra = dict(clutter=30, texture=True, shadow=0.5, gradient=0.8, vignetting=0.3, colour=True,
                                 jpeg=80) if scene else dict(gradient=0.0, vignetting=0.0)
                    if margin_mm is not None:
                        extra["plate"] = replace(ISSUE_PLATE, margin_mm=margin_mm)
                    case = StressCase(f"blur-{d:g}px-{blur:g}", 640, 480, d, tilt_deg=tilt, tilt_azimuth_deg=37.0,
                                      spin_deg=20.0, dark_dots=dark, seed=1000, defocus_px=blur, **extra)
                    image, truth = render_stress_case(case)
                    plate = replace(case.plate, dark_dots=dark)
                    cells = []
                    for iterations in (0, on):
                        det = detect_rrht(image, plate, params=FrameworkParams(
                            subpixel=SubpixelParams(neighbour_iterations=iterations)))
                        if det.ok:
                            e = errors_up_to_symmetry(plate, det.centres, truth)
                            cells.append(f"{np.median(e):.3f} / {e.max():.3f}")
                        else:
                            cells.append("refused")
                    print(f"{d:4g} px  blur {blur:g}  tilt {tilt:2g}  {'dark ' if dark else 'light'}  "
                          f"off {cells[0]:>15s}  on {cells[1]:>15s}", flush=True)


def hand_fit_run(cases) -> None:
    """Per case: RRHT's perspective-corrected ``centres`` and its ``ellipse_centres`` against the true
    projected dot centres and against the rim ellipse of each dot in the image
    (``real_photo_truth.rim_ellipse_centres``, what a hand-fitted ellipse measures), median px."""
    from real_photo_truth import rim_ellipse_centres

    print(f"{'case':18s} {'vs true centre: centres / ellipse':>34s} {'vs rim ellipse: centres / ellipse':>36s}")
    for case in cases:
        image, truth = render_stress_case(case)
        plate = replace(case.plate, dark_dots=case.dark_dots)
        det = detect_grid(image, plate, "rrht")
        if not det.ok:
            print(f"{case.name:18s} refused: {det.reason}")
            continue
        rim = rim_ellipse_centres(image if case.dark_dots else 255 - image, det.ellipse_centres,
                                  np.sqrt(det.axes_px[:, 0] * det.axes_px[:, 1]))

        def med(a, b, plate=plate):
            return float(np.median(errors_up_to_symmetry(plate, a, b)))

        print(f"{case.name:18s} {med(det.centres, truth):17.3f} / {med(det.ellipse_centres, truth):.3f} px "
              f"{med(det.centres, rim):19.3f} / {med(det.ellipse_centres, rim):.3f} px", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=1, help="renders per case (seeds case.seed, +100, +200 …)")
    ap.add_argument("--case", action="append", help="only these cases (repeatable)")
    ap.add_argument("--detector", action="append", choices=DETECTORS,
                    help="only these detectors on the stress cases (repeatable; default all)")
    ap.add_argument("--random", type=int, default=0, help="draw this many random cases instead")
    ap.add_argument("--random-seed", type=int, default=0)
    ap.add_argument("--fisheye", action="store_true", help="random cases through the fisheye lens "
                    "(detector_stress.random_fisheye_case) instead")
    ap.add_argument("--garden", choices=GARDEN_REGIMES, help="with --random: garden photographs of this regime "
                    "(garden_stress.random_garden_case) instead")
    ap.add_argument("--hand-fit", action="store_true", help="RRHT's centres and ellipse centres against the true "
                    "centres and against a hand-fit-like rim ellipse, per case")
    ap.add_argument("--envelope", help="dot sizes px, comma-separated: RRHT on the envelope grid (envelope_run)")
    ap.add_argument("--tilts", default="0,30,50", help="with --envelope: tilts, deg")
    ap.add_argument("--size", help="with --envelope: image size WxH instead of one by dot size")
    ap.add_argument("--defocus", type=float, default=0.0, help="with --envelope: extra blur σ px")
    ap.add_argument("--k1", type=float, default=0.0, help="with --envelope: radial distortion (−0.35: fisheye)")
    ap.add_argument("--blur-sweep", help="dot sizes px, comma-separated: centre errors with the rim fits' neighbour "
                                         "model off and on (blur_sweep_run)")
    ap.add_argument("--blurs", default="1,2,3", help="with --blur-sweep: extra blur σ px")
    ap.add_argument("--scene", action="store_true", help="with --blur-sweep: the envelope's scene, not a plain sheet")
    ap.add_argument("--margin-mm", type=float,
                    help="with --blur-sweep: the sheet's margin beyond the outer dots' centres (default 5 mm)")
    args = ap.parse_args()
    if args.envelope:
        envelope_run([float(x) for x in args.envelope.split(",")], [float(x) for x in args.tilts.split(",")],
                     args.size, args.defocus, args.k1)
        return
    if args.blur_sweep:
        blur_sweep_run([float(x) for x in args.blur_sweep.split(",")], [float(x) for x in args.blurs.split(",")],
                       [float(x) for x in args.tilts.split(",")], args.scene, args.margin_mm)
        return
    if args.hand_fit:
        hand_fit_run([c for c in STRESS_CASES if not args.case or c.name in args.case])
        return
    if args.random:
        random_run(args.random, args.random_seed, args.fisheye, args.garden)
        return
    cases = [c for c in STRESS_CASES if not args.case or c.name in args.case]
    detectors = tuple(d for d in DETECTORS if not args.detector or d in args.detector)
    print(f"cv2 {cv2.__version__}, cv2 threads {cv2.getNumThreads()}; {len(cases)} cases × {args.seeds} seeds, "
          f"{args.repeat} repeats")
    rows = []
    warm = False
    for c, image, truth, plate in stress_images(cases, args.seeds):
        if not warm:  # lazy initialisation and compiled code outside the timings
            for d in detectors:
                run(d, image, plate)
            warm = True
        times = {d: [] for d in detectors}
        cpu = {d: [] for d in detectors}
        out = {}
        for _ in range(args.repeat):
            for d in detectors:
                t0, c0 = time.perf_counter(), time.process_time()
                out[d] = run(d, image, plate)
                times[d].append(time.perf_counter() - t0)
                cpu[d].append(time.process_time() - c0)
        row = {"case": c.name, "seed": c.seed, "size": f"{c.width}x{c.height}", "dot_px": c.dot_px}
        line = f"{c.name:17s} s{c.seed:<4d}"
        for d in detectors:
            err = match_errors(out[d], truth, c.dot_px)
            row[d + "_ms"] = 1e3 * statistics.median(times[d])
            row[d + "_cpu_ms"] = 1e3 * statistics.median(cpu[d])
            row[d + "_err"] = err
            line += f" | {d} {'ok ' if err is not None else '-- '}{row[d + '_ms']:6.0f} ms"
            line += f" {np.median(err):.3f}px" if err is not None else "        "
        rows.append(row)
        print(line, flush=True)
    print()
    print(f"{'detector':15s} {'found':>7s} {'median err px':>14s} {'worst err px':>13s} {'median ms':>10s}")
    for d in detectors:
        errs = [r[d + "_err"] for r in rows if r[d + "_err"] is not None]
        med = statistics.median([float(np.median(e)) for e in errs]) if errs else float("nan")
        worst = max(float(e.max()) for e in errs) if errs else float("nan")
        print(f"{d:15s} {len(errs):3d}/{len(rows):<3d} {med:14.3f} {worst:13.3f} "
              f"{statistics.median(r[d + '_ms'] for r in rows):10.1f}")
    for ref in (d for d in ("cv2", "cv2+clustering", "blob") if d in detectors):
        both = [r for r in rows if r["rrht_err"] is not None and r[ref + "_err"] is not None]
        if both:
            sp = statistics.mean(r[ref + "_ms"] for r in both) / statistics.mean(r["rrht_ms"] for r in both)
            er = (statistics.median(float(np.median(r["rrht_err"])) for r in both)
                  / statistics.median(float(np.median(r[ref + "_err"])) for r in both))
            print(f"on the {len(both)} images both found: {ref} time / rrht time {sp:.2f}x, "
                  f"rrht median error / {ref} median error {er:.2f}")
    big = [r for r in rows if r["size"] == "3024x4032"]
    if big:
        print(f"12 MP photographs: rrht median {statistics.median(r['rrht_ms'] for r in big):.0f} ms, "
              f"worst {max(r['rrht_ms'] for r in big):.0f} ms wall (goal < 500 ms); CPU median "
              f"{statistics.median(r['rrht_cpu_ms'] for r in big):.0f} ms, worst "
              f"{max(r['rrht_cpu_ms'] for r in big):.0f} ms")


if __name__ == "__main__":
    main()
