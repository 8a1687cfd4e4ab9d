"""``fivecal diagnose``: which effect the model lacks, ranked, tested, cross-validated and said in words.

SYNOPSIS
    >>> result = calibrate(machine, measurements)
    >>> d = diagnose(machine, measurements, result)
    >>> d.table            # the `diagnosis` table: rank, family, axis, spec, score, p_value, ...
    >>> d.sentences[0]     # 'camera1 residual along X follows the approach direction of X: ...'
    >>> d.best             # spec to pass to `fivecal calibrate --add-effect`, or None

What is compared, and why. The calibration's whitened residual r (camera 1's sweeps and five-axis
poses, eq. 20) is noise plus whatever the model lacks. Every registered effect family the model does
not hold is a candidate (:mod:`tasks.analysis.diagnosis.candidates`, periods scanned); its columns (eq. 1,
:mod:`tasks.analysis.diagnosis.linearisation`) are scored against r with the model's own columns projected
out (eq. 2, :mod:`tasks.analysis.diagnosis.score`). Candidates are ranked by ΔBIC. The leader is accepted when

- its F-test p-value, multiplied by the number of independent variants tried (candidates and
  scanned frequencies: a Bonferroni bound), is below ``alpha``;
- ΔBIC < −10;
- the cross-validated refit with it (eq. 3, :mod:`tasks.analysis.diagnosis.crossval`, in the score's metric)
  beats the one without significantly (paired test, p < ``alpha``) and by a material amount: the
  cross-validated RMS falls by at least ``min_gain`` (5 % by default). With ten thousand residuals a
  p-value alone flags any trace of structure — on an image campaign with no hidden effect the camera
  self-calibration's own bias let ``lens_distortion`` lower the whitened CV RMS by 2.0 % at p = 8e-9 —
  and a term that changes the prediction by that little is not worth a model parameter. Such
  candidates are named, with their gain, as detectable but not material;
- no other significant candidate explains the residual as well: if adding the leader to a model that
  holds candidate B does not improve the fit significantly (conditional F-test, p > ``alpha``), this
  campaign cannot tell them apart; they are reported as one group and none is accepted.

After accepting, the residual loses what the effect explains and the remaining candidates are
re-scored (periods re-scanned) against it, up to ``max_effects`` times. A candidate whose signature the
PDGE splines and the constant parameters already reproduce (visible fraction < 0.1) is reported as
absorbed; one no camera sees, as unseen; for both, and for groups, the table says which poses would
identify it (:mod:`tasks.identification.identifying_poses`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from threadpoolctl import threadpool_limits

from tasks.analysis.diagnosis.candidates import Candidate, enumerate_candidates
from tasks.analysis.diagnosis.crossval import FOLDS, cv_improvement_p, fold_rows, held_out_errors, rms
from tasks.analysis.diagnosis.linearisation import Linearisation, linearise
from tasks.analysis.diagnosis.profile_noise import gls_transform, profile_noise
from tasks.analysis.diagnosis.score import ABSORBED, Scorer
from tasks.analysis.diagnosis.verdict import explained_sentence, follows, p_text, residual_direction
from tasks.identification.identifying_poses import identifying_poses
from tasks.identification.measurements import Measurements
from tasks.identification.pige_identification import IDENTIFICATION_CAMERA, CalibrationResult
from tasks.machine.description import Machine

DIAGNOSIS_CODE_VERSION = "diagnosis-5"  # bump when diagnose() would return something else for the same inputs
ALPHA = 1e-3
MIN_GAIN = 0.05  # smallest relative fall of the cross-validated RMS that makes a candidate worth accepting
MIN_DELTA_BIC = -10.0
CONFIRM = 5  # top candidates whose cross-validated refit is computed per round (and every significant one)
COLUMNS = ("rank", "family", "axis", "spec", "score", "p_value", "delta_bic", "predicted_rms", "cv_rms",
           "explained", "step", "accepted", "significant", "group", "absorbed", "identifiable", "visible",
           "amplitudes", "sentence")


@dataclass
class Diagnosis:
    """table: the ``diagnosis`` table (one row per candidate; accepted effects first, in the order
    accepted, then the rest by ΔBIC against the final residual). sentences: the verdict.
    best: spec of the first accepted effect (fitted amplitudes), or None. accepted: specs accepted in
    order. cv_rms_before: cross-validated RMS of the model as calibrated (the score's metric). notes: families
    that could not take part."""

    table: pd.DataFrame
    sentences: list[str]
    best: str | None
    accepted: list[str] = field(default_factory=list)
    cv_rms_before: float = float("nan")
    notes: list[str] = field(default_factory=list)


@dataclass
class _Scored:
    cand: Candidate
    G: np.ndarray  # (M, k) whitened columns (eq. 1)
    stats: dict
    amplitude: np.ndarray
    visible: float
    raw_norm: float
    k: int
    cv: float = float("nan")
    cv_p: float = 1.0
    cv_gain: float = 0.0  # 1 − cv / cv of the model without it
    group: list = field(default_factory=list)

    @property
    def absorbed(self) -> bool:
        return self.raw_norm > 0.0 and self.visible < ABSORBED

    @property
    def unseen(self) -> bool:
        return self.raw_norm == 0.0

    @property
    def identifiable(self) -> bool:
        return not (self.absorbed or self.unseen or self.k < self.cand.n_columns)

    @property
    def spec(self) -> str:
        """The fitted spec (amplitudes, phase) when identifiable; the bare family variant otherwise."""
        return self.cand.fitted_effect(self.amplitude).spec() if self.identifiable else self.cand.spec()

    def statistically_significant(self, alpha: float) -> bool:
        return bool(self.stats["p_adjusted"] < alpha and self.stats["delta_bic"] < MIN_DELTA_BIC
                    and not self.absorbed and not self.unseen)

    def detectable(self, alpha: float) -> bool:
        """Significant and confirmed by the cross-validated refit, whatever its size."""
        return self.statistically_significant(alpha) and self.cv_p < alpha

    def significant(self, alpha: float, min_gain: float = MIN_GAIN) -> bool:
        """Detectable and material: the cross-validated RMS falls by at least ``min_gain``."""
        return self.detectable(alpha) and self.cv_gain >= min_gain


def _score_all(lin: Linearisation, scorer: Scorer, cands: list[Candidate]) -> list[_Scored]:
    pairs = [p for c in cands for p in c.pairs()]
    G_all, raw_all = lin.columns(pairs)
    out, start = [], 0
    for c in cands:
        k = c.n_columns
        G, raw = G_all[start:start + k].T, raw_all[start:start + k].T
        start += k
        s = scorer.score(G[None], raw[None])
        st = {key: float(v[0]) for key, v in scorer.statistics(s.delta_rss, s.k).items()}
        out.append(_Scored(c, G, st, s.amplitude[0], float(s.visible[0]), float(s.raw_norm[0]), int(s.k[0])))
    return out


def diagnose(machine: Machine, measurements: Measurements, result: CalibrationResult, candidates=None,
             max_effects: int = 3, alpha: float = ALPHA, folds: int = FOLDS, min_gain: float = MIN_GAIN) -> Diagnosis:
    """Rank the effects ``result``'s model lacks (see the module docstring).

    measurements: what ``result`` was calibrated on. candidates: family names or Effect classes to
    consider (default: every registered family). max_effects: how many to accept one after the other.
    alpha: significance level (after the Bonferroni factor). folds: of the cross-validation.
    min_gain: smallest relative fall of the cross-validated RMS for a candidate to be accepted.
    Returns a :class:`Diagnosis`. Runs with one BLAS thread: its many small products are 50× slower
    when two BLAS threads contend for busy cores."""
    with threadpool_limits(limits=1):
        return _diagnose(machine, measurements, result, candidates, max_effects, alpha, folds, min_gain)


def _diagnose(machine, measurements, result, candidates, max_effects, alpha, folds, min_gain) -> Diagnosis:
    lin = linearise(machine, measurements, result)
    scorer = Scorer(lin.residual, lin.own, gls_transform(*profile_noise(lin)))
    test_folds = fold_rows(lin, folds)
    # held-out errors in the score's metric, which weighs down the PDGE profiles' noise
    T = scorer.transform
    r_cv = T(lin.residual)
    cv_before = rms(held_out_errors(r_cv, T(lin.own), test_folds))
    camera = IDENTIFICATION_CAMERA
    accepted: list[tuple[int, _Scored]] = []
    sentences: list[str] = []
    final: list[_Scored] = []
    notes: list[str] = []
    for step in range(max_effects + 1):
        have = list(result.model.effects) + [a.cand.effect() for _, a in accepted]
        cands, notes = enumerate_candidates(machine, lin, scorer, candidates, have)
        final = _score_all(lin, scorer, cands)
        n_tests = sum(c.trials for c in cands) or 1.0
        for s in final:
            s.stats["p_adjusted"] = min(1.0, s.stats["p_value"] * n_tests)
            s.stats["trials"] = n_tests
        # identifiable candidates first: an absorbed one "explains" only by a huge amplitude on the
        # sliver of its signature that the model cannot reproduce
        final.sort(key=lambda s: (s.absorbed or s.unseen, s.stats["delta_bic"]))
        X_have = T(np.hstack([lin.own] + [a.G for _, a in accepted]))
        e_now = held_out_errors(r_cv, X_have, test_folds)
        cv_now = rms(e_now)
        for i, s in enumerate(final):
            if s.k > 0 and (i < CONFIRM or s.statistically_significant(alpha)):
                e_with = held_out_errors(r_cv, np.hstack([X_have, T(s.G)]), test_folds)
                s.cv, s.cv_p = rms(e_with), cv_improvement_p(e_now, e_with)
                s.cv_gain = 1.0 - s.cv / cv_now if cv_now > 0 else 0.0
        if step == max_effects or not final or not final[0].significant(alpha, min_gain):
            break
        lead = final[0]
        lead.group = [o for o in final[1:]
                      if o.significant(alpha, min_gain) and scorer.conditional(lead.G, o.G)[1] > alpha]
        direction = residual_direction(lin, -lead.G @ lead.amplitude)
        if lead.group:
            members = [lead, *lead.group]
            poses = "; ".join(sorted({identifying_poses(g.cand.effect()) for g in members}))
            sentences.append(f"{camera} residual {direction} is explained equally well by "
                             f"{', '.join(f'`{g.spec}`' for g in members)}: this campaign cannot tell them apart, "
                             f"so none is accepted. Poses that would: {poses}.")
            break
        sentences.append(explained_sentence(camera, direction, lead.cand, lead.spec, lead.stats["explained"],
                                            lead.stats["p_value"], lead.stats["delta_bic"], cv_now, lead.cv))
        accepted.append((step, lead))
        scorer.accept(lead.G)
    sentences += _closing_sentences(final, accepted, camera, alpha, min_gain)
    return Diagnosis(_table(accepted, final, alpha, min_gain), sentences + _identifiability_sentences(final),
                     accepted[0][1].spec if accepted else None, [a.spec for _, a in accepted], cv_before, notes)


def _closing_sentences(final: list[_Scored], accepted, camera: str, alpha: float, min_gain: float) -> list[str]:
    top = next((s for s in final if not (s.absorbed or s.unseen)), None)
    if top is not None and top.group:
        return []
    if top is None:
        return [] if accepted else ["Nothing significant: no candidate acts on this campaign's poses."]
    why = (f"`{top.spec}` ({follows(top.cand)}) would explain {100 * top.stats['explained']:.1f} % of the {camera} "
           f"residual ({p_text(top.stats['p_adjusted'])} after {top.stats['trials']:.0f} trials, "
           f"ΔBIC {top.stats['delta_bic']:+.0f})")
    if top.detectable(alpha):
        why += (f"; it is detectable, but it lowers the cross-validated RMS by only {100 * top.cv_gain:.1f} % "
                f"({top.cv:.3g} with it), below the {100 * min_gain:.0f} % worth a model parameter")
    if not accepted:
        return [f"Nothing significant: the best candidate, {why}."]
    done = ", ".join(f"`{a.spec}`" for _, a in accepted)
    return [f"After {done}, nothing else is significant: the best remaining candidate, {why}."]


def _identifiability_sentences(final: list[_Scored]) -> list[str]:
    """One sentence per family whose variants this campaign cannot see or cannot tell from the model."""
    out, seen = [], set()
    for s in final:
        if not (s.absorbed or s.unseen) or s.cand.family in seen:
            continue
        seen.add(s.cand.family)
        why = ("no camera sees it" if s.unseen else "the PDGE profiles and constant parameters already reproduce "
               f"{100 * (1 - s.visible):.0f} % of its signature")
        out.append(f"`{s.cand.spec()}` is not identifiable from this campaign's poses ({why}); "
                   f"poses that would identify it: {identifying_poses(s.cand.effect())}.")
    return out


def _amplitudes_text(s: _Scored) -> str:
    names = [f"{a} ({ph})" for a in s.cand.amplitudes for ph in ("0°", "90°")] if s.cand.phase else list(
        s.cand.amplitudes)
    return ", ".join(f"{n}={v:.4g}" for n, v in zip(names, s.amplitude, strict=False))


def _row(s: _Scored, rank: int, step: int, accepted: bool, alpha: float, min_gain: float, group: str) -> dict:
    if accepted:
        sentence = "accepted"
    elif group:
        sentence = "cannot be told apart from the others of its group by this campaign"
    elif not s.identifiable:
        sentence = f"not identifiable; poses that would identify it: {identifying_poses(s.cand.effect())}"
    else:
        sentence = ""
    return {"rank": rank, "family": s.cand.family, "axis": s.cand.axis, "spec": s.spec, "score": s.stats["score"],
            "p_value": s.stats["p_value"], "delta_bic": s.stats["delta_bic"], "predicted_rms": s.stats["predicted_rms"],
            "cv_rms": s.cv, "explained": s.stats["explained"], "step": step, "accepted": accepted,
            "significant": s.significant(alpha, min_gain), "group": group, "absorbed": s.absorbed,
            "identifiable": s.identifiable, "visible": s.visible, "amplitudes": _amplitudes_text(s),
            "sentence": sentence}


def _table(accepted, final: list[_Scored], alpha: float, min_gain: float) -> pd.DataFrame:
    rows = [_row(s, i + 1, step, True, alpha, min_gain, "") for i, (step, s) in enumerate(accepted)]
    lead = final[0] if final else None
    grouped = {id(g) for g in lead.group} | {id(lead)} if lead is not None and lead.group else set()
    step_final = len(accepted)
    for s in final:
        label = lead.spec if id(s) in grouped else ""
        rows.append(_row(s, len(rows) + 1, step_final, False, alpha, min_gain, label))
    return pd.DataFrame(rows, columns=list(COLUMNS))
