"""What the diagnosis and the effect fit need to know about an effect family's parameters.

Parameters of an :class:`tasks.machine.effects.Effect` family fall into four roles:

- **amplitude** (``Param.amplitude``): the effect is linear in it; fitted, one column each;
- **phase**: a float in degrees whose name contains ``phase``; the effect is taken to be
  sinusoidal in it, so two columns at phase 0° and 90° fit amplitude and phase linearly:
  a₀ sin(x) + a₉₀ sin(x + 90°) = A sin(x + φ), A = hypot(a₀, a₉₀), φ = atan2(a₉₀, a₀);
- **period**: a float whose name starts with ``period`` or ``wavelength``; scanned against the
  variable it is a period of: the family's axis position (unit mm or deg) or time (unit s, min, h);
- **categorical** (kinds axis, camera, choice): enumerated.

Any other float keeps its default, unless the family lists values to try in a class attribute
``scan_values = {"name": (v1, v2, ...)}``.
"""

from __future__ import annotations

import numpy as np

from tasks.machine.effects import Effect, Param

TIME_UNITS = {"s": 1.0, "min": 60.0, "h": 3600.0}  # seconds per unit


def is_phase(p: Param) -> bool:
    return p.kind == "float" and not p.amplitude and "phase" in p.name and p.unit == "deg"


def is_period(p: Param) -> bool:
    return p.kind == "float" and not p.amplitude and (p.name.startswith("period") or p.name.startswith("wavelength"))


def amplitude_names(cls: type[Effect]) -> list[str]:
    return [p.name for p in cls.params if p.amplitude]


def phase_name(cls: type[Effect]) -> str | None:
    names = [p.name for p in cls.params if is_phase(p)]
    return names[0] if len(names) == 1 else None


def param(cls: type[Effect], name: str) -> Param:
    return next(p for p in cls.params if p.name == name)


def natural_step(p: Param) -> float:
    """Jacobian step of a fitted parameter in its own unit: 1 unit, 1° for a phase, 1e-4 for a
    dimensionless coefficient (distortion terms act on normalised coordinates ≲ 0.25)."""
    return 1e-4 if p.unit == "" else 1.0


def with_amplitudes(effect: Effect, values: dict[str, float]) -> Effect:
    """``effect`` with every amplitude parameter set from ``values`` (missing ones: 0)."""
    return effect.with_values(**{n: float(values.get(n, 0.0)) for n in amplitude_names(type(effect))})


def unit_pair(effect: Effect, name: str, phase_deg: float | None = None) -> tuple[Effect, Effect]:
    """(effect with amplitude ``name`` = 1 and the others 0, effect with all amplitudes 0), optionally
    at ``phase_deg``: their difference is the effect per unit of ``name``."""
    base = effect
    ph = phase_name(type(effect))
    if phase_deg is not None and ph is not None:
        base = base.with_values(**{ph: float(phase_deg)})
    return with_amplitudes(base, {name: 1.0}), with_amplitudes(base, {})


def combine_quadrature(a0: float, a90: float, phase0_deg: float = 0.0) -> tuple[float, float]:
    """(A, φ) with a₀ sin(x + φ₀) + a₉₀ sin(x + φ₀ + 90°) = A sin(x + φ), φ in degrees within (−180, 180]."""
    amp = float(np.hypot(a0, a90))
    phase = (phase0_deg + np.degrees(np.arctan2(a90, a0)) + 180.0) % 360.0 - 180.0
    return amp, float(phase)


def effect_axis(effect: Effect) -> str:
    """The effect's axis (or camera) for tables: its ``axis`` value, else its camera's, else ""."""
    for p in type(effect).params:
        if p.kind == "axis":
            return str(effect[p.name])
    for p in type(effect).params:
        if p.kind == "camera":
            return str(effect[p.name])
    return ""
