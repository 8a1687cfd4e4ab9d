"""The dispensing-test workpiece and the commands that dispense on it and image it (§4.3, §5.3).

The workpiece is mounted on the C table in plate a's place, its frame the machine's ``workpiece``
frame (origin at plate a's centre, z out of it). Its black ring targets sit where the tip dispenses:
each ring has its own dispensing pose, X, Y, Z, A and C drawn by a Latin hypercube over the range of
the campaign's five-axis poses, and the ring is printed at the foot of the nominal tip at that pose,
on a pad whose top is the tip's height less the standoff, rounded to ``step_mm`` (a stepped
workpiece: at the zero command the tip is 20 mm above plate a). The dots thus sample the tip error
over the poses the calibration is judged on, Z included: the error left after compensation changes
with Z (a Z scale error the cameras' bias leaves in the Z PDGE), which one flat surface, reached at
one Z per A, would sample at another mean Z than the five-axis poses. At A = 0 the tool is normal to
the surface and the tip's offset along the tool axis lands on the ring centre, so A's spread is what
makes that component seen. Rings closer than ``min_spacing_mm`` to an earlier one are drawn again.

Dispensing: the nominal machine is asked to hold the tip's opening ``standoff_mm`` above the ring
centre (along the surface normal), tool direction fixed by (A, C); the drop that forms there wets
the surface at the point nearest the opening (tasks.dispensing.tip). Imaging: camera 1 straight
above the ring, A = C = 0, at its working distance from the ring's pad. Both are plain nominal
inverse kinematics: the nominal commands; the compensated ones come from
:func:`tasks.analysis.compensation.compensate` on the same desired tip poses.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.inverse_kinematics import inverse
from tasks.machine.kinematics import forward


@dataclass(frozen=True)
class Workpiece:
    """Ring count and geometry (mm): ring inner/outer diameters, the least distance between ring
    centres, the height step of the pads the rings are printed on (their tops above plate a's plane
    are multiples of it), the standoff of the tip's opening above the surface when it dispenses, the
    nominal dot diameter."""

    rings: int = 240
    ring_inner_mm: float = 2.4
    ring_outer_mm: float = 3.4
    min_spacing_mm: float = 4.4
    step_mm: float = 1.0
    standoff_mm: float = 0.2
    dot_diameter_mm: float = 0.8

    def to_dict(self) -> dict:
        return asdict(self)


def ring_ids(n: int) -> list[str]:
    return [f"ring{i:03d}" for i in range(n)]


def latin_hypercube(n: int, ranges, rng: np.random.Generator) -> np.ndarray:
    """(n, len(ranges)) samples, each column's range cut into n strata used once."""
    out = np.empty((n, len(ranges)))
    for j, (lo, hi) in enumerate(ranges):
        out[:, j] = lo + (rng.permutation(n) + rng.uniform(0.05, 0.95, n)) / n * (hi - lo)
    return out


@dataclass(frozen=True)
class Layout:
    """Ring centres (N, 2) and the heights of their pads' tops (N,) (mm, workpiece frame), and the
    nominal dispensing commands (N, 5) (mm, deg)."""

    centres: np.ndarray
    surface_z_mm: np.ndarray
    commands: np.ndarray


def _nominal_tips(machine: Machine, commands: np.ndarray) -> np.ndarray:
    return forward(machine, commands).tool_in_workpiece()[:, :3, 3]


def ring_layout(machine: Machine, workpiece: Workpiece, command_ranges: np.ndarray, seed: int,
                max_draws: int = 1000) -> Layout:
    """The rings and their dispensing commands: X, Y, Z, A, C over ``command_ranges`` (5, 2) (mm, deg)
    by a Latin hypercube, each ring at the foot of the nominal tip at its pose, on a pad whose top
    is ``standoff_mm`` below the tip rounded to ``step_mm`` (the commands then solved for that pad);
    a ring nearer than ``min_spacing_mm`` to an earlier one redrawn (uniform) up to ``max_draws``
    times."""
    rng = np.random.default_rng([seed, 31])
    ranges = np.asarray(command_ranges, dtype=float)
    drawn = latin_hypercube(workpiece.rings, ranges, rng)
    tips = _nominal_tips(machine, drawn)
    for i in range(workpiece.rings):
        for _ in range(max_draws):
            if i == 0 or np.min(np.linalg.norm(tips[:i, :2] - tips[i, :2], axis=1)) >= workpiece.min_spacing_mm:
                break
            drawn[i] = rng.uniform(ranges[:, 0], ranges[:, 1])
            tips[i] = _nominal_tips(machine, drawn[i:i + 1])[0]
        else:
            raise ValueError(f"no room for {workpiece.rings} rings {workpiece.min_spacing_mm} mm apart over "
                             f"these command ranges: use fewer rings")
    surface = np.round((tips[:, 2] - workpiece.standoff_mm) / workpiece.step_mm) * workpiece.step_mm
    centres = tips[:, :2]
    return Layout(centres, surface, dispensing_commands(machine, workpiece, centres, surface, drawn))


def tool_direction(machine: Machine, a_c_deg: np.ndarray) -> np.ndarray:
    """(N, 3) unit tool axis (tip frame z) in the workpiece frame at rotary commands (A, C) (deg),
    nominal machine (the linear axes do not turn it)."""
    cmd = np.zeros((len(a_c_deg), 5))
    cmd[:, 3:] = a_c_deg
    return forward(machine, cmd).tool_in_workpiece()[:, :3, 2]


def dispensing_commands(machine: Machine, workpiece: Workpiece, centres: np.ndarray, surface_z_mm: np.ndarray,
                        initial: np.ndarray) -> np.ndarray:
    """(N, 5) nominal commands (mm, deg) that hold the tip ``standoff_mm`` above each ring centre
    (N, 2) on its pad at ``surface_z_mm`` (N,) (along the surface normal), the tool axis set by the A
    and C of ``initial`` (N, 5)."""
    d = tool_direction(machine, initial[:, 3:])
    target = np.column_stack([centres, np.asarray(surface_z_mm, dtype=float) + workpiece.standoff_mm])
    return inverse(machine, target, d, initial=initial)


def imaging_commands(machine: Machine, centres: np.ndarray, surface_z_mm: np.ndarray, camera: str = "camera1"
                     ) -> np.ndarray:
    """(N, 5) nominal commands that put ``camera``'s optical axis through each ring centre (N, 2),
    A = C = 0, the camera as far from the ring's pad (its top at ``surface_z_mm`` (N,)) as from plate a
    at the zero command (its working distance on the prototype): Z raised by the pad's height."""
    home = forward(machine, np.zeros((1, 5)))
    cam_in_wp = home.relative(camera, machine.workpiece)[0]
    # where the optical axis (camera z) meets plate a's plane at the zero command (workpiece frame)
    o, z = cam_in_wp[:3, 3], cam_in_wp[:3, 2]
    hit = o - z * (o[2] / z[2])
    cmd = np.zeros((len(centres), 5))
    cmd[:, 0] = centres[:, 0] - hit[0]
    cmd[:, 1] = centres[:, 1] - hit[1]
    cmd[:, 2] = surface_z_mm
    return cmd


def commands_frame(commands: np.ndarray) -> pd.DataFrame:
    """Commands (N, 5) as columns X_mm, Y_mm, Z_mm, A_deg, C_deg."""
    return pd.DataFrame({f"{a}_{'deg' if a in ('A', 'C') else 'mm'}": commands[:, i]
                         for i, a in enumerate(AXIS_ORDER)})
