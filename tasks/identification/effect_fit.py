"""Fit the parameters of the model's effects together with the constant parameters (``fivecal calibrate
--add-effect SPEC``).

SYNOPSIS
    >>> base = ErrorModel(effects=[parse_effect("backlash:axis=X,amount_um=0")])
    >>> result = calibrate(machine, measurements, base=base)       # delegates here
    >>> result.pige_table().query("kind == 'effect'")             # backlash:amount_um ± u

The PDGE profiles come from the sweeps, the effects act on the sweeps too: a profile extracted
without an effect swallows whatever of it varies smoothly along the swept axis, and the effect's
amplitude would then be fitted only to what the spline left. So the fit alternates, as the
extraction and eq. 22 are two separate estimators:

1. extract the PDGEs with the effects at their current values θ_ref in the model (the sweep poses
   corrected for the model's imaging bias, :func:`tasks.identification.imaging.imaging_corrected`);
2. fit the constant parameters and θ by LM (eq. 22) over camera 1's sweeps and five-axis poses,
   with the PDGE profiles moving with θ to first order,
   P_j(θ) = P_j(θ_ref) + Σ_p (θ_p − θ_ref,p) ∂P_j/∂θ_p,
   where ∂P_j/∂θ_p is the extraction's own linear response (:mod:`tasks.identification.pdge_response`)
   to the change θ_p makes in axis j's sweep; the LM therefore sees exactly the part of the effect
   that the extraction cannot absorb (and reports the effect unidentifiable when it absorbs all);
3. repeat from 1 with the fitted constants and θ in the extraction's model (the extraction reads
   everything but the swept axis from the model) until no parameter moves by more than 0.1 of its
   standard uncertainty (at most ``rounds`` times);
4. the joint step of :mod:`tasks.identification.joint_fit` closes the fit, as it closes
   :func:`~tasks.identification.calibration.calibrate`, the effects' parameters refined with
   the profiles and constants (unidentifiable effects reported as the coupled fit found them); the
   alternation's solution is kept beside it (``alternation``: the diagnosis is linearised about it,
   :func:`tasks.analysis.diagnosis.linearisation.alternation_of`). A fitted effect that changes a camera's
   imaging keeps the alternation's solution as the result: the joint step models the poses as
   measured, not corrected for the camera effect.

An effect with a phase (pitch_cyclic, encoder harmonics) is first fitted as two copies at phases
φ₀ and φ₀ + 90° whose amplitudes are linear (:func:`tasks.identification.effect_params.combine_quadrature`),
then with amplitude and phase as parameters.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from tasks.identification.effect_params import (
    amplitude_names,
    combine_quadrature,
    effect_axis,
    natural_step,
    param,
    phase_name,
    unit_pair,
)
from tasks.identification.identifying_poses import identifying_poses
from tasks.identification.imaging import imaging_corrected
from tasks.identification.joint_fit import joint_refine
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import ParamSpec, apply_parameters, default_parameters
from tasks.identification.pdge_extraction import TabulatedProfile, extract_pdges, measured_error_motions
from tasks.identification.pdge_response import axis_responses
from tasks.identification.pige_identification import (
    ALTERNATION_CONVERGED,
    ALTERNATION_ROUNDS,
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    JOINT_START_ROUNDS,
    CalibrationResult,
    alternate,
    identify_pige,
    synthetic_measurements,
)
from tasks.machine.description import Machine
from tasks.machine.effects import Effect, camera_changes
from tasks.machine.error_model import ErrorModel


def acts(machine: Machine, effect: Effect, name: str, meas: Measurements) -> bool:
    """Whether amplitude ``name`` of ``effect`` changes anything (joint, attachment or imaging) at ``meas``."""
    one, zero = unit_pair(effect, name)
    q = machine.commands_to_internal(meas.commands)
    ctx = meas.context
    for a, b in ((one.joint_errors(machine, q, ctx), zero.joint_errors(machine, q, ctx)),
                 (one.attachment_errors(machine, q, ctx), zero.attachment_errors(machine, q, ctx))):
        for key, v in a.items():
            if np.any(np.asarray(v) - np.asarray(b.get(key, 0.0))):
                return True
    for cam in machine.cameras:
        c1, c0 = camera_changes([one], cam, machine, q, ctx), camera_changes([zero], cam, machine, q, ctx)
        if np.any(c1["focal_scale"] != c0["focal_scale"]) or (c1["extra_distortion"] or {}) != (
                c0["extra_distortion"] or {}):
            return True
    return False


def effect_parameters(machine: Machine, effects: list[Effect], meas: Measurements,
                      fit_phase: bool = True) -> list[ParamSpec]:
    """ParamSpecs (kind "effect") of the parameters to fit: every amplitude that acts at ``meas``,
    and the phase of an effect with one acting amplitude (``fit_phase``). Names ``family:param``,
    suffixed ``#k`` when two effects of one family are fitted."""
    out = []
    for i, e in enumerate(effects):
        cls = type(e)
        names = [n for n in amplitude_names(cls) if acts(machine, e, n, meas)]
        ph = phase_name(cls)
        if fit_phase and ph is not None and len(names) == 1:
            names.append(ph)
        for n in names:
            p = param(cls, n)
            out.append(ParamSpec(f"{e.family}:{n}", "effect", effect_axis(e), i, param=n, effect_unit=p.unit,
                                 step=natural_step(p)))
    seen: dict[str, int] = {}
    for s in out:
        seen[s.name] = seen.get(s.name, 0) + 1
    if any(v > 1 for v in seen.values()):
        out = [replace(s, name=f"{s.name}#{s.component}") if seen[s.name] > 1 else s for s in out]
    return out


