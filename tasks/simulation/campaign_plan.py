"""The poses of a measurement campaign, in capture order (§5.2 of the calibration paper).

Stages:
- ``camera_calibration``: per camera, ``trials`` independent trials of ``images_per_trial``
  views of its calibration target (``Machine.plate_seen``) held on a tilting fixture (the
  target's pose relative to the camera is free; the machine stands still). Plate b only turns in
  its own plane on the A axis, so the fixture is needed to give the tilted views that camera
  self-calibration requires, and a target that spans more of the field than the measured plates
  fixes focal length and principal point about three times better.
- ``pdge``: per axis, ``positions`` positions × ``repeats`` repeats, centred on home so that the
  sweep includes zero: X/Y in 1 mm and A in 1° steps as in the seed; Z in 0.2 mm steps (the
  seed's 0.1 mm spans only ±2.5 mm, less than the five-axis poses use) and C over its whole
  stroke, both ends included (``positions`` + 1 when even, so that home is one of them),
  because the five-axis poses turn C through all of it and a
  PDGE is only known where it was swept. Repeats alternate direction (forward, backward, ...),
  so reversal errors show. Camera 1 measures X/Y/Z/C on plate a, camera 2 measures A on plate b.
- ``pige``: five-axis poses (A within ±``max_tilt_deg``, C over its stroke) with camera 1 aimed
  at plate a plus random lateral and height offsets. The defaults keep every axis inside its
  swept range (A ±24° within the A sweep, Y = −40 sin A ± 5 mm within ±25 mm, Z within ±5 mm).
- ``validation``: held-out poses drawn like the ``pige`` ones from an independent stream.

Passes: with ``passes`` > 1 the sweeps' repeats and the five-axis poses are split into that many
passes taken one after the other (pass p: its share of every axis' repeats, then its share of the
``pige`` poses), ``pause_s`` apart; the calibration views come first and the validation poses last.
Spread over time, the passes tell an effect that follows time or temperature from the geometry the
sweeps measure (with one pass the X sweep is minutes old when the validation poses are taken).

Time: each image takes ``seconds_per_image`` (plus the pauses between passes); temperature follows a
warm-up curve with a slow oscillation, so that time and temperature are not collinear.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from tasks.core import se3
from tasks.machine.context import PoseContext, approach_directions
from tasks.machine.description import AXIS_ORDER, CALIBRATION_STAGE, Machine
from tasks.machine.kinematics import forward

STAGES = (CALIBRATION_STAGE, "pdge", "pige", "validation")
SWEEP_STEP = {"X": 1.0, "Y": 1.0, "Z": 0.2, "A": 1.0}  # mm or deg per step; C spans its stroke
SWEEP_CAMERA = {"X": "camera1", "Y": "camera1", "Z": "camera1", "C": "camera1", "A": "camera2"}


@dataclass(frozen=True)
class CampaignPlan:
    """Stage sizes. The defaults are the seed's (§5.2)."""

    calibration_trials: int = 10
    images_per_trial: int = 15
    sweep_positions: int = 50
    sweep_repeats: int = 5
    pige_poses: int = 300
    validation_poses: int = 100
    max_tilt_deg: float = 24.0
    lateral_offset_mm: float = 5.0
    height_offset_mm: float = 1.0
    seconds_per_image: float = 3.0
    sweep_step_scale: float = 1.0
    passes: int = 1
    pause_s: float = 0.0

    @classmethod
    def small(cls) -> CampaignPlan:
        """A reduced plan for fast tests."""
        return cls(calibration_trials=2, images_per_trial=8, sweep_positions=6, sweep_repeats=2,
                   pige_poses=24, validation_poses=8)

    @classmethod
    def context(cls) -> CampaignPlan:
        """A small plan that exercises the context of a move (docs/effects.md): sweeps of 11
        positions at 5 × the default step, which span the five-axis poses' range as the default's 50
        do (X/Y ±25 mm, Z ±5 mm, A ±25°), and two passes 50 minutes apart, each with one repeat of
        every sweep and half the five-axis poses: 206 images over an hour (the
        simulated machine warms up with a time constant of 1 h)."""
        return cls(calibration_trials=2, images_per_trial=8, sweep_positions=11, sweep_repeats=2,
                   pige_poses=48, validation_poses=16, sweep_step_scale=5.0, passes=2, pause_s=3000.0)


PLANS = {"default": CampaignPlan, "small": CampaignPlan.small, "context": CampaignPlan.context}
"""The named plans of ``fivecal simulate --plan``."""


