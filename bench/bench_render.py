"""Full-size (3072×2048) plate images: images per second and ms per image, against baselines.

Each image gets its own intrinsics (focal drift ~1e-4, so no per-camera cache helps) and one of
a few realistic poses (camera 1 / plate "a" at ~280 mm, camera 2 / plate "b" at ~80 mm, tilts up
to 15°).  Run side by side in this process on one core (OpenCV and BLAS threads set to 1):

* ``tasks.simulation.render.render_plate_image`` (tiled exact coverage, coarse undistortion grid);
* baseline "naive": the same physics done full frame — exact Newton undistortion of every
  pixel, per-pixel plate coordinates and edge coverage, full-frame blur (one σ) and noise;
* baseline "cv2 draw": anti-aliased ``cv2.ellipse``/``cv2.fillPoly`` of the projected outlines
  (fitted ellipses, 1/16 px), full-frame blur and noise — fast but only approximately right.

Also prints each renderer's noiseless centroid error against the projected dot centres.

    python bench/bench_render.py [--n 10] [--baseline-n 2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import dataclasses
import math
import time

import cv2
import numpy as np

from tasks.machine.camera_model import CameraModel
from tasks.machine.distortion import project_points_ext, undistort_pixels
from tasks.machine.plate import DotPlate
from tasks.simulation.render import ImagingConditions, blur_sigma_px, gain_map, render_plate_image, true_dot_centres

DIST = (-0.08, 0.12, 1e-4, -2e-4, -0.05)
CAM1 = CameraModel(3072, 2048, 0.0024, 16.0, 1535.7, 1023.2, DIST, focus_distance_mm=280.0, f_number=8.0, name="cam1")
CAM2 = CameraModel(3072, 2048, 0.0024, 16.0, 1538.1, 1020.6, DIST, focus_distance_mm=80.0, f_number=8.0, name="cam2")
PLATE_A = DotPlate(7, 7, 5.0, 2.5, dark_dots=True, margin_mm=5.0, name="a")
PLATE_B = DotPlate(7, 7, 2.0, 1.0, dark_dots=True, margin_mm=3.0, name="b")


def pose(t, rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    """T_cam_plate, plate face towards the camera, tilted rx about X then ry about Y (deg)."""
    rx, ry, rz = np.radians([rx, ry, rz])
    Rx = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    Ry = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    Rz = np.array([[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = t
    return T


SCENES = [
    (CAM1, PLATE_A, pose([3.0, -2.0, 280.0], 2.0, 1.0, 5.0)),
    (CAM1, PLATE_A, pose([-20.0, 12.0, 284.0], 12.0, -8.0, -30.0)),
    (CAM2, PLATE_B, pose([1.0, 1.0, 80.0], 1.0, 2.0, 3.0)),
    (CAM2, PLATE_B, pose([-3.0, 2.0, 81.0], 15.0, 10.0, 60.0)),
]


# --------------------------------------------------------------------------------------------
# Baselines
# --------------------------------------------------------------------------------------------


def _noise_and_quantise(img: np.ndarray, cond: ImagingConditions, rng: np.random.Generator) -> np.ndarray:
    var = np.maximum(img, 0.0) / cond.shot_noise_gain_e_per_dn + cond.read_noise_dn**2
    img = img + np.sqrt(var) * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def naive_render(camera, plate, T, cond, seed, noiseless=False) -> np.ndarray:
    """Full-frame: every pixel undistorted exactly, per-pixel coverage, one blur σ."""
    h, w = camera.height_px, camera.width_px
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    xy = undistort_pixels(np.stack([uu, vv], -1), camera)
    Hi = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))
    hom = xy @ Hi[:, :2].T + Hi[:, 2]
    X, Y = hom[..., 0] / hom[..., 2], hom[..., 1] / hom[..., 2]
    # local scale (mm per px) from the per-pixel Jacobian
    dXu, dXv = np.gradient(X, axis=1), np.gradient(X, axis=0)
    dYu, dYv = np.gradient(Y, axis=1), np.gradient(Y, axis=0)
    p = plate.pitch_mm
    c = np.clip(np.rint(X / p + (plate.cols - 1) / 2), 0, plate.cols - 1)
    r = np.clip(np.rint(Y / p + (plate.rows - 1) / 2), 0, plate.rows - 1)
    dx, dy = X - (c - (plate.cols - 1) / 2) * p, Y - (r - (plate.rows - 1) / 2) * p
    dist = np.hypot(dx, dy) + 1e-12
    gu, gv = (dXu * dx + dYu * dy) / dist, (dXv * dx + dYv * dy) / dist
    dot = np.clip(0.5 - (dist - plate.dot_diameter_mm / 2) / np.hypot(gu, gv), 0, 1)
    hx, hy = plate.half_extent_mm
    ex = (np.abs(X) - hx) / np.hypot(dXu, dXv)
    ey = (np.abs(Y) - hy) / np.hypot(dYu, dYv)
    on = np.clip(0.5 - np.maximum(ex, ey), 0, 1)
    L_plate, L_dot = cond.plate_and_dot_levels(plate)
    img = (cond.background_level + on * ((L_plate - cond.background_level) + dot * (L_dot - L_plate))).astype(
        np.float32
    )
    sigma = float(blur_sigma_px(camera, cond, T[2, 3]))
    img = cv2.GaussianBlur(img, (0, 0), sigma) * gain_map(camera, cond)
    if noiseless:
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return _noise_and_quantise(img, cond, np.random.default_rng(seed))


def cv2_draw_render(camera, plate, T, cond, seed, noiseless=False) -> np.ndarray:
    """Anti-aliased OpenCV drawing of fitted ellipses and the plate outline, at 1/16 px."""
    shift, s = 4, 16.0
    L_plate, L_dot = cond.plate_and_dot_levels(plate)
    img = np.full((camera.height_px, camera.width_px), cond.background_level, np.float32)
    hx, hy = plate.half_extent_mm
    t = np.linspace(-1, 1, 40)
    outline = np.concatenate(
        [
            np.stack([hx * t, -hy + 0 * t], 1),
            np.stack([hx + 0 * t, hy * t], 1),
            np.stack([-hx * t, hy + 0 * t], 1),
            np.stack([-hx + 0 * t, -hy * t], 1),
        ]
    )
    pts = np.c_[outline, np.zeros(len(outline))] @ T[:3, :3].T + T[:3, 3]
    poly = np.rint(project_points_ext(pts, camera) * s).astype(np.int32)
    cv2.fillPoly(img, [poly], L_plate, cv2.LINE_AA, shift)
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    R = plate.dot_diameter_mm / 2
    rim = np.stack([R * np.cos(a), R * np.sin(a), 0 * a], 1)
    for c in plate.dot_centres_mm():
        uv = project_points_ext((c + rim) @ T[:3, :3].T + T[:3, 3], camera).astype(np.float32)
        (cx, cy), (w, h), ang = cv2.fitEllipse(uv)
        cv2.ellipse(
            img,
            (round(cx * s), round(cy * s)),
            (round(w * s / 2), round(h * s / 2)),
            ang,
            0,
            360,
            L_dot,
            -1,
            cv2.LINE_AA,
            shift,
        )
    sigma = float(blur_sigma_px(camera, cond, T[2, 3]))
    img = cv2.GaussianBlur(img, (0, 0), sigma) * gain_map(camera, cond)
    if noiseless:
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return _noise_and_quantise(img, cond, np.random.default_rng(seed))


# --------------------------------------------------------------------------------------------


def centroid_error(img, camera, plate, T, level) -> float:
    """Max |intensity centroid − projected centre| (px) over all dots, noiseless image."""
    centres = true_dot_centres(camera, plate, T)
    scale = camera.fx_px / T[2, 3]
    half = round(scale * (plate.dot_diameter_mm / 2 + 0.3 * (plate.pitch_mm - plate.dot_diameter_mm)))
    err = 0.0
    for u, v in centres:
        j0, i0 = round(u) - half, round(v) - half
        w = np.abs(img[i0 : i0 + 2 * half + 1, j0 : j0 + 2 * half + 1].astype(float) - level)
        jj, ii = np.meshgrid(np.arange(j0, j0 + 2 * half + 1), np.arange(i0, i0 + 2 * half + 1))
        err = max(err, math.hypot((w * jj).sum() / w.sum() - u, (w * ii).sum() / w.sum() - v))
    return err


def workload(n: int, seed: int = 0):
    """n (camera with drifted focal length, plate, pose) triples cycling over SCENES."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        cam, plate, T = SCENES[i % len(SCENES)]
        cam = dataclasses.replace(cam, focal_length_mm=cam.focal_length_mm * (1 + 1e-4 * rng.standard_normal()))
        out.append((cam, plate, T))
    return out


