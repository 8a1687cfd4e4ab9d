"""The results lake's contract: every table, its columns (dtype, unit, frame, meaning), keys and schema version.

SYNOPSIS::

    from tasks.lake.schema import TABLES, schema_version, schema_problems
    TABLES["pige"].keys                      # ('campaign_id', 'name')
    schema_version("pige")                   # 1, stamped in each file's metadata by write_partition
    schema_problems("pige", pq.read_schema(path))   # [] when the file matches the registry
    partition_problems("pige", path)                 # the same, plus its table name and schema_version

    python -m tasks.lake.schema --write docs/results-schema.md   # regenerate the doc's column tables
    python -m tasks.lake.schema --check docs/results-schema.md   # exit 1 if the doc and registry differ

Adding a table is one :class:`TableSchema` entry in ``_TABLES`` (then ``--write`` the doc). Bump a
table's ``version`` when a column is removed, renamed, retyped or changes unit, frame or meaning.

dtypes are the Arrow types in the Parquet file: ``string`` (Arrow string or large_string), ``int64``,
``float64``, ``bool``, ``timestamp[us, UTC]``. Nulls: a float column uses NaN, other columns null.
``campaign_id`` is the hive partition: it is in the folder name, not in the file.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from tasks.core.units import MAX_UNCERTAINTY

PARTITION = "campaign_id"
DTYPES = ("string", "int64", "float64", "bool", "timestamp[us, UTC]")

# frames: a column's ``frame`` is one of these keys (see docs/virtual-machine.md, docs/camera-calibration.md)
COMMAND, IMAGE, PLATE_IN_CAMERA, PLATE_BODY = "machine command", "image", "plate → camera", "plate body"
JOINT, PIGE_FRAME, WORKPIECE, TIP_ROTATION = "joint", "joint (eqs. 9–11)", "workpiece", "nominal tip"
RESIDUAL_PLATE, RESIDUAL_CAMERA, TIP_MODEL = "residual, plate", "residual, camera", "tip, measured − model"
FRAMES = {
    COMMAND: "axis coordinates as commanded: X/Y/Z in mm, A/C in degrees",
    IMAGE: "pixels: u right, v down, origin at the centre of the top-left pixel",
    PLATE_IN_CAMERA: "T_cam_plate maps plate-frame points (mm; origin at the grid centre, z out of the printed "
                     "face) into the OpenCV camera frame (+z optical axis, +x towards +u, +y down)",
    PLATE_BODY: "pose uncertainty as a body perturbation T_measured = T_true · exp(δ̂), δ = (v mm, ω rad) in "
                "the plate frame",
    JOINT: "a PDGE: the error motion of the axis in its own joint frame (local PoE, eq. 8), referred to home "
           "(zero at command 0; the axis-line trends removed, docs/calibrate.md)",
    PIGE_FRAME: "a PIGE, constant or mount: a component of a constant error screw in its joint's frame",
    WORKPIECE: "tip position error: actual minus nominal tip position, in the workpiece (plate a) frame",
    TIP_ROTATION: "tip orientation error: the rotation vector of R_nominal⁻¹ R_actual",
    RESIDUAL_PLATE: "pose residual of eq. 20, e = log(T_model⁻¹ T_measured) = (v, ω): T_measured = T_model · "
                    "exp(ê), v and ω in the plate frame (T_model: the fitted model's T_cam_plate; for a camera "
                    "outside the constant-parameter fit, completed by the constant poses of its chain's two ends, "
                    "fitted to its images: tasks/analysis/residuals.py chain_constant_part)",
    RESIDUAL_CAMERA: "the plate-frame residual (v, ω) rotated into the camera frame by the measured T_cam_plate's "
                     "rotation (same point, the plate origin; no lever arm added)",
    TIP_MODEL: "tip where the measured plate pose puts it minus where the model puts it, plate (workpiece) frame; "
               "RMS over the validation poses",
}


@dataclass(frozen=True)
class Column:
    """One column. unit: "" for identifiers, counts and dimensionless numbers. frame: "" when none
    applies. reproducible: False for wall-clock timings, which differ from run to run."""

    name: str
    dtype: str
    unit: str = ""
    frame: str = ""
    meaning: str = ""
    reproducible: bool = True

    def __post_init__(self):
        if self.dtype not in DTYPES:
            raise ValueError(f"column {self.name}: dtype {self.dtype!r} is not one of {DTYPES}")
        if self.frame and self.frame not in FRAMES:
            raise ValueError(f"column {self.name}: frame {self.frame!r} is not one of {list(FRAMES)}")


@dataclass(frozen=True)
class TableSchema:
    """A lake table: ``<root>/<name>/campaign_id=<id>/part-0.parquet``, one row per ``row``.
    keys: the columns that identify a row (campaign_id first). writer: the code that writes it."""

    name: str
    version: int
    row: str
    writer: str
    keys: tuple[str, ...]
    columns: tuple[Column, ...]

    def __post_init__(self):
        names = [c.name for c in self.columns]
        if len(set(names)) != len(names):
            raise ValueError(f"table {self.name}: duplicate column names")
        if missing := [k for k in self.keys if k != PARTITION and k not in names]:
            raise ValueError(f"table {self.name}: keys {missing} are not columns")

    @property
    def column_names(self) -> list[str]:
        return [c.name for c in self.columns]

    def column(self, name: str) -> Column:
        """The column ``name`` (KeyError naming the table if there is none)."""
        for c in self.columns:
            if c.name == name:
                return c
        raise KeyError(f"table {self.name} has no column {name!r}")


def _c(name, dtype, unit="", frame="", meaning="", reproducible=True) -> Column:
    return Column(name, dtype, unit, frame, meaning, reproducible)


def _s(name, meaning) -> Column:
    return Column(name, "string", meaning=meaning)


def _i(name, meaning, unit="") -> Column:
    return Column(name, "int64", unit, meaning=meaning)


_AXES = (("X", "mm", "um"), ("Y", "mm", "um"), ("Z", "mm", "um"), ("A", "deg", "arcsec"), ("C", "deg", "arcsec"))
_PDGE_COMPONENTS = (("dx_um", "um", "δx"), ("dy_um", "um", "δy"), ("dz_um", "um", "δz"),
                    ("ex_arcsec", "arcsec", "εx"), ("ey_arcsec", "arcsec", "εy"), ("ez_arcsec", "arcsec", "εz"))
_TIP = (("dx_um", "um", WORKPIECE, "x component of the tip position error"),
        ("dy_um", "um", WORKPIECE, "y component of the tip position error"),
        ("dz_um", "um", WORKPIECE, "z component of the tip position error"),
        ("rx_arcsec", "arcsec", TIP_ROTATION, "x component of the tip orientation error"),
        ("ry_arcsec", "arcsec", TIP_ROTATION, "y component of the tip orientation error"),
        ("rz_arcsec", "arcsec", TIP_ROTATION, "z component of the tip orientation error"))
_STATUS = _s("status", "'ok', or why the row has no result (see the message)")
_MESSAGE = _s("message", "what went wrong, naming the file; empty when ok")


def _tip_norms(prefix: str, position: str, orientation: str, tool_direction: str) -> tuple:
    """The three verification columns ``<prefix>_position_um``, ``_orientation_arcsec`` and
    ``_tool_direction_arcsec`` with their meanings."""
    return (_c(f"{prefix}_position_um", "float64", "um", WORKPIECE, position),
            _c(f"{prefix}_orientation_arcsec", "float64", "arcsec", TIP_ROTATION, orientation),
            _c(f"{prefix}_tool_direction_arcsec", "float64", "arcsec", WORKPIECE, tool_direction))


def _pdge_columns() -> tuple[Column, ...]:
    cols = []
    for name, unit, sym in _PDGE_COMPONENTS:
        cols += [_c(name, "float64", unit, JOINT, f"{sym} of the error motion, mean over the repeats"),
                 _c(f"std_{name}", "float64", unit, JOINT, f"standard error of {name}"),
                 _c(f"fit_{name}", "float64", unit, JOINT, f"{sym} of the smoothing-spline model"),
                 _c(f"truth_{name}", "float64", unit, JOINT, f"simulator's true {sym} in the same gauge (NaN "
                    "unless simulated)")]
    return tuple(cols)


def _pose_columns() -> tuple[Column, ...]:
    T = [_c(f"T{i}{j}", "float64", "mm" if j == 3 else "", PLATE_IN_CAMERA,
            f"T_cam_plate row {i}, column {j} ({'translation' if j == 3 else 'rotation'})")
         for i in range(3) for j in range(4)]
    std = [_c(f"std_{n}", "float64", u, PLATE_BODY, f"standard deviation of {s}")
           for n, u, s in (("vx_mm", "mm", "v_x"), ("vy_mm", "mm", "v_y"), ("vz_mm", "mm", "v_z"),
                           ("wx_arcsec", "arcsec", "ω_x"), ("wy_arcsec", "arcsec", "ω_y"),
                           ("wz_arcsec", "arcsec", "ω_z"))]
    unit = ("mm", "mm", "mm", "rad", "rad", "rad")
    cov = [_c(f"cov{i}{j}", "float64", f"{unit[i]}²" if unit[i] == unit[j] else f"{unit[i]}·{unit[j]}", PLATE_BODY,
              f"covariance of δ = (v, ω), element ({i}, {j})") for i in range(6) for j in range(6)]
    return (_s("image_id", "image"), _s("camera", "camera name in campaign.json"), _STATUS, _MESSAGE,
            _c("n_points", "int64", meaning="dot centres used by PnP (null without a pose)"),
            *T, _c("rms_px", "float64", "px", IMAGE, "PnP reprojection RMS"),
            _c("sigma_px", "float64", "px", IMAGE, "pixel noise σ estimated from the residuals"), *std, *cov)


def _compensation_columns() -> tuple[Column, ...]:
    cols = [_s("image_id", "validation image whose commanded pose is compensated")]
    for axis, unit, corr_unit in _AXES:
        cols += [_c(axis, "float64", unit, COMMAND, f"nominal {axis} command"),
                 _c(f"{axis}_compensated", "float64", unit, COMMAND, f"{axis} command after compensation (IK "
                    "of the identified model)"),
                 _c(f"{axis}_correction_{corr_unit}", "float64", corr_unit, COMMAND,
                    f"{axis}_compensated − {axis}")]
    cols.append(_s("orientation_objective", "what A and C were chosen for: 'full' (the whole tip rotation) | "
                   "'tool-axis' (the tool direction exactly) | 'full (…)' where tool-axis was asked for and "
                   "failed, with the reason (docs/calibrate.md, step 6)"))
    return tuple(cols)


_CAMERA_INTRINSICS = (("fx_px", "px", "focal length along u"), ("fy_px", "px", "focal length along v"),
                      ("cx_px", "px", "principal point u"), ("cy_px", "px", "principal point v"),
                      ("k1", "", "radial distortion k1"), ("k2", "", "radial distortion k2"),
                      ("p1", "", "tangential distortion p1"), ("p2", "", "tangential distortion p2"),
                      ("k3", "", "radial distortion k3"))

def _dispense_columns() -> tuple[Column, ...]:
    surface = "on the top of the ring's pad (workpiece frame, z = surface_z_mm)"
    cols = [_s("image_id", "the ring's image in the capture folder"),
            _s("phase", "nominal | compensated | check (compensated with the tip offset folded in)"),
            _s("ring_id", "ring target, row by row over the workpiece"),
            _c("ring_x_mm", "float64", "mm", WORKPIECE, "the ring's printed centre, x"),
            _c("ring_y_mm", "float64", "mm", WORKPIECE, "the ring's printed centre, y"),
            _c("surface_z_mm", "float64", "mm", WORKPIECE, "height of the top of the ring's pad above plate a")]
    for axis, unit, _ in _AXES:
        cols.append(_c(f"{axis}_{'deg' if unit == 'deg' else 'mm'}", "float64", unit, COMMAND,
                       f"{axis} command the dot was dispensed at"))
    for axis, unit, _ in _AXES:
        cols.append(_c(f"image_{axis}_{'deg' if unit == 'deg' else 'mm'}", "float64", unit, COMMAND,
                       f"{axis} command camera 1 imaged the ring at"))
    cols += [_c("ring_u_px", "float64", "px", IMAGE, "ring centre, sensor pixels (NaN: no ring)"),
             _c("ring_v_px", "float64", "px", IMAGE, "ring centre, sensor pixels"),
             _c("dot_u_px", "float64", "px", IMAGE, "dot centre, sensor pixels (NaN: no dot)"),
             _c("dot_v_px", "float64", "px", IMAGE, "dot centre, sensor pixels"),
             _c("ring_meas_x_mm", "float64", "mm", WORKPIECE, f"measured ring centre {surface}, x"),
             _c("ring_meas_y_mm", "float64", "mm", WORKPIECE, f"measured ring centre {surface}, y"),
             _c("dot_x_mm", "float64", "mm", WORKPIECE, f"measured dot centre {surface}, x"),
             _c("dot_y_mm", "float64", "mm", WORKPIECE, f"measured dot centre {surface}, y"),
             _c("dx_um", "float64", "um", WORKPIECE, "δx = dot − ring centre (§5.3)"),
             _c("dy_um", "float64", "um", WORKPIECE, "δy = dot − ring centre (§5.3)"),
             _c("area_px2", "float64", "px²", IMAGE, "A: area inside the sub-pixel outline (§4.3)"),
             _c("perimeter_px", "float64", "px", IMAGE, "P: length of the sub-pixel outline"),
             _c("diameter_px", "float64", "px", IMAGE, "d = √(4A/π)"),
             _c("diameter_mm", "float64", "mm", WORKPIECE, "d on the surface"),
             _c("circularity", "float64", meaning="C = 4πA/P²"),
             _c("nsd_r", "float64", meaning="NSD_r = σ_r/μ_r of the outline's radii from its centroid"),
             _c("cov_i", "float64", meaning="CoV_I = σ_I/μ_I of the grey levels inside the outline"),
             _s("polarity", "bright | dark (§4.3's automatic polarity); empty without a ring"),
             _c("qualified", "bool", meaning="A, C, NSD_r, CoV_I within the thresholds, one dot, not at the border"),
             _s("reason", "why not qualified (no ring, no dot, N dots in the ring, touches the border, the "
                          "features that fail, image missing); empty when qualified"),
             _c("truth_dx_um", "float64", "um", WORKPIECE, "simulator: true δx (where the tip was); NaN for a lab"),
             _c("truth_dy_um", "float64", "um", WORKPIECE, "simulator: true δy; NaN for a lab"),
             _c("truth_diameter_mm", "float64", "mm", WORKPIECE, "simulator: true equivalent diameter"),
             _s("truth_defect", "simulator: none | satellite | void | smear | missing; null for a lab")]
    return tuple(cols)


def _residual_columns() -> tuple[Column, ...]:
    comps = (("dx", "um", "v_x"), ("dy", "um", "v_y"), ("dz", "um", "v_z"), ("rx", "arcsec", "ω_x"),
             ("ry", "arcsec", "ω_y"), ("rz", "arcsec", "ω_z"))
    plate = [_c(f"{n}_{u}", "float64", u, RESIDUAL_PLATE, f"{s} of the pose residual") for n, u, s in comps]
    camera = [_c(f"cam_{n}_{u}", "float64", u, RESIDUAL_CAMERA, f"{s} of the pose residual, camera axes")
              for n, u, s in comps]
    white = [_c(f"white_{n}", "float64", "", RESIDUAL_PLATE, f"{s} whitened as the fit whitens it: (W e), W = L⁻¹, "
                "L Lᵀ = pose covariance + floor (L lower triangular: white_dx = dx/σ_dx, later components "
                "conditional on the earlier ones)") for n, _, s in comps]
    return (
        _s("image_id", "image"), _s("camera", "camera name"), _s("stage", "pdge | pige | validation"),
        _s("group", "swept axis, ... (as in the manifest)"), _i("repeat", "repeat index"),
        _c("used_in_fit", "bool", meaning="the pose is one the constant-parameter fit (eq. 22) minimises "
           "(identification stages of the identification camera); false: held out of that fit"),
        *(_c(f"{a}_{u}", "float64", u, COMMAND, f"commanded {a}") for a, u, _ in _AXES),
        _c("time_s", "float64", "s", meaning="time since the campaign's first image"),
        _c("temperature_c", "float64", "°C", meaning="temperature at capture (20 if the manifest has none)"),
        *(_i(f"approach_{a}", f"direction of {a}'s last move before the image: −1, +1, 0 (never moved)")
          for a, _, _ in _AXES),
        _c("u_mean_px", "float64", "px", IMAGE, "mean detected dot centre u: where the plate is in the image "
           "(NaN without dots)"),
        _c("v_mean_px", "float64", "px", IMAGE, "mean detected dot centre v"),
        _i("n_dots", "finite detected dot centres of the image"),
        *plate,
        _c("position_um", "float64", "um", RESIDUAL_PLATE, "‖v‖"),
        _c("orientation_arcsec", "float64", "arcsec", RESIDUAL_PLATE, "‖ω‖"),
        *camera, *white,
        _c("white_norm", "float64", "", RESIDUAL_PLATE, "‖W e‖, the Mahalanobis norm of the residual (≈ √6 at "
           "the noise level)"))


def _job_area_columns() -> tuple[Column, ...]:
    mapped = "machine X/Y command (mm) in phase planar, else the workpiece frame"
    return (_s("tray_id", "the tray image's id (its file name without suffix)"),
            _s("phase", "compensated | nominal (no compensation) | planar (the paper's Table 2 map)"),
            _s("board_id", "board, numbered in the order the location found them (b00, b01, ...)"),
            _c("ok", "bool", meaning="the board was found with exactly one accepted dispensing area"),
            _s("reason", "why the board was rejected (broken edge, no dispensing area, ...); empty when ok"),
            _c("u_px", "float64", "px", IMAGE, "area centre (refined rectangle), sensor pixels"),
            _c("v_px", "float64", "px", IMAGE, "area centre, sensor pixels"),
            _c("angle_px_deg", "float64", "deg", IMAGE, "long axis, counter-clockwise with v up, [0, 180)"),
            _c("length_px", "float64", "px", IMAGE, "rectangle's long side"),
            _c("width_px", "float64", "px", IMAGE, "rectangle's short side"),
            _i("area_px", "the blob's pixel count (the paper's area, §2.4.2)", "px"),
            _c("x_mm", "float64", "mm", WORKPIECE, f"area centre, {mapped}"),
            _c("y_mm", "float64", "mm", WORKPIECE, f"area centre, {mapped}"),
            _c("angle_deg", "float64", "deg", WORKPIECE, "long axis, counter-clockwise about z, [0, 180)"),
            _c("true_x_mm", "float64", "mm", WORKPIECE, "simulated trays: the true area centre (else NaN)"),
            _c("true_y_mm", "float64", "mm", WORKPIECE, "simulated trays: the true area centre"),
            _c("true_angle_deg", "float64", "deg", WORKPIECE, "simulated trays: the true long axis, [0, 180)"),
            _c("map_error_um", "float64", "um", WORKPIECE,
               "simulated trays: |where the needle is sent − the true centre| (planar: through the true machine)"),
            _s("true_defect", "simulated trays: the matched true board's defect: none | broken_edge | "
                              "missing_component, or unmatched (no true board within 3 mm); null for a real tray"),
            _c("recognised", "bool", meaning="simulated trays: handled as its truth asks (intact: accepted; "
                                             "defective: rejected for its defect; a row 'missed-…', reason "
                                             "'not found', per true board not found); null for a real tray"))


def _job_path_columns() -> tuple[Column, ...]:
    return (_s("tray_id", "the tray image's id"), _s("phase", "as in dispense_areas"),
            _s("method", "optimal | annealing (the paper's SA) | nearest | return_to_origin (the traditional path)"),
            _i("points", "boards in the tour"),
            _c("length_mm", "float64", "mm", COMMAND, "closed tour from home over the area centres (X/Y)"),
            _c("lower_bound_mm", "float64", "mm", COMMAND, "a lower bound of the shortest tour"),
            _c("proven_optimal", "bool", meaning="the tour is proven shortest"),
            _c("plan_s", "float64", "s", meaning="planning time", reproducible=False),
            _c("travel_s", "float64", "s", meaning="travel time of the program with this order (per-axis speed, "
                                                   "acceleration)"),
            _c("dispense_s", "float64", "s", meaning="time with the glue on"),
            _c("chosen", "bool", meaning="the order the program uses"))


def _job_bead_columns() -> tuple[Column, ...]:
    return (_s("tray_id", "the tray image's id"), _s("phase", "as in dispense_areas"), _s("board_id", "board"),
            _c("found", "bool", meaning="a bead was found within 3 mm of the area's measured centre"),
            _c("bead_x_mm", "float64", "mm", WORKPIECE, "measured bead centre"),
            _c("bead_y_mm", "float64", "mm", WORKPIECE, "measured bead centre"),
            _c("bead_length_mm", "float64", "mm", WORKPIECE, "measured bead length"),
            _c("bead_width_mm", "float64", "mm", WORKPIECE, "measured bead width"),
            _c("offset_along_mm", "float64", "mm", WORKPIECE, "measured bead − area centre, along the area's axis"),
            _c("offset_across_mm", "float64", "mm", WORKPIECE, "measured bead − area centre, across it"),
            _c("within_tolerance", "bool", meaning="both measured offsets within ±0.5 mm (§4.6)"),
            _c("true_offset_along_mm", "float64", "mm", WORKPIECE, "true bead − true area centre, along"),
            _c("true_offset_across_mm", "float64", "mm", WORKPIECE, "true bead − true area centre, across"),
            _c("true_bead_length_mm", "float64", "mm", WORKPIECE, "true bead length"),
            _c("true_bead_width_mm", "float64", "mm", WORKPIECE, "true bead width"),
            _c("true_within_tolerance", "bool", meaning="both true offsets within ±0.5 mm"))


_TABLES = (
    TableSchema("images", 1, "manifest row", "tasks/steps/ingest.py (fivecal ingest)", (PARTITION, "manifest_row"), (
        _i("manifest_row", "1-based data row of manifest.csv"),
        _s("image_id", "as in the manifest"),
        _s("path", "image file relative to the campaign folder"),
        _s("camera", "camera name"), _s("stage", "camera_calibration | pdge | pige | validation"),
        _s("group", "calibration trial, swept axis, ... (as in the manifest)"),
        _i("repeat", "repeat index (null if invalid)"),
        *(_c(f"{a}_{u}", "float64", u, COMMAND, f"commanded {a} (NaN if invalid)") for a, u, _ in _AXES),
        _c("timestamp", "timestamp[us, UTC]", "UTC", meaning="capture time (null if invalid)"),
        _c("temperature_c", "float64", "°C", meaning="temperature at capture (NaN if absent)"),
        _s("content_sha256", "sha256 (hex) of the file bytes; null if the file was not read"),
        _i("width_px", "decoded image width (null if not decoded)", "px"),
        _i("height_px", "decoded image height (null if not decoded)", "px"),
        _s("status", "'ok' or a fault code (docs/ingest.md)"),
        _s("message", "the faults found, naming manifest row and file; empty when ok"))),
    TableSchema("dots", 1, "detected dot", "tasks/steps/vision.py (fivecal measure)",
                (PARTITION, "image_id", "row", "col"), (
        _s("image_id", "image"), _s("camera", "camera name"),
        _i("row", "dot row on the plate (0 = first row of the plate frame)"),
        _i("col", "dot column on the plate"),
        _c("u_px", "float64", "px", IMAGE, "dot centre, u"), _c("v_px", "float64", "px", IMAGE, "dot centre, v"),
        _c("residual_rms_px", "float64", "px", IMAGE, "RMS residual of the dot's edge fit"),
        _c("support_ratio", "float64", meaning="fraction of the dot's edge supporting the fit (0–1)"),
        _s("detector", "rrht | blob | hough"))),
    TableSchema("camera_calibration", 1, "self-calibration trial per camera, plus a 'joint' row per camera",
                "tasks/steps/vision.py (fivecal measure)", (PARTITION, "camera", "trial"), (
        _s("camera", "camera name"),
        _s("trial", "trial name, or 'joint': the best estimate, fitted on every calibration view and the camera's "
                    "views of its measured plate in the linear axes' sweeps and the five-axis poses"),
        _STATUS, _MESSAGE,
        _i("n_images", "views used"), _i("n_points", "dot centres used"),
        _c("rms_px", "float64", "px", IMAGE, "OpenCV reprojection RMS sqrt(Σ|r|²/N) (Table 3)"),
        _c("sigma_px", "float64", "px", IMAGE, "sqrt(Σ|r|²/(2N − p))"),
        *(_c(n, "float64", u, IMAGE if u else "", m) for n, u, m in _CAMERA_INTRINSICS),
        *(_c(f"std_{n}", "float64", u, IMAGE if u else "", f"OpenCV standard deviation of {n}")
          for n, u, _ in _CAMERA_INTRINSICS))),
    TableSchema("poses", 1, "image", "tasks/steps/vision.py (fivecal measure)", (PARTITION, "image_id"),
                _pose_columns()),
    TableSchema("detector_comparison", 1, "detector × camera, plus camera 'all' per detector (Table 4)",
                "tasks/vision/detector_comparison.py (fivecal compare-detectors)", (PARTITION, "detector", "camera"), (
        _s("detector", "rrht | blob | hough"), _s("camera", "camera name, or 'all' (pooled)"),
        _i("n_images", "images sampled"), _i("n_in_view", "of them, whole plate in view (truth; null without)"),
        _i("n_found", "whole grid found"),
        _c("detection_rate_pct", "float64", "%", meaning="100·n_found/n_images"),
        _c("detection_rate_in_view_pct", "float64", "%", meaning="the same over the in-view images"),
        _i("n_relabelled", "found grids labelled as a symmetric relabelling of the truth"),
        _c("runtime_mean_ms", "float64", "ms", meaning="wall time of detection per image, mean", reproducible=False),
        _c("runtime_median_ms", "float64", "ms", meaning="wall time of detection per image, median",
           reproducible=False),
        _i("n_dots", "dot centres scored"),
        _c("centre_rms_px", "float64", "px", IMAGE, "RMS distance of found to true centres"),
        _c("centre_max_px", "float64", "px", IMAGE, "max distance of found to true centres"),
        _i("n_poses", "PnP poses obtained"),
        _c("reproj_rms_px", "float64", "px", IMAGE, "PnP reprojection RMS with the calibrated intrinsics"),
        _c("trans_err_mean_um", "float64", "um", PLATE_IN_CAMERA, "mean ‖t_est − t_true‖ of T_cam_plate"),
        _c("trans_err_max_um", "float64", "um", PLATE_IN_CAMERA, "max ‖t_est − t_true‖"),
        _c("rot_err_mean_arcsec", "float64", "arcsec", PLATE_IN_CAMERA, "mean angle of R_estᵀ R_true"),
        _c("rot_err_max_arcsec", "float64", "arcsec", PLATE_IN_CAMERA, "max angle of R_estᵀ R_true"),
        _c("trans_err_truecam_mean_um", "float64", "um", PLATE_IN_CAMERA, "trans_err_mean_um with true intrinsics"),
        _c("rot_err_truecam_mean_arcsec", "float64", "arcsec", PLATE_IN_CAMERA,
           "rot_err_mean_arcsec with true intrinsics"),
        _s("intrinsics_source", "where the intrinsics came from"))),
    TableSchema("pdge", 1, "axis × sweep position", "flows/calibrate.py (fivecal calibrate)",
                (PARTITION, "axis", "position"), (
        _s("axis", "X | Y | Z | A | C"),
        _c("position", "float64", "mm or deg (position_unit)", COMMAND, "commanded position of the swept axis"),
        _s("position_unit", "mm (linear axis) or deg (rotary axis)"),
        _i("n_images", "sweep images averaged at this position"),
        *_pdge_columns(),
        _c("translation_um", "float64", "um", JOINT, "‖(dx, dy, dz)‖ of the measured mean"),
        _c("rotation_arcsec", "float64", "arcsec", JOINT, "‖(ex, ey, ez)‖ of the measured mean"))),
    TableSchema("pige", 2, "identified parameter", "flows/calibrate.py (fivecal calibrate)", (PARTITION, "name"), (
        _s("name", "parameter, e.g. delta_AZ (PIGE), C.dz0 (constant), Y.dx_slope (squareness), camera1.ex (mount)"),
        _s("kind", "pige | constant | squareness | mount"),
        _s("joint", "axis (X, Y, Z, A, C) or attachment (camera1) the parameter belongs to"),
        _s("unit", "um or arcsec: the unit of value, uncertainty, truth, truth_nominal"),
        _c("value", "float64", "unit column", PIGE_FRAME, "estimate (NaN if unidentifiable)"),
        _c("uncertainty", "float64", "unit column", PIGE_FRAME,
           "standard uncertainty (k = 1): √(camera² + noise²) when propagated, else the fit's"),
        _c("uncertainty_fit", "float64", "unit column", PIGE_FRAME,
           "the LM's σ²(JᵀJ)⁻¹ alone: pose noise of the five-axis fit, PDGE profiles and intrinsics exact"),
        _c("uncertainty_noise", "float64", "unit column", PIGE_FRAME,
           "pose noise through PDGE extraction and fit (bootstrap, draws of C + C_floor scaled by "
           "√max(σ², 1), the smoothers' roughness chosen again per draw; NaN when not propagated)"),
        _c("uncertainty_camera", "float64", "unit column", PIGE_FRAME,
           "from the cameras' self-calibrated intrinsics (NaN when not propagated)"),
        _c("identifiable", "bool", meaning="the poses determine it (SVD, docs/calibrate.md)"),
        _s("note", "why not identifiable; for an added effect's amplitude, how many standard uncertainties "
           "it lies from zero; a propagated uncertainty beyond the SVD's limit of identification "
           f"({MAX_UNCERTAINTY:g} µm, arcsec or steps of an effect's parameter); empty otherwise"),
        _c("truth", "float64", "unit column", PIGE_FRAME,
           "simulator's truth in the identification's gauge (NaN unless simulated)"),
        _c("truth_nominal", "float64", "unit column", PIGE_FRAME,
           "simulator's raw PIGE (NaN unless simulated, or not a PIGE)"))),
    TableSchema("compensation", 2, "validation pose", "flows/calibrate.py (fivecal calibrate)",
                (PARTITION, "image_id"), _compensation_columns()),
    TableSchema("verification", 5, "validation pose × phase × source", "flows/calibrate.py (fivecal calibrate)",
                (PARTITION, "phase", "source", "image_id"), (
        _s("image_id", "validation image"),
        _i("pose", "0-based index of the pose within its (phase, source) rows"),
        _s("phase", "before | after (compensation) | after_tip (compensation with the dispensing test's tip "
                    "offset, flows/dispense.py)"),
        _s("source", "vbm (as the vision system measures it) | truth (simulator)"),
        _c("position_um", "float64", "um", WORKPIECE, "‖tip position error‖"),
        _c("orientation_arcsec", "float64", "arcsec", TIP_ROTATION, "‖tip orientation error‖"),
        _c("tool_direction_arcsec", "float64", "arcsec", WORKPIECE,
           "angle between the reached and the desired tool axis: the part of the orientation error five "
           "axes can remove"),
        *(_c(n, "float64", u, f, m) for n, u, f, m in _TIP),
        _i("repeats", "images averaged into the vbm row's measured pose (the after rows: the verification "
           "capture's repeats per pose; null for truth)"),
        *_tip_norms("noise_floor",
                    "expected position error norm from measurement noise alone, for the repeats' mean (vbm "
                    "rows; NaN for truth)",
                    "expected orientation error norm from measurement noise alone (vbm rows; NaN for truth)",
                    "expected tool-direction error from measurement noise alone (vbm rows; NaN for truth)"),
        *_tip_norms("model_uncertainty",
                    "expected tip position error norm at this phase's commands from the identified model's "
                    "uncertainty alone (NaN when not propagated); after_tip: with the constant tool-frame part "
                    "replaced by what the dispensing test's tip fit leaves (tasks/dispensing/tip_uncertainty.py)",
                    "the same for the orientation", "the same for the tool direction"),
        *_tip_norms("model_predicted",
                    "tip position error norm the identified model predicts at this phase's commands (after a "
                    "full compensation ≈ 0)",
                    "the same for the orientation (after a full compensation: the rotation A and C cannot turn)",
                    "the same for the tool direction"))),
    TableSchema("formulations", 1, "kinematic formulation (Table 5)", "flows/calibrate.py (fivecal calibrate)",
                (PARTITION, "formulation"), (
        _s("formulation", "local PoE (ours) | Denavit–Hartenberg | global PoE"),
        _c("mean_single_run_ms", "float64", "ms", meaning="one pose per call, per pose", reproducible=False),
        _c("total_300_ms", "float64", "ms", meaning="one batched call for all the poses", reproducible=False),
        _c("position_error_norm_um", "float64", "um", WORKPIECE, "mean ‖t_f − t_true‖ against the local PoE"),
        _c("orientation_error_norm_arcsec", "float64", "arcsec", WORKPIECE,
           "mean ‖log(R_f⁻¹ R_true)‖ against the local PoE"),
        _s("note", "what the formulation leaves out"))),
    TableSchema("residuals", 2, "image with a machine pose (camera_calibration views excluded)",
                "tasks/analysis/residuals.py pose_residual_table (fivecal calibrate)", (PARTITION, "image_id"),
                _residual_columns()),
    TableSchema("dot_residuals", 1, "detected dot of an image with a measured pose",
                "tasks/analysis/residuals.py dot_residual_table (fivecal calibrate)",
                (PARTITION, "image_id", "row", "col"), (
        _s("image_id", "image"), _s("camera", "camera name"),
        _s("stage", "camera_calibration | pdge | pige | validation"),
        _i("row", "dot row on the plate"), _i("col", "dot column on the plate"),
        _c("u_px", "float64", "px", IMAGE, "detected dot centre, u"),
        _c("v_px", "float64", "px", IMAGE, "detected dot centre, v"),
        _c("du_px", "float64", "px", IMAGE, "detected − projected u (plate dot through the measured pose and the "
           "calibrated intrinsics)"),
        _c("dv_px", "float64", "px", IMAGE, "detected − projected v"))),
    TableSchema("residual_trends", 1, "camera × variable × component of the residual trend figures: does the pose "
                "residual follow the variable?", "tasks/analysis/residual_trends.py trend_tests (fivecal calibrate)",
                (PARTITION, "camera", "variable", "component"), (
        _s("camera", "camera whose images are binned"),
        _s("variable", "the residuals table's variable the images are binned by (X_mm … C_deg, time_s, "
           "temperature_c, u_mean_px, v_mean_px, approach_X … approach_C)"),
        _s("component", "the residuals table's camera-frame component tested (cam_dx_um … cam_rz_arcsec)"),
        _i("bins", "bins holding at least 3 images (equal-count bins; one per value for an approach direction)"),
        _c("span", "float64", "um or arcsec", RESIDUAL_CAMERA, "max − min of the bin means (the component's unit)"),
        _c("statistic", "float64", meaning="Welch's F of the bin means' differences from their common mean, with "
           "the covariance of the bin means: the scatter within each bin plus what the images share through the "
           "identified model's uncertainty (its propagated re-fits)"),
        _c("p_value", "float64", meaning="F tail probability (bins − 1 and Welch's degrees of freedom)"),
        _c("significant", "bool", meaning="p_value below the test's level (5 %): about one panel in twenty on a "
           "campaign that lacks no effect"))),
    TableSchema("model_ladder", 1, "refit of the campaign with a set of effects (a step)",
                "tasks/analysis/model_ladder.py append_step (fivecal calibrate)", (PARTITION, "step"), (
        _i("step", "0 for the first model fitted, then 1, 2, ...; a refit with the same effects replaces its step"),
        _s("effects", "the model's effects without their fitted values (amplitudes, phases): what identifies the "
           "step; canonical specs sorted and joined with '; ' (empty: none)"),
        _s("effect_specs", "the same effects with their fitted values (full canonical specs), same order"),
        _i("n_params", "parameters of the constant-parameter fit"),
        _i("n_residuals", "whitened residuals of that fit (6 per pose)"),
        _c("train_rms", "float64", meaning="RMS of the fit's whitened residuals (1 at the noise level)"),
        _c("cv_rms", "float64", meaning="RMS of whitened residuals of five-axis poses predicted by k-fold refits "
           "that did not see them (1 at the noise level; NaN if not run)"),
        _c("validation_rms", "float64", meaning="RMS of the whitened residuals of the validation poses (held out of "
           "every fit; 1 at the noise level)"),
        _c("validation_position_um", "float64", "um", TIP_MODEL, "RMS tip position discrepancy"),
        _c("validation_orientation_arcsec", "float64", "arcsec", TIP_MODEL, "RMS tip orientation discrepancy"),
        _i("n_validation", "validation poses"),
        _c("noise_floor_position_um", "float64", "um", TIP_MODEL, "validation_position_um of a perfect model: RMS "
           "expected norm from the pose covariances"),
        _c("noise_floor_orientation_arcsec", "float64", "arcsec", TIP_MODEL, "the same for the orientation"),
        _c("bic", "float64", meaning="M ln(RSS/M) + k ln M over the M whitened fit residuals, k identifiable "
           "parameters (lower is better; compare steps of one campaign)"),
        _c("compensated_vbm_position_um", "float64", "um", WORKPIECE, "mean tip position error of the validation "
           "poses compensated with this step's model, as the VBM measures it on the verification capture "
           "(verification phase after, source vbm; NaN: no capture yet)"),
        _c("compensated_vbm_orientation_arcsec", "float64", "arcsec", WORKPIECE, "the same for the orientation"),
        _c("compensated_truth_position_um", "float64", "um", WORKPIECE, "the same, true (simulated campaigns: each "
           "capture image in its context; NaN for a lab's campaign)"),
        _c("compensated_truth_orientation_arcsec", "float64", "arcsec", WORKPIECE, "the same for the orientation"),
        _c("created_at", "timestamp[us, UTC]", "UTC", meaning="when the step was computed", reproducible=False))),
    TableSchema("diagnosis", 2, "candidate effect the model lacks, scored against the fit's residual",
                "tasks/analysis/diagnosis/diagnose.py (fivecal calibrate / fivecal diagnose)", (PARTITION, "rank"), (
        _i("rank", "1 = first accepted effect or, with none accepted, the strongest candidate"),
        _s("family", "effect family (tasks/machine/effects.py or a user module)"),
        _s("axis", "axis (or camera) the candidate acts on; empty when the family has none"),
        _s("spec", "canonical spec with the scanned period/harmonic/driver and fitted amplitudes"),
        _c("score", "float64", meaning="score statistic: residual sum of squares the candidate removes, with the "
           "model's own columns projected out (whitened units)"),
        _c("p_value", "float64", meaning="F-test p-value (before the Bonferroni factor over the variants tried)"),
        _c("delta_bic", "float64", meaning="BIC with the candidate minus BIC without (negative: better)"),
        _c("predicted_rms", "float64", meaning="whitened residual RMS predicted after adding it (1 = noise level)"),
        _c("cv_rms", "float64", meaning="cross-validated RMS with it, in the score's metric "
           "(docs/diagnosis.md §6; NaN: not cross-validated)"),
        _c("explained", "float64", meaning="fraction of the residual sum of squares it explains, in the metric that "
           "carries the PDGE profiles' uncertainty (0..1)"),
        _i("step", "acceptance round the row was scored in"),
        _c("accepted", "bool", meaning="accepted (significant, ΔBIC < −10, confirmed by cross-validation)"),
        _c("significant", "bool", meaning="p below alpha after the Bonferroni factor, ΔBIC < −10, identifiable, "
           "confirmed by the cross-validated refit, and material: the cross-validated RMS falls by at least "
           "5 % (MIN_GAIN)"),
        _s("group", "name of the group of candidates this campaign cannot tell apart (empty: none)"),
        _c("absorbed", "bool", meaning="the PDGE splines and constant parameters already reproduce it"),
        _c("identifiable", "bool", meaning="the campaign's poses identify it"),
        _c("visible", "float64", meaning="fraction of its signature left after projecting out the model's columns"),
        _s("amplitudes", "fitted amplitudes with their units"),
        _s("sentence", "what the row means, in words"))),
    TableSchema("drift", 1, "quantity × campaign, against the reference campaign",
                "tasks/steps/recalibration.py (fivecal recalibrate / serve-recalibration)", (PARTITION, "quantity"), (
        _c("time", "timestamp[us, UTC]", "UTC", meaning="the campaign's first image timestamp"),
        _s("quantity", "PIGE name, or '<axis>.<component>.<mean|std|max>' of a PDGE"),
        _s("kind", "the pige table's kind (pige, constant, mount, effect) or 'pdge'"),
        _s("table", "'pige' or 'pdge'"),
        _c("value", "float64", meaning="in `unit`; NaN when unidentifiable"),
        _c("uncertainty", "float64", meaning="standard uncertainty (k = 1), in `unit`"),
        _s("unit", "'um' or 'arcsec' (an effect parameter: its own unit)"),
        _s("reference_campaign_id", "the campaign drift is measured from"),
        _c("delta_from_reference", "float64", meaning="value − reference value, in `unit`"),
        _c("combined_uncertainty", "float64", meaning="sqrt(u² + u_ref²), in `unit`"),
        _c("z", "float64", meaning="|Δ| / combined_uncertainty"),
        _c("flagged", "bool", meaning="moved past tolerance (docs/recalibration.md)"),
        _s("rule", "abs+sig | abs | sig | within [(u unknown)/(no tolerance)] | reference | unavailable"))),
    TableSchema("dispense_inspection", 1, "ring × phase of the dispensing test",
                "flows/dispense.py (fivecal dispense-test)", (PARTITION, "phase", "ring_id"), _dispense_columns()),
    TableSchema("dispense_areas", 1, "board × phase of a dispensing job's trays (partition: the calibration's "
                "campaign)", "flows/dispense_job.py (fivecal dispense-job)",
                (PARTITION, "tray_id", "phase", "board_id"), _job_area_columns()),
    TableSchema("dispense_paths", 1, "tour method × phase of a dispensing job's trays",
                "flows/dispense_job.py (fivecal dispense-job)", (PARTITION, "tray_id", "phase", "method"),
                _job_path_columns()),
    TableSchema("dispense_beads", 1, "bead × phase of a dispensing job's simulated trays",
                "flows/dispense_job.py (fivecal dispense-job)", (PARTITION, "tray_id", "phase", "board_id"),
                _job_bead_columns()),
)
TABLES: dict[str, TableSchema] = {t.name: t for t in _TABLES}


def schema_for(table: str) -> TableSchema | None:
    """The registry entry of ``table``, or None for a table the registry does not know."""
    return TABLES.get(table)


def schema_version(table: str) -> int | None:
    """The schema version stamped into ``table``'s files (None: not in the registry)."""
    t = TABLES.get(table)
    return None if t is None else t.version


