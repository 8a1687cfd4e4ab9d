"""Watch the error fall: the campaign's model ladder, one row per refit (design §6, issue 5 item 4).

SYNOPSIS
    >>> from tasks.analysis.model_ladder import ladder_step, refit_cross_validated_rms, append_step
    >>> row = ladder_step(machine, result.model, result.pige.fit, measurements,
    ...                   cv_rms=refit_cross_validated_rms(machine, result.model, result.pige.specs, measurements))
    >>> ladder = append_step("c2026w02", row, provenance)     # read, append or replace, write atomically

Each time a campaign is refitted with another set of effects, one step is added to its ``model_ladder``
lake table (registered in :mod:`tasks.lake.schema`; docs/residuals.md). A step says how well that model
explains the campaign, in three ways that answer different questions:

- ``train_rms``: RMS of the whitened residuals the fit minimised (eq. 22; dimensionless). It can only
  fall as parameters are added.
- ``cv_rms``: the same RMS on five-axis poses the fit did not see (k-fold refits, :func:`refit_cross_validated_rms`).
  A parameter that fits noise makes it rise; an effect that is really there makes it fall. Both are 1
  when the model explains everything down to the measurement noise and the pose covariances are honest.
- ``validation_position_um`` / ``validation_orientation_arcsec``: on the held-out ``validation`` poses,
  the RMS difference between the dispensing tip where the measured plate pose puts it and where the
  model puts it (plate/workpiece frame, µm and arcsec) — the error a user of the compensation cares
  about. ``noise_floor_*`` is what the same RMS would be for a perfect model, from the pose covariances
  alone (:func:`tasks.analysis.verification.noise_floor`): the floor the ladder falls towards. Each pose's tilt
  noise reaches the tip with the plate-to-tip lever arm, so this floor is high (tens of µm per pose with
  tens of arcsec of tilt noise) and a model error of a few µm hardly shows above it; hence also
- ``validation_rms``: the whitened RMS of the validation poses' residuals (dimensionless, 1 at the noise
  level) — held out like ``cv_rms`` and as sensitive: each component weighed by its own noise.
- ``compensated_vbm_*`` / ``compensated_truth_*``: the tip error after compensating the validation poses
  with this step's model (mean over them, µm and arcsec), as the VBM measures it on the verification
  capture and, for a simulated campaign, as it truly is: adding the right effect must lower it, not only
  the whitened RMS.

``bic`` = M ln(RSS/M) + k ln M over the M whitened fit residuals (RSS their sum of squares, k the
identifiable parameters): the Bayesian information criterion with the noise scale estimated; lower is
better, and differences between steps of one campaign (same M) are what mean something.

No Prefect import.
"""

from __future__ import annotations

import contextlib
import fcntl
from collections.abc import Iterable, Iterator, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tasks.analysis.verification import measured_tip_poses, noise_floor
from tasks.identification.levenberg_marquardt import FitResult
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import ParamSpec
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    identify_pige,
    pose_residuals,
    synthetic_measurements,
    whitening,
)
from tasks.lake.store import read_table, results_root, write_partition
from tasks.machine.description import Machine
from tasks.machine.effects import Effect, Param, parse_effect
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import tip_pose_error

TABLE = "model_ladder"
LADDER_COLUMNS = ("step", "effects", "effect_specs", "n_params", "n_residuals", "train_rms", "cv_rms", "validation_rms",
                  "validation_position_um", "validation_orientation_arcsec", "n_validation",
                  "noise_floor_position_um", "noise_floor_orientation_arcsec", "bic",
                  "compensated_vbm_position_um", "compensated_vbm_orientation_arcsec",
                  "compensated_truth_position_um", "compensated_truth_orientation_arcsec", "created_at")
TIP_COLUMNS = {("vbm", "position_um"): "compensated_vbm_position_um",
               ("vbm", "orientation_arcsec"): "compensated_vbm_orientation_arcsec",
               ("truth", "position_um"): "compensated_truth_position_um",
               ("truth", "orientation_arcsec"): "compensated_truth_orientation_arcsec"}
"""The ladder's columns of the compensated tip error: (verification source, quantity) -> column."""
VALIDATION_STAGE = "validation"


def _as_effect(e) -> Effect:
    return e if isinstance(e, Effect) else parse_effect(e)


def _fitted(p: Param) -> bool:
    """A parameter the fit estimates (its value is a result, not part of what the effect is): an
    amplitude, or a phase in degrees (fitted with the amplitude; the roles of tasks.analysis.diagnosis)."""
    return p.amplitude or (p.kind == "float" and "phase" in p.name and p.unit == "deg")


def effect_identity(effect) -> str:
    """What an effect *is*, without what the fit estimates: its canonical spec with the amplitude and
    phase parameters left out, e.g. ``thermal_drift:axis=X,driver=time,reference_c=20``. A refit that
    changes only fitted values keeps the identity. Accepts an Effect or a spec string."""
    e = _as_effect(effect)
    fitted = {p.name for p in e.params if _fitted(p)}
    family, _, rest = e.spec().partition(":")
    kept = [kv for kv in rest.split(",") if kv and kv.partition("=")[0] not in fitted]
    return f"{family}:{','.join(kept)}" if kept else family