def time_renderer(fn, jobs, cond) -> tuple[list[float], float]:
    """Wall time per image (s) and the mean process CPU time per image (s)."""
    times = []
    c0 = time.process_time()
    for k, (cam, plate, T) in enumerate(jobs):
        t = time.perf_counter()
        fn(cam, plate, T, cond, k)
        times.append(time.perf_counter() - t)
    return times, (time.process_time() - c0) / max(len(jobs), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=10, help="full-size images for tasks.simulation.render (default 10)")
    ap.add_argument("--baseline-n", type=int, default=2, help="images per baseline (default 2)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cond = ImagingConditions()

    render_plate_image(*SCENES[0], cond, 0)  # warm-up (imports, normal table)
    jobs = workload(args.n)
    base_jobs = workload(args.baseline_n)
    renderers = [
        ("tasks.simulation.render", render_plate_image, jobs),
        ("naive full-frame", naive_render, base_jobs),
        ("cv2 draw", cv2_draw_render, base_jobs),
    ]
    timings = [time_renderer(fn, j, cond) for _, fn, j in renderers]

    # noiseless, in focus, near-frontal: centroid vs projected centre (includes the true
    # distortion bias of a finite dot, ~0.003 px for a and ~0.008 px for b)
    ideal = ImagingConditions.ideal(defocus=False)
    frontal = [
        (CAM1, PLATE_A, pose([3.0, -2.0, 280.0], 0.4, 0.3, 5.0)),
        (CAM2, PLATE_B, pose([1.0, 1.0, 80.0], 0.3, 0.2, 3.0)),
    ]
    print(
        f"{len(jobs)} full-size images {CAM1.width_px}x{CAM1.height_px}, one core; wall = elapsed, cpu = process time"
    )
    print(
        f"{'renderer':18s} {'images':>6s} {'img/s':>7s} {'ms/img':>8s} {'median':>8s} {'cpu ms':>7s} {'vs ours':>8s}"
        "   centroid err max px: cam1/a  cam2/b"
    )
    ref = float(np.mean(timings[0][0]))
    for (name, fn, _), (t, cpu) in zip(renderers, timings, strict=True):
        errs = [
            centroid_error(fn(cam, plate, T, ideal, 0, noiseless=True), cam, plate, T, ideal.light_level)
            for cam, plate, T in frontal
        ]
        mean = float(np.mean(t))
        print(
            f"{name:18s} {len(t):6d} {1 / mean:7.2f} {1000 * mean:8.1f} {1000 * float(np.median(t)):8.1f} "
            f"{1000 * cpu:7.1f} {mean / ref:7.1f}x   {errs[0]:.4f}  {errs[1]:.4f}"
        )
    ours = timings[0][0]
    print(
        "tasks.simulation.render per scene, ms: "
        + ", ".join(
            f"#{i} {SCENES[i][0].name}/{SCENES[i][1].name}: {1000 * float(np.mean(ours[i :: len(SCENES)])):.0f}"
            for i in range(min(len(SCENES), len(ours)))
        )
    )


if __name__ == "__main__":
    main()
