"""Travel time of the head along a path of waypoints, from each axis's speed and acceleration.

Model (point-to-point, rest to rest): the head stops at every waypoint. On each segment every axis
starts together and runs its own symmetric profile over its own displacement d with its maximum speed
v and acceleration a: trapezoidal (accelerate, cruise at v, decelerate) when d ≥ v²/a, taking
d/v + v/a; triangular (never reaching v) otherwise, taking 2·√(d/a). The segment ends when the slowest
axis arrives, so its time is the largest of the axes' times; the path's time is the sum over segments.
Jerk limits, blending between segments and controller latency are not modelled.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def axis_move_time_s(distance_mm: np.ndarray, speed_mm_s: float, accel_mm_s2: float) -> np.ndarray:
    """Rest-to-rest time (s) of one axis over ``distance_mm`` (any shape, mm; sign ignored) with
    maximum speed ``speed_mm_s`` and acceleration ``accel_mm_s2``."""
    d = np.abs(np.asarray(distance_mm, dtype=float))
    v, a = float(speed_mm_s), float(accel_mm_s2)
    trapezoid = d / v + v / a
    triangle = 2.0 * np.sqrt(d / a)
    return np.where(d >= v * v / a, trapezoid, triangle)


def segment_times_s(
    path_mm: np.ndarray, speed_mm_s: Sequence[float], accel_mm_s2: Sequence[float]
) -> np.ndarray:
    """(k−1,) time (s) of each segment of ``path_mm`` (k, 2) or (k, 3) machine waypoints (mm), with
    one maximum speed (mm/s) and acceleration (mm/s²) per axis column: the slowest axis's time."""
    path = np.asarray(path_mm, dtype=float)
    if path.ndim != 2 or path.shape[1] not in (2, 3):
        raise ValueError(f"path_mm must be a (k, 2) or (k, 3) array of waypoints in mm, got shape {path.shape}")
    bad = np.flatnonzero(~np.isfinite(path).all(axis=1))
    if bad.size:
        raise ValueError(f"path_mm row {bad[0]} is not finite: {path[bad[0]].tolist()}")
    speed = np.asarray(speed_mm_s, dtype=float).reshape(-1)
    accel = np.asarray(accel_mm_s2, dtype=float).reshape(-1)
    axes = path.shape[1]
    for name, values in (("speed_mm_s", speed), ("accel_mm_s2", accel)):
        if values.size != axes:
            raise ValueError(f"{name} needs one value per path axis ({axes}), got {values.size}")
        if not (np.isfinite(values).all() and (values > 0).all()):
            raise ValueError(f"{name} must be finite and positive, got {values.tolist()}")
    step = np.diff(path, axis=0)
    per_axis = np.stack([axis_move_time_s(step[:, j], speed[j], accel[j]) for j in range(axes)], axis=1)
    return per_axis.max(axis=1) if len(step) else np.zeros(0)


def travel_time_s(path_mm: np.ndarray, speed_mm_s: Sequence[float], accel_mm_s2: Sequence[float]) -> float:
    """Time (s) to move through the waypoints ``path_mm`` (k, 2) or (k, 3) machine XY(Z) mm, stopping
    at each, with per-axis maximum speed (mm/s) and acceleration (mm/s²): see the module's model."""
    return float(segment_times_s(path_mm, speed_mm_s, accel_mm_s2).sum())
