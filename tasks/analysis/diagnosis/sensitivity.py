"""Per-image sensitivities of the pose residuals (eq. 20) and of the sweeps' error motions (eqs. 13–19)
to small error screws, by batched central differences.

Every effect acts through three kinds of *channels* (:mod:`tasks.machine.effects`):

- ``("joint", j)``: the six-vector (δx, δy, δz mm, εx, εy, εz rad) added to joint j's error screw;
- ``("attachment", a)``: the six-vector of attachment a's error motion in its own frame;
- ``("imaging",)``: the plate-frame twist b by which the camera's imaging biases the measured pose
  (T_meas = T · exp(b), :mod:`tasks.identification.imaging`).

An image's residual depends only on that image's channel values, so one forward-kinematics call
per channel component, with the same small screw added at every image, gives the whole (N, 6, 6)
block of derivatives: d r_n / d u_n for all n at once. A candidate's residual column is then
Σ_blocks D_block[n] · u_block[n] with u its per-image channel values (exact to first order; the
errors are small). The same holds for the error motions E_j that the PDGE extraction reads from
axis j's sweep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.core import se3
from tasks.identification.measurements import Measurements
from tasks.identification.pdge_extraction import measured_error_motions
from tasks.identification.pige_identification import pose_residuals
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.effects import Effect
from tasks.machine.error_model import ErrorModel

STEP = np.array([1e-3] * 3 + [1e-5] * 3)  # 1 µm, 2″: inside the linear range, far above rounding
IMAGING = ("imaging",)


class ScrewProbe(Effect):
    """A constant error screw on one joint or attachment (not registered: a differentiation probe)."""

    family = "_probe"

    def __init__(self, channel: tuple, vector: np.ndarray):  # no Params: a probe, not a family
        self.values = {}
        self.channel = channel
        self.vector = np.asarray(vector, dtype=float)

    def spec(self) -> str:
        return f"_probe:{self.channel}"

    def joint_errors(self, machine, q, context):
        return {self.channel[1]: np.tile(self.vector, (q.shape[0], 1))} if self.channel[0] == "joint" else {}

    def attachment_errors(self, machine, q, context):
        return {self.channel[1]: self.vector} if self.channel[0] == "attachment" else {}


def with_effect(model: ErrorModel, effect: Effect) -> ErrorModel:
    return ErrorModel(pige=model.pige, pdge=model.pdge, effects=[*model.effects, effect],
                      joint_offsets=model.joint_offsets, attachment_offsets=model.attachment_offsets,
                      joint_slopes=model.joint_slopes)


def channels_for(machine: Machine, cameras) -> list[tuple]:
    """Channels that can change what ``cameras`` see: every joint, each camera and the plate it
    views, and the imaging bias. (An attachment no camera sees, e.g. the tip, has no channel.)"""
    atts = []
    for cam in cameras:
        for a in (cam, machine.views[cam]):
            if a not in atts:
                atts.append(a)
    return [*(("joint", a) for a in AXIS_ORDER), *(("attachment", a) for a in atts), IMAGING]


def _central(fun) -> np.ndarray:
    """(N, 6, 6) central differences of fun(probe vector) (N, 6) over the 6 components."""
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = STEP[k]
        cols.append((fun(d) - fun(-d)) / (2 * STEP[k]))
    return np.stack(cols, axis=-1)


@dataclass
class Sensitivity:
    """blocks: {channel: (N, 6, 6)} derivative of a (N, 6) quantity (residual or error motion)
    with respect to the channel's six components at each image."""

    blocks: dict[tuple, np.ndarray]

    def apply(self, u: dict[tuple, np.ndarray]) -> np.ndarray:
        """Σ_channel D[n] · u[n]: u {channel: (B, N, 6)} -> (B, N, 6). Missing channels are zero."""
        out = None
        for ch, val in u.items():
            if ch not in self.blocks:
                continue
            term = np.einsum("nij,bnj->bni", self.blocks[ch], val)
            out = term if out is None else out + term
        return out


def residual_sensitivity(machine: Machine, model: ErrorModel, meas: Measurements) -> Sensitivity:
    """d r / d u for the eq. 20 residuals of ``meas`` (unwhitened, mm and rad) against ``model``."""
    cams = meas.table.camera.unique()
    blocks = {}
    for ch in channels_for(machine, cams):
        if ch == IMAGING:
            # the model's predicted measurement T exp(b): r = log((T e^b)⁻¹ T_meas) ≈ r − b
            blocks[ch] = np.broadcast_to(-np.eye(6), (len(meas), 6, 6)).copy()
            continue
        blocks[ch] = _central(lambda d, ch=ch: pose_residuals(machine, with_effect(model, ScrewProbe(ch, d)), meas))
    return Sensitivity(blocks)


def error_motion_sensitivity(machine: Machine, model: ErrorModel, sweep: Measurements, axis: str) -> Sensitivity:
    """d E_j / d u for the error motions (N_j, 6) that the extraction reads from ``axis``' sweep.

    The imaging channel is the model's imaging bias b, which the extraction sees as measured poses
    corrected to T_meas · exp(−b)."""
    cams = sweep.table.camera.unique()
    blocks = {}
    for ch in channels_for(machine, cams):
        if ch == IMAGING:
            def fun(d):
                moved = Measurements(sweep.table, sweep.T @ se3.exp(-d), sweep.cov, sweep.context)
                return measured_error_motions(machine, model, moved, axis)
        else:
            def fun(d, ch=ch):
                return measured_error_motions(machine, with_effect(model, ScrewProbe(ch, d)), sweep, axis)
        blocks[ch] = _central(fun)
    return Sensitivity(blocks)
