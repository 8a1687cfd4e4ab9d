"""A user-written effect outside the catalogue (docs/user-effects.md, docs/walkthrough.md).

When one axis reverses, its carriage settles against the other side of its guide and shifts the
tool *across* its travel: an offset of ±amount/2 along another linear axis, by the approach
direction of the reversing one. The catalogue's ``backlash`` acts along its own axis only.

    fivecal simulate CAMPAIGN --effect-module docs/examples/cross_backlash.py \
        --effect cross_backlash:axis=X,along=Y,amount_um=8
"""

import numpy as np

from tasks.core.units import UM
from tasks.machine.description import AXIS_ORDER
from tasks.machine.effects import Effect, Param, register

LINEAR = ("X", "Y", "Z")


@register
class CrossBacklash(Effect):
    family = "cross_backlash"
    summary = "reversal of one axis shifts the tool along another linear axis by ±amount/2"
    params = (
        Param("axis", "axis", "", None, "the reversing axis", choices=LINEAR),
        Param("along", "choice", "", None, "the linear axis the shift is along", choices=LINEAR),
        Param("amount_um", "float", "um", None, "total shift between the two approach directions", amplitude=True),
    )
    follows = "the approach direction of {axis}, along {along}"

    def identifying_poses(self) -> str:
        return f"reverse {self['axis']} while {self['along']} stands still"

    def joint_errors(self, machine, q, context):
        """{along: (N, 6)}: ±amount/2 (mm) along ``along`` (X, Y, Z move along base x, y, z), the sign
        of ``axis``' last move (context.approach)."""
        s = np.asarray(context.approach, dtype=float)[:, AXIS_ORDER.index(self["axis"])]
        e = np.zeros((q.shape[0], 6))
        e[:, AXIS_ORDER.index(self["along"])] = 0.5 * self["amount_um"] * UM * s
        return {self["along"]: e}
