"""Where the model fails: pose and dot residuals with everything they could depend on (design §6).

SYNOPSIS
    >>> from tasks.analysis.residuals import pose_residual_table, dot_residual_table, binned_mean
    >>> poses = pose_residual_table(machine, result.model, measurements, dots)   # `residuals` table
    >>> dots_r = dot_residual_table(dots, measurements, cameras, plates)         # `dot_residuals` table
    >>> binned_mean(poses.time_s, poses.cam_dx_um)        # the trend of one component against time

What is compared, and why. A fitted model predicts, for every image, the pose T_cam_plate of the plate
its camera views (forward kinematics at the commanded axes and the image's context). The measured
pose comes from the image (PnP). Their difference, the residual of eq. 20, is what the model fails to
explain: measurement noise plus every effect the model lacks. An effect that the model lacks leaves
structure: the residual follows an axis position (scale, cyclic pitch error), time or temperature
(thermal growth), the direction from which an axis approached (backlash), or the position of the plate
in the image (lens distortion). So each image's residual is stored beside each of these variables, and
:func:`binned_mean` turns "residual against variable" into means with a confidence band that tells
structure from noise.

Two tables (registered in :mod:`tasks.lake.schema`, documented in docs/residuals.md):

- ``residuals``: one row per image with a machine pose (the ``camera_calibration`` views have none),
  the six components of e = log(T_model⁻¹ T_measured) (eq. 20) in the plate frame (µm, arcsec; for a
  camera outside the constant-parameter fit, against the model completed by its chain's constant
  mounts, :func:`chain_constant_part`), the same rotated into the camera frame (``cam_*``), the
  whitened components the fit minimises, and the variables: commands, time, temperature, approach
  direction per axis, camera, stage, group, repeat, mean detected dot position (u, v px).
- ``dot_residuals``: one row per detected dot of an image with a measured pose: detected centre minus
  the projection of the plate dot through the measured pose and the calibrated intrinsics (px). What
  PnP leaves: the image-space errors of the camera model (distortion it lacks, focal drift).

Why a camera-frame copy. The plate frame turns with C and A, so an error of the tool chain along the
machine's X (thermal growth, a scale error) shows in the plate frame as cos C·dx − sin C·dy: over the
five-axis poses its mean against time or X cancels. Camera 1 rides on the linear axes and never turns,
so in its frame the same error keeps one direction. ``cam_*`` = R · (v, ω) with R the rotation of the
measured T_cam_plate: the same residual at the same point (the plate origin), only its components in
camera axes (no lever arm is added).

Units: translations µm, rotations arcsec, pixels px, time s, temperature °C; commands mm / deg.
No Prefect import.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy import stats

from tasks.core import se3
from tasks.core.units import ARCSEC, UM
from tasks.identification.measurements import Measurements
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    pose_residuals,
    whitening,
)
from tasks.machine.camera_model import CameraModel, project_points
from tasks.machine.description import AXIS_ORDER, CALIBRATION_STAGE, COMMAND_COLUMNS, Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.plate import DotPlate

COMPONENTS = ("dx_um", "dy_um", "dz_um", "rx_arcsec", "ry_arcsec", "rz_arcsec")
"""The six residual components (v in µm, ω in arcsec); plate frame, ``cam_`` prefix: camera frame."""
CAMERA_COMPONENTS = tuple(f"cam_{c}" for c in COMPONENTS)
WHITE_COMPONENTS = ("white_dx", "white_dy", "white_dz", "white_rx", "white_ry", "white_rz")
APPROACH_COLUMNS = tuple(f"approach_{a}" for a in AXIS_ORDER)
TREND_VARIABLES = (*COMMAND_COLUMNS, "time_s", "temperature_c", "u_mean_px", "v_mean_px")
"""The continuous variables a residual is plotted against (command units, s, °C, px)."""
CATEGORICAL_VARIABLES = APPROACH_COLUMNS
"""Variables with a few values (approach direction −1, 0, +1): one bin per value."""
POSE_RESIDUAL_COLUMNS = ("image_id", "camera", "stage", "group", "repeat", "used_in_fit", *COMMAND_COLUMNS,
                         "time_s", "temperature_c", *APPROACH_COLUMNS, "u_mean_px", "v_mean_px", "n_dots",
                         *COMPONENTS, "position_um", "orientation_arcsec", *CAMERA_COMPONENTS, *WHITE_COMPONENTS,
                         "white_norm")
DOT_RESIDUAL_COLUMNS = ("image_id", "camera", "stage", "row", "col", "u_px", "v_px", "du_px", "dv_px")
TO_FILE_UNITS = np.array([1 / UM] * 3 + [1 / ARCSEC] * 3)  # mm, rad -> µm, arcsec


def image_positions(dots: pd.DataFrame | None) -> pd.DataFrame:
    """Per image: mean detected dot centre ``u_mean_px``, ``v_mean_px`` (px) and ``n_dots`` (finite
    centres), indexed by image_id. dots: the ``dots`` lake table (image_id, u_px, v_px); None or empty
    gives an empty frame."""
    cols = ["u_mean_px", "v_mean_px", "n_dots"]
    if dots is None or dots.empty:
        return pd.DataFrame(columns=cols, index=pd.Index([], name="image_id"))
    d = dots[["image_id", "u_px", "v_px"]].copy()
    d[["u_px", "v_px"]] = d[["u_px", "v_px"]].astype(float)
    d = d[np.isfinite(d["u_px"]) & np.isfinite(d["v_px"])]
    g = d.groupby("image_id", sort=False)
    out = g[["u_px", "v_px"]].mean().rename(columns={"u_px": "u_mean_px", "v_px": "v_mean_px"})
    out["n_dots"] = g.size()
    return out


def pose_residual_table(machine: Machine, model: ErrorModel, meas: Measurements,
                        dots: pd.DataFrame | None = None) -> pd.DataFrame:
    """The ``residuals`` table: one row per image of ``meas`` outside the ``camera_calibration`` stage.

    machine: the (nominal) machine description. model: the fitted error model. meas: the campaign's
    measurements (:func:`tasks.identification.measurements.assemble_measurements`). dots: the ``dots``
    lake table, for the plate's position in the image (NaN without it).

    Columns (:data:`POSE_RESIDUAL_COLUMNS`):
    - identification: image_id, camera, stage, group, repeat; ``used_in_fit``: the image is one of the
      poses whose whitened residual the constant-parameter fit (eq. 22) minimises (stages
      ``IDENTIFICATION_STAGES`` of ``IDENTIFICATION_CAMERA``); the others (validation poses, other
      cameras' sweeps) are held out of that fit.
    - variables: X_mm … C_deg (commanded), time_s, temperature_c, approach_X … approach_C (−1, 0, +1:
      sign of the axis' last move), u_mean_px, v_mean_px, n_dots.
    - dx_um, dy_um, dz_um, rx_arcsec, ry_arcsec, rz_arcsec: e = log(T_model⁻¹ T_measured) (eq. 20),
      v (µm) and ω (arcsec) in the plate frame; position_um = ‖v‖, orientation_arcsec = ‖ω‖. For a camera
      other than ``IDENTIFICATION_CAMERA`` no parameter of the fit reaches the constant poses of its chain
      (its mount, its plate's mount, and the gauge the fit chose for the axes it sees), so T_model is
      completed by them first: e minus :func:`chain_constant_part`, fitted to that camera's images.
    - cam_*: the same (v, ω) rotated into the camera frame (R of the measured T_cam_plate).
    - white_*: W e with W = L⁻¹, L Lᵀ = C + C_floor (the fit's whitening,
      :func:`tasks.identification.pige_identification.whitening`); dimensionless. L is lower triangular,
      so white_dx = dx/σ_dx and each later component is the standardised residual given the ones before
      it. white_norm = ‖W e‖ (the Mahalanobis distance; about √6 for a pose at the noise level).
    """
    keep = (meas.table["stage"] != CALIBRATION_STAGE).to_numpy()
    m = meas.select(keep) if not keep.all() else meas
    e = pose_residuals(machine, model, m)  # (N, 6) mm, rad, plate frame
    W = whitening(m.cov)
    cameras = m.table["camera"].to_numpy()
    for camera in np.unique(cameras[cameras != IDENTIFICATION_CAMERA]):
        rows = cameras == camera
        e[rows] -= chain_constant_part(m.T[rows], e[rows], W[rows])
    white = np.einsum("nij,nj->ni", W, e)  # (N, 6)
    R = m.T[:, :3, :3]  # (N, 3, 3) plate -> camera rotation
    e_cam = np.concatenate([np.einsum("nij,nj->ni", R, e[:, :3]), np.einsum("nij,nj->ni", R, e[:, 3:])], axis=1)
    t = m.table
    out = pd.DataFrame({c: t[c].to_numpy() for c in ("image_id", "camera", "stage", "group", "repeat")})
    out["used_in_fit"] = (t["stage"].isin(IDENTIFICATION_STAGES) & (t["camera"] == IDENTIFICATION_CAMERA)).to_numpy()
    for axis, col in zip(AXIS_ORDER, COMMAND_COLUMNS, strict=True):
        out[col] = t[axis].to_numpy(dtype=float)
    out["time_s"] = m.context.time_s.astype(float)
    out["temperature_c"] = m.context.temperature_c.astype(float)
    for i, col in enumerate(APPROACH_COLUMNS):
        out[col] = m.context.approach[:, i].astype(np.int64)
    pos = image_positions(dots).reindex(out["image_id"])
    out["u_mean_px"] = pos["u_mean_px"].to_numpy(dtype=float)
    out["v_mean_px"] = pos["v_mean_px"].to_numpy(dtype=float)
    out["n_dots"] = pos["n_dots"].fillna(0).to_numpy(dtype=np.int64)
    phys = e * TO_FILE_UNITS
    out[list(COMPONENTS)] = phys
    out["position_um"] = np.linalg.norm(phys[:, :3], axis=1)
    out["orientation_arcsec"] = np.linalg.norm(phys[:, 3:], axis=1)
    out[list(CAMERA_COMPONENTS)] = e_cam * TO_FILE_UNITS
    out[list(WHITE_COMPONENTS)] = white
    out["white_norm"] = np.linalg.norm(white, axis=1)
    return out[list(POSE_RESIDUAL_COLUMNS)]


def chain_constant_part(T_cam_plate: np.ndarray, e: np.ndarray, W: np.ndarray) -> np.ndarray:
    """The part of one camera's pose residuals that constant poses at the two ends of its chain explain.

    A constant error ξ_C of the camera's mount (camera frame) and ξ_P of its plate's mount (plate frame)
    make T_measured = exp(ξ̂_C) T_model exp(ξ̂_P), so to first order e = Ad(T_model⁻¹) ξ_C + ξ_P: a constant in
    the plate frame plus one that turns with the pose. For a camera whose images the constant-parameter
    fit does not see, these 12 numbers are unknown, and so is the gauge the fit chose for the axes it
    measures (moving an axis line moves both ends of the chain), which takes the same form.

    T_cam_plate: (n, 4, 4) the camera's measured poses (mm). e: (n, 6) their residuals (v mm, ω rad; plate
    frame). W: (n, 6, 6) whitening matrices (the fit's). Returns (n, 6): Ad(T⁻¹) ξ_C + ξ_P with (ξ_C, ξ_P)
    the whitened least-squares fit (minimum norm where the poses leave a combination undetermined, e.g.
    a turn about the one axis the chain rotates about). Same units and frame as ``e``.
    """
    design = np.concatenate([se3.adjoint(se3.inverse(T_cam_plate)), np.broadcast_to(np.eye(6), (len(e), 6, 6))],
                            axis=2)  # (n, 6, 12): (ξ_C, ξ_P) -> e
    A = np.einsum("nij,njk->nik", W, design).reshape(-1, 12)
    b = np.einsum("nij,nj->ni", W, e).reshape(-1)
    xi = np.linalg.lstsq(A, b, rcond=1e-10)[0]
    return design @ xi


def plates_of(machine: Machine, stage: str = "pige") -> dict[str, DotPlate]:
    """{camera: the plate it sees in images of ``stage``} from the machine description
    (``Machine.plate_seen``: the measured plate, or in camera_calibration its target)."""
    return {cam: machine.plates[machine.plate_seen(cam, stage)] for cam in machine.views}


def dot_residual_table(dots: pd.DataFrame, meas: Measurements, cameras: Mapping[str, CameraModel],
                       plates: Mapping[str, DotPlate]) -> pd.DataFrame:
    """The ``dot_residuals`` table: per detected dot of an image with a measured pose, the detected
    centre minus the projection of the plate dot through the measured pose and ``cameras``' intrinsics.

    dots: the ``dots`` lake table (image_id, camera, row, col, u_px, v_px). meas: supplies the measured
    T_cam_plate (mm) and the stage of each image; dots of images without a measured pose, with a
    non-finite centre or of a camera without intrinsics are left out. cameras: {camera: calibrated
    intrinsics} (e.g. :func:`tasks.vision.detector_comparison.intrinsics_from_table`). plates: {camera: the
    plate it views} (:func:`plates_of`).

    Returns :data:`DOT_RESIDUAL_COLUMNS`: image_id, camera, stage, row, col, u_px, v_px (detected, px),
    du_px, dv_px (detected − projected, px; image axes u right, v down). Vectorised over dots (one
    projection call per camera).
    """
    if dots is None or dots.empty:
        return pd.DataFrame({c: pd.Series(dtype=object if c in ("image_id", "camera", "stage") else float)
                             for c in DOT_RESIDUAL_COLUMNS})
    idx = pd.Index(meas.table["image_id"]).get_indexer(dots["image_id"])
    uv = dots[["u_px", "v_px"]].to_numpy(dtype=float)
    ok = (idx >= 0) & np.isfinite(uv).all(axis=1) & dots["camera"].isin(list(cameras)).to_numpy()
    d, idx, uv = dots[ok], idx[ok], uv[ok]
    projected = np.full_like(uv, np.nan)
    cams = d["camera"].to_numpy()
    rows, cols = d["row"].to_numpy(dtype=int), d["col"].to_numpy(dtype=int)
    for cam in np.unique(cams):
        sel = cams == cam
        plate = plates[str(cam)]
        X = plate.dot_centres_mm()[rows[sel] * plate.cols + cols[sel]]  # (M, 3) plate frame
        T = meas.T[idx[sel]]  # (M, 4, 4)
        p_cam = np.einsum("mij,mj->mi", T[:, :3, :3], X) + T[:, :3, 3]
        projected[sel] = project_points(p_cam, cameras[str(cam)])
    out = pd.DataFrame({"image_id": d["image_id"].to_numpy(), "camera": cams,
                        "stage": meas.table["stage"].to_numpy()[idx], "row": rows, "col": cols,
                        "u_px": uv[:, 0], "v_px": uv[:, 1]})
    out["du_px"], out["dv_px"] = uv[:, 0] - projected[:, 0], uv[:, 1] - projected[:, 1]
    return out[list(DOT_RESIDUAL_COLUMNS)]


# --------------------------------------------------------------------------------------------
# Binned means with a confidence band
# --------------------------------------------------------------------------------------------

BIN_COLUMNS = ("bin", "x", "x_lo", "x_hi", "n", "mean", "sem", "half_width", "lo", "hi", "excludes_zero")


def binned_mean(x, y, n_bins: int = 10, confidence: float = 0.95, simultaneous: bool = True,
                categorical: bool = False, min_count: int = 3) -> pd.DataFrame:
    """Mean of ``y`` in bins of ``x`` with a confidence band: the trend of a residual against a variable.

    x, y: (N,) arrays (non-finite pairs dropped). Bins: ``categorical`` — one per distinct x (e.g. an
    approach direction); otherwise up to ``n_bins`` bins of equal count (quantiles of x; tied values stay
    in one bin, so fewer bins may result). Bins with fewer than ``min_count`` points are dropped.

    Band: mean ± t·s/√n per bin (Student t with n − 1 degrees of freedom, s the sample standard
    deviation). With ``simultaneous`` (default) the level is Bonferroni-corrected over the K bins kept,
    t = t_{1 − (1 − confidence)/(2K), n−1}: if y has zero mean everywhere, the whole band covers zero with
    probability ≥ ``confidence``, so a bin whose band excludes zero is structure at that level for the
    panel as a whole, not one bin in twenty by chance.

    Returns one row per bin (:data:`BIN_COLUMNS`): bin (0-based), x (mean of x), x_lo, x_hi (range of x),
    n, mean, sem (s/√n), half_width, lo, hi, excludes_zero. Units: those of x and y.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    good = np.isfinite(x) & np.isfinite(y)
    x, y = x[good], y[good]
    if x.size == 0:
        return pd.DataFrame(columns=list(BIN_COLUMNS))
    if categorical:
        codes = np.unique(x, return_inverse=True)[1]
    else:
        edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, max(1, n_bins) + 1)))
        codes = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    df = pd.DataFrame({"code": codes, "x": x, "y": y})
    g = df.groupby("code")
    out = pd.DataFrame({"x": g["x"].mean(), "x_lo": g["x"].min(), "x_hi": g["x"].max(), "n": g.size(),
                        "mean": g["y"].mean(), "sd": g["y"].std(ddof=1)})
    out = out[out["n"] >= max(min_count, 2)].reset_index(drop=True)
    k = max(len(out), 1)
    alpha = (1.0 - confidence) / (k if simultaneous else 1)
    out["sem"] = out["sd"] / np.sqrt(out["n"])
    out["half_width"] = stats.t.ppf(1.0 - alpha / 2.0, out["n"] - 1) * out["sem"]
    out["lo"], out["hi"] = out["mean"] - out["half_width"], out["mean"] + out["half_width"]
    out["excludes_zero"] = (out["lo"] > 0) | (out["hi"] < 0)
    out.insert(0, "bin", np.arange(len(out)))
    out["n"] = out["n"].astype(np.int64)
    return out[list(BIN_COLUMNS)]


