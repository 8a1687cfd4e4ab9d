"""``fivecal diagnose``: which effect the model lacks, ranked, tested, cross-validated and said in words.

SYNOPSIS
    >>> result = calibrate(machine, measurements)
    >>> d = diagnose(machine, measurements, result)
    >>> d.table            # the `diagnosis` table: rank, family, axis, spec, score, p_value, ...
    >>> d.sentences[0]     # 'camera1 residual along X follows the approach direction of X: ...'
    >>> d.best             # spec to pass to `fivecal calibrate --add-effect`, or None

What is compared, and why. The calibration's whitened residual r (camera 1's sweeps and five-axis
poses, eq. 20) is noise plus whatever the model lacks. Every registered effect family the model does
not hold is a candidate (:mod:`tasks.diagnosis.candidates`, periods scanned); its columns (eq. 1,
:mod:`tasks.diagnosis.linearisation`) are scored against r with the model's own columns projected
out (eq. 2, :mod:`tasks.diagnosis.score`). Candidates are ranked by ΔBIC. The leader is accepted when

- its F-test p-value, multiplied by the number of independent variants tried (candidates and
  scanned frequencies: a Bonferroni bound), is below ``alpha``;
- ΔBIC < −10;
- the cross-validated refit with it (eq. 3, :mod:`tasks.diagnosis.crossval`) beats the one without;
- no other significant candidate explains the residual as well: if adding the leader to a model that
  holds candidate B does not improve the fit significantly (conditional F-test, p > ``alpha``), this
  campaign cannot tell them apart; they are reported as one group and none is accepted.

After accepting, the residual loses what the effect explains and the remaining candidates are
re-scored (periods re-scanned) against it, up to ``max_effects`` times. A candidate whose signature the
PDGE splines and the constant parameters already reproduce (visible fraction < 0.1) is reported as
absorbed; one no camera sees, as unseen; for both, and for groups, the table says which poses would
identify it (:mod:`tasks.diagnosis.suggestions`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from threadpoolctl import threadpool_limits

from tasks.diagnosis.candidates import Candidate, enumerate_candidates
from tasks.diagnosis.crossval import FOLDS, cv_improvement_p, fold_rows, held_out_errors, rms
from tasks.diagnosis.linearisation import Linearisation, linearise
from tasks.diagnosis.profile_noise import gls_transform, profile_noise
from tasks.diagnosis.score import ABSORBED, Scorer
from tasks.diagnosis.suggestions import identifying_poses
from tasks.diagnosis.verdict import explained_sentence, follows, p_text, residual_direction
from tasks.identification.measurements import Measurements
from tasks.identification.pige_identification import IDENTIFICATION_CAMERA, CalibrationResult
from tasks.machine import Machine

ALPHA = 1e-3
MIN_DELTA_BIC = -10.0
CONFIRM = 5  # top candidates whose cross-validated refit is computed per round
COLUMNS = ("rank", "family", "axis", "spec", "score", "p_value", "delta_bic", "predicted_rms", "cv_rms",
           "explained", "step", "accepted", "significant", "group", "absorbed", "identifiable", "visible",
           "amplitudes", "sentence")


@dataclass
class Diagnosis:
    """table: the ``diagnosis`` table (one row per candidate; accepted effects first, in the order
    accepted, then the rest by ΔBIC against the final residual). sentences: the verdict.
    best: spec of the first accepted effect (fitted amplitudes), or None. accepted: specs accepted in
    order. cv_rms_before: cross-validated RMS of the model as calibrated (whitened). notes: families
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
    G: np.ndarray  # (M, k)
    stats: dict
    amplitude: np.ndarray
    visible: float
    raw_norm: float
    k: int
    cv: float = float("nan")
    cv_p: float = 1.0
    group: list = field(default_factory=list)

    @property
    def spec(self) -> str:
        return self.cand.fitted_effect(self.amplitude).spec()


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


def _status(s: _Scored) -> tuple[bool, bool]:
    """(absorbed, unseen)."""
    unseen = s.raw_norm == 0.0
    return (not unseen) and s.visible < ABSORBED, unseen


