"""The virtual machine runs a dispensing program on a simulated tray and the beads appear (truth side).

The glue leaves the needle while it moves with the dispense flag on; a bead of fluid under a
millimetre high is held by surface tension where it touches the surface, so its centre line is the
trace of the real tip on the surface (the foot of the surface normal through it: the true machine at
the program's commands, tasks.dispensing.tip.landing_points). The bead is that line widened to the
bead's width with round ends (a capsule); the width comes from the glue flow and the speed (the paper
measures 2.1–2.3 mm, Figure 27) and is drawn per bead about ``width_mm``. Red SMT adhesive: bright in R,
dark in G, so it stands out against the capacitor and any solder mask (tasks.dispense_job.bead_inspection).

Frames: workpiece frame (mm), which is the tray frame of tasks.dispense_job.boards.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pandas as pd

from tasks.dispense_job.boards import TraySpec, pixels_to_tray, tray_to_pixels
from tasks.dispensing.tip import landing_points
from tasks.machine.description import COMMAND_COLUMNS, Machine
from tasks.machine.error_model import ErrorModel


@dataclass(frozen=True)
class Glue:
    """Bead width (mm) and its per-bead scatter (σ, mm); colour (R, G, B)."""

    width_mm: float = 2.2
    width_sd_mm: float = 0.04
    rgb: tuple[int, int, int] = (196, 34, 30)


def landed_beads(machine: Machine, truth: ErrorModel | None, program: pd.DataFrame) -> dict[str, np.ndarray]:
    """{board_id: (k, 2) the bead's centre line on the surface (mm, workpiece frame)}: where the true
    machine's tip is over the surface at the approach row and every dispense row of each board."""
    rows = program[program["move"].isin(["approach", "dispense"])]
    feet = landing_points(machine, truth, rows[list(COMMAND_COLUMNS)].to_numpy(float))
    out: dict[str, np.ndarray] = {}
    for board in dict.fromkeys(rows["board_id"]):
        out[board] = feet[(rows["board_id"] == board).to_numpy()]
    return out


def bead_truth(lines: dict[str, np.ndarray], widths: dict[str, float]) -> pd.DataFrame:
    """One row per bead: board_id, centre (mm, workpiece frame: the middle of its centre line's ends),
    length (line length + width: round ends) and width (mm), direction (deg, in [0, 180))."""
    rows = []
    for board, line in lines.items():
        ends = line[[0, -1]]
        d = ends[1] - ends[0]
        length = float(np.sum(np.linalg.norm(np.diff(line, axis=0), axis=1)))
        rows.append({"board_id": board, "true_bead_x_mm": float(ends.mean(axis=0)[0]),
                     "true_bead_y_mm": float(ends.mean(axis=0)[1]),
                     "true_bead_length_mm": length + widths[board], "true_bead_width_mm": widths[board],
                     "true_bead_angle_deg": float(np.rad2deg(np.arctan2(d[1], d[0])) % 180.0)})
    return pd.DataFrame(rows)


def draw_widths(boards: list[str], glue: Glue, rng: np.random.Generator) -> dict[str, float]:
    """{board_id: bead width (mm)} drawn about ``glue.width_mm``."""
    return {b: float(glue.width_mm + glue.width_sd_mm * rng.standard_normal()) for b in boards}


def _capsule_sdf(x: np.ndarray, y: np.ndarray, line: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (mm) to the polyline ``line`` (k, 2) widened by ``radius``."""
    p = np.stack([x, y], axis=-1)
    best = np.full(x.shape, np.inf)
    pts = line if len(line) > 1 else np.vstack([line, line])
    for a, b in itertools.pairwise(pts):
        ab = b - a
        t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - (a + t[..., None] * ab), axis=-1))
    return best - radius


def paint_beads(spec: TraySpec, texture: np.ndarray, lines: dict[str, np.ndarray], widths: dict[str, float],
                glue: Glue) -> np.ndarray:
    """A copy of the planar tray texture (H, W, 3) float RGB with every bead painted on it."""
    out = texture.copy()
    height, width = out.shape[:2]
    s = spec.mm_per_px
    for board, line in lines.items():
        r = widths[board] / 2
        lo, hi = line.min(axis=0) - r - 2 * s, line.max(axis=0) + r + 2 * s
        corners = tray_to_pixels(spec, np.array([[lo[0], hi[1]], [hi[0], lo[1]]]))
        ua, va = np.maximum(np.floor(corners[0]).astype(int), 0)
        ub, vb = np.minimum(np.ceil(corners[1]).astype(int) + 1, [width, height])
        if ua >= ub or va >= vb:
            continue
        uu, vv = np.meshgrid(np.arange(ua, ub, dtype=float), np.arange(va, vb, dtype=float))
        xy = pixels_to_tray(spec, np.column_stack([uu.ravel(), vv.ravel()]))
        sdf = _capsule_sdf(xy[:, 0].reshape(uu.shape), xy[:, 1].reshape(uu.shape), line, r)
        cov = np.clip(0.5 - sdf / s, 0.0, 1.0)[..., None]
        patch = out[va:vb, ua:ub]
        patch += cov * (np.asarray(glue.rgb, dtype=float) - patch)
    return out
