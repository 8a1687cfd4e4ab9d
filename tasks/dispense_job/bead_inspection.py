"""Inspect the beads after dispensing (§4.6, Figure 27): length, width and offset from the area's centre.

The glue (red adhesive) is found on the redness R − G of camera 1's image (the capacitor, the pads,
the silkscreen and every solder mask have R − G well below the glue's), 3 × 3 median, Otsu, blobs.
Each bead's centre is its blob's centroid, its length and width its minimum-area rectangle's sides;
centre and rectangle ends are carried onto the workpiece surface by the job's pixel map. A bead is
paired with the dispensing area whose measured centre is nearest (within ``max_pair_mm``); its offset
from that centre is split along and across the area's long axis. The paper's requirement: ±0.5 mm.

Frames: image pixels (u right, v down); workpiece frame (mm).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pandas as pd

from tasks.dispense_job.locate import binarise, blobs, min_area_rect, smooth

TOLERANCE_MM = 0.5  # the paper's dispensing accuracy requirement (§4.6)


def redness(rgb: np.ndarray) -> np.ndarray:
    """R − G clipped to 0–255 (uint8) of an RGB image (H, W, 3) uint8."""
    return np.clip(rgb[..., 0].astype(np.int16) - rgb[..., 1].astype(np.int16), 0, 255).astype(np.uint8)


def find_beads(rgb: np.ndarray, min_px: int) -> pd.DataFrame:
    """One row per glue blob of at least ``min_px`` pixels: centroid (u, v) px, minimum-area
    rectangle's length and width (px), long-axis angle (deg), pixel count, the rectangle's two
    long-side end midpoints (px)."""
    binary, _ = binarise(smooth(redness(rgb)))
    labels, boxes = blobs(binary, min_px)
    rows = []
    for x, y, w, h, count, label in boxes:
        mask = (labels[y:y + h, x:x + w] == label).astype(np.uint8)
        m = cv2.moments(mask, binaryImage=True)
        vv, uu = np.nonzero(mask)
        rect = min_area_rect(np.column_stack([uu + x, vv + y]))
        t = np.deg2rad(rect.angle_deg)
        half = 0.5 * (rect.length_px + 1.0) * np.array([np.cos(t), -np.sin(t)])  # pixel centres → edges
        cu, cv_ = x + m["m10"] / m["m00"], y + m["m01"] / m["m00"]
        rows.append({"u_px": cu, "v_px": cv_, "length_px": rect.length_px + 1.0, "width_px": rect.width_px + 1.0,
                     "angle_deg": rect.angle_deg, "pixels": int(count),
                     "end_a_u": cu - half[0], "end_a_v": cv_ - half[1], "end_b_u": cu + half[0],
                     "end_b_v": cv_ + half[1]})
    return pd.DataFrame(rows, columns=["u_px", "v_px", "length_px", "width_px", "angle_deg", "pixels", "end_a_u",
                                       "end_a_v", "end_b_u", "end_b_v"])


def measure_beads(beads: pd.DataFrame, to_workpiece: Callable[[np.ndarray], np.ndarray],
                  mm_per_px: float) -> pd.DataFrame:
    """The beads on the workpiece: centre (mm), length (mm, between the mapped ends) and width (mm, at
    the local scale of the map: ``mm_per_px`` times the ratio of mapped to pixel length)."""
    if beads.empty:
        return beads.assign(bead_x_mm=[], bead_y_mm=[], bead_length_mm=[], bead_width_mm=[])
    centre = to_workpiece(beads[["u_px", "v_px"]].to_numpy(float))
    a = to_workpiece(beads[["end_a_u", "end_a_v"]].to_numpy(float))
    b = to_workpiece(beads[["end_b_u", "end_b_v"]].to_numpy(float))
    length = np.linalg.norm(b - a, axis=1)
    scale = np.where(beads["length_px"] > 0, length / beads["length_px"], mm_per_px)
    return beads.assign(bead_x_mm=centre[:, 0], bead_y_mm=centre[:, 1], bead_length_mm=length,
                        bead_width_mm=beads["width_px"].to_numpy(float) * scale)


def pair_beads(areas: pd.DataFrame, beads: pd.DataFrame, max_pair_mm: float = 3.0) -> pd.DataFrame:
    """One row per area (columns board_id, area_x_mm, area_y_mm, area_angle_deg): the nearest bead's
    measures and its offset along and across the area's long axis (mm), within the ±0.5 mm tolerance
    or not; NaN and ``found`` False when no bead lies within ``max_pair_mm``."""
    out = []
    bxy = beads[["bead_x_mm", "bead_y_mm"]].to_numpy(float) if len(beads) else np.zeros((0, 2))
    for a in areas.itertuples(index=False):
        rec = {"board_id": a.board_id, "found": False, "bead_x_mm": np.nan, "bead_y_mm": np.nan,
               "bead_length_mm": np.nan, "bead_width_mm": np.nan, "offset_along_mm": np.nan,
               "offset_across_mm": np.nan, "within_tolerance": False}
        if len(bxy):
            d = np.linalg.norm(bxy - [a.area_x_mm, a.area_y_mm], axis=1)
            k = int(np.argmin(d))
            if d[k] <= max_pair_mm:
                b = beads.iloc[k]
                along, across = axis_offsets(b.bead_x_mm - a.area_x_mm, b.bead_y_mm - a.area_y_mm, a.area_angle_deg)
                rec.update(found=True, bead_x_mm=b.bead_x_mm, bead_y_mm=b.bead_y_mm, bead_length_mm=b.bead_length_mm,
                           bead_width_mm=b.bead_width_mm, offset_along_mm=along, offset_across_mm=across,
                           within_tolerance=bool(max(abs(along), abs(across)) <= TOLERANCE_MM))
        out.append(rec)
    return pd.DataFrame(out)


def axis_offsets(dx_mm, dy_mm, angle_deg) -> tuple[float, float]:
    """An offset (mm, workpiece frame) split along and across a direction ``angle_deg`` (deg)."""
    t = np.deg2rad(angle_deg)
    c, s = np.cos(t), np.sin(t)
    return float(c * dx_mm + s * dy_mm), float(-s * dx_mm + c * dy_mm)
