"""Measured plate poses with everything they were taken under.

A :class:`Measurements` holds, for N usable images, the commanded axes, the campaign stage, the
capture context (approach direction of each axis, time, temperature) and the measured pose
``T_cam_plate`` (camera frame, mm) with its 6×6 covariance of the plate-frame twist (v mm, ω rad).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pandas as pd

from tasks.machine.context import PoseContext, approach_directions
from tasks.machine.description import AXIS_ORDER, CALIBRATION_STAGE, COMMAND_COLUMNS
from tasks.vision.poses import covariances_from_table, poses_from_table

INFO_COLUMNS = ("image_id", "camera", "stage", "group", "repeat", "time_s", "temperature_c")


@dataclass
class Measurements:
    """table: (N rows) image_id, camera, stage, group, repeat, X..C (command units), time_s,
    temperature_c. T: (N, 4, 4) measured T_cam_plate (mm). cov: (N, 6, 6) covariance of the
    plate-frame pose error (mm, rad). context: the :class:`PoseContext` of the N poses."""

    table: pd.DataFrame
    T: np.ndarray
    cov: np.ndarray
    context: PoseContext

    def __len__(self) -> int:
        return len(self.table)

    @cached_property
    def commands(self) -> np.ndarray:
        """(N, 5) commanded X, Y, Z (mm), A, C (deg); computed once (the table is not to be modified)."""
        return self.table[list(AXIS_ORDER)].to_numpy(dtype=float)

    @cached_property
    def camera_rows(self) -> dict[str, np.ndarray]:
        """{camera: (N,) bool mask of its rows}; computed once."""
        cams = self.table["camera"].to_numpy()
        return {str(c): cams == c for c in np.unique(cams)}

    def select(self, mask) -> Measurements:
        """The subset of rows where ``mask`` (bool array or Series) holds."""
        idx = np.flatnonzero(np.asarray(mask, dtype=bool))
        return Measurements(self.table.iloc[idx].reset_index(drop=True), self.T[idx], self.cov[idx],
                            self.context.take(idx))

    def stage(self, *stages: str, camera: str | None = None) -> Measurements:
        mask = self.table.stage.isin(stages)
        if camera is not None:
            mask &= self.table.camera == camera
        return self.select(mask)


def capture_context(images: pd.DataFrame) -> pd.DataFrame:
    """Per image (in manifest order): approach direction of each axis, seconds since the first
    image and temperature. Returns image_id, approach_X..approach_C, time_s, temperature_c."""
    ordered = images.sort_values("manifest_row")
    approach = approach_directions(ordered[list(COMMAND_COLUMNS)].to_numpy(dtype=float))
    ts = pd.to_datetime(ordered["timestamp"], utc=True)
    time_s = (ts - ts.min()).dt.total_seconds().to_numpy() if ts.notna().any() else np.zeros(len(ordered))
    out = pd.DataFrame({"image_id": ordered["image_id"].to_numpy()})
    for i, axis in enumerate(AXIS_ORDER):
        out[f"approach_{axis}"] = approach[:, i]
    out["time_s"] = np.nan_to_num(time_s.astype(float))
    temp = ordered["temperature_c"].to_numpy(dtype=float) if "temperature_c" in ordered else np.full(len(out), np.nan)
    out["temperature_c"] = np.where(np.isfinite(temp), temp, 20.0)
    return out


def assemble_measurements(images: pd.DataFrame, poses: pd.DataFrame) -> Measurements:
    """Join the ``images`` and ``poses`` lake tables into :class:`Measurements`.

    Only images whose pose status is ``ok`` and whose pose and covariance are finite are kept;
    the approach directions are computed over every manifest row (failed images moved the
    machine too).
    """
    ctx = capture_context(images)
    merged = images.drop(columns=["temperature_c"], errors="ignore").merge(ctx, on="image_id").merge(
        poses.drop(columns=[c for c in ("camera", "campaign_id") if c in poses], errors="ignore"),
        on="image_id", suffixes=("", "_pose"))
    status = merged["status_pose"] if "status_pose" in merged else merged["status"]
    merged = merged[status == "ok"].sort_values("manifest_row").reset_index(drop=True)
    T = poses_from_table(merged)
    cov = covariances_from_table(merged)
    good = np.isfinite(T).all(axis=(1, 2)) & np.isfinite(cov).all(axis=(1, 2))
    merged, T, cov = merged[good].reset_index(drop=True), T[good], cov[good]
    table = merged[["image_id", "camera", "stage", "group", "repeat", "time_s", "temperature_c"]].copy()
    for axis, col in zip(AXIS_ORDER, COMMAND_COLUMNS, strict=True):
        table[axis] = merged[col].to_numpy(dtype=float)
    approach = merged[[f"approach_{a}" for a in AXIS_ORDER]].to_numpy(dtype=float)
    context = PoseContext(approach, table["time_s"].to_numpy(dtype=float), table["temperature_c"].to_numpy(dtype=float))
    return Measurements(table, T, cov, context)


def planned_measurements(plan: pd.DataFrame, cov: np.ndarray) -> Measurements:
    """Measurements shaped like a campaign plan (:func:`tasks.simulation.campaign_plan.plan_campaign`) with
    identity poses: the frame for synthetic (simulated, pose-level) measurements, e.g.
    :func:`tasks.identification.pige_identification.synthetic_measurements`.

    plan: manifest rows in capture order (camera-calibration rows are left out: the machine does
    not move for them). cov: (6, 6) covariance given to every pose (mm, rad). The context
    (approach directions, time, temperature) comes from the plan as the capture would give it.
    """
    rows = plan[plan.stage != CALIBRATION_STAGE]
    approach = approach_directions(plan[list(AXIS_ORDER)].to_numpy(dtype=float))[rows.index.to_numpy()]
    table = rows[["image_id", "camera", "stage", "group", "repeat", "time_s", "temperature_c",
                  *AXIS_ORDER]].reset_index(drop=True)
    n = len(table)
    context = PoseContext(approach, table["time_s"].to_numpy(dtype=float), table["temperature_c"].to_numpy(dtype=float))
    return Measurements(table, np.tile(np.eye(4), (n, 1, 1)), np.tile(np.asarray(cov, dtype=float), (n, 1, 1)),
                        context)
