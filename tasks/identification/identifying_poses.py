"""Poses that would make an effect identifiable, in words.

An effect is identifiable from a campaign when its signature in the residuals survives what the
PDGE profiles (smooth functions of each swept axis) and the constant parameters can absorb, and
when some camera sees it. What breaks that, and what mends it, depends on what the effect follows:
a period needs a sweep over at least two periods in steps of at most a quarter period; a reversal
error needs positions approached from both sides; a thermal effect needs the same poses repeated
at other temperatures (and, to tell time from temperature, a temperature that does not simply grow
with time); a cradle sag needs tilts beyond the ±24° of the plan's five-axis poses; an error at
the tip needs a measurement of the tip, which no camera sees.

A user family may say it itself with a class attribute or method ``identifying_poses`` (a string,
or ``(self) -> str``).
"""

from __future__ import annotations

from tasks.machine.effects import Effect


def identifying_poses(effect: Effect) -> str:
    """A short instruction naming the poses that would identify ``effect``."""
    own = getattr(type(effect), "identifying_poses", None)
    if own is not None:
        return own(effect) if callable(own) else str(own)
    v = effect.values
    axis = v.get("axis", "")
    fam = effect.family
    if fam == "pitch_cyclic":
        p = float(v["period_mm"])
        return (f"sweep {axis} over ≥ 2 periods ({2 * p:g} mm) in steps ≤ {p / 4:g} mm (a quarter period) "
                f"and spread the five-axis poses' {axis} over that range")
    if fam == "backlash":
        return f"approach each {axis} position from both sides (repeat poses with the last {axis} move reversed)"
    if fam == "thermal_drift":
        if v.get("driver") == "time":
            return "repeat poses later in the campaign (over ≥ 1 h), with temperature held or varied independently"
        return ("repeat poses at other temperatures (≥ 1 K apart), including while the machine cools, "
                "so that temperature does not simply follow time")
    if fam == "gravity_sag":
        return f"capture five-axis poses at {axis} beyond ±30° (e.g. ±60°), and sweep {axis} over that range"
    if fam in ("encoder_eccentricity", "encoder_wobble"):
        return f"sweep {axis} over its whole stroke and spread the five-axis poses' {axis} over it"
    if fam == "scale":
        return (f"a reference length along {axis} independent of the sweep (a scale error along the sweep is "
                f"indistinguishable from {axis}'s positioning error profile)")
    if fam == "focal_drift":
        return (f"vary the camera–plate distance independently of {v.get('axis', 'Z')} (plates at other heights), "
                "since along the sweep a focal drift looks like a positioning error")
    if fam == "lens_distortion":
        return "place the plate at several positions across the image, corners included, with tilted views"
    if fam == "tool_offset":
        return "measure the tip itself (touch-off or a tip-viewing camera): no camera sees the tip"
    if axis:
        return f"move {axis} over more of its stroke in the five-axis poses and repeat them under other conditions"
    return "vary what the effect depends on independently of the swept axes"
