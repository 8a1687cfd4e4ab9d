"""Recognition over many rendered boards: the paper's Tables 5 and 6 against the renderer's truth.

    python bench/bench_locate.py [--trays 30] [--repeats 10] [--defect-rate 0.1] [--seed 0]

Table 5: trays of 20 boards (groups of 120 boards as in the paper), every board scored by
tasks.dispense_job.recognition: intact boards found, defective ones rejected for their defect; the
time per image of the location (the paper's extraction time). Centre error of the accepted areas
against the truth (mm), of the refined rectangle beside the paper's own rectangle (the baseline).
Table 6: one tray imaged ``--repeats`` times (new light and noise each shot), the standard deviation
(eq. 40) of each accepted area's centre (mm).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from tasks.dispense_job.boards import TraySpec, render_tray
from tasks.dispense_job.locate import locate
from tasks.dispense_job.recognition import score_tray


def recognition(trays: int, defect_rate: float, seed: int) -> tuple[pd.DataFrame, list[float]]:
    spec = TraySpec(defect_rate=defect_rate)
    frames, seconds = [], []
    for k in range(trays):
        image, truth, _ = render_tray(spec, seed + k)
        t0 = time.perf_counter()
        located = locate(image, mm_per_px=spec.mm_per_px)
        seconds.append(time.perf_counter() - t0)
        frames.append(score_tray(located, truth, spec).assign(tray=seed + k))
    return pd.concat(frames, ignore_index=True), seconds


def repeatability(repeats: int, seed: int) -> pd.DataFrame:
    spec = TraySpec(defect_rate=0.0)
    frames = []
    for shot in range(repeats):
        image, truth, _ = render_tray(spec, seed, shot=shot)
        scored = score_tray(locate(image, mm_per_px=spec.mm_per_px), truth, spec)
        frames.append(scored.assign(shot=shot))
    df = pd.concat(frames, ignore_index=True)
    # eq. 40: u(p) = sqrt(Σ (p_i − p̄)² / n), the measured centre's scatter over the shots
    return df.groupby("board_id").agg(u_x_mm=("dx_mm", lambda x: float(np.std(x))),
                                      u_y_mm=("dy_mm", lambda x: float(np.std(x))), shots=("ok", "sum"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trays", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--defect-rate", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    df, seconds = recognition(args.trays, args.defect_rate, args.seed)
    df["group"] = np.arange(len(df)) // 120 + 1
    print("Table 5 (paper: 120/120, 120/120, 120/120, 119/120, 120/120; 599/600 correct)")
    print(f"{'group':>5} {'boards':>6} {'intact':>6} {'defective':>9} {'correct':>7} {'rate':>7}")
    for g, part in df.groupby("group"):
        print(f"{g:>5} {len(part):>6} {int((part.defect == '').sum()):>6} {int((part.defect != '').sum()):>9} "
              f"{int(part.correct.sum()):>7} {100 * part.correct.mean():6.1f}%")
    intact, bad = df[df.defect == ""], df[df.defect != ""]
    broken, missing = bad[bad.defect == "broken_edge"], bad[bad.defect == "missing_component"]
    print(f"all: {int(df.correct.sum())}/{len(df)} correct; intact found {int(intact.ok.sum())}/{len(intact)}; "
          f"defective rejected for their defect {int(bad.correct.sum())}/{len(bad)} "
          f"(broken edge {int(broken.correct.sum())}/{len(broken)}, missing component "
          f"{int(missing.correct.sum())}/{len(missing)}); accepted although defective {int(bad.ok.sum())}")
    wrong = df[~df.correct]
    if len(wrong):
        print("not correct:\n" + wrong[["tray", "board_id", "defect", "reason"]].to_string(index=False))
    print(f"location time per 2448 × 2048 image: median {1e3 * np.median(seconds):.0f} ms, max "
          f"{1e3 * np.max(seconds):.0f} ms (paper: 620–1099 ms per group image)")
    ok = df[df.ok & (df.defect == "")]
    for name, col in (("refined", "centre_error_mm"), ("paper's rectangle (baseline)", "paper_centre_error_mm")):
        e = ok[col]
        print(f"centre error, {name}: median {1e3 * e.median():.2f} µm, 95 % {1e3 * e.quantile(0.95):.2f} µm, "
              f"max {1e3 * e.max():.2f} µm over {len(e)} areas")
    worst = ok.nlargest(3, "centre_error_mm")[["tray", "board_id", "centre_error_mm", "paper_centre_error_mm",
                                                  "angle_error_deg", "length_mm", "width_mm"]]
    print("largest refined centre errors (mm):\n" + worst.to_string(index=False))
    ratio = ok.centre_error_mm.max() / ok.paper_centre_error_mm.max()
    print(f"ratio refined / paper's rectangle (max error): {ratio:.3f}")
    da = ok.angle_error_deg.abs()
    print(f"angle error: median |Δ| {da.median():.3f}°, max {da.max():.3f}°; "
          f"length {ok.length_mm.median():.3f} mm ({ok.length_mm.min():.3f}–{ok.length_mm.max():.3f}), width "
          f"{ok.width_mm.median():.3f} mm ({ok.width_mm.min():.3f}–{ok.width_mm.max():.3f}); true 4 × 2 mm")

    rep = repeatability(args.repeats, args.seed + 1000)
    print(f"Table 6: {args.repeats} shots of one tray (paper: u(p) 0.011–0.014 mm, < 0.02 mm)")
    ux, uy = 1e3 * rep.u_x_mm, 1e3 * rep.u_y_mm
    print(f"u(p) over {len(rep)} boards: x median {ux.median():.2f} µm max {ux.max():.2f} µm; y median "
          f"{uy.median():.2f} µm max {uy.max():.2f} µm; boards found in every shot "
          f"{int((rep.shots == args.repeats).sum())}/{len(rep)}")


if __name__ == "__main__":
    main()
