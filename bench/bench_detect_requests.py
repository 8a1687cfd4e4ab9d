"""Benchmark: ``fivecal detect`` on files as users write them, and asked for the plate right and wrong.

    .venv/bin/python bench/bench_detect_requests.py --files 12,12,6 --seed 500   # garden draws through the CLI
    .venv/bin/python bench/bench_detect_requests.py --plates 150 --seed 402 [--fisheye]   # wrong plates asked

``--files D,F,P``: D distant, F fisheye and P phone garden photographs
(:func:`tasks.simulation.garden_stress.random_garden_case`, seed ``--seed``), each written to disk as a grey PNG,
a colour JPEG, a 16-bit PNG (full range, and 12-bit data with an offset), a BGRA PNG, turned by a quarter
turn, and as a JPEG stored turned with EXIF orientation 6 (the CLI reads the stored pixels); and the grey PNG
asked for with the other polarity, inverted, as 3 × 4, as plates it does not hold (3 × 3, 2 × 3, 4 × 2, 4 × 4,
5 × 3), with the diameter or the pitch wrong (2 or 5 mm, 12 mm) and with another row pitch (9, 4.5 mm). Each
through ``fivecal detect … --json`` (typer's CliRunner, in process). Verdict: found when every dot lies within
a quarter of the dot size of the true centre its label names under a turn of the grid that keeps its
handedness (a half turn; a quarter turn for 3 × 4), refused, or WRONG (anything labelled of a plate the image
does not hold, a mirrored labelling, a dot off).

``--plates N``: N random stress draws (:func:`tasks.simulation.detector_stress.random_case`, with
``--fisheye`` :func:`~tasks.simulation.detector_stress.random_fisheye_case`): the sheet printed larger than
asked (5 × 3, 4 × 4 or 5 × 4, asked for as 4 × 3) and the 4 × 3 sheet asked for as 3 × 3, 2 × 3, 4 × 2 and
3 × 2; any grid labelled is wrong.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from typer.testing import CliRunner

from fivecal.cli import app
from tasks.simulation.detector_stress import ISSUE_PLATE, random_case, random_fisheye_case, render_stress_case
from tasks.simulation.garden_stress import random_garden_case, render_garden_case
from tasks.simulation.render import plate_in_view
from tasks.vision.detection import detect_grid


def turned(truth_grid: np.ndarray, width: int) -> np.ndarray:
    """Truth (rows, cols, 2) px of an image of ``width`` px turned a quarter counter-clockwise (np.rot90)."""
    return np.stack([truth_grid[..., 1], width - 1 - truth_grid[..., 0]], axis=-1)


def cli_verdict(out: dict, truth_grid: np.ndarray | None, rows: int, cols: int, dot_px: float) -> str:
    """found / refused / WRONG of one ``fivecal detect --json`` answer (module docstring)."""
    if not out.get("ok"):
        return "refused"
    if truth_grid is None:
        return "WRONG"
    g = np.array([[d["u_px"], d["v_px"]] for d in out["dots"]]).reshape(rows, cols, 2)
    turns = (0, 2) if g.shape == truth_grid.shape else (1, 3)
    worst = min(np.linalg.norm(np.rot90(g, k, axes=(0, 1)) - truth_grid, axis=2).max() for k in turns)
    return "found" if worst < 0.25 * dot_px else "WRONG"


def files_run(counts: tuple[int, int, int], seed: int) -> None:
    runner = CliRunner()
    tally: dict[str, dict[str, int]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for regime, n in zip(("distant", "fisheye", "phone"), counts, strict=True):
            rng, tints = np.random.default_rng(seed), np.random.default_rng(seed + 1)
            for i in range(n):
                case = random_garden_case(rng, f"{regime}-{i}", regime)
                if case is None:
                    continue
                img, truth = render_garden_case(case)
                dark, dot, w = case.geometry.dark_dots, case.geometry.dot_px, img.shape[1]
                tg = truth.reshape(4, 3, 2)
                base = Path(tmp) / case.name
                tint = np.array([tints.uniform(0.7, 1.0), 1.0, tints.uniform(0.8, 1.2)])
                bgr = np.clip(img[..., None] * tint / (tint @ [0.114, 0.587, 0.299]), 0, 255).astype(np.uint8)
                forms = {"png": img, "colour.jpg": bgr, "16bit.png": img.astype(np.uint16) * 257,
                         "12bit.png": img.astype(np.uint16) * 16 + 100,
                         "bgra.png": cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA),
                         "turned.png": np.ascontiguousarray(np.rot90(img))}
                files = {}
                for form, data in forms.items():
                    path = f"{base}.{form}"
                    cv2.imwrite(path, data)
                    files[form] = (path, turned(tg, w) if form == "turned.png" else tg)
                exif = Image.Exif()
                exif[0x0112] = 6
                Image.fromarray(np.ascontiguousarray(np.rot90(img))).save(f"{base}.exif6.jpg", quality=90, exif=exif)
                files["exif6.jpg (stored pixels)"] = (f"{base}.exif6.jpg", turned(tg, w))
                cv2.imwrite(f"{base}.inverted.png", 255 - img)
                own = [] if dark else ["--light-dots"]
                plate = ["--pitch-mm", "6", "--diameter-mm", "4"]
                runs = [(form, path, ["--rows", "4", "--cols", "3", *plate, *own], t, 4, 3)
                        for form, (path, t) in files.items()]
                png = files["png"][0]
                runs += [("other polarity", png, ["--rows", "4", "--cols", "3", *plate,
                                                  *([] if own else ["--light-dots"])], tg, 4, 3),
                         ("inverted", f"{base}.inverted.png", ["--rows", "4", "--cols", "3", *plate, *own], tg, 4, 3),
                         ("as 3x4", png, ["--rows", "3", "--cols", "4", *plate, *own], tg, 3, 4)]
                runs += [(f"as {r}x{c}", png, ["--rows", str(r), "--cols", str(c), *plate, *own], None, r, c)
                         for r, c in ((3, 3), (2, 3), (4, 2), (4, 4), (5, 3))]
                runs += [(f"{what}", png, ["--rows", "4", "--cols", "3", *args, *own], tg, 4, 3) for what, args in (
                    ("diameter 2 mm", ["--pitch-mm", "6", "--diameter-mm", "2"]),
                    ("diameter 5 mm", ["--pitch-mm", "6", "--diameter-mm", "5"]),
                    ("pitch 12 mm", ["--pitch-mm", "12", "--diameter-mm", "4"]),
                    ("row pitch 9 mm", [*plate, "--row-pitch-mm", "9"]),
                    ("row pitch 4.5 mm", [*plate, "--row-pitch-mm", "4.5"]))]
                for what, path, args, t, r, c in runs:
                    res = runner.invoke(app, ["detect", path, *args, "--json"])
                    out = json.loads(res.stdout) if res.stdout.lstrip().startswith("{") else {"ok": False}
                    v = cli_verdict(out, t, r, c, dot)
                    tally.setdefault(what, {"found": 0, "refused": 0, "WRONG": 0})[v] += 1
                    if v == "WRONG":
                        print(f"WRONG: {case.name} {what}", flush=True)
    print(f"\nfivecal detect on garden draws (seed {seed}: {counts[0]} distant, {counts[1]} fisheye, "
          f"{counts[2]} phone)")
    for what, t in tally.items():
        print(f"{what:28s} found {t['found']:3d}  refused {t['refused']:3d}  WRONG {t['WRONG']:3d}")


def plates_run(n: int, seed: int, fisheye: bool) -> None:
    rng = np.random.default_rng(seed)
    tally: dict[str, dict[str, int]] = {}

    def count(what: str, ok: bool, name: str) -> None:
        tally.setdefault(what, {"refused": 0, "WRONG": 0})["WRONG" if ok else "refused"] += 1
        if ok:
            print(f"WRONG: {name} {what}", flush=True)

    for i in range(n):
        case = (random_fisheye_case if fisheye else random_case)(rng, f"random-{i}")
        if case is None:
            continue
        asked = replace(ISSUE_PLATE, dark_dots=case.dark_dots)
        printed = [(5, 3), (4, 4), (5, 4)][i % 3]
        big = replace(case, plate=replace(ISSUE_PLATE, rows=printed[0], cols=printed[1]))
        if plate_in_view(big.camera(), replace(big.plate, dark_dots=big.dark_dots), big.pose(), border_px=1.0):
            image, _ = render_stress_case(big)
            count(f"{printed[0]}x{printed[1]} printed, 4x3 asked", detect_grid(image, asked, "rrht").ok, case.name)
        image, _ = render_stress_case(case)
        for r, c in ((3, 3), (2, 3), (4, 2), (3, 2)):
            count(f"4x3 printed, {r}x{c} asked", detect_grid(image, replace(asked, rows=r, cols=c), "rrht").ok,
                  case.name)
    print(f"\nwrong plates asked of {n} {'random fisheye' if fisheye else 'random'} draws (seed {seed})")
    for what, t in tally.items():
        print(f"{what:28s} refused {t['refused']:4d}  WRONG {t['WRONG']:3d}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", help="garden draws per regime: distant,fisheye,phone")
    ap.add_argument("--plates", type=int, default=0, help="random draws asked for the wrong plate")
    ap.add_argument("--fisheye", action="store_true", help="with --plates: random fisheye draws")
    ap.add_argument("--seed", type=int, default=500)
    args = ap.parse_args()
    if args.files:
        files_run(tuple(int(x) for x in args.files.split(",")), args.seed)
    if args.plates:
        plates_run(args.plates, args.seed, args.fisheye)


if __name__ == "__main__":
    main()
