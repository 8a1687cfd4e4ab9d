"""Where the compensated job's needle error comes from: the pixel map or the commands.

    python bench/dispense_job_error_split.py --campaign DIR/p10 --tray TRAY.png --results DIR

A 5 × 3 grid of points over the tray, seen by the true camera on the true machine (perfect pixels),
mapped back through camera 1's calibrated model and the identified model (the ``compensated``
phase's map), then commanded (compensated) and landed on the true machine. Prints the map's error
(mapped − true point) and the commands' error (landed − mapped), mean and scatter per axis (µm),
beside the same with the true camera and the true model (zero, as a check). Then the commands' error
alone, |landed − intended| (µm), at workpiece points along x (rows: y = −40, 0, 40 mm) from the
tray's far side to beyond its near side, each labelled with its X command: how the compensation
holds outside the X range the campaign's sweeps measured.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from prefect import flow

from flows.dispense_job import load_calibration
from tasks.dispense_job.camera_view import project_to_camera
from tasks.dispense_job.pixel_map import commands_at, pixels_to_workpiece
from tasks.dispense_job.tray_io import STANDOFF_MM, read_tray
from tasks.dispensing.tip import landing_points
from tasks.machine.description import load_machine


@flow(name="dispense-job-error-split")
def _calibration(campaign: str, results: str):
    return load_calibration(Path(campaign), Path(results))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--campaign", type=Path, required=True)
    ap.add_argument("--tray", type=Path, required=True)
    ap.add_argument("--results", type=Path, required=True)
    args = ap.parse_args()
    cal = _calibration(str(args.campaign.resolve()), str(args.results))
    tray = read_tray(args.tray)
    true_cam = load_machine("prototype").cameras["camera1"]
    xs, ys = np.meshgrid(np.linspace(-45, 45, 5), np.linspace(-35, 35, 3))
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    uv = project_to_camera(cal.machine, cal.truth, true_cam, tray.imaging_command, pts, tray.surface_z_mm)
    for name, cam, model in (("calibrated camera + identified model", cal.camera, cal.model),
                             ("true camera + true model (check)", true_cam, cal.truth)):
        wp = pixels_to_workpiece(cal.machine, model, cam, tray.imaging_command, uv, tray.surface_z_mm)
        landed = landing_points(cal.machine, cal.truth, commands_at(cal.machine, model, wp, tray.surface_z_mm,
                                                                    STANDOFF_MM))
        m, c = 1e3 * (wp - pts), 1e3 * (landed - wp)
        print(f"{name}: map error mean ({m[:, 0].mean():+.1f}, {m[:, 1].mean():+.1f}) µm, scatter "
              f"({m[:, 0].std():.1f}, {m[:, 1].std():.1f}); command error mean ({c[:, 0].mean():+.1f}, "
              f"{c[:, 1].mean():+.1f}) µm, scatter ({c[:, 0].std():.1f}, {c[:, 1].std():.1f}); total |landed − true| "
              f"mean {np.linalg.norm(landed - pts, axis=1).mean() * 1e3:.1f} µm")
    print("commands' error |landed − intended| (µm) at workpiece (x, y), labelled with the X command:")
    for y in (-40.0, 0.0, 40.0):
        pts = np.column_stack([np.array([-112, -90, -60, -40, -25, -10, 0, 10, 25, 40, 60], float), np.full(11, y)])
        cmd = commands_at(cal.machine, cal.model, pts, tray.surface_z_mm, STANDOFF_MM)
        err = 1e3 * np.linalg.norm(landing_points(cal.machine, cal.truth, cmd) - pts, axis=1)
        print(f"  y {y:+.0f} mm: " + "  ".join(f"X {c:+.0f}: {e:.1f}" for c, e in zip(cmd[:, 0], err, strict=True)))


if __name__ == "__main__":
    main()
