"""The constant parameters that the PIGE fit identifies, and how they enter the error model.

Each parameter is one component of a constant error screw (internal units mm or rad):
- ``pige``: the 11 PIGEs of Table 2 (:data:`tasks.machine.error_model.PIGE_SCREWS`);
- ``constant``: home values of a joint's error motion that no PIGE covers but that the referred
  PDGE profiles leave out (the zero offsets of C and A, the axial offset of C);
- ``squareness``: the slope of a linear axis' straightness perpendicular to its motion (µm per
  mm, shown as arcsec): Y toward X, Z toward X and Z toward Y, the motion-direction errors of eq. 21;
- ``mount``: the hand–eye correction of a camera on its link (rotations and the depth along the
  optical axis). It absorbs what self-calibration leaves in the intrinsics: a principal-point error
  acts as a small camera rotation and a focal-length error as a depth offset;
- ``effect``: an amplitude (or phase) of one of the model's effects (:mod:`tasks.machine.effects`), in
  that parameter's own unit; ``calibrate(..., base=ErrorModel(effects=[...]))`` fits them
  (:mod:`tasks.identification.effect_fit`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from tasks.core.units import ARCSEC, UM
from tasks.machine.error_model import PIGE_NAMES, PIGE_SCREWS, ErrorModel


@dataclass(frozen=True)
class ParamSpec:
    """name: shown in tables. kind: "pige" | "constant" | "squareness" | "mount" | "effect".
    target: joint or attachment (for an effect: its axis or camera, if it has one).
    component: 0..5 of (dx, dy, dz, ex, ey, ez); for an effect: its index in the model's ``effects``.
    param, effect_unit, step (effects only): the effect's parameter, its unit and the Jacobian step
    in that unit (0: one unit). An effect parameter is fitted in its own unit (scale 1)."""

    name: str
    kind: str
    target: str
    component: int
    param: str = ""
    effect_unit: str = ""
    step: float = 0.0

    @property
    def is_angle(self) -> bool:
        if self.kind == "effect":
            return self.effect_unit == "arcsec"
        return self.component >= 3 or self.kind == "squareness"

    @property
    def unit(self) -> str:
        if self.kind == "effect":
            return self.effect_unit
        return "arcsec" if self.is_angle else "um"

    @property
    def scale(self) -> float:
        """Internal units per file unit (mm per µm or rad per arcsec; 1 for an effect's parameter)."""
        if self.kind == "effect":
            return 1.0
        return ARCSEC if self.is_angle else UM

    @property
    def jacobian_step(self) -> float:
        """Difference step of the Jacobian (internal units): 1 µm, 1″ or one unit of an effect's parameter."""
        if self.kind == "effect":
            return self.step or 1.0
        return self.scale


COMPONENT_NAMES = ("dx", "dy", "dz", "ex", "ey", "ez")


def pige_params(names=PIGE_NAMES) -> list[ParamSpec]:
    return [ParamSpec(n, "pige", PIGE_SCREWS[n][0], PIGE_SCREWS[n][1]) for n in names]


def constant_param(joint: str, component: int) -> ParamSpec:
    return ParamSpec(f"{joint}.{COMPONENT_NAMES[component]}0", "constant", joint, component)


def squareness_param(axis: str, component: int) -> ParamSpec:
    """Slope of ``axis``' translation ``component`` (0..2) per unit of travel; unit: arcsec (rad)."""
    return ParamSpec(f"{axis}.{COMPONENT_NAMES[component]}_slope", "squareness", axis, component)


def mount_param(attachment: str, component: int) -> ParamSpec:
    return ParamSpec(f"{attachment}.{COMPONENT_NAMES[component]}", "mount", attachment, component)


def default_parameters(tool_link: str = "Z", plate: str = "plate_a") -> list[ParamSpec]:
    """The 11 PIGEs, the constant error of ``tool_link`` at home (6) and the orientation of
    ``plate`` on its link (3): 20 parameters, the complete set for the camera-to-plate chain (4 per
    rotary and 2 per linear axis plus 6, less the 3 that fix the base frame: X's direction and the
    XY plane).

    Why these: the PDGE profiles are referred to home, so the errors present at home (every axis'
    PDGE value there) appear as one constant camera-to-plate pose plus, because the base frame is
    defined by X and Y, a constant rotation of the workpiece chain (the plate's 3). The constant
    pose is put on the tool chain's last link, not on the camera's mounting: camera and tip are
    taken to be mounted as designed (docs/virtual-machine.md), so a constant error the camera sees
    moves the tip as well. The PIGEs move the axis lines and act only away from home."""
    return [*pige_params(), *(constant_param(tool_link, k) for k in range(6)),
            *(mount_param(plate, k) for k in (3, 4, 5))]


def apply_parameters(base: ErrorModel, specs: list[ParamSpec], values: np.ndarray) -> ErrorModel:
    """``base`` with the parameters set to ``values`` (internal units), added to what base holds.
    An ``effect`` parameter is added to that parameter of ``base.effects[spec.component]``."""
    pige = dict(base.pige)
    joints = {k: np.array(v, dtype=float) for k, v in base.joint_offsets.items()}
    mounts = {k: np.array(v, dtype=float) for k, v in base.attachment_offsets.items()}
    slopes = {k: np.array(v, dtype=float) for k, v in base.joint_slopes.items()}
    effects = list(base.effects)
    targets = {"constant": joints, "mount": mounts, "squareness": slopes}
    for spec, v in zip(specs, values, strict=True):
        if spec.kind == "pige":
            pige[spec.name] = pige.get(spec.name, 0.0) + float(v)
        elif spec.kind == "effect":
            e = effects[spec.component]
            effects[spec.component] = e.with_values(**{spec.param: e[spec.param] + float(v)})
        else:
            targets[spec.kind].setdefault(spec.target, np.zeros(6))[spec.component] += float(v)
    return replace(base, pige=pige, joint_offsets=joints, attachment_offsets=mounts, joint_slopes=slopes,
                   effects=effects)
