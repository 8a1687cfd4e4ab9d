"""Benchmark: RRHT dot-grid detection vs the cv2.findCirclesGrid baseline, same images, same process.

    .venv/bin/python bench/bench_detection.py            # 12 full-size images, 5 repeats
    .venv/bin/python bench/bench_detection.py --quick    # 4 images, 3 repeats
    .venv/bin/python bench/bench_detection.py --hough    # also time the HoughCircles baseline
    taskset -c 0 .venv/bin/python bench/bench_detection.py --threads 1    # both detectors on one core
    .venv/bin/python bench/bench_detection.py --kernel-threads 2          # RRHT's compiled kernels on 2 threads

Images are rendered by ``tasks.simulation.render`` (3072×2048, the prototype's two cameras and plates, lens
distortion, defocus, vignetting, illumination gradient, shot and read noise) at poses with in-plane
rotations and tilts up to 30°, and held in memory as PNG bytes. Per image, the PNG is decoded,
then each detector runs ``--repeat`` times with the detectors interleaved (so that a busy machine
slows both alike); the median time per detector is kept. Centre error is the RMS distance (px) of
the detected centres to ``true_dot_centres`` (the projected 3D dot centres). Both detectors get
the expected in-plane rotation (the commanded angle) and no scale hint unless ``--hint``.
Wall times (``time.perf_counter``) and the process's CPU time (``time.process_time``, every
thread; on a host busy with other jobs the wall time also counts the waits for a core) are
both kept, and the calling thread's CPU time (``time.thread_time``: the work that does not run on
helper threads; on free cores about the wall time when the helpers keep up). ``--threads N`` sets
OpenCV's threads (``cv2.setNumThreads``: findCirclesGrid's and RRHT's OpenCV calls) and RRHT's own
(:mod:`tasks.vision.detection.parallel`, both its stage and its kernel threads) to N; by default OpenCV
uses the CPUs the process may run on, RRHT's stages one thread and its compiled kernels (those that
release the GIL) 2 threads while the host is not busy (load average below the CPUs), else one;
``--kernel-threads N`` sets only the latter.
Prints per-image rows, the summary ratios, and where RRHT's time goes.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.render import ImagingConditions, plate_in_view, render_plate_image, true_dot_centres
from tasks.vision.detection import detect_grid
from tasks.vision.detection.parallel import kernel_threads, set_kernel_threads, set_threads, threads

DIST1 = (-0.062, 0.115, 0.00012, -0.00018, -0.041)
DIST2 = (-0.071, 0.132, -0.00009, 0.00015, -0.056)
CAM1 = CameraModel(3072, 2048, 0.0024, 16.0, 1541.3, 1019.8, DIST1, focus_distance_mm=300.0, f_number=8.0)
CAM2 = CameraModel(3072, 2048, 0.0024, 16.0, 1529.6, 1027.1, DIST2, focus_distance_mm=80.0, f_number=8.0)
CAM_NEAR = CameraModel(3072, 2048, 0.0024, 16.0, 1536.0, 1024.0, DIST1, focus_distance_mm=130.0, f_number=8.0)
PLATE_A = DotPlate(7, 7, 5.0, 2.5, dark_dots=True, margin_mm=5.0, name="a")
PLATE_B = DotPlate(7, 7, 2.0, 1.0, dark_dots=True, margin_mm=2.0, name="b")


def pose(t, rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    """T_cam_plate with the printed face towards the camera; rz turns the plate clockwise on screen."""
    return facing_camera_pose(t, rx, ry, rz)


def scenes(n: int, seed: int = 0):
    """n (name, camera, plate, T_cam_plate, rotation_deg) with the whole plate in view."""
    rng = np.random.default_rng(seed)
    kinds = [("cam1/a", CAM1, PLATE_A, (260.0, 320.0)), ("cam2/b", CAM2, PLATE_B, (72.0, 90.0)),
             ("near/a", CAM_NEAR, PLATE_A, (115.0, 150.0))]
    out = []
    while len(out) < n:
        name, cam, plate, (z0, z1) = kinds[len(out) % len(kinds)]
        tilt = rng.uniform(0, 30) if len(out) >= len(kinds) else 0.0
        az = rng.uniform(0, 2 * np.pi)
        rz = rng.uniform(-180, 180)
        T = pose([rng.uniform(-5, 5), rng.uniform(-4, 4), rng.uniform(z0, z1)],
                 tilt * math.cos(az), tilt * math.sin(az), rz)
        if plate_in_view(cam, plate, T, border_px=20.0):
            out.append((f"{name} tilt {tilt:4.1f}", cam, plate, T, -rz))
    return out


def rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(((a - b) ** 2).sum(axis=1).mean()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--hint", action="store_true", help="pass px_per_mm_hint to every detector")
    ap.add_argument("--hough", action="store_true", help="also run the HoughCircles baseline")
    ap.add_argument("--threads", type=int, default=None,
                    help="OpenCV's and RRHT's threads (default: OpenCV the CPUs, RRHT one, its kernels 1–2)")
    ap.add_argument("--kernel-threads", type=int, default=None,
                    help="threads of RRHT's compiled kernels only (default: 2 unless the host is busy, else 1)")
    args = ap.parse_args()
    if args.threads is not None:
        cv2.setNumThreads(args.threads)
        set_threads(args.threads)
        set_kernel_threads(args.threads)
    if args.kernel_threads is not None:
        set_kernel_threads(args.kernel_threads)
    n_img, reps = (4, 3) if args.quick else (args.images, args.repeat)
    dets = ["rrht", "blob"] + (["hough"] if args.hough else [])
    print(f"cv2 {cv2.__version__}, numpy {np.__version__}, cv2 threads {cv2.getNumThreads()}, RRHT threads "
          f"{threads()} (kernels {kernel_threads()}), CPUs {len(os.sched_getaffinity(0))}; "
          f"{n_img} images, {reps} repeats, hint={args.hint}")
    rows = []
    stage_sums: dict[str, list[float]] = {}
    for i, (name, cam, plate, T, rot) in enumerate(scenes(n_img)):
        img = render_plate_image(cam, plate, T, ImagingConditions(), seed=100 + i)
        truth = true_dot_centres(cam, plate, T)
        png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1].tobytes()
        hint = cam.fx_px / T[2, 3] if args.hint else None
        dec_t = []
        times: dict[str, list[float]] = {d: [] for d in dets}
        cpu: dict[str, list[float]] = {d: [] for d in dets}
        main_cpu: dict[str, list[float]] = {d: [] for d in dets}
        stages: dict[str, list[float]] = {}
        results = {}
        for _ in range(reps):
            t0 = time.perf_counter()
            im = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
            dec_t.append(time.perf_counter() - t0)
            for d in dets:
                t0, c0, m0 = time.perf_counter(), time.process_time(), time.thread_time()
                res = detect_grid(im, plate, d, expected_rotation_deg=rot, px_per_mm_hint=hint)
                times[d].append(time.perf_counter() - t0)
                cpu[d].append(time.process_time() - c0)
                main_cpu[d].append(time.thread_time() - m0)
                results[d] = res
                if d == "rrht":
                    for k, v in res.timings_s.items():
                        stages.setdefault(k, []).append(v)
        r = results["rrht"]
        for k, v in stages.items():
            stage_sums.setdefault(k, []).append(statistics.median(v))
        stage_sums.setdefault("decode", []).append(statistics.median(dec_t))
        row = {"name": name, "dot_px": float(np.nanmean(2 * r.axes_px[:, 0])) if r.ok else float("nan")}
        for d in dets:
            row[d + "_ms"] = 1e3 * statistics.median(times[d])
            row[d + "_cpu_ms"] = 1e3 * statistics.median(cpu[d])
            row[d + "_main_ms"] = 1e3 * statistics.median(main_cpu[d])
            row[d + "_err"] = rms(results[d].centres, truth) if results[d].ok else float("nan")
            row[d + "_reason"] = results[d].reason
        rows.append(row)
        line = f"{name:22s} dot {row['dot_px']:5.0f}px"
        for d in dets:
            line += f" | {d} {row[d + '_ms']:6.1f} ms err {row[d + '_err']:.4f}px"
        print(line)
        for d in dets:
            if row[d + "_reason"]:
                print(f"    {d} failed: {row[d + '_reason']}")
    print()
    for d in dets:
        ms = [r[d + "_ms"] for r in rows]
        err = [r[d + "_err"] for r in rows if np.isfinite(r[d + "_err"])]
        print(f"{d:6s}: {statistics.mean(ms):7.1f} ms/image (median {statistics.median(ms):.1f}), "
              f"centre RMS {np.sqrt(np.mean(np.square(err))) if err else float('nan'):.4f} px over "
              f"{len(err)}/{len(rows)} detected")
    both = [r for r in rows if np.isfinite(r["rrht_err"]) and np.isfinite(r["blob_err"])]
    sp = statistics.mean(r["blob_ms"] for r in rows) / statistics.mean(r["rrht_ms"] for r in rows)
    sp_cpu = statistics.mean(r["blob_cpu_ms"] for r in rows) / statistics.mean(r["rrht_cpu_ms"] for r in rows)
    print(f"speed ratio findCirclesGrid/RRHT time: {sp:.2f}x wall, {sp_cpu:.2f}x CPU  (goal ≥ 2x); CPU ms/image: "
          + ", ".join(f"{d} {statistics.mean(r[d + '_cpu_ms'] for r in rows):.1f}" for d in dets)
          + "; calling thread's CPU ms/image: "
          + ", ".join(f"{d} {statistics.mean(r[d + '_main_ms'] for r in rows):.1f}" for d in dets))
    if both:
        e_r = np.sqrt(np.mean([r["rrht_err"] ** 2 for r in both]))
        e_b = np.sqrt(np.mean([r["blob_err"] ** 2 for r in both]))
        print(f"error ratio RRHT/findCirclesGrid (images both detected): {e_r / e_b:.2f}  (goal < 1)")
    print("\nRRHT time breakdown, mean over images of the median ms per stage (decode: PNG → array, "
          "done once for both detectors and not in their times):")
    order = ["decode", "preprocess", "edges", "sampling", "fitting_coarse", "ordering", "rim_sampling",
             "ellipse_fitting", "perspective"]
    notes = {"preprocess": "downsample, median, gamma", "edges": "Sobel, Canny, chain-code filter",
             "sampling": "RRHT gradient-guided sampling + accumulator", "fitting_coarse": "candidate LSQ + rim ratio",
             "ordering": "lattice + orientation", "rim_sampling": "full-res ray profiles, step fits",
             "ellipse_fitting": "RANSAC + LSQ ellipses", "perspective": "homography + centre bias"}
    for k in order + [k for k in stage_sums if k not in order]:
        if k in stage_sums:
            print(f"  {k:16s} {1e3 * statistics.mean(stage_sums[k]):6.2f}   {notes.get(k, '')}")


if __name__ == "__main__":
    main()
