"""PDGEs of each axis from its single-axis sweep (eqs. 13–19 of the calibration paper).

For an image of the sweep of axis j, everything but j's error motion is taken from the current
model. With P the pose of j's frame before its error (base frame), T_bc the camera pose, T_pred
the modelled and T_meas the measured T_cam_plate, the error motion of j is the conjugate

    E_j = Q · (T_pred · T_meas⁻¹) · Q⁻¹      j on the camera's chain  (eqs. 18–19 analogue)
    E_j = Q · (T_meas · T_pred⁻¹) · Q⁻¹      j on the plate's chain   (eqs. 15–17)
    Q = P⁻¹ · T_bc,

read as the six components (δx, δy, δz, εx, εy, εz) of eq. 8 (εy = asin R13, εx = −atan2(R23, R33),
εz = −atan2(R12, R11)). The images of a position are averaged over repeats, then each component
is smoothed by a weighted smoothing spline whose roughness is chosen by generalised
cross-validation.

Gauge (what a sweep cannot tell, and where it goes):
- the value at home is indistinguishable from the constant errors that the PIGE fit identifies,
  so every profile is referred to home (zero at command 0);
- what a change of the axis line would produce (:func:`line_error_signatures`: for a linear
  axis the linear trends of its perpendicular translations, i.e. its direction; for a rotary one
  the once-per-turn patterns of a tilted or shifted axis) is removed by least squares: the PIGEs
  and, for X's direction and the XY plane, the camera's mounting carry it. The fit of the
  constant parameters over the sweeps and the five-axis poses then sees these trends in the
  residuals and identifies the squareness of the linear axes from their motion directions
  (eq. 21) together with the other PIGEs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline

from tasks.core import se3
from tasks.identification.measurements import Measurements
from tasks.identification.smoothing import smooth
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import COMPONENT_SCALE, ErrorModel
from tasks.machine.kinematics import forward, ideal_joint_motion

COMPONENT_COLUMNS = ("dx_um", "dy_um", "dz_um", "ex_arcsec", "ey_arcsec", "ez_arcsec")


@dataclass
class TabulatedProfile:
    """Six error motions of one axis tabulated at ``positions`` (internal units: mm or rad) and
    interpolated by a natural cubic spline, held constant beyond the tabulated range.
    values: (K, 6) in mm / rad."""

    positions: np.ndarray
    values: np.ndarray
    _spline: CubicSpline | None = field(default=None, init=False, repr=False, compare=False)

    def _fit(self) -> CubicSpline:
        if self._spline is None:
            self._spline = CubicSpline(np.asarray(self.positions, float), np.asarray(self.values, float),
                                       axis=0, bc_type="natural")
        return self._spline

    def __call__(self, position: np.ndarray) -> np.ndarray:
        """(N,) positions (mm or rad) -> (N, 6) error motions (mm, rad)."""
        pos = np.asarray(position, dtype=float)
        if len(self.positions) < 2:
            return np.broadcast_to(np.asarray(self.values, float).reshape(-1, 6)[0], (*pos.shape, 6)).copy()
        return self._fit()(np.clip(pos, self.positions[0], self.positions[-1]))

    def to_dict(self) -> dict:
        return {"kind": "tabulated", "positions": np.asarray(self.positions).tolist(),
                "values": (np.asarray(self.values) / COMPONENT_SCALE).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> TabulatedProfile:
        return cls(np.asarray(d["positions"], float), np.asarray(d["values"], float).reshape(-1, 6) * COMPONENT_SCALE)


def error_motion_components(E: np.ndarray) -> np.ndarray:
    """Inverse of :func:`tasks.core.se3.error_motion`: (N, 4, 4) -> (N, 6) (δ mm, ε rad), eq. 8 order."""
    R = E[:, :3, :3]
    ey = np.arcsin(np.clip(R[:, 0, 2], -1.0, 1.0))
    ex = np.arctan2(-R[:, 1, 2], R[:, 2, 2])
    ez = np.arctan2(-R[:, 0, 1], R[:, 0, 0])
    return np.column_stack([E[:, :3, 3], ex, ey, ez])


def without_pdge(model: ErrorModel, axis: str) -> ErrorModel:
    """A copy of ``model`` whose ``axis`` has no PDGE profile and no home offset."""
    return ErrorModel(pige=model.pige, pdge={a: p for a, p in model.pdge.items() if a != axis},
                      effects=model.effects, joint_offsets={a: v for a, v in model.joint_offsets.items() if a != axis},
                      attachment_offsets=model.attachment_offsets)


def measured_error_motions(machine: Machine, model: ErrorModel, sweep: Measurements, axis: str) -> np.ndarray:
    """Error motions (N, 6) (mm, rad) of ``axis`` at each image of its sweep, everything else as in ``model``.

    sweep: images of one camera in which only ``axis`` moved.
    """
    cameras = sweep.table.camera.unique()
    if len(cameras) != 1:
        raise ValueError(f"sweep of {axis}: expected one camera, got {list(cameras)}")
    camera = str(cameras[0])
    fk = forward(machine, sweep.commands, without_pdge(model, axis), sweep.context)
    T_bc = fk.pose(camera)
    T_pred = fk.camera_view(camera)
    chain = machine.chain_of(axis)
    i = chain.index(axis)
    P = (fk.pose(chain[i - 1]) if i else np.eye(4)) @ machine.link_offsets[axis]
    Q = se3.inverse(P) @ T_bc
    on_camera_chain = axis in machine.parents(machine.attachments[camera].link)
    D = T_pred @ se3.inverse(sweep.T) if on_camera_chain else sweep.T @ se3.inverse(T_pred)
    return error_motion_components(Q @ D @ se3.inverse(Q))


def line_error_basis(machine: Machine, axis: str) -> np.ndarray:
    """(m, 6) unit error screws (joint frame) that move ``axis``' line: for a linear axis the two
    rotations that tilt its direction (m = 2), for a rotary axis also the two translations that
    shift it (m = 4). The PIGEs of Table 2 are such screws."""
    d = np.abs(np.asarray(machine.axes[axis].direction, dtype=float))
    perp = [k for k in range(3) if d[k] < 0.5]
    rows = [3 + k for k in perp] + ([] if not machine.axes[axis].is_rotary else perp)
    return np.eye(6)[rows]


def line_error_signatures(machine: Machine, axis: str, q: np.ndarray) -> np.ndarray:
    """(K, 6, m) error motions (mm, rad per unit screw) that each line error of
    :func:`line_error_basis` produces at positions ``q`` (K,) (mm or rad): E·J·E⁻¹·J⁻¹ to first
    order, e − Ad_J e with J = e^{ξ̂θ}. Zero at home."""
    basis = line_error_basis(machine, axis)  # (m, 6)
    J = ideal_joint_motion(machine, axis, np.asarray(q, dtype=float))
    moved = np.einsum("kij,mj->kim", se3.adjoint(J), basis)  # (K, 6, m)
    return basis.T[None] - moved


def referred_to_home(machine: Machine, axis: str, q: np.ndarray, values: np.ndarray,
                     reference: TabulatedProfile) -> tuple[np.ndarray, np.ndarray]:
    """Apply the gauge of this module to ``values`` (N, 6) at positions ``q`` (N,) (internal units).

    The home value of ``reference`` is subtracted, then the least-squares combination (in µm and
    arcsec) of the line-error signatures that best fits ``reference`` over its positions. Returns
    (referred values, the line-error coefficients removed (m,) in mm / rad, rows of
    :func:`line_error_basis`)."""
    home = reference(np.zeros(1))[0]
    x = np.asarray(reference.positions, float)
    sig = line_error_signatures(machine, axis, x) / COMPONENT_SCALE[None, :, None]  # per unit screw, file units
    target = (reference(x) - home) / COMPONENT_SCALE
    A = sig.reshape(-1, sig.shape[2])
    coef = np.linalg.lstsq(A, target.ravel(), rcond=None)[0] if x.size >= 2 else np.zeros(A.shape[1])
    removed = np.einsum("kcm,m->kc", line_error_signatures(machine, axis, q), coef)
    return values - home - removed, coef


@dataclass
class PdgeResult:
    """table: the ``pdge`` lake table (see docs/results). profiles: {axis: TabulatedProfile}
    referred to home (mm, rad). line_errors: {axis: (m,) the line-error coefficients removed
    (mm / rad, rows of :func:`line_error_basis`)}. smoothing: {axis: (6,) the spline roughness λ
    of each component (:mod:`tasks.identification.smoothing`)}."""

    table: pd.DataFrame
    profiles: dict[str, TabulatedProfile]
    line_errors: dict[str, np.ndarray]
    smoothing: dict[str, np.ndarray] = field(default_factory=dict)


def position_means(e: np.ndarray, where: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(k, 6) the mean of the error motions e (N, 6) at each of a sweep's k positions (``where`` (N,)
    each image's position, ``count`` (k,) images per position)."""
    means = np.zeros((count.size, e.shape[1]))
    np.add.at(means, where, e)
    return means / count[:, None]