def _model(base: ErrorModel, effects: list[Effect], pdge: dict | None = None) -> ErrorModel:
    return ErrorModel(pige=dict(base.pige), pdge=dict(base.pdge) if pdge is None else {**base.pdge, **pdge},
                      effects=list(effects), joint_offsets=dict(base.joint_offsets),
                      attachment_offsets=dict(base.attachment_offsets), joint_slopes=dict(base.joint_slopes))


def _set(effects: list[Effect], specs: list[ParamSpec], values) -> list[Effect]:
    out = list(effects)
    for s, v in zip(specs, values, strict=True):
        out[s.component] = out[s.component].with_values(**{s.param: float(v)})
    return out


def profile_derivatives(machine: Machine, ext: ErrorModel, measurements: Measurements, specs: list[ParamSpec],
                        responses) -> list[dict[str, np.ndarray]]:
    """Per effect parameter, {axis: (K, 6)} ∂P_j/∂θ_p of the referred profile at the sweep positions
    (mm, rad per unit of the parameter): central differences of the error motions the extraction
    reads, through the extraction's linear map."""
    out = []
    for s in specs:
        h = s.jacobian_step
        sides = []
        for sign in (1.0, -1.0):
            e = ext.effects[s.component]
            moved = _model(ext, _set(ext.effects, [s], [e[s.param] + sign * h]))
            sides.append((moved, imaging_corrected(machine, moved, measurements)))
        derivs = {}
        for axis, resp in responses.items():
            e_pm = []
            for model, meas in sides:
                sweeps = meas.stage("pdge")
                e_pm.append(measured_error_motions(machine, model, sweeps.select(sweeps.table.group == axis), axis))
            derivs[axis] = resp.profile_change(((e_pm[0] - e_pm[1]) / (2 * h))[None])[0]
        out.append(derivs)
    return out


