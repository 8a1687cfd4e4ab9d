"""The dispensing-test workpiece and the commands that dispense on it and image it (§4.3, §5.3).

The workpiece replaces plate a on the C table (the machine's ``workpiece`` frame: origin at its
centre, z out of its surface). Black ring targets are printed on its surface on a grid; each ring
gets its own dispensing orientation (A, C), spread over the A/C range of the campaign's five-axis
poses by a Latin hypercube, so that the tip's offset along the tool axis shows in the dots (at
A = 0 the tool is normal to the surface and that component lands on the ring centre).

Dispensing: the nominal machine is asked to hold the tip's opening ``standoff_mm`` above the ring
centre (along the surface normal), tool direction fixed by (A, C); the drop that forms there wets
the surface at the point nearest the opening (tasks.dispensing.tip). Imaging: camera 1 straight above the ring, A = C
= 0, at its working distance. Both are plain nominal inverse kinematics: the nominal commands; the
compensated ones come from :func:`tasks.compensation.compensate` on the same desired tip poses.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from tasks.inverse_kinematics import inverse
from tasks.kinematics import forward
from tasks.machine import AXIS_ORDER, Machine


@dataclass(frozen=True)
class Workpiece:
    """Ring layout (mm, workpiece frame) and ring geometry.

    rows × cols rings at ``pitch_mm``; ring inner/outer diameters (mm); standoff of the tip's
    opening above the surface when it dispenses (mm); nominal dot diameter (mm)."""

    rows: int = 7
    cols: int = 9
    pitch_mm: float = 6.0
    ring_inner_mm: float = 2.4
    ring_outer_mm: float = 3.4
    standoff_mm: float = 0.2
    dot_diameter_mm: float = 0.8

    def ring_centres(self) -> np.ndarray:
        """(N, 2) ring centres (mm) in the workpiece frame, row by row."""
        u = (np.arange(self.cols) - (self.cols - 1) / 2) * self.pitch_mm
        v = (np.arange(self.rows) - (self.rows - 1) / 2) * self.pitch_mm
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu.ravel(), vv.ravel()], axis=1)

    def to_dict(self) -> dict:
        return asdict(self)


def ring_ids(n: int) -> list[str]:
    return [f"ring{i:03d}" for i in range(n)]


def dispensing_orientations(n: int, a_range_deg, c_range_deg, seed: int) -> np.ndarray:
    """(n, 2) A, C (deg): a Latin hypercube over the two ranges (each stratum used once)."""
    rng = np.random.default_rng([seed, 31])
    out = np.empty((n, 2))
    for j, (lo, hi) in enumerate((a_range_deg, c_range_deg)):
        strata = (rng.permutation(n) + rng.uniform(0.05, 0.95, n)) / n
        out[:, j] = lo + strata * (hi - lo)
    return out


def tool_direction(machine: Machine, a_c_deg: np.ndarray) -> np.ndarray:
    """(N, 3) unit tool axis (tip frame z) in the workpiece frame at rotary commands (A, C) (deg),
    nominal machine (the linear axes do not turn it)."""
    cmd = np.zeros((len(a_c_deg), 5))
    cmd[:, 3:] = a_c_deg
    return forward(machine, cmd).tool_in_workpiece()[:, :3, 2]


def dispensing_commands(machine: Machine, workpiece: Workpiece, a_c_deg: np.ndarray) -> np.ndarray:
    """(N, 5) nominal commands (mm, deg) that hold the tip ``standoff_mm`` above each ring centre
    (along the surface normal), tool axis set by (A, C) per ring."""
    centres = workpiece.ring_centres()
    d = tool_direction(machine, a_c_deg)
    target = np.column_stack([centres, np.full(len(centres), workpiece.standoff_mm)])
    initial = np.zeros((len(centres), 5))
    initial[:, 3:] = a_c_deg
    return inverse(machine, target, d, initial=initial)


def imaging_commands(machine: Machine, workpiece: Workpiece, camera: str = "camera1") -> np.ndarray:
    """(N, 5) nominal commands that put ``camera``'s optical axis through each ring centre, A = C = 0,
    the camera at the same height as at the zero command (its working distance on the prototype)."""
    centres = workpiece.ring_centres()
    home = forward(machine, np.zeros((1, 5)))
    cam_in_wp = home.relative(camera, machine.workpiece)[0]
    # the optical axis (camera z) meets the surface at this point (workpiece frame) at the zero command
    o, z = cam_in_wp[:3, 3], cam_in_wp[:3, 2]
    hit = o - z * (o[2] / z[2])
    cmd = np.zeros((len(centres), 5))
    cmd[:, 0] = centres[:, 0] - hit[0]
    cmd[:, 1] = centres[:, 1] - hit[1]
    return cmd


def commands_frame(commands: np.ndarray) -> pd.DataFrame:
    """Commands (N, 5) as columns X_mm, Y_mm, Z_mm, A_deg, C_deg."""
    return pd.DataFrame({f"{a}_{'deg' if a in ('A', 'C') else 'mm'}": commands[:, i]
                         for i, a in enumerate(AXIS_ORDER)})
