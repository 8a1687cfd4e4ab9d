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


def score_tray(located: Located, truth: pd.DataFrame, spec: TraySpec, match_mm: float = 3.0) -> pd.DataFrame:
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
                    rec["correct"] = t.defect == ""
                else:
                    want = EXPECTED_REASON.get(t.defect)
                    rec["correct"] = want is not None and res.reason.startswith(want)
        rows.append(rec)
    return pd.DataFrame(rows)