def arrow_dtype(t: pa.DataType) -> str:
    """The registry's name of an Arrow type (:data:`DTYPES`), else Arrow's own name."""
    if pa.types.is_string(t) or pa.types.is_large_string(t):
        return "string"
    if pa.types.is_int64(t):
        return "int64"
    if pa.types.is_float64(t):
        return "float64"
    if pa.types.is_boolean(t):
        return "bool"
    if pa.types.is_timestamp(t) and t.unit == "us" and t.tz in ("UTC", "+00:00"):
        return "timestamp[us, UTC]"
    return str(t)


def schema_problems(table: str, schema: pa.Schema) -> list[str]:
    """What differs between a file's Arrow ``schema`` and the registry (names, order aside, and dtypes)."""
    t = TABLES.get(table)
    if t is None:
        return [f"table {table!r} is not in the registry (tasks/lake/schema.py)"]
    got = {f.name: arrow_dtype(f.type) for f in schema}
    problems = [f"{table}: column {c.name} ({c.dtype}) missing from the file" for c in t.columns if c.name not in got]
    problems += [f"{table}: column {n} ({d}) is not in the registry" for n, d in got.items()
                 if n not in t.column_names]
    problems += [f"{table}: column {c.name} is {got[c.name]} in the file, {c.dtype} in the registry"
                 for c in t.columns if c.name in got and got[c.name] != c.dtype]
    return problems


