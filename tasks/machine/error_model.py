"""Geometric errors of the machine: PIGEs (Table 2, eqs. 9–11) and PDGEs (Table 1, eq. 8).

Every error is an error screw in the local frame of the joint it belongs to. The PDGE error
motion is applied before the joint motion; the PIGEs move the joint's axis line (eq. 12):
``link_offset · e^{ξ_D(θ)} · E_I · e^{ξ θ} · E_I⁻¹`` with ``E_I = e^{ξ_I}``, so a PIGE acts in
proportion to the joint's travel and is zero at home (what a sweep refers to home cannot hide it).
A rotation PIGE tilts the axis (for a linear axis: its direction of motion, i.e. squareness); a
translation PIGE of a rotary axis shifts its line.

PIGE names follow the paper's symbols (ASCII spelling) and each is defined by its unit screw in
the joint frame. The paper leaves the axis of each α/β open; we take α/β to be the rotation that
changes the angle between the two named axes:

==========  =====  ============================  ==============================================
name        joint  unit screw (local frame)      meaning
==========  =====  ============================  ==============================================
delta_AZ    A      translation z                 radial error of A along z
delta_AY    A      translation y                 radial error of A along y
alpha_AZ    A      rotation about y              A's +x end tipped toward −z (A–Z squareness)
beta_AY     A      rotation about z              A's +x end turned toward +y (A–Y squareness)
delta_CX    C      translation x                 radial error of C along x
delta_CY    C      translation y                 radial error of C along y
beta_CY     C      rotation about x              C's +z end tipped toward −y (C–Y squareness)
alpha_CX    C      rotation about y              C's +z end tipped toward +x (C–X squareness)
gamma_YX    Y      rotation about z              Y's +y end turned toward −x (Y–X squareness)
alpha_YZ    Z      rotation about x              Z's +z end tipped toward −y (Z–Y squareness)
beta_XZ     Z      rotation about y              Z's +z end tipped toward +x (Z–X squareness)
==========  =====  ============================  ==============================================

Within a joint the factors are multiplied in the order of eqs. 9–11 (the table order above). Signs
follow the right-hand rule about the screw's axis; tests/machine/test_sign_conventions.py pins them.
Units: files and reports use µm and arcsec; inside, mm and rad.

PDGEs: each axis has six error motions (δx, δy, δz, εx, εy, εz) as smooth functions of its own
position θ: a constant part, Chebyshev polynomials over the stroke and sinusoids (ball-screw and
guide-way waviness, or harmonics of a rotary axis). The constant part is kept (the paper's
"absolute representation": Fig. 11 histograms have non-zero means).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from tasks.core import se3
from tasks.core.units import ARCSEC, UM
from tasks.machine.description import AXIS_ORDER
from tasks.machine.effects import parse_effect

# name -> (joint, screw index 0..5 in (tx, ty, tz, rx, ry, rz)), in the product order of eqs. 9–11
PIGE_SCREWS: dict[str, tuple[str, int]] = {
    "delta_AZ": ("A", 2),
    "delta_AY": ("A", 1),
    "alpha_AZ": ("A", 4),
    "beta_AY": ("A", 5),
    "delta_CX": ("C", 0),
    "delta_CY": ("C", 1),
    "beta_CY": ("C", 3),
    "alpha_CX": ("C", 4),
    "gamma_YX": ("Y", 5),
    "alpha_YZ": ("Z", 3),
    "beta_XZ": ("Z", 4),
}
PIGE_NAMES = tuple(PIGE_SCREWS)
ERROR_COMPONENTS = ("dx", "dy", "dz", "ex", "ey", "ez")
# file units (µm, arcsec) -> internal (mm, rad), per component of a six-vector
COMPONENT_SCALE = np.array([UM, UM, UM, ARCSEC, ARCSEC, ARCSEC])


def pige_is_angle(name: str) -> bool:
    return PIGE_SCREWS[name][1] >= 3


def pige_to_internal(name: str, value_file_units: float) -> float:
    return value_file_units * (ARCSEC if pige_is_angle(name) else UM)


def pige_to_file_units(name: str, value_internal: float) -> float:
    return value_internal / (ARCSEC if pige_is_angle(name) else UM)


def pige_unit(name: str) -> str:
    return "arcsec" if pige_is_angle(name) else "um"


def pige_joint_transforms(pige: dict[str, float]) -> dict[str, np.ndarray]:
    """Constant PIGE transforms E_I = e^{ξ_I} per joint (eqs. 9–11) that move its axis, values in mm / rad.

    Returns {joint: (4, 4)} for joints that have at least one PIGE. Cached (they are constant):
    the returned arrays are shared and must not be modified.
    """
    return _pige_joint_transforms(tuple(sorted(pige.items())))


@lru_cache(maxsize=64)
def _pige_joint_transforms(items: tuple) -> dict[str, np.ndarray]:
    pige = dict(items)
    out: dict[str, np.ndarray] = {}
    for name, (joint, k) in PIGE_SCREWS.items():
        value = pige.get(name, 0.0)
        if value == 0.0:
            continue
        screw = np.zeros(6)
        screw[k] = value
        factor = se3.exp(screw)
        out[joint] = out[joint] @ factor if joint in out else factor
    return out


@dataclass
class AxisProfile:
    """Six error motions of one axis as smooth functions of its position.

    All arrays in internal units (mm, rad). ``position`` is in internal units too
    (mm for linear axes, rad for rotary ones).

    offset: (6,) constant part.
    chebyshev: (6, K) coefficients of T_1..T_K on s = position / half_range.
    sine_amplitude: (6, M); sine_wavelength: (M,) in position units; sine_phase: (6, M) rad.
    """

    half_range: float
    offset: np.ndarray = field(default_factory=lambda: np.zeros(6))
    chebyshev: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))
    sine_amplitude: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))
    sine_wavelength: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sine_phase: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))

    def __call__(self, position: np.ndarray) -> np.ndarray:
        """(N,) positions -> (N, 6) error motions (mm, rad)."""
        pos = np.asarray(position, dtype=float)
        out = np.broadcast_to(self.offset, (*pos.shape, 6)).copy()
        if self.chebyshev.shape[1]:
            s = pos / self.half_range
            basis = np.polynomial.chebyshev.chebvander(s, self.chebyshev.shape[1])[..., 1:]  # (N, K)
            out += basis @ self.chebyshev.T
        if self.sine_wavelength.size:
            # a sin(w x + p) = sin(w x) (a cos p) + cos(w x) (a sin p): trig on (N, M) only
            wx = 2.0 * np.pi * pos[..., None] / self.sine_wavelength  # (N, M)
            out += np.sin(wx) @ (self.sine_amplitude * np.cos(self.sine_phase)).T
            out += np.cos(wx) @ (self.sine_amplitude * np.sin(self.sine_phase)).T
        return out

    def scaled(self, translation: float, rotation: float) -> AxisProfile:
        """The same shapes with translational and rotational parts multiplied."""
        s = np.array([translation] * 3 + [rotation] * 3)
        return AxisProfile(
            self.half_range,
            self.offset * s,
            self.chebyshev * s[:, None],
            self.sine_amplitude * s[:, None],
            self.sine_wavelength.copy(),
            self.sine_phase.copy(),
        )

    def to_dict(self) -> dict:
        """File form: µm / arcsec, wavelengths in mm or rad as stored."""
        sc = COMPONENT_SCALE
        return {
            "half_range": self.half_range,
            "offset": (self.offset / sc).tolist(),
            "chebyshev": (self.chebyshev / sc[:, None]).tolist(),
            "sine_amplitude": (self.sine_amplitude / sc[:, None]).tolist(),
            "sine_wavelength": self.sine_wavelength.tolist(),
            "sine_phase": self.sine_phase.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> AxisProfile:
        sc = COMPONENT_SCALE
        cheb = np.asarray(d.get("chebyshev", np.zeros((6, 0))), dtype=float).reshape(6, -1)
        amp = np.asarray(d.get("sine_amplitude", np.zeros((6, 0))), dtype=float).reshape(6, -1)
        return cls(
            half_range=float(d["half_range"]),
            offset=np.asarray(d.get("offset", np.zeros(6)), dtype=float) * sc,
            chebyshev=cheb * sc[:, None],
            sine_amplitude=amp * sc[:, None],
            sine_wavelength=np.asarray(d.get("sine_wavelength", []), dtype=float),
            sine_phase=np.asarray(d.get("sine_phase", np.zeros((6, 0))), dtype=float).reshape(6, -1),
        )


@dataclass
class ErrorModel:
    """Everything that makes the real machine differ from its description.

    pige: {name: value} in mm / rad (missing names are zero).
    pdge: {axis: AxisProfile}; axes without a profile have no PDGE.
    effects: extra physical effects (see :mod:`tasks.machine.effects`), each adding to joint error
    screws, attachment poses or camera intrinsics.
    joint_offsets: {axis: (6,)} constant error motions added to the axis' PDGE (mm, rad): the
    home values that identification fits when its PDGE profiles are referred to home.
    joint_slopes: {axis: (6,)} error motions per unit of the axis' position (per mm or per rad),
    e.g. the squareness of a linear axis as the slope of its perpendicular straightness.
    attachment_offsets: {attachment: (6,)} constant mounting errors in the attachment's own
    frame (mm, rad), e.g. a camera's hand–eye correction.
    """

    pige: dict[str, float] = field(default_factory=dict)
    pdge: dict[str, AxisProfile] = field(default_factory=dict)
    effects: list = field(default_factory=list)
    joint_offsets: dict[str, np.ndarray] = field(default_factory=dict)
    attachment_offsets: dict[str, np.ndarray] = field(default_factory=dict)
    joint_slopes: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def none(cls) -> ErrorModel:
        return cls()

    def joint_error_vectors(self, machine, q: np.ndarray, context) -> dict[str, np.ndarray]:
        """{axis: (N, 6)} PDGE six-vectors (mm, rad) plus every effect's joint errors.

        q: (N, 5) joint values in AXIS_ORDER (mm, rad). context: :class:`tasks.machine.context.PoseContext`.
        """
        out: dict[str, np.ndarray] = {}
        for axis, profile in self.pdge.items():
            out[axis] = profile(q[:, AXIS_ORDER.index(axis)])
        for axis, offset in self.joint_offsets.items():
            out[axis] = out[axis] + offset if axis in out else np.tile(np.asarray(offset, dtype=float), (q.shape[0], 1))
        for axis, slope in self.joint_slopes.items():
            e = np.outer(q[:, AXIS_ORDER.index(axis)], np.asarray(slope, dtype=float))
            out[axis] = out[axis] + e if axis in out else e
        for effect in self.effects:
            for axis, e in effect.joint_errors(machine, q, context).items():
                out[axis] = out[axis] + e if axis in out else np.broadcast_to(e, (q.shape[0], 6)).copy()
        return out

    def attachment_error_vectors(self, machine, q: np.ndarray, context) -> dict[str, np.ndarray]:
        """{attachment: (N, 6)} error motions of attachments in their own frame (mm, rad)."""
        out: dict[str, np.ndarray] = {name: np.tile(np.asarray(e, dtype=float), (q.shape[0], 1))
                                      for name, e in self.attachment_offsets.items()}
        for effect in self.effects:
            for name, e in effect.attachment_errors(machine, q, context).items():
                e = np.broadcast_to(e, (q.shape[0], 6))
                out[name] = out[name] + e if name in out else e.copy()
        return out

    def to_dict(self) -> dict:
        return {
            "pige": {n: pige_to_file_units(n, v) for n, v in self.pige.items()},
            "pige_units": {n: pige_unit(n) for n in self.pige},
            "pdge": {a: p.to_dict() for a, p in self.pdge.items()},
            "effects": [e.spec() for e in self.effects],
            "joint_offsets": {a: (np.asarray(v) / COMPONENT_SCALE).tolist() for a, v in self.joint_offsets.items()},
            "attachment_offsets": {a: (np.asarray(v) / COMPONENT_SCALE).tolist()
                                   for a, v in self.attachment_offsets.items()},
            "joint_slopes": {a: (np.asarray(v) / COMPONENT_SCALE).tolist() for a, v in self.joint_slopes.items()},
        }

    @classmethod
    def from_dict(cls, d: dict, families: dict | None = None) -> ErrorModel:
        """The model of :meth:`to_dict`; families: effect families beyond the catalogue
        (:func:`tasks.machine.effects.parse_effect`)."""
        return cls(
            pige={n: pige_to_internal(n, float(v)) for n, v in d.get("pige", {}).items()},
            pdge={a: AxisProfile.from_dict(p) for a, p in d.get("pdge", {}).items()},
            effects=[parse_effect(s, families) for s in d.get("effects", [])],
            joint_offsets={a: np.asarray(v, dtype=float) * COMPONENT_SCALE
                           for a, v in d.get("joint_offsets", {}).items()},
            attachment_offsets={a: np.asarray(v, dtype=float) * COMPONENT_SCALE
                                for a, v in d.get("attachment_offsets", {}).items()},
            joint_slopes={a: np.asarray(v, dtype=float) * COMPONENT_SCALE
                          for a, v in d.get("joint_slopes", {}).items()},
        )
