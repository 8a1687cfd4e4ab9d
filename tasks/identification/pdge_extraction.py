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
cross-validation (a periodic one for a rotary axis swept over its whole turn).

Gauge (what a sweep cannot tell, and where it goes):
- the value at home is indistinguishable from the constant errors that the PIGE fit identifies,
  so every profile is referred to home (zero at command 0);
- the linear trend of a linear axis' translations perpendicular to its motion is its direction:
  for X it defines the base x axis, for Y's z component the XY plane, and the rest are the
  squareness errors of eq. 21 (:mod:`tasks.identification.squareness`). Those trends are
  removed from the profiles and reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline, make_smoothing_spline

from tasks import se3
from tasks.error_model import COMPONENT_SCALE, ERROR_COMPONENTS, ErrorModel
from tasks.identification.measurements import Measurements
from tasks.kinematics import forward
from tasks.machine import AXIS_ORDER, Machine

COMPONENT_COLUMNS = ("dx_um", "dy_um", "dz_um", "ex_arcsec", "ey_arcsec", "ez_arcsec")


@dataclass
class TabulatedProfile:
    """Six error motions of one axis tabulated at ``positions`` (internal units: mm or rad) and
    interpolated by cubic splines; periodic over 2π when ``periodic``, otherwise held constant
    beyond the tabulated range. values: (K, 6) in mm / rad."""

    positions: np.ndarray
    values: np.ndarray
    periodic: bool = False
    _spline: CubicSpline | None = field(default=None, init=False, repr=False, compare=False)

    def _fit(self) -> CubicSpline:
        if self._spline is None:
            x, y = np.asarray(self.positions, float), np.asarray(self.values, float)
            if self.periodic:
                x, y = np.append(x, x[0] + 2 * np.pi), np.vstack([y, y[:1]])
                self._spline = CubicSpline(x, y, axis=0, bc_type="periodic")
            elif x.size >= 2:
                self._spline = CubicSpline(x, y, axis=0, bc_type="natural")
        return self._spline

    def __call__(self, position: np.ndarray) -> np.ndarray:
        """(N,) positions (mm or rad) -> (N, 6) error motions (mm, rad)."""
        pos = np.asarray(position, dtype=float)
        if len(self.positions) < 2:
            return np.broadcast_to(np.asarray(self.values, float).reshape(-1, 6)[0], (*pos.shape, 6)).copy()
        x0 = self.positions[0]
        if self.periodic:
            pos = (pos - x0) % (2 * np.pi) + x0
        else:
            pos = np.clip(pos, self.positions[0], self.positions[-1])
        return self._fit()(pos)

    def to_dict(self) -> dict:
        return {"kind": "tabulated", "positions": np.asarray(self.positions).tolist(),
                "values": (np.asarray(self.values) / COMPONENT_SCALE).tolist(), "periodic": self.periodic}

    @classmethod
    def from_dict(cls, d: dict) -> TabulatedProfile:
        return cls(np.asarray(d["positions"], float), np.asarray(d["values"], float).reshape(-1, 6) * COMPONENT_SCALE,
                   bool(d.get("periodic", False)))


def error_motion_components(E: np.ndarray) -> np.ndarray:
    """Inverse of :func:`tasks.se3.error_motion`: (N, 4, 4) -> (N, 6) (δ mm, ε rad), eq. 8 order."""
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


def _smooth(x: np.ndarray, y: np.ndarray, w: np.ndarray, periodic: bool) -> np.ndarray:
    """Weighted smoothing spline through (x, y) with GCV-chosen roughness, evaluated at x."""
    if x.size < 5:
        return y.copy()
    w = w / w.mean()  # GCV is scale-free in the weights but ill-conditioned for weights ~1e8
    if periodic:  # three turns side by side, keep the middle one
        xs = np.concatenate([x - 2 * np.pi, x, x + 2 * np.pi])
        return make_smoothing_spline(xs, np.tile(y, 3), w=np.tile(w, 3))(x)
    return make_smoothing_spline(x, y, w=w)(x)


def _is_full_turn(machine: Machine, axis: str, positions_cmd: np.ndarray) -> bool:
    ax = machine.axes[axis]
    return ax.is_rotary and positions_cmd.size > 4 and np.ptp(positions_cmd) + np.diff(positions_cmd).max() >= 359.0


def referred_to_home(machine: Machine, axis: str, q: np.ndarray, values: np.ndarray,
                     reference: TabulatedProfile) -> tuple[np.ndarray, np.ndarray]:
    """Apply the gauge of this module to ``values`` (N, 6) at positions ``q`` (N,) (internal units).

    The home value of ``reference`` is subtracted; for a linear axis the linear trend of
    ``reference``'s perpendicular translations is subtracted too. Returns (referred values,
    slopes (6,) removed per unit of position)."""
    home = reference(np.zeros(1))[0]
    slopes = np.zeros(6)
    ax = machine.axes[axis]
    if not ax.is_rotary:
        x = np.asarray(reference.positions, float)
        fit = reference(x) - home
        along = int(np.argmax(np.abs(ax.direction)))
        for k in range(3):
            if k != along and x.size >= 2:
                slopes[k] = float(x @ fit[:, k] / (x @ x))
    return values - home - np.outer(q, slopes), slopes


