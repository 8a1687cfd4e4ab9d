"""Catalogue of physical effects beyond the nominal error model.

An effect is a named family with documented parameters and units. It is written as a spec
string ``family:key=value,...`` (e.g. ``pitch_cyclic:axis=X,period_mm=5,amplitude_um=6``) and
can add to

- the error screw of a joint (``joint_errors``: {axis: (N, 6)} in the joint's local frame,
  (δx, δy, δz) mm and (εx, εy, εz) rad, added to the PDGE six-vector of eq. 8);
- the pose of an attachment (``attachment_errors``: {name: (N, 6)} in the attachment's frame);
- a camera's imaging (``camera_changes``: focal-length scale per image, extra distortion).

A new family is a subclass of :class:`Effect` registered with :func:`register`; it then parses,
lists and injects like a built-in one (see docs/effects.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from tasks.core.units import ARCSEC, UM
from tasks.machine.description import AXIS_ORDER, Machine

LINEAR_AXES = ("X", "Y", "Z")
ROTARY_AXES = ("A", "C")


@dataclass(frozen=True)
class Param:
    """One parameter of an effect family.

    kind: "axis", "camera", "choice" or "float". unit: e.g. "um", "mm", "arcsec", "ppm".
    amplitude: True if the effect is linear in this parameter (what a fit can estimate directly);
    other float parameters (period, phase) shape the effect and are scanned, not fitted linearly.
    """

    name: str
    kind: str
    unit: str = ""
    default: object = None
    doc: str = ""
    choices: tuple[str, ...] = ()
    amplitude: bool = False


class Effect:
    """Base class of effect families. Subclasses set ``family``, ``summary`` and ``params``."""

    family: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()

    def __init__(self, **values):
        known = {p.name: p for p in self.params}
        unknown = set(values) - set(known)
        if unknown:
            raise ValueError(
                f"effect {self.family!r}: unknown parameter(s) {sorted(unknown)}; "
                f"expected {sorted(known)}"
            )
        self.values: dict[str, object] = {}
        for p in self.params:
            raw = values.get(p.name, p.default)
            if raw is None:
                raise ValueError(f"effect {self.family!r}: parameter {p.name!r} ({p.doc}) is required")
            self.values[p.name] = self._coerce(p, raw)

    def _coerce(self, p: Param, raw):
        if p.kind == "float":
            try:
                value = float(raw)
            except (TypeError, ValueError):
                raise ValueError(
                    f"effect {self.family!r}: {p.name}={raw!r} is not a number ({p.unit})"
                ) from None
            if not np.isfinite(value):
                raise ValueError(f"effect {self.family!r}: {p.name}={raw!r} is not finite")
            return value
        value = str(raw)
        if p.choices and value not in p.choices:
            raise ValueError(f"effect {self.family!r}: {p.name}={value!r} must be one of {list(p.choices)}")
        return value

    def __getitem__(self, name: str):
        return self.values[name]

    def with_values(self, **changes) -> Effect:
        """A copy of this effect with some parameter values changed (e.g. a fitted amplitude)."""
        return type(self)(**{**self.values, **changes})

    def spec(self) -> str:
        """The canonical spec string: ``family:key=value,...`` in parameter order."""
        parts = []
        for p in self.params:
            v = self.values[p.name]
            parts.append(f"{p.name}={v:g}" if isinstance(v, float) else f"{p.name}={v}")
        return f"{self.family}:{','.join(parts)}"

    def __repr__(self) -> str:
        return f"<effect {self.spec()}>"

    def __eq__(self, other) -> bool:
        return isinstance(other, Effect) and self.spec() == other.spec()

    def __hash__(self) -> int:
        return hash(self.spec())

    # Hooks; each returns nothing by default.
    def joint_errors(self, machine: Machine, q: np.ndarray, context) -> dict[str, np.ndarray]:
        """{axis: (N, 6)} additions to joint error screws (mm, rad). q: (N, 5) mm/rad."""
        return {}

    def attachment_errors(self, machine: Machine, q: np.ndarray, context) -> dict[str, np.ndarray]:
        """{attachment: (N, 6) or (6,)} error motions in the attachment frame (mm, rad)."""
        return {}

    def camera_changes(self, camera: str, machine: Machine, q: np.ndarray, context) -> dict:
        """Changes to one camera's imaging: {"focal_scale": (N,), "extra_distortion": dict}."""
        return {}


