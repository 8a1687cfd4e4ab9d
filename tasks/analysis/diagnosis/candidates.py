"""Candidate effects: every registered family the model lacks, its parameterised variants scanned.

SYNOPSIS
    >>> cands = enumerate_candidates(machine, lin, model_effects=result.model.effects)
    >>> cands[0].spec(), cands[0].pairs()          # template spec, (one, zero) per column

A family (:data:`tasks.machine.effects.EFFECTS`, built-in or user-registered) becomes one candidate per
combination of its categorical parameters (axis over its choices, camera over the machine's
cameras, choice over its choices). Its amplitudes are the candidate's columns (with a phase, two
columns each: 0° and 90°, :mod:`tasks.identification.effect_params`). A period is not guessed: it is
scanned (:func:`scan_period`) by a generalised periodogram of the residual against the variable it
is a period of, the score of eq. (2) over a frequency grid from 1/span to the sweep's Nyquist
frequency (5 × oversampled, at most 400 frequencies), then refined by a bounded search around the
three highest peaks. The number of independent frequencies, span × bandwidth, counts as trials in
the significance test.
A candidate whose amplitudes act nowhere in this campaign (a rotary amount on a linear axis) drops
those columns; one with no acting amplitude is dropped.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from tasks.analysis.diagnosis.linearisation import Linearisation
from tasks.analysis.diagnosis.score import Scorer
from tasks.identification.effect_fit import acts
from tasks.identification.effect_params import (
    TIME_UNITS,
    amplitude_names,
    combine_quadrature,
    effect_axis,
    is_period,
    is_phase,
    phase_name,
    unit_pair,
)
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.effects import EFFECTS, Effect

GRID_OVERSAMPLING = 5
MAX_GRID = 400  # frequencies per scan (the oversampling gives way beyond it)
REFINED_PEAKS = 3


@dataclass
class Candidate:
    """One effect variant. values: every non-amplitude parameter (categoricals, scanned or default
    floats); amplitudes: the acting amplitude parameters (columns); phase: the quadrature phase
    parameter or None. scanned: {param: value} chosen by a scan; trials: how many independent
    variants the scan tried (for the multiplicity of the significance test); periodogram: (f, ΔRSS)."""

    cls: type[Effect]
    values: dict
    amplitudes: tuple[str, ...]
    phase: str | None = None
    scanned: dict = field(default_factory=dict)
    trials: float = 1.0
    period_variable: str | None = None
    periodogram: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def family(self) -> str:
        return self.cls.family

    @property
    def axis(self) -> str:
        return effect_axis(self.effect())

    def effect(self, amplitudes: dict | None = None, **overrides) -> Effect:
        vals = {**self.values, **{a: 0.0 for a in amplitude_names(self.cls)}, **(amplitudes or {}), **overrides}
        return self.cls(**vals)

    def pairs(self) -> list[tuple[Effect, Effect]]:
        """(one, zero) per column: each amplitude, at phase 0° and 90° when there is a phase."""
        base = self.effect()
        out = []
        for a in self.amplitudes:
            if self.phase is None:
                out.append(unit_pair(base, a))
            else:
                out += [unit_pair(base, a, 0.0), unit_pair(base, a, 90.0)]
        return out

    @property
    def n_columns(self) -> int:
        return len(self.amplitudes) * (2 if self.phase else 1)

    def fitted_effect(self, coef: np.ndarray) -> Effect:
        """The effect at the fitted column coefficients (amplitudes; quadrature pairs combined)."""
        amps, extra = {}, {}
        if self.phase is None:
            amps = {a: float(c) for a, c in zip(self.amplitudes, coef, strict=False)}
        else:
            for i, a in enumerate(self.amplitudes):
                amp, ph = combine_quadrature(float(coef[2 * i]), float(coef[2 * i + 1]))
                amps[a] = amp
                extra[self.phase] = ph
        return self.effect(amps, **extra)

    def key(self) -> tuple:
        """Family and categorical values: what "the model already has this effect" compares."""
        return (self.family, *(str(self.values[p.name]) for p in self.cls.params
                               if p.kind in ("axis", "camera", "choice")))

    def spec(self) -> str:
        return self.effect().spec()


def _categorical_choices(machine: Machine, p) -> list[str]:
    if p.kind == "camera":
        return list(machine.cameras)
    if p.kind == "axis":
        return list(p.choices or AXIS_ORDER)
    return list(p.choices) if p.choices else [str(p.default)]


def family_variants(machine: Machine, cls: type[Effect]) -> list[dict]:
    """Every combination of ``cls``' categorical parameters, plus its other floats at their default
    (or each value of ``cls.scan_values``); periods and phases are left to the scan (value None)."""
    axes = []
    for p in cls.params:
        if p.amplitude:
            continue
        if p.kind in ("axis", "camera", "choice"):
            axes.append([(p.name, v) for v in _categorical_choices(machine, p)])
        elif is_period(p):
            axes.append([(p.name, None)])
        elif is_phase(p):
            axes.append([(p.name, 0.0)])
        else:
            grid = getattr(cls, "scan_values", {}).get(p.name)
            if grid:
                axes.append([(p.name, float(v)) for v in grid])
            elif p.default is not None:
                axes.append([(p.name, p.default)])
            else:
                return []  # a required shape parameter with nothing to scan: cannot be a candidate
    return [dict(combo) for combo in itertools.product(*axes)]


def period_variable(cls: type[Effect], values: dict, name: str) -> tuple[str, float] | None:
    """(variable, scale) a period parameter refers to: ("time", seconds per unit) or (axis, 1) for a
    period in the axis' command unit (mm, deg)."""
    p = next(p for p in cls.params if p.name == name)
    if p.unit in TIME_UNITS:
        return "time", TIME_UNITS[p.unit]
    axis = next((str(values[q.name]) for q in cls.params if q.kind == "axis"), None)
    return (axis, 1.0) if axis is not None else None