def _fit_round(machine, measurements, poses, base, effects, const_specs, x_const, fit_phase):
    """One extraction + coupled LM at the effects' current values. Returns (fit, specs, ext model).

    The extraction's profiles are made by its linear map (:meth:`AxisResponse.profile`, equal to
    ``extract_pdges``' to 1e-6 µm and a few times faster, the GCV search being in closed form)."""
    specs_e = effect_parameters(machine, effects, poses, fit_phase)
    # the extraction reads everything but the swept axis from the model: constants and effects included
    ext = apply_parameters(_model(base, effects), const_specs, x_const)
    corrected = imaging_corrected(machine, ext, measurements)
    responses = axis_responses(machine, ext, corrected)
    profiles = {axis: resp.profile() for axis, resp in responses.items()}
    derivs = profile_derivatives(machine, ext, measurements, specs_e, responses)
    theta_ref = np.array([effects[s.component][s.param] for s in specs_e])
    zeroed = _set(effects, specs_e, np.zeros(len(specs_e)))
    start = _model(base, zeroed, profiles)
    n_const = len(const_specs)

    def adjust(model: ErrorModel, x: np.ndarray) -> ErrorModel:
        d = x[n_const:] - theta_ref
        if not np.any(d):
            return model
        moved = dict(model.pdge)
        for axis in profiles:
            prof = moved[axis]
            change = sum(dk * der[axis] for dk, der in zip(d, derivs, strict=True))
            moved[axis] = TabulatedProfile(prof.positions, prof.values + change)
        return replace(model, pdge=moved)

    x0 = np.concatenate([x_const, theta_ref])
    fit = identify_pige(machine, start, poses, const_specs + specs_e, x0=x0, adjust=adjust)
    return fit, specs_e, ext


def _split_phases(effects: list[Effect], machine, poses) -> tuple[list[Effect], list[tuple[int, int, float]]]:
    """Effects with a phase and one acting amplitude -> two copies at φ₀ and φ₀ + 90°.
    Returns the new list and (index φ₀ copy, index +90° copy, φ₀) per split effect."""
    out, pairs = [], []
    for e in effects:
        ph = phase_name(type(e))
        acting = [n for n in amplitude_names(type(e)) if acts(machine, e, n, poses)]
        if ph is None or len(acting) != 1:
            out.append(e)
            continue
        phi0 = float(e[ph])
        out.append(e)
        out.append(e.with_values(**{ph: phi0 + 90.0}))
        pairs.append((len(out) - 2, len(out) - 1, phi0))
    return out, pairs


def _join_phases(split: list[Effect], pairs) -> list[Effect]:
    drop = {b for _, b, _ in pairs}
    out = []
    for i, e in enumerate(split):
        if i in drop:
            continue
        pair = next((p for p in pairs if p[0] == i), None)
        if pair is not None:
            name = [n for n in amplitude_names(type(e)) if split[i][n] != 0.0 or split[pair[1]][n] != 0.0]
            if name:
                amp, phase = combine_quadrature(split[i][name[0]], split[pair[1]][name[0]], pair[2])
                e = e.with_values(**{name[0]: amp, phase_name(type(e)): phase})
        out.append(e)
    return out


def _keep_unidentified(fit, identifiable: np.ndarray):
    """``fit`` (a PigeFit) with the parameters whose ``identifiable`` (P,) is false reported
    unidentifiable: the joint step's closing LM holds the profiles fixed and cannot see that they
    absorb an effect; the coupled fit, whose profiles move with it, can."""
    ok = fit.fit.identifiable & identifiable
    cov = fit.fit.covariance.copy()
    cov[~ok, :] = np.nan
    cov[:, ~ok] = np.nan
    return replace(fit, fit=replace(fit.fit, identifiable=ok, covariance=cov))


def _joint_truth(machine: Machine, clean: Measurements, specs: list[ParamSpec], pdge) -> object:
    """The truth's exact poses ``clean`` calibrated as calibrate() does for its truth gauge: the
    alternation's start and the joint step, with the noisy fit's smoothers (``pdge``)."""
    poses = clean.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    clean_pdge, fit, _ = alternate(machine, ErrorModel(), clean, poses, specs, rounds=JOINT_START_ROUNDS,
                                   smoothing=pdge.smoothing)
    return joint_refine(machine, ErrorModel(), clean, poses, clean_pdge, fit, penalty_of=pdge)[1]