def pooled_variance(e: np.ndarray, where: np.ndarray, means: np.ndarray) -> np.ndarray:
    """(6,) within-position variance of the error motions e (N, 6) over a sweep's repeats
    (homoscedastic), ``where`` (N,) each image's position and ``means`` (k, 6) the positions' means;
    with fewer than 3 degrees of freedom of repeats, half the variance of consecutive means."""
    dof = len(e) - len(means)
    if dof >= 3:
        pooled = ((e - means[where]) ** 2).sum(axis=0) / dof
    else:
        pooled = np.var(np.diff(means, axis=0), axis=0) / 2 if len(means) > 2 else np.ones(6)
    return np.maximum(pooled, 1e-18)


def repeats_noise(pooled: np.ndarray, count: np.ndarray) -> np.ndarray | None:
    """The variance of a position's mean at the mean repeat count, per component (6,), for the
    smoother's discrepancy choice (:func:`tasks.identification.smoothing.smooth`'s ``noise_var``):
    only where the repeats give it (at least 3 degrees of freedom), else None."""
    return pooled / count.mean() if count.sum() - count.size >= 3 else None


def extract_axis(machine: Machine, model: ErrorModel, sweep: Measurements, axis: str,
                 truth: ErrorModel | None = None, lam: np.ndarray | None = None
                 ) -> tuple[pd.DataFrame, TabulatedProfile, np.ndarray, np.ndarray]:
    """The PDGE rows, smooth referred profile, removed line errors and spline roughness (6,) of one
    axis from its sweep. lam: the roughness to use (default: chosen by
    :meth:`tasks.identification.smoothing.SplineBasis.roughness`)."""
    e = measured_error_motions(machine, model, sweep, axis)  # (N, 6) mm, rad
    # the images of a position averaged over its repeats (numpy, not groupby: this runs in every
    # round of the alternation and of each uncertainty re-fit)
    positions_cmd, where, count = np.unique(sweep.table[axis].to_numpy(dtype=float), return_inverse=True,
                                            return_counts=True)
    values = position_means(e, where, count)
    ax = machine.axes[axis]
    q = ax.to_internal(positions_cmd)
    pooled = pooled_variance(e, where, values)
    std = np.sqrt(pooled[None, :] / count[:, None])
    # one weight per position (the repeats' count): the pooled variance of a component scales all
    # its weights alike, and the smoother is invariant to that
    fitted, lam = smooth(q, values, count, lam, repeats_noise(pooled, count))
    raw_profile = TabulatedProfile(q, fitted)
    fit_ref, line = referred_to_home(machine, axis, q, fitted, raw_profile)
    meas_ref, _ = referred_to_home(machine, axis, q, values, raw_profile)
    profile = TabulatedProfile(q, fit_ref)
    true_ref = np.full_like(meas_ref, np.nan)
    if truth is not None and axis in truth.pdge:
        true_values = truth.pdge[axis](q)
        true_ref, _ = referred_to_home(machine, axis, q, true_values, TabulatedProfile(q, true_values))
    columns = {"axis": axis, "position": positions_cmd, "position_unit": "deg" if ax.is_rotary else "mm",
               "n_images": count}
    for k, col in enumerate(COMPONENT_COLUMNS):
        columns[col] = meas_ref[:, k] / COMPONENT_SCALE[k]
        columns[f"std_{col}"] = std[:, k] / COMPONENT_SCALE[k]
        columns[f"fit_{col}"] = fit_ref[:, k] / COMPONENT_SCALE[k]
        columns[f"truth_{col}"] = true_ref[:, k] / COMPONENT_SCALE[k]
    file_units = meas_ref / COMPONENT_SCALE
    columns["translation_um"] = np.linalg.norm(file_units[:, :3], axis=1)
    columns["rotation_arcsec"] = np.linalg.norm(file_units[:, 3:], axis=1)
    rows = pd.DataFrame(columns)
    return rows, profile, line, lam


def extract_pdges(machine: Machine, model: ErrorModel, measurements: Measurements,
                  truth: ErrorModel | None = None, smoothing: dict[str, np.ndarray] | None = None) -> PdgeResult:
    """PDGEs of every axis that has a sweep (stage ``pdge``, group = axis name).

    smoothing: {axis: (6,) λ} to hold the smoothers of an earlier extraction (default: chosen anew)."""
    tables, profiles, lines, lams = [], {}, {}, {}
    sweeps = measurements.stage("pdge")
    for axis in AXIS_ORDER:
        sweep = sweeps.select(sweeps.table.group == axis)
        if len(sweep) < 2:
            continue
        rows, profile, line, lams[axis] = extract_axis(machine, model, sweep, axis, truth,
                                                       None if smoothing is None else smoothing.get(axis))
        tables.append(rows)
        profiles[axis] = profile
        lines[axis] = line
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    return PdgeResult(table, profiles, lines, lams)
