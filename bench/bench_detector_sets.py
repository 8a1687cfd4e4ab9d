"""Benchmark: every own image set with every detector, in one process on the same images; a markdown summary.

    .venv/bin/python bench/bench_detector_sets.py [PHOTO_DIR ...] [--quick] [--set NAME]... [--out summary.md]

Sets (``--set`` selects by name prefix, repeatable; ``--list`` prints them):

* ``stress``: the named stress cases (tasks.simulation.detector_stress.STRESS_CASES), 3 seeds each;
* ``random``: ``bench_stress.py --random 150`` (seed 0), the draws with every dot in view;
* ``random-fisheye``: ``bench_stress.py --random 80 --fisheye`` (seed 0);
* ``garden-REGIME-SEED``: garden photographs (tasks.simulation.garden_stress), phone / fisheye / distant,
  development seed 100 and held-out seed 200 (counts below);
* ``photos-NAME``: each PHOTO_DIR written by bench/real_photo_truth.py (absent folders are listed as
  skipped). Their truth is the rim ellipse of each dot, a hand fit: the centre error is taken against
  the rim ellipse of the image as delivered (``rim_in_image_px``), and RRHT's ellipse centres
  (``rrht ellipse``, what ``fivecal detect`` prints) are scored beside its corrected centres.

Each image is rendered or read once and handed to every detector in turn (bench_stress.run:
rrht, blob, hough, cv2.findCirclesGrid with and without CALIB_CB_CLUSTERING), one call each; RRHT's
wall time is kept (after one untimed warm-up call). Scoring is bench_stress.score: RRHT found when
every dot lies within a quarter of the dot size of the true centre its label names, up to the grid's
symmetry, else wrong; the others found when one-to-one within a quarter of the dot size. Per set and
detector: found / refused / wrong and the median over the found images of the per-image median centre
error (px); RRHT's time median / worst (ms). Per-image lines go to stdout, the table to stdout and
``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_real_photos import photographs, regime
from bench_stress import random_images, run, score, stress_images

from tasks.machine.plate import DotPlate
from tasks.simulation.detector_stress import STRESS_CASES
from tasks.vision.detection import detect_grid

DETECTORS = ("rrht", "rrht ellipse", "blob", "hough", "cv2", "cv2+clustering")
HEADERS = {"rrht": "rrht", "rrht ellipse": "rrht ellipse centres", "blob": "blob (our findCirclesGrid)",
           "hough": "hough", "cv2": "cv2.findCirclesGrid", "cv2+clustering": "findCirclesGrid + clustering"}

OLDER_TRUTH = ("written before bench/real_photo_truth.py recorded `rim_in_image_px`: errors against `truth_px` "
               "(through the lens, the rim centre mapped through it, not the hand fit of the distorted dot)")

GARDEN_COUNTS = {"phone": (10, 2), "fisheye": (40, 10), "distant": (40, 10)}
"""Draws per garden regime and seed: (full run, ``--quick``)."""


@dataclass
class Image:
    """One image of a set: grey pixels, the plate asked for, the truth px (rows*cols, 2) that decides
    found / wrong, the truth the centre error is measured against, the dot size px."""

    name: str
    image: np.ndarray
    plate: DotPlate
    truth: np.ndarray
    error_truth: np.ndarray
    dot_px: float


@dataclass
class ImageSet:
    """A named set: how to make its images, whether its truth is a hand-fit rim ellipse."""

    name: str
    what: str
    images: Callable[[], Iterable[Image]]
    hand_fit: bool = False
    missing: str = ""
    note: str = ""


def stress_set(seeds: int) -> Iterator[Image]:
    for c, image, truth, plate in stress_images(STRESS_CASES, seeds):
        yield Image(f"{c.name} s{c.seed}", image, plate, truth, truth, c.dot_px)


def random_set(n: int, seed: int, fisheye: bool = False, garden: str | None = None) -> Iterator[Image]:
    for geometry, image, truth, plate, _ in random_images(n, seed, fisheye, garden):
        yield Image(geometry.name, image, plate, truth, truth, geometry.dot_px)


def photo_set(folder: Path) -> Iterator[Image]:
    for jpath, image, plate, truth, dot_px, others in photographs(folder):
        yield Image(jpath.stem, image, plate, truth, others["image rim"], dot_px)


def image_sets(photo_dirs: list[Path], quick: bool) -> list[ImageSet]:
    """Every set in the order of the table; ``quick``: fewer seeds and draws."""
    sets = [ImageSet("stress", f"named stress cases × {1 if quick else 3} seeds",
                     lambda: stress_set(1 if quick else 3)),
            ImageSet("random", f"--random {40 if quick else 150}, seed 0", lambda: random_set(40 if quick else 150, 0)),
            ImageSet("random-fisheye", f"--random {20 if quick else 80} --fisheye, seed 0",
                     lambda: random_set(20 if quick else 80, 0, fisheye=True))]
    for seed, kind in ((100, "development"), (200, "held out")):
        for regime_name, counts in GARDEN_COUNTS.items():
            n = counts[1] if quick else counts[0]
            sets.append(ImageSet(f"garden-{regime_name}-{seed}",
                                 f"garden {regime_name}, {kind}, {n} draws of seed {seed}",
                                 lambda n=n, seed=seed, r=regime_name: random_set(n, seed, garden=r)))
    for folder in photo_dirs:
        missing = "" if folder.is_dir() and any(folder.glob("*.json")) else f"{folder} absent or empty: skipped"
        older = not missing and any("rim_in_image_px" not in json.loads(j.read_text()) for j in folder.glob("*.json"))
        sets.append(ImageSet(f"photos-{folder.name}", f"photographs {folder}", lambda f=folder: photo_set(f),
                             hand_fit=True, missing=missing, note=OLDER_TRUTH if older else ""))
    return sets


def detect_all(item: Image, detectors: tuple[str, ...]) -> tuple[dict[str, np.ndarray | None], float, str]:
    """Every detector's centres on one image (None: refused), RRHT's wall time (s) and its reason."""
    t0 = time.perf_counter()
    det = detect_grid(item.image, item.plate, "rrht")
    seconds = time.perf_counter() - t0
    rrht = {"rrht": det.centres if det.ok else None, "rrht ellipse": det.ellipse_centres if det.ok else None}
    out = {d: rrht[d] if d in rrht else run(d, item.image, item.plate) for d in detectors}
    return out, seconds, "" if det.ok else det.reason


def score_image(item: Image, centres: dict[str, np.ndarray | None]) -> dict[str, tuple[str, float | None]]:
    """Per detector: (verdict, the image's median centre error px against ``error_truth`` when found)."""
    scored = {}
    for d, c in centres.items():
        verdict, e = score(d, c, item.plate, item.truth, item.dot_px)
        if verdict == "found" and item.error_truth is not item.truth:
            e = score(d, c, item.plate, item.error_truth, item.dot_px)[1]
        scored[d] = (verdict, float(np.median(e)) if e is not None else None)
    return scored


def summarise(rows: list[dict[str, tuple[str, float | None]]], detectors: tuple[str, ...]) -> dict[str, str]:
    """Per detector the table cell "found / refused / wrong, median px" of one set's scored images."""
    cells = {}
    for d in detectors:
        n = {v: sum(r[d][0] == v for r in rows) for v in ("found", "refused", "wrong")}
        errs = [r[d][1] for r in rows if r[d][0] == "found" and r[d][1] is not None]
        med = f", {statistics.median(errs):.3f}" if errs else ""
        cells[d] = f"{n['found']} / {n['refused']} / {n['wrong']}{med}"
    return cells


def table(results: list[tuple[ImageSet, int, dict[str, str] | None, list[float]]]) -> str:
    """The markdown table: one row per set, one column per detector, RRHT's time last."""
    head = "| Set (images) | " + " | ".join(HEADERS[d] for d in DETECTORS) + " | rrht time median / worst (ms) |"
    lines = [head, "|" + "---|" * (len(DETECTORS) + 2)]
    for s, n, cells, times in results:
        if cells is None:
            lines.append(f"| {s.name}: {s.missing} |" + " |" * (len(DETECTORS) + 1))
            continue
        row = [cells.get(d, "–") if (d != "rrht ellipse" or s.hand_fit) else "–" for d in DETECTORS]
        t = f"{1e3 * statistics.median(times):.0f} / {1e3 * max(times):.0f}" if times else "–"
        lines.append(f"| {s.name} ({n}){' †' if s.note else ''} | " + " | ".join(row) + f" | {t} |")
    notes = sorted({s.note for s, *_ in results if s.note})
    return "\n".join(lines + [""] + [f"† {note}" for note in notes] if notes else lines)


def run_sets(sets: list[ImageSet]) -> list[tuple[ImageSet, int, dict[str, str] | None, list[float]]]:
    """Run every detector on every image of each set (printing a line per image); the table's rows. A set
    of photographs also gets one row per regime of the hidden set its names imitate."""
    results, warm = [], False
    for s in sets:
        if s.missing:
            print(f"{s.name}: {s.missing}", flush=True)
            results.append((s, 0, None, []))
            continue
        detectors = DETECTORS if s.hand_fit else tuple(d for d in DETECTORS if d != "rrht ellipse")
        rows, times, regimes = [], [], []
        for item in s.images():
            if not warm:  # the compiled kernels' loading and lazy initialisation outside the timings
                detect_all(item, detectors)
                warm = True
            centres, seconds, reason = detect_all(item, detectors)
            scored = score_image(item, centres)
            rows.append(scored)
            times.append(seconds)
            regimes.append(regime(item.name))
            print(f"{s.name:20s} {item.name:44s} {1e3 * seconds:6.0f} ms | "
                  + " | ".join(f"{d} {v[:5]}" + (f" {e:.3f}" if e is not None else "") for d, (v, e) in scored.items())
                  + (f" | rrht: {reason}" if reason else ""), flush=True)
        results.append((s, len(rows), summarise(rows, detectors), times))
        if s.hand_fit and len(set(regimes)) > 1:
            for g in sorted(set(regimes)):
                idx = [i for i, r in enumerate(regimes) if r == g]
                sub = ImageSet(f"{s.name}: {g}", s.what, s.images, hand_fit=True, note=s.note)
                results.append((sub, len(idx), summarise([rows[i] for i in idx], detectors), [times[i] for i in idx]))
    return results


def git_commit() -> str:
    """The checkout's commit (short), or "unknown"."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def provenance(started: float, load_start: tuple[float, ...], commit: str, argv: list[str]) -> str:
    """One line: date, commit at the start, OpenCV, load average at the start and end, wall time, command."""
    return (f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, code {commit}, OpenCV {cv2.__version__} "
            f"({cv2.getNumThreads()} threads), load average {load_start[0]:.1f} → {os.getloadavg()[0]:.1f} on "
            f"{os.cpu_count()} CPUs, run {time.perf_counter() - started:.0f} s: "
            f"`python bench/bench_detector_sets.py {' '.join(argv)}`")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photo_dirs", nargs="*", type=Path, help="folders written by bench/real_photo_truth.py")
    ap.add_argument("--set", action="append", dest="sets",
                    help="only the sets whose name starts with this (repeatable)")
    ap.add_argument("--quick", action="store_true", help="1 seed of the named cases, fewer random and garden draws")
    ap.add_argument("--out", type=Path, help="also write the markdown table here")
    ap.add_argument("--list", action="store_true", help="print the sets and exit")
    args = ap.parse_args()
    sets = [s for s in image_sets(args.photo_dirs, args.quick)
            if not args.sets or any(s.name.startswith(p) for p in args.sets)]
    if args.list:
        print("\n".join(f"{s.name:24s} {s.what}" + (f" ({s.missing})" if s.missing else "") for s in sets))
        return
    started, load_start, commit = time.perf_counter(), os.getloadavg(), git_commit()
    results = run_sets(sets)
    text = (table(results) + "\n\nfound / refused / wrong, median over the found images of the per-image median "
            "centre error (px; photographs: against the rim ellipse of the image as delivered)\n"
            + provenance(started, load_start, commit, sys.argv[1:]) + "\n")
    print("\n" + text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
