"""The dispensing capture: what a lab is asked for, and the simulator playing the machine.

A capture is one workpiece: the machine dispenses a dot at every ring at the phase's commands,
then camera 1 images each ring from straight above (A = C = 0). The folder
``<campaign>/captures/dispense-<phase>-<key>/`` holds

* ``dispense_plan.csv`` (written by fivecal): per ring, image_id, path, phase, ring_id, the ring
  centre and the height of its pad's top (mm, workpiece frame), the dispensing commands (X_mm …
  C_deg) and the imaging commands (image_X_mm … image_C_deg);
* ``images/camera1/<image_id>.png`` and ``manifest.csv`` (written by the lab, or by the simulator):
  the plan's rows plus ``roi_x0``, ``roi_y0``, the sensor pixel of the image's top-left pixel
  (0, 0 for a full frame), and ``binning`` (1 for a full-resolution image);
* ``truth/dots.csv`` for a simulated capture: the true dot − ring offset (where the tip was), the
  true diameter, NSD_r and defect of each dot.

The simulator renders each image as a region of interest of camera 1's full-resolution sensor
around the ring (the demo campaigns' binned images would give 180 µm pixels, four times too coarse
for a 0.8 mm dot).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from tasks.campaign.folder import TRUTH_DIR
from tasks.core.atomic_io import atomic_write_text, staged_folder
from tasks.dispensing.dot_render import Lighting, RingScene, draw_defect, random_dot, render_scene
from tasks.dispensing.tip import landing_points
from tasks.dispensing.workpiece import Workpiece, commands_frame, ring_ids
from tasks.machine.camera_model import project_points
from tasks.machine.description import Machine, load_machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.simulate import read_truth

PLAN_FILE = "dispense_plan.csv"
ROI_PX = 128
DEFECT_RATE = 0.04
CAMERA = "camera1"


def plan_rows(phase: str, centres: np.ndarray, surface_z_mm: np.ndarray, dispense: np.ndarray, imaging: np.ndarray
              ) -> pd.DataFrame:
    """The capture's rows (see the module docstring), one per ring: centres (N, 2) and pad heights
    (N,) mm, dispensing and imaging commands (N, 5)."""
    ids = ring_ids(len(dispense))
    rows = pd.DataFrame({"image_id": [f"{phase}_{r}" for r in ids], "phase": phase, "ring_id": ids,
                         "ring_x_mm": centres[:, 0], "ring_y_mm": centres[:, 1], "surface_z_mm": surface_z_mm})
    rows.insert(1, "path", [f"images/{CAMERA}/{i}.png" for i in rows["image_id"]])
    rows = pd.concat([rows, commands_frame(dispense),
                      commands_frame(imaging).add_prefix("image_")], axis=1)
    return rows


def write_plan(folder: Path, rows: pd.DataFrame) -> Path:
    """Write ``dispense_plan.csv`` into ``folder``; returns its path."""
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / PLAN_FILE, rows.to_csv(index=False))
    return folder / PLAN_FILE


def lighting_of(seed: int) -> Lighting:
    """The campaign's lighting: bright or dark dots (one polarity per campaign), 40 DN contrast."""
    rng = np.random.default_rng([seed, 311])
    return Lighting(contrast=40.0 * (1 if rng.uniform() < 0.5 else -1))


def simulate_dispense_capture(campaign_folder: Path, out_folder: Path, rows: pd.DataFrame, workpiece: Workpiece,
                              seed: int) -> Path:
    """Dispense at the rows' commands on the true machine, image every ring with camera 1 and write
    the capture folder (replaced whole). Returns it."""
    campaign_folder, out_folder = Path(campaign_folder), Path(out_folder)
    truth = read_truth(campaign_folder)[1]
    machine = load_machine("prototype")
    dispense = rows[["X_mm", "Y_mm", "Z_mm", "A_deg", "C_deg"]].to_numpy(float)
    imaging = rows[["image_X_mm", "image_Y_mm", "image_Z_mm", "image_A_deg", "image_C_deg"]].to_numpy(float)
    centres = rows[["ring_x_mm", "ring_y_mm"]].to_numpy(float)
    surface = rows["surface_z_mm"].to_numpy(float)
    offsets = landing_points(machine, truth, dispense) - centres
    with staged_folder(out_folder) as staging:
        (staging / "images" / CAMERA).mkdir(parents=True)
        (staging / TRUTH_DIR).mkdir()
        rng = np.random.default_rng([seed, 3131, len(rows)])
        lighting = lighting_of(seed)
        truth_rows, roi = [], []
        for i, row in enumerate(rows.itertuples(index=False)):
            ring_px, jac = ring_projection(machine, truth, imaging[i], centres[i], surface[i])
            x0, y0 = int(np.rint(ring_px[0])) - ROI_PX // 2, int(np.rint(ring_px[1])) - ROI_PX // 2
            defect = draw_defect(rng, DEFECT_RATE)
            dot = random_dot(rng, offsets[i], workpiece.dot_diameter_mm, defect)
            scene = RingScene((ring_px[0] - x0, ring_px[1] - y0), jac, workpiece.ring_inner_mm, workpiece.ring_outer_mm,
                              () if defect == "missing" else (dot,))
            image = render_scene(scene, (ROI_PX, ROI_PX), lighting, rng)
            cv2.imwrite(str(staging / row.path), image)
            roi.append((x0, y0))
            truth_rows.append({"image_id": row.image_id, "truth_dx_um": offsets[i, 0] * 1e3,
                               "truth_dy_um": offsets[i, 1] * 1e3, "truth_diameter_mm": dot.equivalent_diameter_mm(),
                               "truth_nsd_r": dot.nsd_r(), "truth_defect": defect or "none"})
        manifest = rows.assign(roi_x0=[r[0] for r in roi], roi_y0=[r[1] for r in roi], binning=1)
        pd.DataFrame(truth_rows).to_csv(staging / TRUTH_DIR / "dots.csv", index=False)
        manifest.to_csv(staging / "manifest.csv", index=False)
    return out_folder


def ring_projection(machine: Machine, errors: ErrorModel | None, imaging: np.ndarray, centre_mm: np.ndarray,
                    surface_z_mm: float, camera=None) -> tuple[np.ndarray, np.ndarray]:
    """Where camera 1 (full resolution; ``camera`` overrides its intrinsics) sees a ring centre (2,)
    on the surface at ``surface_z_mm`` (workpiece frame) at the imaging command (5,) on the machine
    ``errors`` describes: pixel (2,) and the local projection (2, 2) px per mm of the workpiece's x
    and y (central differences over ±0.5 mm)."""
    cam = camera or machine.cameras[CAMERA]
    T = forward(machine, imaging[None], errors).relative(machine.workpiece, CAMERA)[0]
    pts = np.array([[0, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0, 0.5, 0], [0, -0.5, 0]], float)
    pts[:, :2] += centre_mm
    pts[:, 2] = surface_z_mm
    px = project_points(pts @ T[:3, :3].T + T[:3, 3], cam)
    jac = np.column_stack([(px[1] - px[2]) / 1.0, (px[3] - px[4]) / 1.0])
    return px[0], jac
