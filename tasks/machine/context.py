"""What a pose's errors may depend on besides the axis positions.

A :class:`PoseContext` travels with a batch of N poses: commanded positions, the direction
from which each axis approached its position, the time since the campaign started and the
machine temperature. Effects (backlash, thermal drift, ...) read it; the pure geometric errors
ignore it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PoseContext:
    """approach: (N, 5) in {-1, 0, +1}, sign of the last move of each axis (0: never moved),
    columns in AXIS_ORDER. time_s: (N,) seconds since the campaign started.
    temperature_c: (N,) machine temperature (°C)."""

    approach: np.ndarray
    time_s: np.ndarray
    temperature_c: np.ndarray

    @classmethod
    def neutral(cls, n: int, temperature_c: float = 20.0) -> PoseContext:
        return cls(np.zeros((n, 5)), np.zeros(n), np.full(n, temperature_c))

    def take(self, idx) -> PoseContext:
        return PoseContext(self.approach[idx], self.time_s[idx], self.temperature_c[idx])


def approach_directions(commands: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Sign of the last move of each axis, for poses visited in the given order.

    commands: (N, 5) in capture order. start: (5,) position before the first pose (default zeros).
    An axis that did not move keeps the direction of its previous move. Returns (N, 5) in
    {-1, 0, +1}. Vectorised: forward-fill of the non-zero move signs.
    """
    c = np.asarray(commands, dtype=float)
    prev = np.zeros((1, c.shape[1])) if start is None else np.asarray(start, dtype=float)[None]
    step = np.sign(np.diff(np.vstack([prev, c]), axis=0))  # (N, 5)
    n = step.shape[0]
    idx = np.where(step != 0, np.arange(n)[:, None], -1)
    last = np.maximum.accumulate(idx, axis=0)  # last row index with a move, per axis
    out = np.take_along_axis(step, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, out, 0.0)