def effects_key(effects: Iterable) -> str:
    """The ``effects`` cell of a step, which identifies it: the :func:`effect_identity` of each effect,
    sorted and joined with '; ' — one string per set of effects, whatever their order and fitted values
    ('' for none). Accepts Effect objects or spec strings."""
    return "; ".join(sorted(effect_identity(e) for e in effects))


def effect_specs(effects: Iterable) -> str:
    """The ``effect_specs`` cell: the full canonical specs (fitted values included), in the order of
    :func:`effects_key`."""
    es = sorted((_as_effect(e) for e in effects), key=effect_identity)
    return "; ".join(e.spec() for e in es)


def _rms(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=float)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def validation_errors(machine: Machine, model: ErrorModel, meas: Measurements,
                      camera: str = IDENTIFICATION_CAMERA) -> pd.DataFrame:
    """Per held-out validation pose of ``camera``: where the measured plate pose puts the tip against
    where ``model`` puts it, and the noise floor of that comparison.

    Both tips are in the plate (workpiece) frame: measured T_cam_plate⁻¹ · T_cam_tip and predicted
    T_model⁻¹ · T_cam_tip, with T_cam_tip of ``model`` (camera and tip ride on the same link).
    Returns the columns of :func:`tasks.machine.kinematics.tip_pose_error` (µm, arcsec), noise_floor_position_um
    and noise_floor_orientation_arcsec (expected norms from the pose covariance alone) and white_sq (the
    squared norm of the whitened plate-pose residual, as the fit whitens it); empty when there are no
    validation poses.
    """
    val = meas.stage(VALIDATION_STAGE, camera=camera)
    if len(val) == 0:
        return pd.DataFrame(columns=["position_um", "orientation_arcsec", "noise_floor_position_um",
                                     "noise_floor_orientation_arcsec", "white_sq"])
    predicted = synthetic_measurements(machine, model, val).T  # (N, 4, 4) model T_cam_plate
    measured_tips = measured_tip_poses(machine, model, val.commands, val.T, camera)
    model_tips = measured_tip_poses(machine, model, val.commands, predicted, camera)
    out = tip_pose_error(measured_tips, model_tips)
    out["noise_floor_position_um"], out["noise_floor_orientation_arcsec"] = noise_floor(measured_tips, val.cov)
    white = np.einsum("nij,nj->ni", whitening(val.cov), pose_residuals(machine, model, val))  # (N, 6)
    out["white_sq"] = np.sum(white**2, axis=1)
    return out


def compensated_tip_errors(verification: pd.DataFrame) -> dict[str, float]:
    """The ladder's compensated tip error columns (:data:`TIP_COLUMNS`) from a ``verification`` table:
    the mean position (µm) and orientation (arcsec) error of its ``after`` rows, per source (vbm,
    truth); NaN for a source it lacks."""
    after = verification[verification["phase"] == "after"]
    return {col: float(after.loc[after["source"] == source, quantity].mean()) if (after["source"] == source).any()
            else float("nan") for (source, quantity), col in TIP_COLUMNS.items()}


def ladder_step(machine: Machine, model: ErrorModel, fit: FitResult, meas: Measurements, *,
                cv_rms: float = float("nan"), camera: str = IDENTIFICATION_CAMERA,
                tip: dict[str, float] | None = None) -> dict[str, Any]:
    """One row of the ladder for a fitted model (``step`` is set by :func:`append_step`).

    model: the fitted model (its ``effects`` name the step). fit: the constant-parameter fit
    (``CalibrationResult.pige.fit``): its whitened residuals give train_rms, n_residuals and bic, its
    parameters n_params. meas: the campaign's measurements (the validation poses of ``camera`` give the
    validation errors and their noise floor). cv_rms: from :func:`refit_cross_validated_rms` (NaN if not run).
    tip: the compensated tip error of this model (:func:`compensated_tip_errors`; missing columns NaN).
    """
    r = np.asarray(fit.residual, dtype=float)
    m = r.size
    k = int(np.count_nonzero(fit.identifiable))
    rss = float(r @ r)
    bic = m * np.log(rss / m) + k * np.log(m) if m and rss > 0 else float("nan")
    val = validation_errors(machine, model, meas, camera)
    return {"effects": effects_key(model.effects), "effect_specs": effect_specs(model.effects),
            "n_params": int(fit.x.size), "n_residuals": int(m),
            "train_rms": _rms(r), "cv_rms": float(cv_rms),
            "validation_rms": float(np.sqrt(val["white_sq"].mean() / 6)) if len(val) else float("nan"),
            "validation_position_um": _rms(val["position_um"]),
            "validation_orientation_arcsec": _rms(val["orientation_arcsec"]), "n_validation": len(val),
            "noise_floor_position_um": _rms(val["noise_floor_position_um"]),
            "noise_floor_orientation_arcsec": _rms(val["noise_floor_orientation_arcsec"]), "bic": float(bic),
            **{col: float((tip or {}).get(col, float("nan"))) for col in TIP_COLUMNS.values()},
            "created_at": pd.Timestamp(datetime.now(UTC))}