EFFECTS: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Add an effect family to the catalogue (usable as a class decorator)."""
    if not cls.family:
        raise ValueError(f"{cls.__name__} has no family name")
    EFFECTS[cls.family] = cls
    return cls


def parse_effect(spec: str, families: dict[str, type[Effect]] | None = None) -> Effect:
    """Parse ``family:key=value,...`` into an :class:`Effect`; errors name the bad part.

    families: extra families known to this parse only, beside the catalogue (e.g. the simulator's
    recorded user modules, :func:`private_families`); they win over a catalogue family of the same name."""
    family, _, rest = str(spec).strip().partition(":")
    known = {**EFFECTS, **(families or {})}
    if family not in known:
        raise ValueError(f"unknown effect family {family!r} in {spec!r}; known: {sorted(known)}")
    values = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"effect spec {spec!r}: {item!r} is not key=value")
        values[key.strip()] = value.strip()
    return known[family](**values)


def _along_axis(machine: Machine, axis: str, value: np.ndarray) -> np.ndarray:
    """(N,) scalar error along an axis -> (N, 6): translation along a linear axis' direction,
    rotation about a rotary axis' direction (mm or rad)."""
    ax = machine.axes[axis]
    d = np.asarray(ax.direction, dtype=float)
    out = np.zeros((value.shape[0], 6))
    if ax.is_rotary:
        out[:, 3:] = value[:, None] * d
    else:
        out[:, :3] = value[:, None] * d
    return out


def _axis_param(choices=AXIS_ORDER, doc="axis") -> Param:
    return Param("axis", "axis", default=None, doc=doc, choices=tuple(choices))


@register
class Scale(Effect):
    family = "scale"
    summary = "linear scale error: error along the axis proportional to its position"
    params = (
        _axis_param(),
        Param("ppm", "float", "ppm", None, "error per unit of travel, parts per million", amplitude=True),
    )

    def joint_errors(self, machine, q, context):
        a = self["axis"]
        return {a: _along_axis(machine, a, self["ppm"] * 1e-6 * q[:, AXIS_ORDER.index(a)])}


@register
class PitchCyclic(Effect):
    family = "pitch_cyclic"
    summary = "lead-screw periodic error: sinusoidal error along a linear axis"
    params = (
        _axis_param(LINEAR_AXES),
        Param("period_mm", "float", "mm", None, "period of the error along the travel"),
        Param("amplitude_um", "float", "um", None, "amplitude", amplitude=True),
        Param("phase_deg", "float", "deg", 0.0, "phase at zero position"),
    )

    def joint_errors(self, machine, q, context):
        a = self["axis"]
        pos = q[:, AXIS_ORDER.index(a)]
        v = self["amplitude_um"] * UM * np.sin(2 * np.pi * pos / self["period_mm"] + np.deg2rad(self["phase_deg"]))
        return {a: _along_axis(machine, a, v)}


@register
class Backlash(Effect):
    family = "backlash"
    summary = "reversal error: offset of ±amount/2 along the axis depending on approach direction"
    params = (
        _axis_param(),
        Param("amount_um", "float", "um", 0.0, "total reversal error of a linear axis", amplitude=True),
        Param("amount_arcsec", "float", "arcsec", 0.0, "total reversal error of a rotary axis", amplitude=True),
    )

    def joint_errors(self, machine, q, context):
        a = self["axis"]
        amount = self["amount_arcsec"] * ARCSEC if machine.axes[a].is_rotary else self["amount_um"] * UM
        return {a: _along_axis(machine, a, 0.5 * amount * context.approach[:, AXIS_ORDER.index(a)])}


@register
class ThermalDrift(Effect):
    family = "thermal_drift"
    summary = "thermal growth along a linear axis with time since start or with temperature"
    params = (
        _axis_param(LINEAR_AXES),
        Param("driver", "choice", "", "temperature", "what the growth follows", ("time", "temperature")),
        Param("um_per_k", "float", "um/K", 0.0, "growth per kelvin above reference_c (driver=temperature)",
              amplitude=True),
        Param("um_per_hour", "float", "um/h", 0.0, "growth per hour since start (driver=time)", amplitude=True),
        Param("reference_c", "float", "degC", 20.0, "temperature of zero growth"),
    )

    def joint_errors(self, machine, q, context):
        if self["driver"] == "time":
            v = self["um_per_hour"] * UM * context.time_s / 3600.0
        else:
            v = self["um_per_k"] * UM * (context.temperature_c - self["reference_c"])
        return {self["axis"]: _along_axis(machine, self["axis"], np.asarray(v, dtype=float))}