def partition_problems(table: str, path: str | Path) -> list[str]:
    """What is wrong with the partition file ``path`` of ``table`` against the contract: its
    columns and dtypes (:func:`schema_problems`) and its ``fivecal`` metadata (table name and
    schema version). [] when it conforms. For a table's own schema test::

        assert partition_problems("drift", partition_path("drift", campaign_id, root) / "part-0.parquet") == []
    """
    import json

    import pyarrow.parquet as pq

    schema = pq.read_schema(path)
    problems = schema_problems(table, schema)
    meta = json.loads((schema.metadata or {}).get(b"fivecal", b"{}"))
    if meta.get("table") != table:
        problems.append(f"{path}: metadata table is {meta.get('table')!r}, not {table!r}")
    if meta.get("schema_version") != schema_version(table):
        problems.append(f"{path}: schema_version {meta.get('schema_version')!r} in the file, "
                        f"{schema_version(table)!r} in the registry")
    return problems


def conform(table: str, df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with the lossless casts that make its Arrow types the registry's: an int64 column
    that arrives as float (NaN for missing) becomes nullable Int64, a string column that is all
    null becomes str. Other columns, and tables not in the registry, are left as they are.
    Raises ValueError naming the table and column when an int64 column holds a non-integer."""
    t = TABLES.get(table)
    if t is None:
        return df
    casts = {}
    for c in t.columns:
        if c.name not in df.columns:
            continue
        s = df[c.name]
        if c.dtype == "int64" and pd.api.types.is_float_dtype(s.dtype):
            v = s.to_numpy(dtype=float, na_value=np.nan)
            bad = ~np.isnan(v) & (v != np.round(v))
            if bad.any():
                raise ValueError(f"{table}.{c.name}: non-integer value {float(v[bad][0])!r} in row "
                                 f"{int(np.flatnonzero(bad)[0])} of an int64 column")
            casts[c.name] = s.astype("Int64")
        elif c.dtype == "string" and s.dtype == object and len(s) and s.isna().all():
            casts[c.name] = s.astype("str")
    return df.assign(**casts) if casts else df


# --------------------------------------------------------------------------------------------
# The doc's column tables
# --------------------------------------------------------------------------------------------

BEGIN, END = "<!-- schema tables: generated by `python -m tasks.lake.schema --write`; do not edit -->", \
    "<!-- end of generated schema tables -->"


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|") or "—"


def table_markdown(t: TableSchema) -> str:
    """One table's section: version, row, keys, writer, then one line per column."""
    lines = [f"### `{t.name}` (schema version {t.version})", "",
             f"One row per {t.row}. Keys: {', '.join(f'`{k}`' for k in t.keys)}. Written by {t.writer}.", "",
             "| column | dtype | unit | frame | meaning |", "|---|---|---|---|---|",
             f"| `{PARTITION}` | string | — | — | hive partition (the folder name, not stored in the file) |"]
    for c in t.columns:
        meaning = c.meaning + (" (a timing: not reproducible)" if not c.reproducible else "")
        lines.append(f"| `{c.name}` | {c.dtype} | {_cell(c.unit)} | {_cell(c.frame)} | {_cell(meaning)} |")
    return "\n".join(lines)


def registry_markdown() -> str:
    """The frames glossary and every table's section, in registry order, between the markers."""
    frames = "\n".join(["### Frames", "", "| frame | meaning |", "|---|---|",
                         *(f"| {name} | {_cell(text)} |" for name, text in FRAMES.items())])
    return "\n\n".join([BEGIN, frames, *(table_markdown(t) for t in _TABLES), END])


def _generated_section(text: str) -> tuple[int, int]:
    m = re.search(re.escape(BEGIN) + r".*?" + re.escape(END), text, flags=re.S)
    if m is None:
        raise ValueError("the generated-section markers are missing")
    return m.start(), m.end()


def doc_is_current(path: Path) -> bool:
    """True when the doc's generated section equals :func:`registry_markdown`."""
    text = Path(path).read_text(encoding="utf-8")
    a, b = _generated_section(text)
    return text[a:b] == registry_markdown()


def write_doc(path: Path) -> None:
    """Replace the generated section of ``path`` with the registry's tables."""
    text = Path(path).read_text(encoding="utf-8")
    a, b = _generated_section(text)
    Path(path).write_text(text[:a] + registry_markdown() + text[b:], encoding="utf-8")


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="The results lake's schema registry and its doc.")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", type=Path, metavar="DOC", help="regenerate the column tables of DOC")
    g.add_argument("--check", type=Path, metavar="DOC", help="exit 1 if DOC's column tables are out of date")
    g.add_argument("--print", action="store_true", help="print the column tables")
    a = p.parse_args(argv)
    try:
        if a.print:
            print(registry_markdown())
        elif a.write:
            write_doc(a.write)
        elif not doc_is_current(a.check):
            print(f"{a.check}: the column tables differ from tasks/lake/schema.py; run "
                  f"python -m tasks.lake.schema --write {a.check}", file=sys.stderr)
            return 1
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(_main())
