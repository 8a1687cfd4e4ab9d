"""The dispensing test over a panel of simulated campaigns: reads each campaign's dispensing summary
(``<reports>/<campaign_id>/<run>/dispensing/summary.json``, the latest run) and its
``dispense_inspection`` table, and prints per seed the true constant tool-frame tip error over the
validation poses after compensation and after the tip fit, the tip offset found, and how the
measured dot offsets agree with the true ones (qualified dots), then the median and the worst seed.

    .venv/bin/python bench/dispense_panel.py --results R --reports P CAMPAIGN_ID...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.lake.store import read_table


def panel_row(campaign_id: str, results: Path, reports: Path) -> dict | None:
    runs = sorted((reports / campaign_id).glob("*/dispensing/summary.json"))
    if not runs:
        return None
    s = json.loads(runs[-1].read_text())
    rows = read_table("dispense_inspection", results, campaign_id)
    good = rows[rows["qualified"]]
    ex, ey = good["dx_um"] - good["truth_dx_um"], good["dy_um"] - good["truth_dy_um"]
    t = s["truth"]
    return {"campaign": campaign_id, "const before µm": float(np.linalg.norm(t["constant_before_um"])),
            "const after_tip µm": float(np.linalg.norm(t["constant_after_tip_um"])),
            "pos after µm": t["position_after_um"], "pos after_tip µm": t["position_after_tip_um"],
            "tip x": s["tip_offset_um"][0], "tip y": s["tip_offset_um"][1], "tip z": s["tip_offset_um"][2],
            "u z": s["tip_offset_uncertainty_um"][2],
            "mean meas−true x µm": float(ex.mean()), "mean meas−true y µm": float(ey.mean()),
            "mean |meas−true| µm": float(np.hypot(ex, ey).mean()),
            "rms meas−true per axis µm": float(np.sqrt(np.mean(np.concatenate([ex, ey]) ** 2))),
            "fit dots": s["tip_fit_dots"], "qualified": f"{len(good)}/{len(rows)}"}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", type=Path, required=True)
    p.add_argument("--reports", type=Path, required=True)
    p.add_argument("campaigns", nargs="+")
    a = p.parse_args()
    rows = [r for c in a.campaigns if (r := panel_row(c, a.results, a.reports)) is not None]
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 250, "display.max_columns", 30):
        print(df.round(2).to_string(index=False))
        num = df.select_dtypes("number")
        print("\nmedian:\n" + num.median().round(2).to_string())
        worst = df.loc[df["const after_tip µm"].idxmax(), "campaign"]
        print(f"\nworst seed (constant after the tip fit): {worst}; "
              f"max const after_tip {df['const after_tip µm'].max():.2f} µm, "
              f"max |mean meas−true| {df[['mean meas−true x µm', 'mean meas−true y µm']].abs().max().max():.2f} µm")


if __name__ == "__main__":
    main()