def aim_camera(machine: Machine, camera: str, rotary_deg: np.ndarray, offsets_mm: np.ndarray) -> np.ndarray:
    """Commands (N, 5) that put ``camera`` over the centre of its plate, on the ideal machine.

    rotary_deg: (N, 2) A and C (deg). offsets_mm: (N, 3) added to X, Y, Z. The camera stands on
    its optical axis at its focus distance from the plate centre. Valid when the camera rides on
    the tool chain's linear axes (a pure translation of the camera).
    """
    n = rotary_deg.shape[0]
    cmd = np.zeros((n, 5))
    cmd[:, 3:] = rotary_deg
    fk = forward(machine, cmd)
    plate = fk.pose(machine.views[camera])[:, :3, 3]
    cam = fk.pose(camera)
    distance = machine.cameras[camera].focus_distance_mm
    wanted = plate - distance * cam[:, :3, 2]  # camera z is the optical axis
    cmd[:, :3] = wanted - cam[:, :3, 3] + offsets_mm
    return cmd


def sweep_positions(machine: Machine, axis: str, positions: int, step_scale: float = 1.0) -> np.ndarray:
    """The commanded positions (mm or deg) of ``axis``' PDGE sweep, centred on home, in steps of
    ``step_scale`` × SWEEP_STEP.

    An axis without a step in SWEEP_STEP (C) is swept over its whole stroke, both ends included
    (a rotary axis with a limited stroke is not periodic: its error at +180° need not equal the one
    at −180°), in an even number of steps so that home is among them: ``positions`` rounded up to
    an odd count."""
    if axis in SWEEP_STEP:
        return (np.arange(positions) - positions // 2) * SWEEP_STEP[axis] * step_scale
    lo, hi = machine.axes[axis].stroke
    return np.linspace(lo, hi, positions + 1 - positions % 2)


def _sweep(machine: Machine, axis: str, plan: CampaignPlan) -> pd.DataFrame:
    positions = sweep_positions(machine, axis, plan.sweep_positions, plan.sweep_step_scale)
    rows = []
    for r in range(plan.sweep_repeats):
        order = positions if r % 2 == 0 else positions[::-1]
        cmd = np.zeros((order.size, 5))
        cmd[:, AXIS_ORDER.index(axis)] = order
        rows.append(pd.DataFrame({"repeat": r, **{a: cmd[:, i] for i, a in enumerate(AXIS_ORDER)}}))
    df = pd.concat(rows, ignore_index=True)
    df["camera"] = SWEEP_CAMERA[axis]
    df["group"] = axis
    return df


def five_axis_poses(machine: Machine, n: int, plan: CampaignPlan, rng: np.random.Generator) -> np.ndarray:
    """(n, 5) commands with camera 1 aimed at plate a: A within ±max_tilt, C uniform, offsets."""
    lo_c, hi_c = machine.axes["C"].stroke
    rotary = np.column_stack([
        rng.uniform(-plan.max_tilt_deg, plan.max_tilt_deg, n),
        rng.uniform(lo_c, hi_c, n),
    ])
    offsets = np.column_stack([
        rng.uniform(-plan.lateral_offset_mm, plan.lateral_offset_mm, (n, 2)),
        rng.uniform(-plan.height_offset_mm, plan.height_offset_mm, n),
    ])
    return aim_camera(machine, "camera1", rotary, offsets)


FIXTURE_MARGIN = 1.05
"""A self-calibration view keeps its target's corners this factor inside the field's edges."""


def fixture_poses(machine: Machine, camera: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) poses of the camera's self-calibration target in the camera frame (mm).

    Tilts up to 35° about a random in-plane axis, any in-plane rotation, distance within ±8 % of
    focus, and the target shifted anywhere its image stays inside the field: per view, its four
    corners' pinhole projection at that tilt and spin bounds the shift along the image's x and y,
    with a 5 % margin. The views so reach the field's edges and corners, where the machine's
    images put the plates (an X or Y sweep's ends): there the lens distortion is measured, not
    extrapolated (docs/camera-calibration.md).
    """
    cam = machine.cameras[camera]
    plate = machine.plates[machine.plate_seen(camera, CALIBRATION_STAGE)]
    d = cam.focus_distance_mm * rng.uniform(0.92, 1.08, n)
    tilt = np.deg2rad(rng.uniform(10, 35, n))
    tilt_dir = rng.uniform(0, 2 * np.pi, n)
    spin = rng.uniform(-np.pi, np.pi, n)
    axis = np.column_stack([np.cos(tilt_dir), np.sin(tilt_dir), np.zeros(n)])
    # plate faces the camera: rotate 180° about x, then tilt, then spin about the plate normal
    R = se3.exp_so3(axis * tilt[:, None]) @ se3.rot_x(np.full(n, np.pi)) @ se3.rot_z(spin)
    hx, hy = plate.half_extent_mm
    corners = np.array([[sx * hx, sy * hy, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    offsets = np.einsum("nij,kj->nki", R, corners)  # (n, 4, 3) about the target's centre
    reach = offsets[..., :2] * (d[:, None] / (d[:, None] + offsets[..., 2]))[..., None] * FIXTURE_MARGIN
    half = np.array([cam.width_px, cam.height_px]) * cam.pixel_size_mm / cam.focal_length_mm / 2 * d[:, None]
    up = np.maximum(half - reach.max(axis=1), 0.0)  # how far the centre may move towards +x, +y
    down = np.maximum(half + reach.min(axis=1), 0.0)  # ... towards -x, -y
    u = rng.uniform(-1, 1, (n, 2))
    shift = np.where(u >= 0, u * up, u * down)
    return se3.from_rotation_translation(R, np.column_stack([shift, d]))


def temperature_at(time_s: np.ndarray, start_c: float = 20.0) -> np.ndarray:
    """Machine temperature (°C): +1.2 K warm-up (time constant 1 h) plus ±0.25 K, 40 min period."""
    t = np.asarray(time_s, dtype=float)
    return start_c + 1.2 * (1.0 - np.exp(-t / 3600.0)) + 0.25 * np.sin(2 * np.pi * t / 2400.0)


def _five_axis_rows(stage: str, cmd: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({"camera": "camera1", "stage": stage, "group": stage, "repeat": 0,
                         **{a: cmd[:, i] for i, a in enumerate(AXIS_ORDER)}})


def plan_campaign(machine: Machine, plan: CampaignPlan, seed: int) -> tuple[pd.DataFrame, dict[int, np.ndarray]]:
    """All images of a campaign in capture order.

    Returns the manifest rows (image_id, camera, stage, group, repeat, X..C commands, time_s,
    temperature_c) and, for fixture views, {row index: T_cam_plate (4, 4)}.
    """
    rng = np.random.default_rng([seed, 1])
    parts = []
    fixture: list[np.ndarray] = []
    for camera in machine.cameras:
        poses = fixture_poses(machine, camera, plan.calibration_trials * plan.images_per_trial, rng)
        fixture.extend(poses)
        trial = np.repeat(np.arange(plan.calibration_trials), plan.images_per_trial)
        parts.append(pd.DataFrame({
            "camera": camera, "stage": CALIBRATION_STAGE,
            "group": [f"trial{t:02d}" for t in trial], "repeat": 0,
            **{a: 0.0 for a in AXIS_ORDER},
        }))
    sweeps = [_sweep(machine, axis, plan).assign(stage="pdge") for axis in ("X", "Y", "Z", "A", "C")]
    five_axis = {stage: five_axis_poses(machine, n, plan, np.random.default_rng([seed, stream]))
                 for stage, n, stream in (("pige", plan.pige_poses, 2), ("validation", plan.validation_poses, 3))}
    pige_share = np.array_split(np.arange(plan.pige_poses), plan.passes)
    pass_of = [np.zeros(len(p), dtype=int) for p in parts]
    for p in range(plan.passes):
        for df in sweeps:
            mine = df[df["repeat"] * plan.passes // plan.sweep_repeats == p]
            parts.append(mine)
            pass_of.append(np.full(len(mine), p))
        parts.append(_five_axis_rows("pige", five_axis["pige"][pige_share[p]]))
        pass_of.append(np.full(len(pige_share[p]), p))
    parts.append(_five_axis_rows("validation", five_axis["validation"]))
    pass_of.append(np.full(plan.validation_poses, plan.passes - 1))
    df = pd.concat(parts, ignore_index=True)
    df.insert(0, "image_id", [f"img{i:05d}" for i in range(len(df))])
    df["time_s"] = np.arange(len(df)) * plan.seconds_per_image + np.concatenate(pass_of) * plan.pause_s
    df["temperature_c"] = temperature_at(df["time_s"].to_numpy())
    n_fixture = len(fixture)
    fixture_map = dict(zip(range(n_fixture), fixture, strict=True))
    return df[["image_id", "camera", "stage", "group", "repeat", *AXIS_ORDER, "time_s", "temperature_c"]], fixture_map


def plan_context(plan: pd.DataFrame) -> PoseContext:
    """The context of every planned image (rows in capture order, AXIS_ORDER columns, time_s,
    temperature_c): the approach direction of each axis from the moves of the plan (home before
    the first row), the time and the temperature of the plan."""
    return PoseContext(approach_directions(plan[list(AXIS_ORDER)].to_numpy(dtype=float)),
                       plan["time_s"].to_numpy(float), plan["temperature_c"].to_numpy(float))