def _variable_values(lin: Linearisation, variable: str) -> tuple[np.ndarray, float]:
    """Values of ``variable`` over the identification images and the sweeps (command units or s) and
    its finest regular step (the sweep step of an axis, the time between images)."""
    tables = [lin.ident.table] + [link.response.sweep.table for link in lin.sweeps.values()]
    if variable == "time":
        v = np.concatenate([t.time_s.to_numpy(float) for t in tables])
        steps = np.diff(np.unique(lin.measurements.table.time_s.to_numpy(float)))
    else:
        v = np.concatenate([t[variable].to_numpy(float) for t in tables])
        sweep = lin.sweeps.get(variable)
        pos = np.unique(sweep.response.sweep.table[variable].to_numpy(float)) if sweep else np.unique(v)
        steps = np.diff(pos)
    steps = steps[steps > 0]
    return v, float(np.median(steps)) if steps.size else 1.0


def scan_period(lin: Linearisation, scorer: Scorer, cand: Candidate, name: str) -> Candidate:
    """``cand`` with its period ``name`` chosen by the generalised periodogram (eq. 2 over a grid of
    frequencies, then a bounded refinement)."""
    variable, unit_scale = period_variable(cand.cls, cand.values, name)
    v, step = _variable_values(lin, variable)
    span = float(v.max() - v.min())
    if span <= 0:
        return cand
    f_lo, f_hi = 1.0 / span, 0.5 / step
    n = int(min(MAX_GRID, max(8, np.ceil(GRID_OVERSAMPLING * span * (f_hi - f_lo)))))
    freqs = np.linspace(f_lo, f_hi, n)  # cycles per command unit (or per second)

    def variant(f: float) -> Candidate:
        return Candidate(cand.cls, {**cand.values, name: 1.0 / f / unit_scale}, cand.amplitudes, cand.phase)

    def delta(fs: np.ndarray) -> np.ndarray:
        pairs = [p for f in fs for p in variant(f).pairs()]
        G, _ = lin.columns(pairs)
        k = cand.n_columns
        return scorer.score(G.reshape(len(fs), k, -1).transpose(0, 2, 1)).delta_rss

    power = delta(freqs)
    df = freqs[1] - freqs[0] if n > 1 else f_lo
    # refine the highest few local maxima (the grid may be coarser than a peak when MAX_GRID binds)
    peaks = [i for i in range(n) if power[i] >= power[max(i - 1, 0)] and power[i] >= power[min(i + 1, n - 1)]]
    f_best, p_best = float(freqs[int(np.argmax(power))]), float(power.max())
    for i in sorted(peaks, key=lambda i: -power[i])[:REFINED_PEAKS]:
        res = minimize_scalar(lambda f: -delta(np.array([f]))[0], bounds=(max(freqs[i] - df, f_lo * 0.5),
                              freqs[i] + df), method="bounded", options={"xatol": df * 1e-3})
        if -res.fun > p_best:
            f_best, p_best = float(res.x), float(-res.fun)
    out = variant(f_best)
    out.scanned = {name: 1.0 / f_best / unit_scale}
    out.trials = max(span * (f_hi - f_lo), 1.0)  # independent frequencies
    out.period_variable = variable
    out.periodogram = (freqs, power)
    return out


def enumerate_candidates(machine: Machine, lin: Linearisation, scorer: Scorer, families=None,
                         model_effects=()) -> tuple[list[Candidate], list[str]]:
    """Candidates of every family in ``families`` (names or classes; default: all registered) that the
    model lacks, periods scanned against ``scorer``'s residual. Returns (candidates, notes on families
    that could not take part)."""
    classes = [EFFECTS[f] if isinstance(f, str) else f for f in (families or list(EFFECTS.values()))]
    have = set()
    for e in model_effects:
        cls = type(e)
        have.add((cls.family, *(str(e[p.name]) for p in cls.params if p.kind in ("axis", "camera", "choice"))))
    out, notes = [], []
    probe = lin.ident
    for cls in classes:
        variants = family_variants(machine, cls)
        if not variants:
            notes.append(f"{cls.family}: a required shape parameter has no default and no scan_values; not scanned")
            continue
        for values in variants:
            try:
                template = cls(**{**values, **{a: 0.0 for a in amplitude_names(cls)},
                                  **{k: 1.0 for k, v in values.items() if v is None}})
            except ValueError as err:
                notes.append(f"{cls.family}: {err}")
                continue
            amps = tuple(a for a in amplitude_names(cls) if acts(machine, template, a, probe)
                         or any(acts(machine, template, a, link.response.sweep) for link in lin.sweeps.values()))
            if not amps:
                continue
            ph = phase_name(cls) if len(amps) == 1 else None
            cand = Candidate(cls, {k: (1.0 if v is None else v) for k, v in values.items()}, amps, ph)
            if cand.key() in have:
                continue
            for name in [k for k, v in values.items() if v is None]:
                cand = scan_period(lin, scorer, cand, name)
            out.append(cand)
    return out, notes
