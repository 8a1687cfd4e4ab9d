"""Ingest and dot-detection throughput on a local Dask cluster of 1 and of 2 workers (ratio 2 vs 1).

    .venv/bin/python bench/bench_dask_ingest.py                 # 153 full-size images, chunks of 8
    .venv/bin/python bench/bench_dask_ingest.py --size small    # 768×512 images (quick)

The campaign is the larger one of ``bench/bench_memory.py`` (simulated once into ``--work``).
In this process, one after the other, with one Prefect temporary server and a fresh, empty
Prefect result storage for every run (so that every image is checked and every grid detected
afresh; the bench checks that nothing came from the cache):

* the ingest flow (read, hash and decode every image; write the images table), then
* detection: every detection chunk of measure (``tasks.steps.vision.detect_chunk``, RRHT) in a
  small flow of this bench, on the ingested images,

each on: a local Dask cluster of 1 worker process, one of 2 worker processes (one thread each;
``flows.runners.local_dask_cluster``, the cluster of ``--dask-workers``),
and, for reference, the default runner (threads of this process). Both clusters are started and
their workers have run a warm-up ingest and detection of a small campaign before the clock starts
(start-up and warm-up are printed apart; the Prefect temporary server starts in the first
warm-up). The runners then take turns, ``--repeats`` rounds, and each keeps its best time, so that
a burst of other work on the machine slows one round rather than one runner.
Throughput is images per second of flow wall time. The ratio is 2 workers over 1 worker. The CPU
time per image (this process, the workers and the Prefect server, best round) shows what the
work costs whatever the load: if it is the same for 1 and 2 workers, a ratio below 2 means that
the second core was busy with other work, not that the work does not spread.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_memory import BASE_PLAN, bench_campaign, scaled_plan  # noqa: E402


def detection_flow():
    """A flow that detects the dots of every ingested image of a campaign, chunk by chunk, as measure does."""
    from prefect import flow

    from tasks.campaign.ingest import load_campaign_metadata
    from tasks.lake.store import read_table
    from tasks.steps.vision import detect_chunk
    from tasks.vision.pipeline import campaign_plates, detection_chunks, with_detection_inputs

    @flow(name="bench-detect")
    def detect_all(campaign: str, results_root: str, chunk_size: int) -> dict:
        metadata = load_campaign_metadata(campaign)
        images = with_detection_inputs(metadata, read_table("images", Path(results_root), metadata["campaign_id"]))
        plates = campaign_plates(metadata)
        futures = [detect_chunk.submit(Path(campaign), rows, plates, "rrht")
                   for rows in detection_chunks(images, chunk_size)]
        found = sum(int((f.result()[1]["detection_status"] == "ok").sum()) for f in futures)
        return {"n_detected": found, "cached": sum(f.state.name == "Cached" for f in futures)}

    return detect_all


def cpu_seconds() -> float:
    """CPU time (user + system, s) used so far by this process and its live descendants (workers, server)."""
    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.Error:
            continue
        total += t.user + t.system
    return total


def timed_runs(campaign: Path, runner, chunk_size: int, scratch: Path) -> dict[str, float]:
    """Ingest then detection with ``runner`` and an empty result storage: wall and CPU times (s), counts."""
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings

    from flows.ingest import ingest_campaign

    scratch.mkdir(parents=True)
    results = scratch / "results"
    with temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: scratch / "storage"}):
        c0, t0 = cpu_seconds(), time.perf_counter()
        ingest = ingest_campaign.with_options(task_runner=runner)(str(campaign), str(results), chunk_size=chunk_size)
        c1, t1 = cpu_seconds(), time.perf_counter()
        detect = detection_flow().with_options(task_runner=runner)(str(campaign), str(results), chunk_size)
        c2, t2 = cpu_seconds(), time.perf_counter()
    if ingest["chunks_cached"] or detect["cached"]:
        raise RuntimeError("a run was served from Prefect's cache: its time measures nothing")
    return {"ingest_s": t1 - t0, "detect_s": t2 - t1, "ingest_cpu_s": c1 - c0, "detect_cpu_s": c2 - c1,
            "n_images": ingest["n_images"], "n_ok": ingest["n_ok"], "n_detected": detect["n_detected"]}


def start_cluster(stack: contextlib.ExitStack, n_workers: int, warm_up: Path, scratch: Path):
    """A local Dask cluster of ``n_workers`` processes (one thread each), warmed up, and its start-up time (s).

    Warm-up: one untimed run on the small campaign ``warm_up`` in chunks of 2, so that every worker
    has imported the tasks and run a first Prefect task (a first task in a new process takes ~4 s).
    """
    from flows.runners import image_task_runner, local_dask_cluster

    t0 = time.perf_counter()
    cluster = stack.enter_context(local_dask_cluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                                     dashboard_address=None, silence_logs=40))
    runner = image_task_runner(dask_address=cluster.scheduler_address)
    timed_runs(warm_up, runner, 2, scratch)
    return runner, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", choices=("full", "small"), default="full", help="image size of the campaign")
    ap.add_argument("--scale", type=int, default=4, help="campaign size, in bench_memory's base campaigns")
    ap.add_argument("--chunk-size", type=int, default=8, help="images per task (ingest and detection)")
    ap.add_argument("--repeats", type=int, default=2, help="interleaved runs per runner; the best is kept")
    ap.add_argument("--work", type=Path, default=ROOT / "data" / "bench", help="where the campaign is kept")
    args = ap.parse_args()

    # one Prefect temporary server for this process, with its own database; quiet logs
    scratch = Path(tempfile.mkdtemp(prefix="bench-dask-"))
    os.environ.update(PREFECT_HOME=str(scratch / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
                      PREFECT_LOGGING_LEVEL="WARNING")
    from prefect.task_runners import ThreadPoolTaskRunner

    from flows.runners import LOCAL_THREADS

    args.work.mkdir(parents=True, exist_ok=True)
    campaign = bench_campaign(args.work, f"mem-{args.size}-x{args.scale}", scaled_plan(BASE_PLAN, args.scale),
                              args.size)
    warm_up = bench_campaign(args.work, "mem-small-x1", BASE_PLAN, "small")
    print(f"{campaign.name}: {args.size}-size images, chunks of {args.chunk_size}, best of {args.repeats} "
          f"interleaved runs; {os.cpu_count()} cores shared with other work (load average "
          f"{os.getloadavg()[0]:.1f}): the times are noisy")
    with contextlib.ExitStack() as stack:
        runners = {name: start_cluster(stack, n, warm_up, scratch / f"warm-up-{n}")
                   for name, n in (("dask 1 worker", 1), ("dask 2 workers", 2))}
        runners[f"threads ({LOCAL_THREADS})"] = (ThreadPoolTaskRunner(max_workers=LOCAL_THREADS), None)
        runs: dict[str, list[dict]] = {name: [] for name in runners}
        for i in range(args.repeats):
            for name, (runner, _) in runners.items():
                runs[name].append(timed_runs(campaign, runner, args.chunk_size, scratch / f"{name}-{i}"))
    timed = ("ingest_s", "detect_s", "ingest_cpu_s", "detect_cpu_s")
    best = {name: {**rs[0], **{k: min(r[k] for r in rs) for k in timed}} for name, rs in runs.items()}
    print(f"{'runner':16s} {'images':>6s} {'ingest s':>9s} {'ingest img/s':>13s} {'detect s':>9s} "
          f"{'detect img/s':>13s}   CPU ms/image ingest, detect {'start+warm-up s':>16s}")
    for name, r in best.items():
        startup = runners[name][1]
        start = f"{startup:16.1f}" if startup is not None else f"{'-':>16s}"
        print(f"{name:16s} {r['n_images']:6d} {r['ingest_s']:9.1f} {r['n_images'] / r['ingest_s']:13.2f} "
              f"{r['detect_s']:9.1f} {r['n_detected'] / r['detect_s']:13.2f}   "
              f"{1e3 * r['ingest_cpu_s'] / r['n_images']:12.0f} {1e3 * r['detect_cpu_s'] / r['n_images']:14.0f} "
              f"{start}")
    one, two = best["dask 1 worker"], best["dask 2 workers"]
    print(f"throughput ratio, 2 workers / 1 worker: ingest {one['ingest_s'] / two['ingest_s']:.2f}x, "
          f"detection {one['detect_s'] / two['detect_s']:.2f}x  (ideal on {os.cpu_count()} idle cores: 2x)")


if __name__ == "__main__":
    main()
