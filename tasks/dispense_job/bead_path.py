"""The single-board bead: a straight stroke of the needle along the dispensing area's long axis (the
automated-dispensing paper, §3.2.1, its Figures 12–13).

The paper's area is the 4 × 2 mm capacitor with 0.25 mm margins at the short ends and 0.2 mm along the
long sides, leaving a usable W1 × W2 = 3.5 × 1.6 mm, and a needle of inner diameter ϕ1 = 2.5 mm that
lays a bead as wide as itself; the needle moves at v1 = 0.9 mm/s while dispensing. The paper shows the
stroke (A to C) but gives no rule for its length; here it is the shortest stroke whose swept needle
disc (radius r = ϕ1/2) covers the whole usable rectangle: its end-caps must reach the rectangle's
corners, so each end sits √(r² − (W2/2)²) inside the usable length,

    stroke = max(0, W1 − 2·√(r² − (W2/2)²)),

1.58 mm for the paper's numbers: a bead 1.58 + 2.5 = 4.08 mm long laid in 1.75 s (its per-board
budget: 4 s). The bead is as wide as the glue spreads, which the paper measured at 2.1–2.3 mm: planned
with that width as ``needle_mm`` (the job passes the glue's 2.2 mm) the stroke is 1.99 mm and the bead
4.19 mm long, inside the paper's measured 4.1–4.4 mm.
"""

from __future__ import annotations

import numpy as np

PAPER_AREA_MM = (4.0, 2.0)  # the capacitor, length × width
PAPER_MARGIN_MM = (0.25, 0.2)  # at each short end (W1 = 3.5 mm), along each long side (W2 = 1.6 mm)
PAPER_NEEDLE_MM = 2.5  # needle inner diameter ϕ1 = bead width W3
PAPER_BEAD_SPEED_MM_S = 0.9  # v1, the needle's speed while dispensing


def bead_path(
    centre_mm: np.ndarray,
    angle_deg: float,
    size_mm: np.ndarray,
    margin_mm: tuple[float, float] = PAPER_MARGIN_MM,
    needle_mm: float = PAPER_NEEDLE_MM,
) -> np.ndarray:
    """(2, 2) machine XY (mm) of the bead's start A and end C on a dispensing area.

    centre_mm: the area's centre (machine XY, mm); angle_deg: direction of the area's first side,
    counter-clockwise from machine +x; size_mm: (extent along that side, extent across it), mm — the
    long axis is the longer of the two; margin_mm: (kept free at each short end, along each long
    side); needle_mm: the width of the bead laid (the needle's bore by default). The stroke runs
    along the long axis through the centre, from its −x end (for a long axis
    along ±y: its −y end); its length is the module's formula. A stroke of length 0 (a dot) returns
    A = C."""
    centre = np.asarray(centre_mm, dtype=float).reshape(2)
    size = np.asarray(size_mm, dtype=float).reshape(2)
    if not (np.isfinite(centre).all() and np.isfinite(size).all() and np.isfinite(angle_deg)):
        raise ValueError(f"bead_path needs finite inputs, got centre {centre.tolist()}, angle {angle_deg}, "
                         f"size {size.tolist()}")
    if (size <= 0).any():
        raise ValueError(f"dispensing area size must be positive, got {size.tolist()} mm")
    end_margin, side_margin = (float(v) for v in margin_mm)
    angle = np.deg2rad(angle_deg) + (0.0 if size[0] >= size[1] else np.pi / 2)
    length, width = size.max(), size.min()
    usable_length, usable_width = length - 2.0 * end_margin, width - 2.0 * side_margin
    if usable_length <= 0 or usable_width <= 0:
        raise ValueError(f"margins {margin_mm} mm leave nothing of a {length:g} × {width:g} mm area")
    radius = 0.5 * float(needle_mm)
    if radius < 0.5 * usable_width:
        raise ValueError(f"a {needle_mm:g} mm needle cannot cover the {usable_width:g} mm usable width in one stroke")
    half_stroke = max(0.0, 0.5 * usable_length - np.sqrt(radius**2 - (0.5 * usable_width) ** 2))
    axis = np.array([np.cos(angle), np.sin(angle)])
    if axis[0] < -1e-12 or (abs(axis[0]) <= 1e-12 and axis[1] < 0):
        axis = -axis  # start from the −x (or −y) end whatever way the side was measured
    return np.stack([centre - half_stroke * axis, centre + half_stroke * axis])


def bead_time_s(path_mm: np.ndarray, speed_mm_s: float = PAPER_BEAD_SPEED_MM_S) -> float:
    """Time (s) to lay the bead along ``path_mm`` (k, 2) mm at the dispensing speed (mm/s; the
    paper's v1 by default), moving at constant speed."""
    if not speed_mm_s > 0:
        raise ValueError(f"dispensing speed must be positive, got {speed_mm_s} mm/s")
    steps = np.diff(np.asarray(path_mm, dtype=float), axis=0)
    return float(np.linalg.norm(steps, axis=1).sum() / speed_mm_s)