@register
class GravitySag(Effect):
    family = "gravity_sag"
    summary = "sag of the A cradle under gravity: drop along its local z growing as 1 - cos(A)"
    params = (
        Param("amplitude_um", "float", "um", None, "drop at A = 90 deg", amplitude=True),
        Param("axis", "axis", "", "A", "the tilting axis", ROTARY_AXES),
    )

    def joint_errors(self, machine, q, context):
        a = self["axis"]
        out = np.zeros((q.shape[0], 6))
        out[:, 2] = -self["amplitude_um"] * UM * (1.0 - np.cos(q[:, AXIS_ORDER.index(a)]))
        return {a: out}


class _EncoderHarmonic(Effect):
    harmonic: ClassVar[int] = 1
    params = (
        _axis_param(ROTARY_AXES),
        Param("amplitude_arcsec", "float", "arcsec", None, "amplitude of the angular error", amplitude=True),
        Param("phase_deg", "float", "deg", 0.0, "phase"),
    )

    def joint_errors(self, machine, q, context):
        a = self["axis"]
        theta = q[:, AXIS_ORDER.index(a)]
        v = self["amplitude_arcsec"] * ARCSEC * np.sin(self.harmonic * theta + np.deg2rad(self["phase_deg"]))
        return {a: _along_axis(machine, a, v)}


@register
class EncoderEccentricity(_EncoderHarmonic):
    family = "encoder_eccentricity"
    summary = "rotary encoder eccentricity: angular error at the 1st harmonic of the axis angle"
    harmonic = 1


@register
class EncoderWobble(_EncoderHarmonic):
    family = "encoder_wobble"
    summary = "rotary encoder wobble/ellipticity: angular error at the 2nd harmonic of the axis angle"
    harmonic = 2


@register
class FocalDrift(Effect):
    family = "focal_drift"
    summary = "camera focal length changing linearly with an axis position (Z by default)"
    params = (
        Param("camera", "camera", "", "camera1", "camera whose focal length drifts"),
        Param("ppm_per_mm", "float", "ppm/mm", None, "relative focal-length change per mm of travel",
              amplitude=True),
        Param("axis", "axis", "", "Z", "axis whose position drives the drift", LINEAR_AXES),
    )

    def camera_changes(self, camera, machine, q, context):
        if camera != self["camera"]:
            return {}
        return {"focal_scale": 1.0 + self["ppm_per_mm"] * 1e-6 * q[:, AXIS_ORDER.index(self["axis"])]}


@register
class LensDistortion(Effect):
    family = "lens_distortion"
    summary = "lens distortion beyond the 5-parameter model: radial r^8 and thin-prism terms"
    params = (
        Param("camera", "camera", "", "camera1", "affected camera"),
        Param("k4", "float", "", 0.0, "radial coefficient of r^8 (normalised coordinates)", amplitude=True),
        Param("s1", "float", "", 0.0, "thin prism x r^2", amplitude=True),
        Param("s2", "float", "", 0.0, "thin prism x r^4", amplitude=True),
        Param("s3", "float", "", 0.0, "thin prism y r^2", amplitude=True),
        Param("s4", "float", "", 0.0, "thin prism y r^4", amplitude=True),
    )

    def camera_changes(self, camera, machine, q, context):
        if camera != self["camera"]:
            return {}
        return {"extra_distortion": {k: self[k] for k in ("k4", "s1", "s2", "s3", "s4")}}


@register
class ToolOffset(Effect):
    family = "tool_offset"
    summary = "dispensing-tip offset from its nominal mounting, in the tip frame"
    params = (
        Param("dx_um", "float", "um", 0.0, "offset along tip x", amplitude=True),
        Param("dy_um", "float", "um", 0.0, "offset along tip y", amplitude=True),
        Param("dz_um", "float", "um", 0.0, "offset along tip z (tool axis)", amplitude=True),
    )

    def attachment_errors(self, machine, q, context):
        e = np.zeros(6)
        e[:3] = np.array([self["dx_um"], self["dy_um"], self["dz_um"]]) * UM
        return {machine.tip: e}


def camera_changes(effects, camera: str, machine: Machine, q: np.ndarray, context) -> dict:
    """Combined camera changes of several effects: focal_scale (N,) multiplied, distortion terms added."""
    focal = np.ones(q.shape[0])
    extra: dict[str, float] = {}
    for e in effects:
        ch = e.camera_changes(camera, machine, q, context)
        if "focal_scale" in ch:
            focal = focal * ch["focal_scale"]
        for k, v in ch.get("extra_distortion", {}).items():
            extra[k] = extra.get(k, 0.0) + v
    return {"focal_scale": focal, "extra_distortion": extra or None}