@dataclass
class PdgeResult:
    """table: the ``pdge`` lake table (see docs/results). profiles: {axis: TabulatedProfile}
    referred to home (mm, rad). slopes: {axis: (6,) removed linear trends (mm per mm)}."""

    table: pd.DataFrame
    profiles: dict[str, TabulatedProfile]
    slopes: dict[str, np.ndarray]


def extract_axis(machine: Machine, model: ErrorModel, sweep: Measurements, axis: str,
                 truth: ErrorModel | None = None) -> tuple[pd.DataFrame, TabulatedProfile, np.ndarray]:
    """The PDGE rows, smooth referred profile and removed slopes of one axis from its sweep."""
    e = measured_error_motions(machine, model, sweep, axis)  # (N, 6) mm, rad
    pos_cmd = sweep.table[axis].to_numpy(dtype=float)
    frame = pd.DataFrame(e, columns=ERROR_COMPONENTS).assign(position=pos_cmd)
    grouped = frame.groupby("position")
    mean = grouped[list(ERROR_COMPONENTS)].mean()
    count = grouped.size().to_numpy()
    positions_cmd = mean.index.to_numpy(dtype=float)
    ax = machine.axes[axis]
    q = ax.to_internal(positions_cmd)
    # pooled within-position variance per component (homoscedastic repeats); 1 repeat: point-to-point scatter
    dev = frame[list(ERROR_COMPONENTS)] - grouped[list(ERROR_COMPONENTS)].transform("mean")
    dof = max(int(len(frame) - len(mean)), 0)
    if dof >= 3:
        pooled = (dev.to_numpy() ** 2).sum(axis=0) / dof
    else:
        pooled = np.var(np.diff(mean.to_numpy(), axis=0), axis=0) / 2 if len(mean) > 2 else np.ones(6)
    pooled = np.maximum(pooled, 1e-18)
    std = np.sqrt(pooled[None, :] / count[:, None])
    periodic = _is_full_turn(machine, axis, positions_cmd)
    values = mean.to_numpy()
    fitted = np.column_stack([_smooth(q, values[:, k], count / pooled[k], periodic) for k in range(6)])
    raw_profile = TabulatedProfile(q, fitted, periodic)
    fit_ref, slopes = referred_to_home(machine, axis, q, fitted, raw_profile)
    meas_ref, _ = referred_to_home(machine, axis, q, values, raw_profile)
    profile = TabulatedProfile(q, fit_ref, periodic)
    rows = pd.DataFrame({"axis": axis, "position": positions_cmd, "position_unit": "deg" if ax.is_rotary else "mm",
                         "n_images": count})
    for k, col in enumerate(COMPONENT_COLUMNS):
        rows[col] = meas_ref[:, k] / COMPONENT_SCALE[k]
        rows[f"std_{col}"] = std[:, k] / COMPONENT_SCALE[k]
        rows[f"fit_{col}"] = fit_ref[:, k] / COMPONENT_SCALE[k]
        rows[f"truth_{col}"] = np.nan
    if truth is not None and axis in truth.pdge:
        true_values = truth.pdge[axis](q)
        true_ref, _ = referred_to_home(machine, axis, q, true_values, TabulatedProfile(q, true_values, periodic))
        for k, col in enumerate(COMPONENT_COLUMNS):
            rows[f"truth_{col}"] = true_ref[:, k] / COMPONENT_SCALE[k]
    rows["translation_um"] = np.linalg.norm(rows[list(COMPONENT_COLUMNS[:3])].to_numpy(), axis=1)
    rows["rotation_arcsec"] = np.linalg.norm(rows[list(COMPONENT_COLUMNS[3:])].to_numpy(), axis=1)
    return rows, profile, slopes


def extract_pdges(machine: Machine, model: ErrorModel, measurements: Measurements,
                  truth: ErrorModel | None = None) -> PdgeResult:
    """PDGEs of every axis that has a sweep (stage ``pdge``, group = axis name)."""
    tables, profiles, slopes = [], {}, {}
    sweeps = measurements.stage("pdge")
    for axis in AXIS_ORDER:
        sweep = sweeps.select(sweeps.table.group == axis)
        if len(sweep) < 2:
            continue
        rows, profile, slope = extract_axis(machine, model, sweep, axis, truth)
        tables.append(rows)
        profiles[axis] = profile
        slopes[axis] = slope
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    return PdgeResult(table, profiles, slopes)
