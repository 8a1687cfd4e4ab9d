"""Tray images and their sidecars: what ``fivecal dispense-job`` reads, and the simulator writing them.

A tray image ``NAME.png`` (camera 1, colour) comes with ``NAME.json``:

* ``imaging_command``: the five commands (X, Y, Z mm, A, C deg) camera 1 took the image at;
* ``surface_z_mm``: the height of the tray's surface above plate a's plane (workpiece frame);
* ``mm_per_px``: the image scale on the tray (the acceptance rules are in mm);
* ``home_xy_mm`` (optional): the X/Y commands of the needle's home, where every tour starts and ends
  (default 0, 0; a simulated tray: over the tray's corner at −x, −y, as the paper's zero point);
* ``hand_eye`` (optional): the paper's hand–eye pairs ``[u, v, X, Y]`` (pixel, machine command of the
  needle over the mark) for the planar map (§4.2, Table 2);
* ``simulated`` (simulated trays only): the seed, the tray's layout (tasks.dispense_job.boards.TraySpec)
  and the campaign whose true machine took the image; its truth is ``NAME.truth.csv`` (one row per
  board, tasks.dispense_job.boards.board_truth).

The simulated tray lies in the workpiece frame (its centre at the origin) on the simulated campaign's
true machine; camera 1 images it from straight above its centre.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from tasks.core.atomic_io import atomic_write_text
from tasks.dispense_job.boards import TraySpec, apply_light, board_truth, paint_tray, place_boards
from tasks.dispense_job.camera_view import camera_image, hand_eye_marks, project_to_camera
from tasks.dispense_job.pixel_map import jog_over
from tasks.dispensing.workpiece import imaging_commands
from tasks.machine.description import load_machine
from tasks.simulation.simulate import read_truth

SURFACE_Z_MM = 19.8  # the dispensing test's workpiece height: the tip meets it near the zero Z command
STANDOFF_MM = 0.2
CAMERA_MM_PER_PX = 0.045  # camera 1 of the prototype at its 300 mm working distance


@dataclass(frozen=True)
class Tray:
    """A tray image and its sidecar (see the module docstring); ``truth`` None unless simulated."""

    tray_id: str
    image_path: Path
    imaging_command: np.ndarray
    surface_z_mm: float
    mm_per_px: float
    hand_eye: np.ndarray | None
    simulated: dict | None
    truth: pd.DataFrame | None
    home_xy_mm: tuple[float, float] = (0.0, 0.0)

    def read_rgb(self) -> np.ndarray:
        """The image as (H, W, 3) uint8 RGB; ValueError naming the file when it cannot be read."""
        bgr = cv2.imread(str(self.image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{self.image_path}: not a readable image")
        return bgr[..., ::-1].copy()


def read_tray(image: Path) -> Tray:
    """The tray of an image path; ValueError naming the file for a missing or malformed sidecar."""
    image = Path(image)
    if not image.is_file():
        raise ValueError(f"{image}: no such image")
    side = image.with_suffix(".json")
    if not side.is_file():
        raise ValueError(f"{image}: its sidecar {side.name} (imaging command, surface height, scale) is missing")
    try:
        meta = json.loads(side.read_text())
        cmd = np.asarray(meta["imaging_command"], dtype=float).reshape(5)
        surface, scale = float(meta["surface_z_mm"]), float(meta["mm_per_px"])
        home = tuple(float(v) for v in meta.get("home_xy_mm", (0.0, 0.0)))
        if len(home) != 2:
            raise ValueError(f"home_xy_mm has {len(home)} numbers")
    except (KeyError, ValueError, TypeError, json.JSONDecodeError) as e:
        raise ValueError(f"{side}: malformed sidecar ({e}); it needs imaging_command (5 numbers), surface_z_mm, "
                         f"mm_per_px") from None
    hand_eye = np.asarray(meta["hand_eye"], dtype=float).reshape(-1, 4) if meta.get("hand_eye") else None
    truth_path = image.with_suffix(".truth.csv")
    truth = pd.read_csv(truth_path, dtype={"defect": str}) if truth_path.is_file() else None
    if truth is not None:
        truth["defect"] = truth["defect"].fillna("")
    return Tray(image.stem, image, cmd, surface, scale, hand_eye, meta.get("simulated"), truth, home)


def simulate_tray(out_image: Path, campaign: Path, seed: int, boards: int = 20, spec: TraySpec | None = None,
                  shot: int = 0) -> Path:
    """Render a tray of ``boards`` boards as camera 1 of the simulated campaign's true machine sees it,
    with its sidecar (hand–eye pairs from the true machine: the needle jogged over nine marks) and
    truth; returns the image path."""
    spec = spec or TraySpec()
    machine = load_machine("prototype")
    truth_model = read_truth(Path(campaign))[1]
    imaging = imaging_commands(machine, np.zeros((1, 2)), np.array([SURFACE_Z_MM]))[0]
    placed = place_boards(spec, np.random.default_rng([seed, 34]), boards)
    texture = paint_tray(spec, placed)
    camera = machine.cameras["camera1"]
    view = camera_image(texture.astype(np.float32), spec, machine, truth_model, camera, imaging, SURFACE_Z_MM)
    lit = apply_light(camera_spec(spec, camera), [], view.astype(np.float64), np.random.default_rng([seed, 34, shot]))
    marks = hand_eye_marks(spec)
    mark_px = project_to_camera(machine, truth_model, camera, imaging, marks, SURFACE_Z_MM)
    jogged = jog_over(machine, truth_model, marks, SURFACE_Z_MM, STANDOFF_MM)
    out_image = Path(out_image)
    out_image.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_image), lit[..., ::-1])
    w, h = spec.size_mm
    corner = jog_over(machine, None, np.array([[-w / 2, -h / 2]]), SURFACE_Z_MM, STANDOFF_MM)[0, :2]
    meta = {"imaging_command": imaging.tolist(), "surface_z_mm": SURFACE_Z_MM, "mm_per_px": CAMERA_MM_PER_PX,
            "home_xy_mm": corner.tolist(),
            "hand_eye": np.column_stack([mark_px, jogged[:, :2]]).tolist(),
            "simulated": {"campaign": str(Path(campaign).resolve()), "seed": seed, "boards": boards, "shot": shot,
                          "spec": spec.to_dict()}}
    atomic_write_text(out_image.with_suffix(".json"), json.dumps(meta, indent=1))
    board_truth(spec, placed).to_csv(out_image.with_suffix(".truth.csv"), index=False)
    return out_image


def camera_spec(spec: TraySpec, camera) -> TraySpec:
    """The light's geometry on camera 1's sensor (fall-off about the sensor's centre; no glare spots,
    which need the boards' pixels: glare is left to the planar bench)."""
    return replace(spec, image_px=(camera.width_px, camera.height_px), glare_spots=0)


def tray_spec(tray: Tray) -> TraySpec:
    """The layout of a simulated tray (ValueError when the tray is not simulated)."""
    if not tray.simulated:
        raise ValueError(f"{tray.image_path}: not a simulated tray")
    d = dict(tray.simulated["spec"])
    for k in ("board_mm", "component_mm", "component_offset_mm", "image_px"):
        d[k] = tuple(d[k])
    return TraySpec(**d)
