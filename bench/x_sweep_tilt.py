"""The plate tilt that camera 1 reads along the X and Y sweeps, against the simulator's truth, for
four sets of intrinsics: the self-calibration views' joint fit with k3 free, with k3 held at 0
(``tasks.vision.pipeline.FIX_K3``), the pipeline's (the held-k3 fit refined on the machine's images of
plate a: ``tasks.vision.pipeline.calibrate_cameras``) and the true ones.

For each seed, camera 1 is self-calibrated again from the campaign's ``dots`` (all three ways),
every X and Y sweep image is posed by PnP from its detected dots, and the rotation of the measured
T_cam_plate against the true one (``truth/images.parquet``) is averaged per sweep position: about y
for the X sweep (X's εy), about x for the Y sweep (Y's εx). The per-position means are smoothed by a
cubic in the position and referred to home, as the PDGE profiles are; printed: its RMS over the
sweep and its values at the two ends (arcsec).

    python bench/x_sweep_tilt.py --seeds 10 67 --campaigns /work/panel/small --results RESULTS

RESULTS: a lake that holds the campaigns' ``images`` and ``dots`` tables (any ``fivecal calibrate``
of them: detection does not depend on the intrinsics).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.core import se3
from tasks.lake.store import read_table
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import CALIBRATION_STAGE
from tasks.vision.camera_calibration import calibrate_camera, trial_views
from tasks.vision.pipeline import calibrate_cameras, campaign_plates, nominal_cameras, plates_by_camera
from tasks.vision.poses import estimate_poses

POSE_COLUMNS = [f"T{i}{j}" for i in range(3) for j in range(4)]
SWEEPS = {"X": 1, "Y": 0}  # the sweep and the plate-frame rotation component it reads (y, x)


def _poses(table: pd.DataFrame) -> np.ndarray:
    T = np.tile(np.eye(4), (len(table), 1, 1))
    T[:, :3] = table[POSE_COLUMNS].to_numpy(float).reshape(-1, 3, 4)
    return T


def sweep_tilt(dots: pd.DataFrame, images: pd.DataFrame, true_poses: pd.DataFrame, camera: CameraModel,
               plate, axis: str) -> pd.Series:
    """Per position of ``axis``' sweep: the cubic-smoothed mean rotation (arcsec) of the plate pose
    measured with ``camera`` against the true pose, referred to home."""
    sweep = images[(images.stage == "pdge") & (images.group == axis)]
    posed = estimate_poses(dots[dots.image_id.isin(sweep.image_id)].assign(camera="camera1"), camera, plate)
    posed = posed[posed.status == "ok"]
    D = se3.inverse(_poses(true_poses.loc[posed.image_id])) @ _poses(posed)
    w = np.degrees(se3.log(D)[:, 3 + SWEEPS[axis]]) * 3600
    pos = sweep.set_index("image_id").loc[posed.image_id, f"{axis}_mm"].to_numpy(float)
    mean = pd.Series(w).groupby(pos).mean()
    coef = np.polyfit(mean.index.to_numpy(float), mean.to_numpy(float), 3)
    return pd.Series(np.polyval(coef, mean.index) - np.polyval(coef, 0.0), index=mean.index)


def seed_row(campaign: Path, results: Path) -> dict:
    meta = json.loads((campaign / "campaign.json").read_text())
    cid = meta["campaign_id"]
    truth = json.loads((campaign / "truth" / "truth.json").read_text())["cameras"]["camera1"]
    true_poses = pd.read_parquet(campaign / "truth" / "images.parquet").set_index("image_id")
    images, dots = read_table("images", results, cid), read_table("dots", results, cid)
    views = trial_views(dots, images, "camera1", plates_by_camera(meta, CALIBRATION_STAGE)["camera1"])
    nominal = nominal_cameras(meta)["camera1"]
    cameras = {"k3 free": calibrate_camera(views, nominal, camera="camera1").best_estimate,
               "k3 = 0": calibrate_camera(views, nominal, camera="camera1", fix_k3=True).best_estimate,
               "refined": calibrate_cameras(dots, images, meta)[1]["camera1"],
               "true": CameraModel(**{**truth, "distortion": tuple(truth["distortion"])})}
    plate = campaign_plates(meta)["plate_a"]
    row = {"campaign": cid}
    for name, camera in cameras.items():
        row[f"k3 ({name})"] = camera.distortion[4]
        for axis in SWEEPS:
            t = sweep_tilt(dots, images, true_poses, camera, plate, axis)
            row[f"{axis} rms ({name})"] = float(np.sqrt(np.mean(t**2)))
            row[f"{axis} ends ({name})"] = f"{t.iloc[0]:+.1f} / {t.iloc[-1]:+.1f}"
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 67, 161, 262, 497, 519, 619, 639, 848, 957])
    ap.add_argument("--campaigns", required=True, help="folder of the s<seed> campaigns")
    ap.add_argument("--results", required=True, help="results root holding their images and dots tables")
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        rows.append(seed_row(Path(args.campaigns) / f"s{seed}", Path(args.results)))
        print(pd.DataFrame(rows[-1:]).to_string(index=False, header=len(rows) == 1, float_format="{:.2f}".format),
              flush=True)
    table = pd.DataFrame(rows)
    rms = [c for c in table.columns if " rms " in c]
    print("median / worst over the seeds (arcsec):")
    print(table[rms].agg(["median", "max"]).round(2).to_string())


if __name__ == "__main__":
    main()
