"""Score a located tray against the renderer's truth: the paper's recognition (Table 5) and
repeatability (Table 6) figures, per board.

A board is correctly handled when an intact board is found with its dispensing area, a board with a
broken edge is rejected for its broken edge and a board without its capacitor is rejected for having
no dispensing area. Errors are in mm on the tray (planar scale ``mm_per_px``), angles in degrees.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from tasks.dispense_job.boards import TraySpec, tray_to_pixels
from tasks.dispense_job.locate import Located

EXPECTED_REASON = {"broken_edge": "broken edge", "missing_component": "no dispensing area"}
MATCH_MM = 3.0  # a found board is the true board whose centre lies within this distance (pockets: 21 mm)


def handled_correctly(defect: str, ok: bool, reason: str) -> bool:
    """An intact board (defect "") accepted, or a defective one rejected for its defect."""
    if ok:
        return defect == ""
    want = EXPECTED_REASON.get(defect)
    return want is not None and reason.startswith(want)


def match_found_boards(board_xy_mm: np.ndarray, ok: np.ndarray, reasons: list[str], truth: pd.DataFrame,
                       match_mm: float = MATCH_MM) -> tuple[list[str], list[bool], pd.DataFrame]:
    """Found boards against the true ones, on the tray (mm, tray frame).

    board_xy_mm: (n, 2) the found boards' centres; ok, reasons: their verdicts. Returns per found
    board the defect of the true board within ``match_mm`` (``none`` for an intact one, ``unmatched``
    when there is none) and whether it was handled correctly, and the truth rows of the true boards
    no found board matched."""
    true_xy = truth[["board_x_mm", "board_y_mm"]].to_numpy(float)
    defects, correct, matched = [], [], np.zeros(len(truth), bool)
    for xy, good, reason in zip(np.asarray(board_xy_mm, float).reshape(-1, 2), ok, reasons, strict=True):
        d = np.linalg.norm(true_xy - xy, axis=1) if len(true_xy) else np.array([np.inf])
        k = int(np.argmin(d))
        if d[k] > match_mm:
            defects.append("unmatched")
            correct.append(False)
            continue
        matched[k] = True
        defect = truth["defect"].iloc[k]
        defects.append(defect or "none")
        correct.append(handled_correctly(defect, bool(good), reason))
    return defects, correct, truth[~matched]


def score_tray(located: Located, truth: pd.DataFrame, spec: TraySpec, match_mm: float = MATCH_MM) -> pd.DataFrame:
    """One row per true board: matched (a found board within ``match_mm`` of its centre), ok (found
    and accepted), reason, correct (see the module docstring), and for accepted boards the centre
    error of the refined and of the paper's rectangle (mm), the angle error (deg, modulo 180) and the
    measured length and width (mm)."""
    s = spec.mm_per_px
    found = np.array([[b.board.rect.u, b.board.rect.v] for b in located.boards]).reshape(-1, 2)
    true_px = tray_to_pixels(spec, truth[["board_x_mm", "board_y_mm"]].to_numpy(float))
    rows = []
    for k, t in enumerate(truth.itertuples(index=False)):
        rec = {"board_id": t.board_id, "defect": t.defect, "matched": False, "ok": False, "reason": "not found",
               "correct": False, "centre_error_mm": np.nan, "paper_centre_error_mm": np.nan,
               "dx_mm": np.nan, "dy_mm": np.nan, "angle_error_deg": np.nan, "length_mm": np.nan,
               "width_mm": np.nan}
        if len(found):
            d = np.linalg.norm(found - true_px[k], axis=1) * s
            i = int(np.argmin(d))
            if d[i] <= match_mm:
                res = located.boards[i]
                rec.update(matched=True, ok=res.ok, reason=res.reason)
                if res.ok:
                    r, p = res.area.rect, res.area.paper_rect
                    dx, dy = (r.u - t.area_u_px) * s, -(r.v - t.area_v_px) * s  # tray frame: y up
                    da = (r.angle_deg - t.area_angle_deg + 90.0) % 180.0 - 90.0
                    rec.update(dx_mm=dx, dy_mm=dy, centre_error_mm=float(np.hypot(dx, dy)),
                               paper_centre_error_mm=float(np.hypot(p.u - t.area_u_px, p.v - t.area_v_px) * s),
                               angle_error_deg=da, length_mm=r.length_px * s, width_mm=r.width_px * s)
                rec["correct"] = handled_correctly(t.defect, res.ok, res.reason)
        rows.append(rec)
    return pd.DataFrame(rows)