def refit_cross_validated_rms(machine: Machine, model: ErrorModel, specs: Sequence[ParamSpec], meas: Measurements,
                        folds: int = 5, seed: int = 0) -> float:
    """RMS of the whitened residuals of five-axis poses predicted by fits that did not see them.

    The ``pige``-stage poses of the identification camera are dealt into ``folds`` folds (a seeded
    permutation). For each fold, the parameters ``specs`` are refitted (:func:`identify_pige`, starting
    from ``model``, i.e. the fitted model plus a correction) on every identification pose outside the
    fold — the sweeps always stay in — and the fold's residuals are whitened as the fit whitens them.
    The PDGE profiles of ``model`` stay as they are: they come from the sweeps only, so no five-axis pose
    leaks into them. Returns sqrt(mean of the squared whitened residuals) over all folds
    (dimensionless; 1 at the noise level); NaN with fewer than 2 five-axis poses.
    """
    poses = meas.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    five_axis = np.flatnonzero((poses.table["stage"] == "pige").to_numpy())
    folds = min(folds, five_axis.size)
    if folds < 2:
        return float("nan")
    fold_of = np.full(len(poses), -1)
    fold_of[np.random.default_rng(seed).permutation(five_axis)] = np.arange(five_axis.size) % folds
    squares = []
    for f in range(folds):
        refit = identify_pige(machine, model, poses.select(fold_of != f), list(specs))
        test = poses.select(fold_of == f)
        e = pose_residuals(machine, refit.model, test)
        squares.append(np.einsum("nij,nj->ni", whitening(test.cov), e) ** 2)
    return float(np.sqrt(np.mean(np.concatenate(squares))))


@contextlib.contextmanager
def _ladder_lock(campaign_id: str, root: str | Path | None) -> Iterator[None]:
    """Serialise read-modify-write of one campaign's ladder (flock on ``<root>/.locks/``)."""
    folder = results_root(root) / ".locks"
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f"{TABLE}.{campaign_id}.lock", "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def read_ladder(campaign_id: str, root: str | Path | None = None) -> pd.DataFrame:
    """The campaign's ladder (:data:`LADDER_COLUMNS`, by step), empty if it has none yet."""
    df = read_table(TABLE, root, campaign_id)
    if df.empty:
        return pd.DataFrame(columns=list(LADDER_COLUMNS))
    df = df.drop(columns="campaign_id").sort_values("step", kind="stable").reset_index(drop=True)
    for col in TIP_COLUMNS.values():  # steps written before these columns existed
        if col not in df:
            df[col] = float("nan")
    return df


def add_step(ladder: pd.DataFrame, row: dict[str, Any]) -> pd.DataFrame:
    """``ladder`` with ``row`` added: a row with the same ``effects`` (the same effects, whatever their
    fitted values) is replaced in place (keeping its step number), otherwise ``row`` becomes step max + 1
    (0 for the first). Pure; see :func:`append_step`."""
    row = {c: row.get(c) for c in LADDER_COLUMNS if c != "step"}
    same = ladder["effects"].astype(str) == row["effects"] if len(ladder) else pd.Series(dtype=bool)
    if same.any():
        step = int(ladder.loc[same, "step"].iloc[0])
        ladder = ladder[~same]
    else:
        step = int(ladder["step"].max()) + 1 if len(ladder) else 0
    new = pd.DataFrame([{"step": step, **row}], columns=list(LADDER_COLUMNS))
    frames = [f for f in (ladder, new) if len(f)]
    out = pd.concat(frames, ignore_index=True) if len(frames) > 1 else new
    out["created_at"] = pd.to_datetime(out["created_at"], utc=True).astype("datetime64[us, UTC]")
    for c in ("step", "n_params", "n_residuals", "n_validation"):
        out[c] = out[c].astype(np.int64)
    for c in TIP_COLUMNS.values():
        out[c] = pd.to_numeric(out[c], errors="coerce").astype(float)
    return out.sort_values("step", kind="stable").reset_index(drop=True)[list(LADDER_COLUMNS)]


def append_step(campaign_id: str, row: dict[str, Any], provenance: dict[str, Any],
                root: str | Path | None = None) -> pd.DataFrame:
    """Add ``row`` (:func:`ladder_step`) to the campaign's ``model_ladder`` partition and write it.

    Reads the partition, replaces the step with the same effects or appends a new one
    (:func:`add_step`), and writes the whole partition with :func:`tasks.lake.store.write_partition`
    (atomic). Concurrent refits of one campaign are serialised by a lock file, so no step is lost.
    Returns the ladder as written.
    """
    with _ladder_lock(campaign_id, root):
        ladder = add_step(read_ladder(campaign_id, root), row)
        write_partition(TABLE, campaign_id, ladder, provenance, root)
    return ladder
