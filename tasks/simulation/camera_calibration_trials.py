"""Camera self-calibration measured on the virtual machine (Table 3 of the calibration paper).

At pose level, no images: the campaign plan's fixture poses, true projected dot centres and Gaussian
pixel noise. ``python -m tasks.simulation.camera_calibration_trials [--sigma 0.03] [--seed 0]``
prints Table 3 and each camera's errors against the truth (docs/camera-calibration.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from tasks.vision.camera_calibration import calibrate_camera, compare_to_truth, nominal_camera, table3


def simulated_trials(camera: str, sigma_px: float, seed: int, plan=None, machine=None) -> dict[str, tuple]:
    """Calibration views of ``camera`` on the virtual machine at pose level (no images): the
    campaign plan's fixture poses, true projected dot centres, Gaussian pixel noise σ (seeded).
    For tests and the measurement in docs/camera-calibration.md."""
    from tasks.machine.description import CALIBRATION_STAGE, load_machine
    from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign
    from tasks.simulation.render import true_dot_centres

    machine = machine or load_machine("prototype")
    poses, fixture = plan_campaign(machine, plan or CampaignPlan(), seed)
    cam = machine.cameras[camera]
    plate = machine.plates[machine.plate_seen(camera, CALIBRATION_STAGE)]
    rng = np.random.default_rng([seed, 101, list(machine.cameras).index(camera)])
    obj = plate.dot_centres_mm()
    out: dict[str, tuple] = {}
    for i in np.flatnonzero((poses["camera"] == camera) & (poses["stage"] == CALIBRATION_STAGE)):
        uv = true_dot_centres(cam, plate, fixture[int(i)]) + rng.normal(0.0, sigma_px, (len(obj), 2))
        views = out.setdefault(str(poses["group"].iloc[i]), ([], [], []))
        views[0].append(obj)
        views[1].append(uv)
        views[2].append(str(poses["image_id"].iloc[i]))
    return out


def _main(argv: Sequence[str] | None = None) -> None:
    import argparse
    import time

    from tasks.machine.description import load_machine

    p = argparse.ArgumentParser(description="Self-calibration of both cameras on the virtual machine "
                                            "(true dot centres + Gaussian pixel noise): Table 3 and errors.")
    p.add_argument("--sigma", type=float, default=0.03, help="pixel noise per coordinate (px)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fix-k3", action="store_true")
    a = p.parse_args(argv)
    machine = load_machine("prototype")
    pd.set_option("display.width", 200)
    cals = []
    for name, true_cam in machine.cameras.items():
        t0 = time.perf_counter()
        spec = {"width_px": true_cam.width_px, "height_px": true_cam.height_px,
                "pixel_size_mm": true_cam.pixel_size_mm, "focal_length_mm": true_cam.focal_length_mm}
        trials = simulated_trials(name, a.sigma, a.seed, machine=machine)
        cal = calibrate_camera(trials, nominal_camera(spec, name), fix_k3=a.fix_k3)
        cals.append(cal)
        seen = np.concatenate([uv for views in trials.values() for uv in views[1]])
        errs = compare_to_truth(cal.trials, true_cam, seen)
        print(f"== {name}: {time.perf_counter() - t0:.1f} s")
        print(cal.summary.to_string(float_format=lambda x: f"{x:.5g}"))
        print("per-trial errors against the truth (max |.| over trials):",
              {k: round(float(errs[k].abs().max()), 4) for k in
               ("focal_error_pct", "pp_error_px", "distortion_max_px", "distortion_max_px_seen")})
        print("  focal error % per trial:", np.round(errs["focal_error_pct"].to_numpy(), 4).tolist())
        j = cal.joint
        print(f"joint ({j.n_images} images): rms {j.rms_px:.4f} px, sigma {j.sigma_px:.4f} px, "
              f"std fx {j.std_intrinsics[0]:.3f} px, std cx/cy {j.std_intrinsics[2]:.3f}/{j.std_intrinsics[3]:.3f} px")
        best = compare_to_truth(cal, true_cam, seen)
        print("best estimate vs truth:", {k: round(float(v), 4) for k, v in best.items()})
    print("== Table 3 (reprojection RMS, px)")
    print(table3(cals).to_string(float_format=lambda x: f"{x:.4f}"))


if __name__ == "__main__":
    _main()
