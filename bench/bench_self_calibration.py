"""What refining the self-calibration on the machine's images costs a campaign, side by side.

On one measured campaign (its lake's ``images`` and ``dots`` tables), one numeric thread as the
measure flow's task runs it, best of ``--repeat`` runs:
- ``joint fit only``: every camera's trials and joint fit on its calibration views (the self-calibration
  without the refinement);
- ``refined``: ``tasks.vision.pipeline.calibrate_cameras`` (the same, then camera 1 refined on its
  images of plate a in the linear axes' sweeps and the five-axis poses);
- the intrinsics covariance the uncertainty propagation computes, over the calibration views alone
  and over the views the refined fit reads;
- the dot centres of every image made unbiased with the refined intrinsics, as ``plate_poses`` makes
  them before PnP (``tasks.vision.centre_bias.unbiased_dots``).

    python bench/bench_self_calibration.py --campaign CAMPAIGN --results RESULTS
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import pandas as pd
from threadpoolctl import threadpool_limits

from tasks.lake.store import read_table
from tasks.machine.description import CALIBRATION_STAGE
from tasks.vision.camera_calibration import calibrate_camera, trial_views
from tasks.vision.centre_bias import unbiased_dots
from tasks.vision.intrinsics_uncertainty import intrinsics_covariances
from tasks.vision.pipeline import (
    calibrate_cameras,
    campaign_plates,
    nominal_cameras,
    nominal_machine,
    plate_names,
    plates_by_camera,
)


def joint_fit_only(dots, images, metadata) -> dict:
    """Every camera's trials and joint fit on its calibration views alone: {camera: CameraModel}."""
    targets = plates_by_camera(metadata, CALIBRATION_STAGE)
    return {cam: calibrate_camera(trial_views(dots, images, cam, targets[cam]), nominal, camera=cam,
                                  fix_k3=True).best_estimate
            for cam, nominal in nominal_cameras(metadata).items()}


def best_of(repeat: int, fn, *args) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--campaign", required=True)
    ap.add_argument("--results", required=True)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    metadata = json.loads((Path(args.campaign) / "campaign.json").read_text())
    cid = metadata["campaign_id"]
    images, dots = read_table("images", args.results, cid), read_table("dots", args.results, cid)
    targets, measured = plates_by_camera(metadata, CALIBRATION_STAGE), plates_by_camera(metadata)
    sweeps = nominal_machine(metadata).linear_axes
    cv2.setNumThreads(1)
    with threadpool_limits(1):
        t_base, base = best_of(args.repeat, joint_fit_only, dots, images, metadata)
        t_new, (_, refined) = best_of(args.repeat, calibrate_cameras, dots, images, metadata)
        t_cov_base, _ = best_of(args.repeat, intrinsics_covariances, dots, images, base, targets)
        t_cov_new, _ = best_of(args.repeat, intrinsics_covariances, dots, images, refined, targets, measured, sweeps)
        plate_of = pd.Series(plate_names(metadata, images).to_numpy(), index=images["image_id"].to_numpy())
        t_unbiased, _ = best_of(args.repeat, unbiased_dots, dots, plate_of, refined, campaign_plates(metadata))
    print(f"{cid}: {len(images)} images, best of {args.repeat}")
    print(f"self-calibration: joint fit only {t_base:.2f} s, refined {t_new:.2f} s (×{t_new / t_base:.2f}, "
          f"+{t_new - t_base:.2f} s)")
    print(f"intrinsics covariance: calibration views {t_cov_base:.2f} s, with the machine's views {t_cov_new:.2f} s "
          f"(+{t_cov_new - t_cov_base:.2f} s)")
    n_views = dots["image_id"].nunique()
    print(f"unbiased centres (tasks.vision.centre_bias.unbiased_dots, as plate_poses makes them): {n_views} images "
          f"{t_unbiased:.2f} s, {1e3 * t_unbiased / n_views:.1f} ms an image")


if __name__ == "__main__":
    main()