def diagnose(machine: Machine, measurements: Measurements, result: CalibrationResult, candidates=None,
             max_effects: int = 3, alpha: float = ALPHA, folds: int = FOLDS) -> Diagnosis:
    """Rank the effects ``result``'s model lacks (see the module docstring).

    measurements: what ``result`` was calibrated on. candidates: family names or Effect classes to
    consider (default: every registered family). Returns a :class:`Diagnosis`. Runs with one BLAS
    thread: its many small products are 50× slower when two BLAS threads contend for busy cores."""
    with threadpool_limits(limits=1):
        return _diagnose(machine, measurements, result, candidates, max_effects, alpha, folds)


def _diagnose(machine, measurements, result, candidates, max_effects, alpha, folds) -> Diagnosis:
    lin = linearise(machine, measurements, result)
    scorer = Scorer(lin.residual, lin.own, gls_transform(*profile_noise(lin)))
    test_folds = fold_rows(lin, folds)
    cv_before = rms(held_out_errors(lin.residual, lin.own, test_folds))
    accepted: list[_Scored] = []
    accepted_rows, sentences = [], []
    notes: list[str] = []
    camera = IDENTIFICATION_CAMERA
    final: list[_Scored] = []
    for step in range(max_effects + 1):
        have = list(result.model.effects) + [a.cand.effect() for a in accepted]
        cands, notes = enumerate_candidates(machine, lin, scorer, candidates, have)
        scored = _score_all(lin, scorer, cands)
        n_tests = sum(c.trials for c in cands) or 1.0
        for s in scored:
            s.stats["p_adjusted"] = min(1.0, s.stats["p_value"] * n_tests)
        # identifiable candidates first: an absorbed one "explains" only by a huge amplitude on the
        # sliver of its signature the model cannot reproduce
        scored.sort(key=lambda s: (any(_status(s)), s.stats["delta_bic"]))
        X_have = np.hstack([lin.own] + [a.G for a in accepted]) if accepted else lin.own
        e_now = held_out_errors(lin.residual, X_have, test_folds)
        cv_now = rms(e_now)
        for s in scored[:CONFIRM]:
            if s.stats["delta_bic"] < 0 and s.k > 0:
                e_with = held_out_errors(lin.residual, np.hstack([X_have, s.G]), test_folds)
                s.cv, s.cv_p = rms(e_with), cv_improvement_p(e_now, e_with)
        final = scored
        if step == max_effects or not scored:
            break
        lead = scored[0]
        absorbed, unseen = _status(lead)
        significant = (lead.stats["p_adjusted"] < alpha and lead.stats["delta_bic"] < MIN_DELTA_BIC
                       and lead.cv_p < alpha and not absorbed and not unseen)
        if not significant:
            break
        for other in scored[1:]:
            if other.stats["p_adjusted"] >= alpha or other.k == 0:
                continue
            _, p_lead_given_other = scorer.conditional(lead.G, other.G)
            if p_lead_given_other > alpha:
                lead.group.append(other)
        if lead.group:
            names = ", ".join(f"`{g.spec}`" for g in [lead, *lead.group])
            sentences.append(f"{camera} residual {residual_direction(lin, -lead.G @ lead.amplitude)} is explained "
                             f"equally well by {names}: this campaign cannot tell them apart, none is accepted. "
                             f"Poses that would: {'; '.join(sorted({identifying_poses(g.cand.effect()) for g in [lead, *lead.group]}))}.")
            break
        direction = residual_direction(lin, -lead.G @ lead.amplitude)
        sentences.append(explained_sentence(camera, direction, lead.cand, lead.spec, lead.stats["explained"],
                                            lead.stats["p_value"], lead.stats["delta_bic"], cv_now, lead.cv))
        accepted.append(lead)
        accepted_rows.append((step, lead))
        scorer.accept(lead.G)
    if not accepted:
        top = final[0] if final else None
        if top is None:
            sentences.append("Nothing significant: no candidate acts on this campaign's poses.")
        else:
            sig = "" if not sentences else " "
            sentences.insert(0, (f"Nothing significant{sig}: the best candidate, `{top.spec}` ({follows(top.cand)}), "
                                 f"would explain {100 * top.stats['explained']:.1f} % of the {camera} residual "
                                 f"({p_text(top.stats['p_adjusted'])} after {sum(c.cand.trials for c in final):.0f} "
                                 f"trials, ΔBIC {top.stats['delta_bic']:+.0f})."))
    elif final:
        top = final[0]
        if not (top.stats["p_adjusted"] < alpha and top.stats["delta_bic"] < MIN_DELTA_BIC):
            sentences.append(f"After {', '.join(f'`{a.spec}`' for a in accepted)}, nothing else is significant "
                             f"(best remaining: `{top.spec}`, {p_text(top.stats['p_adjusted'])} after "
                             f"{sum(c.cand.trials for c in final):.0f} trials, ΔBIC {top.stats['delta_bic']:+.0f}).")
    for s in final:
        absorbed, unseen = _status(s)
        if absorbed and s.stats["delta_bic"] > MIN_DELTA_BIC and s.cand.family:
            pass
    table = _table(accepted_rows, final, alpha)
    warned = _identifiability_sentences(final)
    return Diagnosis(table, sentences + warned, accepted[0].spec if accepted else None,
                     [a.spec for a in accepted], cv_before, notes)


