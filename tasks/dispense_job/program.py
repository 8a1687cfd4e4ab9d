"""The dispensing program: the CSV of commands the machine runs (§3.2, Figure 21).

One row per move, in the tour's order: from home, for every board a ``travel`` to above its bead's
first point at the safe height, an ``approach`` down to the dispensing height, the ``dispense`` moves
along the bead with the glue on at the bead speed, a ``retract`` to the safe height; last the travel
``home``. Every row carries the five commands X, Y, Z (mm), A, C (deg) — compensated when the job is
compensated — the dispense flag (1: glue on during the move to this row's position) and the speed
(mm/s) of the move to it.

The machine's speeds are the paper's (§4.3: the needle travels at 3.5 mm/s; Table 7 and eq. 30: the
bead at about 1 mm/s); its accelerations are not stated, 100 mm/s² per axis is assumed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from tasks.machine.description import COMMAND_COLUMNS


@dataclass(frozen=True)
class Motion:
    """Speeds (mm/s) and accelerations (mm/s², per axis X, Y, Z) of the moves; the lift of the safe
    height above the dispensing height (mm)."""

    travel_mm_s: float = 3.5
    bead_mm_s: float = 1.0
    accel_mm_s2: tuple[float, float, float] = (100.0, 100.0, 100.0)
    lift_mm: float = 2.0

    def to_dict(self) -> dict:
        return asdict(self)


def program_rows(order: np.ndarray, board_ids: list[str], bead_commands: list[np.ndarray], home: np.ndarray,
                 motion: Motion, home_between: bool = False) -> pd.DataFrame:
    """The program (see the module docstring). ``order``: the tour's board indices (a closed tour may
    start and end with home's index −1 or repeat the first; only board indices ≥ 0 are used, each once);
    ``bead_commands[i]``: (k, 5) commands along board i's bead; ``home``: (5,) the home command;
    ``home_between``: back home after every board (the paper's traditional path, Figure 15a)."""
    rows = []

    def add(board: str, move: str, cmd: np.ndarray, on: int, speed: float) -> None:
        rows.append({"step": len(rows), "board_id": board, "move": move,
                     **{c: float(v) for c, v in zip(COMMAND_COLUMNS, cmd, strict=True)},
                     "dispense": on, "speed_mm_s": speed})

    add("", "start", home, 0, motion.travel_mm_s)
    seen = set()
    for i in (int(k) for k in order):
        if i < 0 or i in seen or i >= len(board_ids):
            continue
        seen.add(i)
        bead = bead_commands[i]
        up = bead[0].copy()
        up[2] += motion.lift_mm
        add(board_ids[i], "travel", up, 0, motion.travel_mm_s)
        add(board_ids[i], "approach", bead[0], 0, motion.travel_mm_s)
        for cmd in bead[1:]:
            add(board_ids[i], "dispense", cmd, 1, motion.bead_mm_s)
        end = bead[-1].copy()
        end[2] += motion.lift_mm
        add(board_ids[i], "retract", end, 0, motion.travel_mm_s)
        if home_between and len(seen) < len(board_ids):
            add("", "home", home, 0, motion.travel_mm_s)
    add("", "home", home, 0, motion.travel_mm_s)
    return pd.DataFrame(rows)


def program_time_s(program: pd.DataFrame, motion: Motion, travel_time) -> tuple[float, float]:
    """(travel seconds, dispensing seconds) of a program: each run of consecutive moves with the glue
    off (at the travel speed) or on (at the bead speed) is timed by ``travel_time(path_mm (k, 3),
    speed_mm_s (3,), accel_mm_s2 (3,))`` over its X, Y, Z waypoints (row k's flag is that of the move
    into row k)."""
    xyz = program[["X_mm", "Y_mm", "Z_mm"]].to_numpy(float)
    flag = program["dispense"].to_numpy(int)
    totals = {0: 0.0, 1: 0.0}
    first = 1
    for k in range(2, len(program) + 1):
        if k == len(program) or flag[k] != flag[first]:
            speed = motion.bead_mm_s if flag[first] else motion.travel_mm_s
            totals[int(flag[first])] += float(travel_time(xyz[first - 1:k], (speed,) * 3, motion.accel_mm_s2))
            first = k
    return totals[0], totals[1]


def write_program(path, program: pd.DataFrame) -> None:
    """Write the program as CSV (the columns of :func:`program_rows`)."""
    program.to_csv(path, index=False, float_format="%.6f")

