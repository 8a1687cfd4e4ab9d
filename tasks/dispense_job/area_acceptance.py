"""Which candidates are dispensing areas: the paper's aspect-ratio and area acceptance (§2.4.1–2.4.2).

The paper keeps an edge when the target's aspect ratio and area match those measured beforehand under
the microscope: aspect ratio within 0.5–2 and area within 2200–2300 px against its 4 × 2 mm reference
of 2241 px (eq. 28: S = S₀·W₁/W₀). The pixel window is −1.8 %…+2.6 % of the reference; here the rules
are in millimetres (the image scale known), the area window a relative tolerance about the nominal
4 × 2 mm = 8 mm², the aspect ratio long/short side about its nominal 2 (the paper's 0.5–2 has the
capacitor's own ratio 2 at its edge: a window centred on it is used instead).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class AcceptanceRules:
    """Nominal dispensing area (length, width; mm), the accepted relative area tolerance, the accepted
    aspect-ratio window (long/short), the smallest blob considered at all (mm²), the board's size (mm)
    and the deepest notch in an intact board's outline (mm)."""

    area_mm: tuple[float, float] = (4.0, 2.0)
    area_tolerance: float = 0.06
    aspect_range: tuple[float, float] = (1.7, 2.3)
    min_blob_mm2: float = 0.2
    board_mm: tuple[float, float] = (16.0, 12.0)
    max_notch_mm: float = 0.5


def accept_area(length_mm: float, width_mm: float, area_mm2: float, rules: AcceptanceRules) -> tuple[bool, str]:
    """(accepted, reason) of a candidate: its rectangle's sides (mm) and its blob's area (mm², eq. 28)."""
    nominal = rules.area_mm[0] * rules.area_mm[1]
    aspect = length_mm / width_mm if width_mm > 0 else float("inf")
    lo, hi = rules.aspect_range
    if not lo <= aspect <= hi:
        return False, f"aspect ratio {aspect:.2f} outside {lo}–{hi}"
    if abs(area_mm2 / nominal - 1.0) > rules.area_tolerance:
        return False, (f"area {area_mm2:.2f} mm² outside {nominal:.1f} mm² ± {100 * rules.area_tolerance:.0f} %")
    return True, ""