def trend_summary(residuals: pd.DataFrame, components: Sequence[str] = CAMERA_COMPONENTS,
                  variables: Sequence[str] = TREND_VARIABLES + CATEGORICAL_VARIABLES, n_bins: int = 10,
                  confidence: float = 0.95, centre: Sequence[str] = ()) -> pd.DataFrame:
    """For each camera × variable × component: does the residual follow the variable?

    residuals: the ``residuals`` table. centre: cameras whose residual is centred first (its mean over
    the given images subtracted per component): for a subset of a camera's images (one stage, say) whose
    mean the fit did not hold at zero. A camera outside the fit needs none: its residuals are already
    taken against its chain's constant mounts (:func:`chain_constant_part`). Variables that do not vary
    for a camera are skipped.

    Returns camera, variable, component, n_bins, max_abs_mean (largest |bin mean|, the component's unit),
    span (max − min of the bin means), significant (some bin's simultaneous ``confidence`` band excludes
    zero), chi2 (Σ (mean/sem)² over the bins) and p_value (χ² with n_bins degrees of freedom; the bins
    are independent sets of images). Sorted most significant first.
    """
    rows = []
    for camera, g in residuals.groupby("camera", sort=True):
        g = centred(g, components) if camera in set(centre) else g
        for var in variables:
            x = g[var].to_numpy(dtype=float)
            if np.unique(x[np.isfinite(x)]).size < 2:
                continue
            for comp in components:
                b = binned_mean(x, g[comp], n_bins, confidence, categorical=var in CATEGORICAL_VARIABLES)
                if b.empty:
                    continue
                chi2 = float(np.sum((b["mean"] / b["sem"]) ** 2))
                rows.append({"camera": camera, "variable": var, "component": comp, "n_bins": len(b),
                             "max_abs_mean": float(b["mean"].abs().max()),
                             "span": float(b["mean"].max() - b["mean"].min()),
                             "significant": bool(b["excludes_zero"].any()), "chi2": chi2,
                             "p_value": float(stats.chi2.sf(chi2, len(b)))})
    cols = ["camera", "variable", "component", "n_bins", "max_abs_mean", "span", "significant", "chi2", "p_value"]
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values(["significant", "p_value"], ascending=[False, True], kind="stable").reset_index(drop=True)


def centred(residuals: pd.DataFrame, components: Sequence[str]) -> pd.DataFrame:
    """``residuals`` with each of ``components`` minus its mean over the rows."""
    out = residuals.copy()
    out[list(components)] = out[list(components)] - out[list(components)].mean()
    return out


def worst_poses(residuals: pd.DataFrame, n: int = 10) -> pd.DataFrame:
    """The ``n`` rows with the largest whitened residual norm (``white_norm``), largest first."""
    return residuals.sort_values("white_norm", ascending=False, kind="stable").head(n).reset_index(drop=True)