def _identifiability_sentences(final: list[_Scored]) -> list[str]:
    """One sentence per family whose variants this campaign cannot see or cannot separate from the model."""
    out, seen = [], set()
    for s in final:
        absorbed, unseen = _status(s)
        if not (absorbed or unseen) or s.cand.family in seen:
            continue
        seen.add(s.cand.family)
        why = ("no camera sees it" if unseen else
               f"the PDGE profiles and constant parameters already reproduce {100 * (1 - s.visible):.0f} % of its signature")
        out.append(f"`{s.cand.spec()}` is not identifiable from this campaign's poses ({why}); "
                   f"poses that would identify it: {identifying_poses(s.cand.effect())}.")
    return out


def _row(s: _Scored, rank: int, step: int, accepted: bool, alpha: float, group: str) -> dict:
    absorbed, unseen = _status(s)
    sig = bool(s.stats["p_adjusted"] < alpha and s.stats["delta_bic"] < MIN_DELTA_BIC)
    amps = ", ".join(f"{a}={v:.4g}" for a, v in zip(
        [f"{a}@{ph}" for a in s.cand.amplitudes for ph in (("0", "90") if s.cand.phase else ("",))],
        s.amplitude, strict=False))
    return {"rank": rank, "family": s.cand.family, "axis": s.cand.axis, "spec": s.spec, "score": s.stats["score"],
            "p_value": s.stats["p_value"], "delta_bic": s.stats["delta_bic"], "predicted_rms": s.stats["predicted_rms"],
            "cv_rms": s.cv, "explained": s.stats["explained"], "step": step, "accepted": accepted, "significant": sig,
            "group": group, "absorbed": absorbed, "identifiable": not (absorbed or unseen or s.k < s.cand.n_columns),
            "visible": s.visible, "amplitudes": amps.replace("@,", ",").replace("@=", "=").replace("@", " at ")
            .replace(" at 0=", " (0°)=").replace(" at 90=", " (90°)="),
            "sentence": "" if not (absorbed or unseen) else f"not identifiable: {identifying_poses(s.cand.effect())}"}


def _table(accepted_rows, final: list[_Scored], alpha: float) -> pd.DataFrame:
    rows = []
    for step, s in accepted_rows:
        grp = ""
        rows.append(_row(s, len(rows) + 1, step, True, alpha, grp))
    step_final = len(accepted_rows)
    lead_groups = {id(g): f"with {final[0].spec}" for g in (final[0].group if final else [])}
    for s in final:
        rows.append(_row(s, len(rows) + 1, step_final, False, alpha, lead_groups.get(id(s), "")))
    return pd.DataFrame(rows, columns=list(COLUMNS))