def calibrate_with_effects(machine: Machine, measurements: Measurements, base: ErrorModel,
                           truth: ErrorModel | None = None, specs: list[ParamSpec] | None = None,
                           rounds: int = ALTERNATION_ROUNDS) -> CalibrationResult:
    """The calibration of :func:`tasks.identification.calibration.calibrate` with the parameters
    of ``base.effects`` fitted too (their values in ``base`` are the starting point), by the alternation
    and then the joint step (the alternation's solution alone when a fitted effect acts on a camera's
    imaging; it is kept in ``alternation``, which the diagnosis linearises about). The pige table
    lists them with kind "effect"; ``notes`` says which the poses cannot identify and what would.
    Runs with one BLAS thread (many small products; two contending threads are far slower)."""
    with threadpool_limits(limits=1):
        return _calibrate_with_effects(machine, measurements, base, truth, specs, rounds)


def _calibrate_with_effects(machine, measurements, base, truth, specs, rounds) -> CalibrationResult:
    const_specs = specs or default_parameters()
    poses = measurements.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    effects = list(base.effects)
    x_const = np.zeros(len(const_specs))
    n_const = len(const_specs)
    split, pairs = _split_phases(effects, machine, poses)
    if pairs:  # phases: first a linear fit of the two quadrature amplitudes
        fit, specs_e, _ = _fit_round(machine, measurements, poses, base, split, const_specs, x_const,
                                     fit_phase=False)
        x_const = fit.fit.x[:n_const]
        effects = _join_phases(_set(split, specs_e, fit.fit.x[n_const:]), pairs)
    for _ in range(max(rounds, 1)):
        fit, specs_e, ext = _fit_round(machine, measurements, poses, base, effects, const_specs, x_const,
                                       fit_phase=True)
        before = np.concatenate([x_const, [effects[s.component][s.param] for s in specs_e]])
        x_const = fit.fit.x[:n_const]
        effects = _set(effects, specs_e, fit.fit.x[n_const:])
        u = np.where(fit.fit.identifiable, fit.fit.uncertainty, np.inf)
        if np.all(np.abs(fit.fit.x - before) <= ALTERNATION_CONVERGED * u):
            break
    pdge = extract_pdges(machine, ext, imaging_corrected(machine, ext, measurements), truth)  # the table
    alternation = CalibrationResult(pdge, fit, extraction_model=ext)
    held = not fit.fit.identifiable[n_const:].any()
    # the calibration of that model ends with the joint step, as calibrate() does: without it the
    # compensated tip carries the alternation's profile errors (docs/effects.md). The joint step models
    # the poses as measured, so a fitted effect that changes a camera's imaging keeps the alternation's.
    joint = held or not any(_acts_on_cameras(e) for e in effects)
    if joint:
        skeleton = _model(base, _set(effects, specs_e, np.zeros(len(specs_e))))
        pdge, fit, _ = joint_refine(machine, skeleton, measurements, poses, pdge, fit)
        fit = _keep_unidentified(fit, alternation.pige.fit.identifiable)
    notes = []
    for i, s in enumerate(specs_e):
        if not fit.fit.identifiable[n_const + i]:
            e = fit.model.effects[s.component]
            notes.append(f"`{e.spec()}`: {s.param} is not identifiable from this campaign's poses "
                         f"(the sweeps' PDGE profiles and the constant parameters absorb it, or no camera sees it); "
                         f"poses that would identify it: {identifying_poses(e)}.")
    truth_fit = None
    if truth is not None:  # the truth in the fit's gauge: the same calibration of its exact poses
        clean = synthetic_measurements(machine, truth, measurements)
        if truth.effects:
            truth_fit = calibrate_with_effects(machine, clean, ErrorModel(effects=list(truth.effects)),
                                               specs=const_specs).pige
        elif joint:  # as calibrate() expresses the truth for a fit that ends with the joint step
            truth_fit = _joint_truth(machine, clean, const_specs, pdge)
        else:  # the alternation, as this fit's
            clean_poses = clean.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
            _, truth_fit, _ = alternate(machine, ErrorModel(), clean, clean_poses, const_specs)
    if joint:
        return CalibrationResult(pdge, fit, truth_fit, truth, extraction_model=ext, notes=notes, joint=True,
                                 alternation=alternation)
    return CalibrationResult(pdge, fit, truth_fit, truth, extraction_model=ext, notes=notes)


def _acts_on_cameras(effect: Effect) -> bool:
    return type(effect).camera_changes is not Effect.camera_changes
