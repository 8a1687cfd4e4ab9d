"""Peak memory of ingest + measure for a campaign and for one four times larger (goal: ratio ≈ 1).

    .venv/bin/python bench/bench_memory.py                    # full-size images, 38 and 152 of them
    .venv/bin/python bench/bench_memory.py --size small       # 768×512 images (quick)
    .venv/bin/python bench/bench_memory.py --dask-workers 2   # image work on a local Dask cluster

Both campaigns are simulated once (the same plan, every stage count times ``--scale``) into
``--work`` and re-used. Each measurement runs ``fivecal``'s measure flow (ingest, detection,
camera self-calibration, poses) in a fresh child process with its own Prefect temporary server,
database and result storage, so that nothing is served from a cache and no earlier run's memory
is counted. Memory is the resident set size (RSS), two ways:

* flow process: the child's own peak RSS (``getrusage`` ru_maxrss, exact). With the default
  runner all image work runs in this process (threads), so this is the number the goal is about.
* process tree: the sum of the RSS of the child and all its descendants (the Prefect server,
  Dask workers), sampled every 20 ms by this process (psutil), and its largest value; pages
  shared between processes are counted once per process.

The ratio is large campaign over base campaign, measured one after the other in this run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tasks.simulation.campaign_plan import CampaignPlan  # noqa: E402

BASE_PLAN = CampaignPlan(calibration_trials=2, images_per_trial=5, sweep_positions=2, sweep_repeats=1,
                         pige_poses=6, validation_poses=2)
SAMPLE_S = 0.02


def scaled_plan(plan: CampaignPlan, scale: int) -> CampaignPlan:
    """``plan`` with every stage's image count multiplied by ``scale`` (so the campaign is scale× larger)."""
    return replace(plan, calibration_trials=plan.calibration_trials * scale,
                   sweep_positions=plan.sweep_positions * scale, pige_poses=plan.pige_poses * scale,
                   validation_poses=plan.validation_poses * scale)


def bench_campaign(work: Path, name: str, plan: CampaignPlan, size: str, seed: int = 7) -> Path:
    """A simulated campaign ``work/name`` of ``plan`` at ``size``, written once and re-used while its
    truth.json records the same plan, size and seed."""
    from tasks.simulation.simulate import write_campaign

    folder = work / name
    truth = folder / "truth" / "truth.json"
    if truth.is_file():
        doc = json.loads(truth.read_text())
        if doc.get("plan") == asdict(plan) and doc.get("size") == size and doc.get("seed") == seed:
            return folder
    staging = work / f".{name}.partial"
    subprocess.run(["rm", "-rf", str(staging), str(folder)], check=True)
    t0 = time.perf_counter()
    write_campaign(staging, name, seed=seed, size=size, plan=plan)
    staging.rename(folder)
    print(f"  simulated {folder} in {time.perf_counter() - t0:.0f} s")
    return folder


