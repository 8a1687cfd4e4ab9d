"""Table 5: local PoE (ours) vs Denavit–Hartenberg vs global PoE on the prototype.

The three formulations run one after another in this process, on the same 300 five-axis
commands (camera 1 aimed at plate a, as the PIGE stage) and the same error model. Times are the
best of ``--repeats``. The ratios are each formulation's time over the local PoE's. Error norms
are measured against the local PoE with all errors, which is the simulator's truth. For scale,
the bench also prints the ideal model (no errors) against the same truth, the split of the error
norms into PIGE-only and PDGE-only models (both alternatives carry the PIGEs exactly: the PIGE-only
norms are rounding), the norms with the PDGE of one axis at a time, which DH parameter carries
each PIGE, and what the DH projection drops of each joint's PDGE.

    python bench/bench_formulations.py [--poses 300] [--repeats 20]
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from tasks.core.units import ARCSEC, UM
from tasks.machine.description import load_machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.formulations import (
    DH,
    GLOBAL_POE,
    LOCAL_POE,
    compare_formulations,
    dh_lost_error,
    dh_parameter_table,
    dh_pige_parameters,
    dh_tool_in_workpiece,
    global_poe_tool_in_workpiece,
)
from tasks.machine.kinematics import forward, position_orientation_error
from tasks.report.tables import format_table5
from tasks.simulation.campaign_plan import CampaignPlan, five_axis_poses
from tasks.simulation.prototype_errors import load_prototype_errors


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    machine = load_machine("prototype")
    errors = load_prototype_errors()
    cmds = five_axis_poses(machine, args.poses, CampaignPlan(), np.random.default_rng(0))

    table = compare_formulations(machine, errors, cmds, repeats=args.repeats)
    ref = table.set_index("formulation").loc[LOCAL_POE]
    print(f"Table 5 — {args.poses} five-axis poses, all PIGEs and PDGEs, best of {args.repeats}")
    print(format_table5(table))
    print()
    print("times relative to local PoE (same process):")
    for r in table.itertuples(index=False):
        print(f"  {r.formulation:20s} single run {r.mean_single_run_ms / ref.mean_single_run_ms:5.2f}x   "
              f"batched total {r.total_300_ms / ref.total_300_ms:5.2f}x")

    dt, dR = position_orientation_error(forward(machine, cmds).tool_in_workpiece(),
                                        forward(machine, cmds, errors).tool_in_workpiece())
    print(f"\nfor scale, the ideal model (no errors) against the same truth: {dt.mean() / UM:.1f} µm, "
          f"{dR.mean() / ARCSEC:.1f}″")

    print("\nerror norms (µm / ″) with part of the error model only:")
    for label, em in (("PIGEs only", ErrorModel(pige=errors.pige)), ("PDGEs only", ErrorModel(pdge=errors.pdge))):
        t = compare_formulations(machine, em, cmds, repeats=1)
        cells = "   ".join(f"{r.formulation}: {r.position_error_norm_um:.3g} / {r.orientation_error_norm_arcsec:.3g}"
                           for r in t.itertuples(index=False))
        print(f"  {label:10s}  {cells}")

    print("\nerror norms (µm / ″) with the PIGEs and the PDGE of one axis only (where each alternative loses):")
    for axis in errors.pdge:
        em = ErrorModel(pige=errors.pige, pdge={axis: errors.pdge[axis]})
        truth = forward(machine, cmds, em).tool_in_workpiece()
        cells = []
        for name, fn in ((DH, dh_tool_in_workpiece), (GLOBAL_POE, global_poe_tool_in_workpiece)):
            dt, dR = position_orientation_error(fn(machine, cmds, em), truth)
            cells.append(f"{name}: {dt.mean() / UM:.3g} / {dR.mean() / ARCSEC:.3g}")
        print(f"  PDGE of {axis}  " + "   ".join(cells))

    with pd.option_context("display.width", 160, "display.max_columns", 20):
        print("\nmodified DH parameters derived from the machine description (α, a: of link i-1 -> i):")
        print(dh_parameter_table(machine).to_string(index=False))
        print("\nDH quantities that change per unit PIGE (1 µm or 1″; parameters signed, base/tool frames as norms):")
        carriers = dh_pige_parameters(machine)
        carriers["change"] = carriers["change"].round(4)
        print(carriers.to_string(index=False))
        print("\nper joint, mean over the poses of the PDGE error the DH projection drops (first order):")
        print(dh_lost_error(machine, errors, cmds).round(2).to_string(index=False))


if __name__ == "__main__":
    main()
