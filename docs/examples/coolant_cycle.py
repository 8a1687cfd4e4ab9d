"""A user-written effect outside the catalogue (docs/user-effects.md, docs/walkthrough.md): a
coolant pump's cycle moves one linear axis periodically in time.

    fivecal simulate CAMPAIGN --effect-module docs/examples/coolant_cycle.py \
        --effect coolant_cycle:axis=Y,period_s=420,amplitude_um=6,phase_deg=40
"""

import numpy as np

from tasks.effects import Effect, Param, register
from tasks.error_model import UM
from tasks.machine import AXIS_ORDER


@register
class CoolantCycle(Effect):
    family = "coolant_cycle"
    summary = "periodic error in time along a linear axis (a coolant pump's cycle)"
    params = (
        Param("axis", "axis", "", None, "axis the error moves", choices=("X", "Y", "Z")),
        Param("period_s", "float", "s", None, "period of the cycle"),
        Param("amplitude_um", "float", "um", None, "amplitude", amplitude=True),
        Param("phase_deg", "float", "deg", 0.0, "phase at the campaign's start"),
    )
    follows = "time with a {period_s} s period"
    identifying_poses = "repeat poses over ≥ 2 cycles, at random times"

    def joint_errors(self, machine, q, context):
        """{axis: (N, 6)}: amplitude·sin(2π t / period + phase) along the axis (mm), t = context.time_s."""
        axis = self["axis"]
        t = np.asarray(context.time_s, dtype=float)
        v = self["amplitude_um"] * UM * np.sin(2 * np.pi * t / self["period_s"] + np.deg2rad(self["phase_deg"]))
        e = np.zeros((q.shape[0], 6))
        e[:, AXIS_ORDER.index(axis)] = v
        return {axis: e}