def child_env(scratch: Path) -> dict[str, str]:
    """Environment of a child run: its own Prefect home (database), result storage, no telemetry."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(PREFECT_HOME=str(scratch / "prefect-home"), PREFECT_LOCAL_STORAGE_PATH=str(scratch / "storage"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="WARNING",
               PYTHONPATH=str(ROOT) + os.pathsep + env.get("PYTHONPATH", ""))
    return env


def tree_rss(proc: psutil.Process) -> dict[str, int]:
    """RSS in bytes of ``proc`` and each descendant, by role (flow / prefect-server / dask / other)."""
    out = {"flow": 0, "prefect-server": 0, "dask": 0, "other": 0}
    for i, p in enumerate([proc, *proc.children(recursive=True)]):
        try:
            rss = p.memory_info().rss
            cmd = " ".join(p.cmdline())
        except psutil.Error:
            continue
        role = ("flow" if i == 0 else "prefect-server" if "uvicorn" in cmd or ("prefect" in cmd and "server" in cmd)
                else "dask" if "multiprocessing" in cmd else "other")
        out[role] += rss
    return out


def measure_peak(campaign: Path, dask_workers: int | None) -> dict:
    """Run ingest + measure on ``campaign`` in a child process; its peaks (bytes) and wall time (s)."""
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        scratch = Path(tmp)
        cmd = [sys.executable, __file__, "--child", str(campaign), str(scratch / "results")]
        if dask_workers:
            cmd += ["--dask-workers", str(dask_workers)]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=child_env(scratch), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        ps = psutil.Process(proc.pid)
        peak, at_peak = 0, {}
        while proc.poll() is None:
            sample = tree_rss(ps)
            if sum(sample.values()) > peak:
                peak, at_peak = sum(sample.values()), sample
            time.sleep(SAMPLE_S)
        out, err = proc.communicate()
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"child run on {campaign} failed ({proc.returncode}):\n{err[-3000:]}")
    child = json.loads(out.strip().splitlines()[-1])
    return {**child, "tree_peak": peak, "tree_at_peak": at_peak, "wall_s": wall}


def run_child(campaign: str, results: str, dask_workers: int | None) -> None:
    """In the child: measure the campaign and print one JSON line with the flow process's peak RSS."""
    import resource

    from flows.measure import run_measure

    summary = run_measure(campaign, results, dask_workers=dask_workers)
    assert summary["cached"]["detect"] == 0, "detection was served from a cache: the run measured nothing"
    print(json.dumps({"n_images": summary["n_images"], "n_detected": summary["n_detected"],
                      "n_poses": summary["n_poses"],
                      "flow_peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", choices=("full", "small"), default="full", help="image size of both campaigns")
    ap.add_argument("--scale", type=int, default=4, help="how many times larger the second campaign is")
    ap.add_argument("--dask-workers", type=int, default=None, help="run the image work on a local Dask cluster")
    ap.add_argument("--work", type=Path, default=ROOT / "data" / "bench", help="where the campaigns are kept")
    ap.add_argument("--child", nargs=2, metavar=("CAMPAIGN", "RESULTS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        run_child(*args.child, args.dask_workers)
        return

    args.work.mkdir(parents=True, exist_ok=True)
    runner = f"local Dask cluster of {args.dask_workers} workers" if args.dask_workers else "threads (default runner)"
    print(f"ingest + measure, {args.size}-size images, image work on {runner}; {os.cpu_count()} cores, "
          f"shared with other work (memory is little affected by load, the wall times are)")
    base = bench_campaign(args.work, f"mem-{args.size}-x1", BASE_PLAN, args.size)
    large = bench_campaign(args.work, f"mem-{args.size}-x{args.scale}", scaled_plan(BASE_PLAN, args.scale), args.size)
    rows = [(base, measure_peak(base, args.dask_workers)), (large, measure_peak(large, args.dask_workers))]
    mib = 2.0 ** 20
    print(f"{'campaign':16s} {'images':>6s} {'grids':>6s} {'poses':>6s} {'wall s':>7s} {'flow peak MiB':>14s} "
          f"{'tree peak MiB':>14s}   tree at its peak (MiB)")
    for folder, r in rows:
        parts = ", ".join(f"{k} {v / mib:.0f}" for k, v in r["tree_at_peak"].items() if v)
        print(f"{folder.name:16s} {r['n_images']:6d} {r['n_detected']:6d} {r['n_poses']:6d} {r['wall_s']:7.1f} "
              f"{r['flow_peak'] / mib:14.0f} {r['tree_peak'] / mib:14.0f}   {parts}")
    (_, a), (_, b) = rows
    print(f"ratio {args.scale}x campaign / base: images {b['n_images'] / a['n_images']:.2f}, "
          f"flow-process peak RSS {b['flow_peak'] / a['flow_peak']:.3f}, process-tree peak RSS "
          f"{b['tree_peak'] / a['tree_peak']:.3f}  (goal ≈ 1)")


if __name__ == "__main__":
    main()
