"""The dispensing job's report: the paper's tables beside ours (markdown).

Recognition of the trays (Table 5's terms), where the needle is sent against the truth (simulated
trays), path length and time of the planned tour against the traditional return-to-origin path
(Tables 4 and 8), the beads' dimensions and offsets (Figure 27, the ±0.5 mm requirement of §4.6),
per phase (compensated, nominal, planar).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from tasks.dispense_job.program import write_program
from tasks.report.publish import publish_report

PAPER = {
    "tour": "20 boards: 1670.2 mm → 946.8 mm (Table 4 group averages 1654.9–1713.4 → 940.1–959.8 mm)",
    "time": "Table 8: 374.0–429.4 s → 293.6–298.1 s, 21.5–30.7 % saved",
    "length": "4100–4400 µm",
    "width": "2100–2300 µm",
    "tolerance": "±0.5 mm",
    "recognition": "Table 5: 599 of 600 boards (the one missed had a broken edge)",
    "repeatability": "Table 6: u(p) 0.011–0.014 mm, < 0.02 mm",
}


def _table(df: pd.DataFrame) -> str:
    if df.empty:
        return "(none)\n"
    head = "| " + " | ".join(map(str, df.columns)) + " |\n|" + "---|" * len(df.columns) + "\n"
    return head + "".join("| " + " | ".join(_fmt(v) for v in row) + " |\n" for row in df.itertuples(index=False))


def _fmt(v) -> str:
    if isinstance(v, float | np.floating):
        return "–" if not np.isfinite(v) else f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"
    return str(v)


def recognition_section(areas: pd.DataFrame, failures: list[str]) -> str:
    """Boards found, accepted and rejected (with reasons) per tray; trays that failed."""
    a = areas[areas.phase == areas.phase.iloc[0]] if len(areas) else areas
    rows = []
    for tray, part in a.groupby("tray_id"):
        missed = part.reason == "not found"
        reasons = part.loc[~part.ok & ~missed, "reason"].str.split(":").str[0].value_counts()
        row = {"tray": tray, "boards found": int((~missed).sum()), "accepted": int(part.ok.sum()),
               "rejected": "; ".join(f"{n} × {r}" for r, n in reasons.items()) or "none"}
        if part.recognised.notna().any():  # a simulated tray: scored against its truth
            wrong = part[~part.recognised.astype(bool)]
            row |= {"true boards": int((part.true_defect != "unmatched").sum()),
                    "handled as the truth asks": int(part.recognised.sum()),
                    "wrong": "; ".join(f"{b} ({d}: {'accepted' if ok else r})" for b, d, ok, r in
                                       zip(wrong.board_id, wrong.true_defect, wrong.ok, wrong.reason, strict=True))
                             or "none"}
        rows.append(row)
    out = f"## Recognition\n\nPaper: {PAPER['recognition']}.\n\n" + _table(pd.DataFrame(rows))
    if failures:
        out += "\nTrays that failed (the others went on):\n\n" + "".join(f"- {f}\n" for f in failures)
    return out


def mapping_section(areas: pd.DataFrame) -> str:
    """Where the needle is sent against the true area centre (simulated trays), per phase (µm)."""
    ok = areas[areas.ok & np.isfinite(areas.map_error_um)]
    if ok.empty:
        return ""
    g = ok.groupby("phase").map_error_um
    df = pd.DataFrame({"areas": g.size(), "median (µm)": g.median(), "max (µm)": g.max()}).reset_index()
    return ("## Where the needle is sent\n\n|needle over the area's centre on the true machine − true centre|, "
            "before any glue:\n\n" + _table(df))


def path_section(paths: pd.DataFrame) -> str:
    """Tour length and time per method against return-to-origin, per tray and phase."""
    if paths.empty:
        return ""
    rows = []
    for (tray, phase), part in paths.groupby(["tray_id", "phase"]):
        base = part[part.method == "return_to_origin"]
        b_len = float(base.length_mm.iloc[0]) if len(base) else np.nan
        b_t = float((base.travel_s + base.dispense_s).iloc[0]) if len(base) else np.nan
        for p in part.itertuples(index=False):
            total = p.travel_s + p.dispense_s
            rows.append({"tray": tray, "phase": phase, "method": p.method, "boards": p.points,
                         "length (mm)": p.length_mm, "lower bound (mm)": p.lower_bound_mm,
                         "proven optimal": p.proven_optimal, "time (s)": total,
                         "length saved": f"{100 * (1 - p.length_mm / b_len):.1f} %",
                         "time saved": f"{100 * (1 - total / b_t):.1f} %"})
    return (f"## Paths (Tables 4 and 8)\n\nPaper: {PAPER['tour']}; {PAPER['time']}. Time = travel (per-axis "
            "speed and acceleration) + glue on.\n\n" + _table(pd.DataFrame(rows)))


def bead_section(beads: pd.DataFrame) -> str:
    """Bead dimensions and offsets per phase, measured and true (simulated trays)."""
    if beads.empty:
        return ""
    rows = []
    for phase, b in beads.groupby("phase", sort=False):
        f = b[b.found]
        true_off = np.hypot(b.true_offset_along_mm, b.true_offset_across_mm)
        meas_off = np.hypot(f.offset_along_mm, f.offset_across_mm)
        rows.append({"phase": phase, "beads": len(b), "found": len(f),
                     "length (µm)": f"{1e3 * f.bead_length_mm.min():.0f}–{1e3 * f.bead_length_mm.max():.0f}",
                     "width (µm)": f"{1e3 * f.bead_width_mm.min():.0f}–{1e3 * f.bead_width_mm.max():.0f}",
                     "measured offset median / max (µm)": f"{1e3 * meas_off.median():.0f} / {1e3 * meas_off.max():.0f}",
                     "true offset median / max (µm)": f"{1e3 * true_off.median():.0f} / {1e3 * true_off.max():.0f}",
                     "within ±0.5 mm (true)": f"{int(b.true_within_tolerance.sum())}/{len(b)}"})
    return (f"## Beads (Figure 27)\n\nPaper: length {PAPER['length']}, width {PAPER['width']}, accuracy "
            f"{PAPER['tolerance']}. Offsets: bead centre − area centre; measured through the phase's own map, "
            "true from the simulator.\n\n" + _table(pd.DataFrame(rows)))


def write_dispense_job_report(out_dir: Path, header: str, areas: pd.DataFrame, paths: pd.DataFrame,
                              beads: pd.DataFrame, failures: list[str],
                              programs: dict[str, pd.DataFrame] | None = None,
                              images: dict[str, np.ndarray] | None = None) -> Path:
    """Publish the job's report folder at ``out_dir`` whole (:func:`tasks.report.publish.publish_report`):
    ``report.md``, ``index.html``, each program as ``<name>.csv`` (:func:`write_program`) and each
    image of a dispensed tray as ``<name>.png`` (RGB arrays). Returns the path of ``report.md``."""
    text = "\n".join([f"# Dispensing job\n\n{header}\n", recognition_section(areas, failures),
                      mapping_section(areas), path_section(paths), bead_section(beads),
                      f"## Recognition over many boards, repeatability\n\n{PAPER['recognition']}; "
                      f"{PAPER['repeatability']}. Ours: `python bench/bench_locate.py` (docs/dispense-job.md).\n"])

    def write_files(folder: Path) -> None:
        for name, program in (programs or {}).items():
            write_program(folder / f"{name}.csv", program)
        for name, rgb in (images or {}).items():
            if not cv2.imwrite(str(folder / f"{name}.png"), np.ascontiguousarray(rgb[..., ::-1])):
                raise OSError(f"could not write {folder / name}.png")

    return publish_report(out_dir, "Dispensing job", lambda _figures: text, write_files)["markdown"]
