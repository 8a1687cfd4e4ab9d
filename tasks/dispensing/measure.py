"""Measuring a dispensing capture: every ring image inspected, ring and dot centres carried from
pixels onto the workpiece surface. Analysis side: no truth is read here.

Pixels to millimetres: each centre's pixel (the image's region-of-interest offset added) is
undistorted with camera 1's calibrated intrinsics (at full resolution) and its ray intersected with
the top of the ring's pad (the manifest's ``surface_z_mm``) at the camera pose the identified model
gives for the imaging command.
The dot − ring offset is a difference over a millimetre at the image centre, so neither the pose nor
the intrinsics' bias reaches it beyond a few nanometres.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from tasks.core import se3
from tasks.core.units import UM
from tasks.dispensing.inspection import InspectionConfig, inspect_ring_image
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward

REQUIRED = ("image_id", "path", "phase", "ring_id", "ring_x_mm", "ring_y_mm", "surface_z_mm", "X_mm", "Y_mm",
            "Z_mm", "A_deg", "C_deg", "image_X_mm", "image_Y_mm", "image_Z_mm", "image_A_deg", "image_C_deg")
FEATURES = ("area_px2", "perimeter_px", "diameter_px", "circularity", "nsd_r", "cov_i")


def load_capture_manifest(folder: Path) -> pd.DataFrame:
    """The capture's manifest.csv; ValueError naming the file and the missing columns. roi_x0/roi_y0
    default to 0 (full frames), binning to 1."""
    path = Path(folder) / "manifest.csv"
    df = pd.read_csv(path)
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}")
    for col, default in (("roi_x0", 0), ("roi_y0", 0), ("binning", 1)):
        if col not in df.columns:
            df[col] = default
    return df


def inspect_capture(folder: Path, manifest: pd.DataFrame, cfg: InspectionConfig) -> pd.DataFrame:
    """One row per manifest row: ring and dot centres (px, in the image), the dot's §4.3 features,
    polarity, qualified and the reason when not. An unreadable image is a row with its reason."""
    out = []
    for row in manifest.itertuples(index=False):
        rec = {"image_id": row.image_id, "ring_u_px": np.nan, "ring_v_px": np.nan, "dot_u_px": np.nan,
               "dot_v_px": np.nan, **dict.fromkeys(FEATURES, np.nan), "polarity": "", "qualified": False,
               "reason": ""}
        gray = cv2.imread(str(Path(folder) / row.path), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            rec["reason"] = f"image {row.path} missing or unreadable"
            out.append(rec)
            continue
        result = inspect_ring_image(gray, cfg)
        rec.update(polarity=result.polarity, qualified=bool(result.qualified), reason=result.reason)
        if result.ring is not None:
            rec.update(ring_u_px=result.ring.x_px, ring_v_px=result.ring.y_px)
        if result.dot is not None:
            d = result.dot
            rec.update(dot_u_px=d.x_px, dot_v_px=d.y_px, **{f: getattr(d, f) for f in FEATURES})
        out.append(rec)
    return pd.DataFrame(out)


def full_resolution(camera: CameraModel, factor: int) -> CameraModel:
    """The unbinned sensor of a camera model fitted to images binned by ``factor`` (the inverse of
    :meth:`CameraModel.scaled`)."""
    if factor == 1:
        return camera
    return replace(camera, width_px=camera.width_px * factor, height_px=camera.height_px * factor,
                   pixel_size_mm=camera.pixel_size_mm / factor, cx_px=(camera.cx_px + 0.5) * factor - 0.5,
                   cy_px=(camera.cy_px + 0.5) * factor - 0.5)


def pixels_to_surface(machine: Machine, model: ErrorModel | None, camera: CameraModel, imaging: np.ndarray,
                      uv: np.ndarray, surface_z_mm, camera_name: str = "camera1") -> np.ndarray:
    """(N, 2) points (mm, workpiece frame) of the surfaces z = ``surface_z_mm`` (scalar or (N,)) seen at
    sensor pixels ``uv`` (N, 2) from the imaging commands (N, 5); NaN where ``uv`` is NaN."""
    T = se3.inverse(forward(machine, imaging, model).relative(machine.workpiece, camera_name))  # camera in wp
    ok = np.all(np.isfinite(uv), axis=1)
    out = np.full((len(uv), 2), np.nan)
    if not ok.any():
        return out
    norm = cv2.undistortPoints(uv[ok].reshape(-1, 1, 2).astype(np.float64), camera.matrix,
                               camera.dist_coeffs).reshape(-1, 2)
    rays = np.column_stack([norm, np.ones(len(norm))])
    d = np.einsum("nij,nj->ni", T[ok, :3, :3], rays)
    o = T[ok, :3, 3]
    s = (np.broadcast_to(surface_z_mm, (len(uv),))[ok] - o[:, 2]) / d[:, 2]
    out[ok] = (o + s[:, None] * d)[:, :2]
    return out


def dispense_rows(manifest: pd.DataFrame, inspected: pd.DataFrame, machine: Machine, model: ErrorModel,
                  camera: CameraModel) -> pd.DataFrame:
    """The ``dispense_inspection`` rows of one capture (truth columns not included): commands, ring and
    dot centres in sensor pixels and on the ring's pad (the manifest's ``surface_z_mm``) (mm),
    dx_um/dy_um (dot − ring, workpiece frame),
    the dot's diameter in mm and its features. ``camera``: camera 1 at full resolution."""
    df = manifest.merge(inspected, on="image_id", how="left")
    roi = df[["roi_x0", "roi_y0"]].to_numpy(float)
    binning = df["binning"].to_numpy(float)[:, None]
    # image pixel -> sensor pixel: pixel centres of a binned image sit at (i + ½)·b − ½
    ring_px = (df[["ring_u_px", "ring_v_px"]].to_numpy(float) + 0.5) * binning - 0.5 + roi
    dot_px = (df[["dot_u_px", "dot_v_px"]].to_numpy(float) + 0.5) * binning - 0.5 + roi
    surface_z_mm = df["surface_z_mm"].to_numpy(float)
    imaging = df[["image_X_mm", "image_Y_mm", "image_Z_mm", "image_A_deg", "image_C_deg"]].to_numpy(float)
    ring_mm = pixels_to_surface(machine, model, camera, imaging, ring_px, surface_z_mm)
    dot_mm = pixels_to_surface(machine, model, camera, imaging, dot_px, surface_z_mm)
    # the local scale for the diameter: a pixel step at the dot, on the surface
    step = pixels_to_surface(machine, model, camera, imaging, dot_px + np.array([1.0, 0.0]), surface_z_mm)
    mm_per_px = np.linalg.norm(step - dot_mm, axis=1) * binning[:, 0]
    out = df.drop(columns=["ring_u_px", "ring_v_px", "dot_u_px", "dot_v_px", "path"])
    out["ring_u_px"], out["ring_v_px"] = ring_px[:, 0], ring_px[:, 1]
    out["dot_u_px"], out["dot_v_px"] = dot_px[:, 0], dot_px[:, 1]
    out["ring_meas_x_mm"], out["ring_meas_y_mm"] = ring_mm[:, 0], ring_mm[:, 1]
    out["dot_x_mm"], out["dot_y_mm"] = dot_mm[:, 0], dot_mm[:, 1]
    out["dx_um"] = (dot_mm[:, 0] - ring_mm[:, 0]) / UM
    out["dy_um"] = (dot_mm[:, 1] - ring_mm[:, 1]) / UM
    out["diameter_mm"] = out["diameter_px"] * mm_per_px
    out["qualified"] = out["qualified"].fillna(False).astype(bool)
    out["reason"] = out["reason"].fillna("not inspected")
    return out
