"""The dispensing job end to end over a panel: calibrated simulated campaigns × simulated trays of 20 boards.

    python bench/dispense_job_panel.py --campaigns DIR/p10 DIR/p67 --trays 1 2 3 --out DIR \\
        [--results DIR] [--reports DIR]

For each campaign (calibrated first: ``fivecal calibrate``, optionally ``fivecal dispense-test``):
``fivecal simulate-tray`` for each tray seed (skipped when the image exists), then one
``fivecal dispense-job`` over the campaign's trays (all three phases), then the lake tables are read
and summarised per phase: where the needle is sent against the true area centres, the true bead
offsets against ±0.5 mm, bead sizes, and the tours (optimal, annealing, nearest against the
traditional return-to-origin path: length and time saved). Median and worst over the trays.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from tasks.campaign.ingest import load_campaign_metadata
from tasks.lake.store import read_table

CLI = [sys.executable, "-c", "from fivecal.cli import app; app()"]


def run_campaign(campaign: Path, seeds: list[int], out: Path, results: Path, reports: Path) -> str:
    trays = []
    for s in seeds:
        image = out / campaign.name / f"tray{s}.png"
        if not image.is_file():
            subprocess.run([*CLI, "simulate-tray", str(image), "--campaign", str(campaign), "--seed", str(s)],
                           check=True)
        trays.append(str(image))
    subprocess.run([*CLI, "dispense-job", *trays, "--campaign", str(campaign), "--results", str(results),
                    "--reports", str(reports)], check=True)
    return load_campaign_metadata(campaign)["campaign_id"]


def summarise(areas: pd.DataFrame, beads: pd.DataFrame, paths: pd.DataFrame) -> None:
    print("where the needle is sent: |needle over the area centre − true centre| (µm), per phase")
    ok = areas[areas.ok]
    for phase, a in ok.groupby("phase", sort=False):
        per_tray = a.groupby(["campaign", "tray_id"]).map_error_um.median()
        print(f"  {phase:12s} median {a.map_error_um.median():7.1f}  max {a.map_error_um.max():7.1f}  "
              f"worst tray's median {per_tray.max():7.1f}  over {len(a)} areas, {len(per_tray)} trays")
    print("true bead offset from the true area centre (µm) and the ±0.5 mm requirement (§4.6)")
    for phase, b in beads.groupby("phase", sort=False):
        off = 1e3 * np.hypot(b.true_offset_along_mm, b.true_offset_across_mm)
        meas = 1e3 * np.hypot(b.offset_along_mm, b.offset_across_mm)
        print(f"  {phase:12s} true median {off.median():6.1f} max {off.max():6.1f}; measured median "
              f"{meas.median():6.1f} max {meas.max():6.1f}; within ±0.5 mm {int(b.true_within_tolerance.sum())}/"
              f"{len(b)}; found {int(b.found.sum())}/{len(b)}")
    f = beads[beads.found]
    print(f"bead length {1e3 * f.bead_length_mm.min():.0f}–{1e3 * f.bead_length_mm.max():.0f} µm (true "
          f"{1e3 * beads.true_bead_length_mm.min():.0f}–{1e3 * beads.true_bead_length_mm.max():.0f}), width "
          f"{1e3 * f.bead_width_mm.min():.0f}–{1e3 * f.bead_width_mm.max():.0f} µm (true "
          f"{1e3 * beads.true_bead_width_mm.min():.0f}–{1e3 * beads.true_bead_width_mm.max():.0f}); paper "
          f"4100–4400 and 2100–2300 µm")
    comp = paths[paths.phase == "compensated"]
    print("tours (compensated phase), per tray: length and time against return-to-origin "
          "(paper: 1670.2 → 946.8 mm; time 21.5–30.7 % saved)")
    rows = []
    for (camp, tray), p in comp.groupby(["campaign", "tray_id"]):
        base = p[p.method == "return_to_origin"].iloc[0]
        for r in p.itertuples(index=False):
            rows.append({"campaign": camp, "tray": tray, "method": r.method, "points": r.points,
                         "length_mm": r.length_mm, "proven": r.proven_optimal,
                         "time_s": r.travel_s + r.dispense_s,
                         "length_saved_pct": 100 * (1 - r.length_mm / base.length_mm),
                         "time_saved_pct": 100 * (1 - (r.travel_s + r.dispense_s) / (base.travel_s + base.dispense_s))})
    df = pd.DataFrame(rows)
    print(df.to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    g = df.groupby("method")
    print(pd.DataFrame({"length median": g.length_mm.median(), "time saved median %": g.time_saved_pct.median(),
                        "time saved worst %": g.time_saved_pct.min()}).to_string(float_format=lambda v: f"{v:.1f}"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--campaigns", type=Path, nargs="+", required=True)
    ap.add_argument("--trays", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--results", type=Path, default=Path("data/results"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))
    args = ap.parse_args()
    tables = {"dispense_areas": [], "dispense_beads": [], "dispense_paths": []}
    for c in args.campaigns:
        cid = run_campaign(c, args.trays, args.out, args.results, args.reports)
        for name, parts in tables.items():
            parts.append(read_table(name, args.results, cid).assign(campaign=cid))
    summarise(*(pd.concat(tables[n], ignore_index=True) for n in ("dispense_areas", "dispense_beads",
                                                                   "dispense_paths")))


if __name__ == "__main__":
    main()