def catalogue_text() -> str:
    """Human-readable listing of every registered family and its parameters."""
    lines = []
    for name in sorted(EFFECTS):
        cls = EFFECTS[name]
        lines.append(f"{name}: {cls.summary}")
        for p in cls.params:
            req = "required" if p.default is None else f"default {p.default}"
            choice = f" one of {'/'.join(p.choices)}" if p.choices else ""
            unit = f" [{p.unit}]" if p.unit else ""
            lines.append(f"    {p.name}{unit}: {p.doc}{choice} ({req})")
    return "\n".join(lines)


ENTRY_POINT_GROUP = "fivecal.effects"


def load_effect_modules(modules, entry_point_group: str | None = ENTRY_POINT_GROUP) -> list[str]:
    """Import user modules so that the effect families they define register themselves with
    :func:`register`; returns the families now known. A module is a dotted path on ``sys.path``
    (e.g. ``mylab.effects``) or a ``.py`` file; installed packages may also advertise modules under the
    entry-point group ``entry_point_group`` (None: skip). One that cannot be imported raises
    ``ValueError`` naming it. See docs/user-effects.md."""
    import importlib
    import importlib.util
    import sys
    from importlib.metadata import entry_points

    for name in modules:
        name = str(name)
        try:
            if name.endswith(".py"):
                path = Path(name)
                module_name = f"fivecal_user_effects_{path.stem}"
                spec = importlib.util.spec_from_file_location(module_name, path)
                if spec is None or not path.is_file():
                    raise ImportError(f"no such file {path}")
                module = importlib.util.module_from_spec(spec)
                sys.modules[module_name] = module
                spec.loader.exec_module(module)
            else:
                importlib.import_module(name)
        except ImportError as e:
            raise ValueError(f"effect module {name!r} could not be imported: {e}") from None
    if entry_point_group:
        for ep in entry_points(group=entry_point_group):
            ep.load()
    return sorted(EFFECTS)


def recorded_effects(specs, recorded_modules, modules=None) -> list[Effect]:
    """The effects a calibration fitted, from the specs it recorded (its ``pige`` provenance's
    ``effects``): the user modules that define their families imported first, ``modules`` when given
    (``--effect-module``), else the ones the calibration recorded (``effect_modules``). ValueError
    naming the module or the spec that cannot be read, and what to pass instead."""
    modules = list(modules) if modules else [str(m) for m in recorded_modules or []]
    try:
        load_effect_modules(modules)
        return [parse_effect(s) for s in specs or []]
    except ValueError as e:
        raise ValueError(f"the calibration's effects cannot be read ({e}): pass the module that defines their "
                         f"family with --effect-module (calibrated with effect modules {list(recorded_modules or [])})"
                         ) from None


def module_source_file(module: str) -> Path:
    """The ``.py`` file of an effect module given as :func:`load_effect_modules` takes it (a ``.py``
    path or a dotted path, imported to find its file); ValueError naming it when it has none."""
    import importlib

    if str(module).endswith(".py"):
        path = Path(module)
    else:
        try:
            path = Path(getattr(importlib.import_module(str(module)), "__file__", "") or "")
        except ImportError as e:
            raise ValueError(f"effect module {module!r} could not be imported: {e}") from None
    if path.suffix != ".py" or not path.is_file():
        raise ValueError(f"effect module {module!r}: no Python source file to record ({path})")
    return path


def private_families(paths) -> dict[str, type[Effect]]:
    """The effect families that the ``.py`` files ``paths`` register, without adding them to the
    catalogue: each file is executed afresh and :data:`EFFECTS` is restored afterwards, so that
    code which lists the catalogue (the diagnosis' candidates) never sees them. For the simulator's
    side only: a campaign's truth can hold a family the analysis must not know (a hidden effect)."""
    import importlib.util

    saved = dict(EFFECTS)
    found: dict[str, type[Effect]] = {}
    try:
        for path in map(Path, paths):
            spec = importlib.util.spec_from_file_location(f"fivecal_truth_effects_{path.stem}", path)
            if spec is None or not path.is_file():
                raise ValueError(f"effect module {path}: no such file")
            spec.loader.exec_module(importlib.util.module_from_spec(spec))
            found.update({k: v for k, v in EFFECTS.items() if saved.get(k) is not v})
    finally:
        EFFECTS.clear()
        EFFECTS.update(saved)
    return found
