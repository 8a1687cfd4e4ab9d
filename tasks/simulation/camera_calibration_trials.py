"""Camera self-calibration measured on the virtual machine (Table 3 of the calibration paper).

At pose level, no images: the campaign plan's fixture poses, true projected dot centres and Gaussian
pixel noise. ``python -m tasks.simulation.camera_calibration_trials [--sigma 0.03] [--seed 0]``
prints Table 3 and each camera's errors against the truth (docs/camera-calibration.md).

With ``--render``: the calibration views alone of a campaign of each seed, rendered and measured as
``fivecal simulate`` and ``fivecal measure`` do them (the same fixture poses, exposures and RRHT
detector; no other image), self-calibrated with k3 held as the pipeline does, and the error of the
joint estimate set against its stated covariance
(:func:`tasks.vision.intrinsics_uncertainty.intrinsics_covariance`), seed by seed:
``python -m tasks.simulation.camera_calibration_trials --render --size full --camera camera1
--seeds 1 2 3``.
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


def rendered_trials(camera: str, seed: int, size: str = "full", machine=None) -> tuple[dict[str, tuple], object]:
    """(trials as :func:`simulated_trials` gives them, the true camera at ``size``): the calibration
    views of the default plan of campaign ``seed``, rendered as ``fivecal simulate`` renders them
    (the same exposures and image seeds) and measured by the RRHT detector, told the plate's
    in-plane angle as the pipeline's prediction tells it. Views without a grid are left out."""
    import math

    from tasks.machine.description import CALIBRATION_STAGE, load_machine
    from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign
    from tasks.simulation.render import render_plate_image, true_dot_centres
    from tasks.simulation.simulate import SIZES, imaging_conditions
    from tasks.vision.detection import detect_grid

    machine = machine or load_machine("prototype")
    poses, fixture = plan_campaign(machine, CampaignPlan(), seed)
    cam = machine.cameras[camera].scaled(SIZES[size])
    plate = machine.plates[machine.plate_seen(camera, CALIBRATION_STAGE)]
    out: dict[str, tuple] = {}
    for i in np.flatnonzero((poses["camera"] == camera) & (poses["stage"] == CALIBRATION_STAGE)):
        T = fixture[int(i)]
        uv = true_dot_centres(cam, plate, T)
        image = render_plate_image(cam, plate, T, imaging_conditions(seed, int(i)),
                                   seed=int(np.random.default_rng([seed, 11, int(i)]).integers(2**63)))
        d = uv[1] - uv[0]
        det = detect_grid(image, plate, "rrht", expected_rotation_deg=math.degrees(math.atan2(-d[1], d[0])))
        if not det.ok:
            continue
        views = out.setdefault(str(poses["group"].iloc[i]), ([], [], []))
        views[0].append(plate.dot_centres_mm())
        views[1].append(np.where(det.found[:, None], det.centres, np.nan))
        views[2].append(str(poses["image_id"].iloc[i]))
    return out, cam


CHECKED = ("f_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2")
"""The intrinsics the pipeline's self-calibration fits (it holds k3 at 0: tasks.vision.pipeline.FIX_K3)."""


def intrinsics_error_check(camera: str, seeds: Sequence[int], size: str = "full") -> pd.DataFrame:
    """One row per seed: the joint self-calibration of :func:`rendered_trials` (k3 held; run again on
    the centres without the lens's share of their bias, as the pipeline does:
    :func:`tasks.vision.centre_bias.unbiased_view` with the first estimate) against the truth.
    Columns: seed, views, focal_error_ppm (estimate − truth), focal_sigma_ppm (the stated
    standard deviation, cluster-robust), z_<θ> = (estimate − truth)/σ for the fitted intrinsics and
    m2 = Δθᵀ Σ⁻¹ Δθ over them (χ² with 7 degrees of freedom if the stated covariance is right)."""
    from tasks.machine.description import CALIBRATION_STAGE, load_machine
    from tasks.vision.centre_bias import unbiased_view
    from tasks.vision.intrinsics_uncertainty import (
        INTRINSIC_PARAMETERS,
        intrinsics_covariance,
        intrinsics_vector,
    )

    machine = load_machine("prototype")
    plate = machine.plates[machine.plate_seen(camera, CALIBRATION_STAGE)]
    k = [INTRINSIC_PARAMETERS.index(n) for n in CHECKED]
    rows = []
    for seed in seeds:
        trials, true_cam = rendered_trials(camera, seed, size)
        spec = {"width_px": true_cam.width_px, "height_px": true_cam.height_px,
                "pixel_size_mm": true_cam.pixel_size_mm, "focal_length_mm": true_cam.focal_length_mm,
                "focus_distance_mm": true_cam.focus_distance_mm}
        first = calibrate_camera(trials, nominal_camera(spec, camera), fix_k3=True).best_estimate
        trials = {t: (objs, [unbiased_view(m, first, plate) for m in imgs], ids)
                  for t, (objs, imgs, ids) in trials.items()}
        estimate = calibrate_camera(trials, nominal_camera(spec, camera), fix_k3=True).best_estimate
        views = [(o, m) for objs, imgs, _ in trials.values() for o, m in zip(objs, imgs, strict=True)]
        cov = intrinsics_covariance(views, estimate)[np.ix_(k, k)]
        error = (intrinsics_vector(estimate) - intrinsics_vector(true_cam))[k]
        f = intrinsics_vector(true_cam)[0]
        rows.append({"seed": seed, "views": len(views), "focal_error_ppm": error[0] / f * 1e6,
                     "focal_sigma_ppm": np.sqrt(cov[0, 0]) / f * 1e6,
                     **{f"z_{n}": e / np.sqrt(v) for n, e, v in zip(CHECKED, error, np.diag(cov), strict=True)},
                     "m2": float(error @ np.linalg.solve(cov, error))})
    return pd.DataFrame(rows)


def _print_check(table: pd.DataFrame) -> None:
    from scipy import stats

    print(table.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    n, dof = len(table), len(CHECKED)
    z = table[[f"z_{c}" for c in CHECKED]]
    print(f"pooled m2/{dof} {table.m2.sum() / (dof * n):.2f} (χ² on {dof * n} dof: upper tail "
          f"{stats.chi2.sf(table.m2.sum(), dof * n):.3f}); mean z {z.mean().round(2).to_dict()}; "
          f"RMS z {np.sqrt((z**2).mean()).round(2).to_dict()}; focal error {table.focal_error_ppm.mean():+.1f} ppm "
          f"mean, {table.focal_error_ppm.std():.1f} ppm SD, stated σ {table.focal_sigma_ppm.median():.1f} ppm median")


def _main(argv: Sequence[str] | None = None) -> None:
    import argparse
    import time

    from tasks.machine.description import load_machine

    p = argparse.ArgumentParser(description="Self-calibration of both cameras on the virtual machine "
                                            "(true dot centres + Gaussian pixel noise): Table 3 and errors.")
    p.add_argument("--sigma", type=float, default=0.03, help="pixel noise per coordinate (px)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fix-k3", action="store_true")
    p.add_argument("--render", action="store_true",
                   help="rendered and detected calibration views of --seeds, against the stated covariance")
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7, 8])
    p.add_argument("--size", choices=("full", "small"), default="full")
    p.add_argument("--camera", default="camera1")
    a = p.parse_args(argv)
    pd.set_option("display.width", 200)
    if a.render:
        _print_check(intrinsics_error_check(a.camera, a.seeds, a.size))
        return
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
