"""Benchmark: the detectors on real photographs of a large dot grid, cut down to a small one.

    .venv/bin/python bench/bench_real_photos.py PHOTO... [--rows 4 --cols 3] [--out DIR]

Real photographs of a plate with many dots (e.g. the UCL calibration grid of
SciKit-Surgery/scikit-surgeryimage, tests/data/calib-ucl-circles, BSD-3-Clause; not committed
here) are turned into photographs of a rows × cols grid: every dot-like region of the photograph
is found (:func:`tasks.detection.blobs.contour_candidates`, full resolution), the rows × cols
block of dots nearest the image centre is kept and every other region (the rest of the grid and
any fiducials) is inpainted from the paper around it (``cv2.inpaint``). The dots kept are the
photograph's own pixels: its blur, noise, colour, lighting, perspective and lens distortion.

There is no ground truth, so accuracy is measured as consistency: the RMS residual (px) of a
homography fitted to the detector's rows × cols centres (over a block of a few dots a lens's
distortion is nearly projective; with ``--camera`` the centres are undistorted first, and the
residual is then mostly centre noise), and the distance of
each detector's centres to rrht's. Detectors as in bench/bench_stress.py, in the same process on
the same images. ``--out`` writes the cut-down images and rrht's debug drawings.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_stress import DETECTORS, run

from tasks.detection import detect_grid
from tasks.detection.blobs import contour_candidates
from tasks.detection.debug_image import draw_detection
from tasks.detection.grid import build_lattice, reduce_lattice
from tasks.detection.perspective import fit_homography, project
from tasks.plate import DotPlate


def cut_down(grey: np.ndarray, rows: int, cols: int) -> tuple[np.ndarray, float] | None:
    """(image with only a rows × cols block of dots left, pitch / diameter), or None."""
    blobs = contour_candidates(grey, True, 6.0, max(grey.shape) / 6.0)
    if len(blobs) < rows * cols:
        return None
    d = 2 * np.sqrt(blobs.axes[:, 0] * blobs.axes[:, 1])
    common = np.abs(d / np.median(d) - 1.0) < 0.4  # the grid's dots, not its fiducials
    pts, dd = blobs.centres[common], d[common]
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    ratio = float(np.median(nn) / np.median(dd))
    mn, assigned = build_lattice(pts, dd, ratio)
    sel = np.flatnonzero(assigned)
    if len(sel) < rows * cols:
        return None
    g = reduce_lattice(mn[sel])
    h, w = grey.shape
    centre = np.array([w / 2, h / 2])
    seed = int(np.argmin(np.linalg.norm(pts[sel] - centre, axis=1)))
    lo = g[seed] - np.array([rows // 2, cols // 2])
    block = np.all((g >= lo) & (g < lo + np.array([rows, cols])), axis=1)
    if block.sum() != rows * cols:
        return None
    keep = np.zeros(len(blobs), bool)
    keep[np.flatnonzero(common)[sel[block]]] = True
    mask = np.zeros(grey.shape, np.uint8)
    for (u, v), (a, b), th, k in zip(blobs.centres, blobs.axes, blobs.theta, keep, strict=True):
        if not k:
            cv2.ellipse(mask, ((float(u), float(v)), (2.6 * a + 6, 2.6 * b + 6), float(np.degrees(th))), 255, -1)
    return cv2.inpaint(grey, mask, 5, cv2.INPAINT_TELEA), ratio


def homography_rms(centres: np.ndarray, plate: DotPlate, camera: tuple[np.ndarray, np.ndarray] | None) -> float:
    """RMS residual (px) of a homography from the plate's dot positions to ``centres`` (rows*cols, 2),
    given in the plate's row-major order; with ``camera`` (K (3, 3), OpenCV distortion) the
    centres are undistorted first (to pixels of the same K)."""
    xy = plate.dot_centres_mm()[:, :2]
    if camera is not None:
        k, dist = camera
        centres = cv2.undistortPoints(centres.reshape(-1, 1, 2), k, dist, P=k).reshape(-1, 2)
    h = fit_homography(xy, centres)
    return float(np.sqrt(np.mean(np.sum((project(h, xy) - centres) ** 2, axis=1))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="+", type=Path)
    ap.add_argument("--rows", type=int, default=4)
    ap.add_argument("--cols", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--camera", nargs=2, type=Path, metavar=("K.txt", "DIST.txt"),
                    help="the photos' intrinsic matrix and distortion (whitespace-separated text, OpenCV model): "
                         "centres are undistorted before the homography fit")
    args = ap.parse_args()
    camera = None
    if args.camera:
        camera = (np.loadtxt(args.camera[0]).reshape(3, 3), np.loadtxt(args.camera[1]).ravel())
    rows = []
    for path in args.photos:
        raw = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if raw is None:
            print(f"{path}: not an image OpenCV can read")
            continue
        grey = cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
        cut = cut_down(grey, args.rows, args.cols)
        if cut is None:
            print(f"{path.name}: no {args.rows}x{args.cols} block of dots to keep")
            continue
        image, ratio = cut
        plate = DotPlate(args.rows, args.cols, ratio, 1.0)
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(args.out / f"{path.stem}_grid.png"), image)
            cv2.imwrite(str(args.out / f"{path.stem}_debug.png"),
                        draw_detection(image, detect_grid(image, plate, "rrht"), plate))
        out, times = {}, {d: [] for d in DETECTORS}
        for _ in range(args.repeat):
            for d in DETECTORS:
                t0 = time.perf_counter()
                out[d] = run(d, image, plate)
                times[d].append(time.perf_counter() - t0)
        ref = out["rrht"]
        row = {"photo": path.name}
        line = f"{path.name:32s} pitch/d {ratio:4.2f}"
        for d in DETECTORS:
            c = out[d]
            row[d + "_ms"] = 1e3 * statistics.median(times[d])
            if c is None or not np.isfinite(c).all():
                row[d + "_rms"] = row[d + "_to_rrht"] = None
                line += f" | {d} --"
                continue
            if d == "rrht":
                row[d + "_rms"] = homography_rms(c, plate, camera)
            else:  # their own order: put their centres in rrht's order (nearest), then fit
                j = cKDTree(c).query(ref)[1] if ref is not None else np.arange(len(c))
                one_to_one = ref is not None and len(set(j)) == len(c)
                row[d + "_rms"] = homography_rms(c[j], plate, camera) if one_to_one else None
            row[d + "_to_rrht"] = (float(np.median(cKDTree(c).query(ref)[0])) if ref is not None else None)
            line += f" | {d} ok {row[d + '_ms']:5.0f} ms H-rms {row[d + '_rms'] or float('nan'):.3f}"
        rows.append(row)
        print(line, flush=True)
    if not rows:
        return
    print(f"\n{'detector':15s} {'found':>7s} {'median H-rms px':>16s} {'median |c - rrht| px':>21s} {'median ms':>10s}")
    for d in DETECTORS:
        ok = [r for r in rows if r[d + "_rms"] is not None]
        rms = statistics.median(r[d + "_rms"] for r in ok) if ok else float("nan")
        to = [r[d + "_to_rrht"] for r in ok if r[d + "_to_rrht"] is not None]
        print(f"{d:15s} {len(ok):3d}/{len(rows):<3d} {rms:16.3f} {statistics.median(to) if to else float('nan'):21.3f} "
              f"{statistics.median(r[d + '_ms'] for r in rows):10.1f}")


if __name__ == "__main__":
    main()
