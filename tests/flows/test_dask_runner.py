"""Image work on Dask (flows/runners.py) gives the same results as the default thread runner.

The claims: the runner choice is what the options ask for (and refuses to guess between an
existing and a local cluster); every task that the image flows submit pickles (Dask ships it to
worker processes); and ingest + measure of one campaign on two Dask worker processes write
images, dots, camera_calibration and poses tables identical, value for value, to the default
runner's, with every image checked and every grid detected afresh (nothing from a cache) and the
work spread over both workers.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys

import cloudpickle
import pandas as pd
import pytest
from prefect.task_runners import ThreadPoolTaskRunner

from flows.runners import LOCAL_THREADS, image_task_runner, local_dask_cluster
from tasks.simulation.campaign_plan import CampaignPlan

# enough calibration views for intrinsics (so that poses are estimated), 41 images
PLAN = CampaignPlan(calibration_trials=2, images_per_trial=5, sweep_positions=2, sweep_repeats=1, pige_poses=3,
                    validation_poses=1)
MEASURE_TABLES = ("images", "dots", "camera_calibration", "poses")


def test_default_runner_is_threads_of_this_process():
    runner = image_task_runner()
    assert isinstance(runner, ThreadPoolTaskRunner) and runner._max_workers == LOCAL_THREADS


def test_address_connects_to_an_existing_cluster_and_workers_start_a_local_one():
    from prefect_dask import DaskTaskRunner

    existing = image_task_runner(dask_address="tcp://127.0.0.1:8786")
    assert isinstance(existing, DaskTaskRunner) and existing.address == "tcp://127.0.0.1:8786"
    assert existing._cluster is None and not existing.cluster_kwargs  # nothing started for an existing cluster
    local = image_task_runner(dask_workers=3)
    assert isinstance(local, DaskTaskRunner) and local.address is None
    assert local.cluster_kwargs["n_workers"] == 3 and local.cluster_kwargs["processes"]
    assert local.cluster_kwargs["threads_per_worker"] == 1 and local.cluster_class is local_dask_cluster


@pytest.mark.parametrize(("address", "workers", "message"), [
    ("tcp://127.0.0.1:8786", 2, "not both"),
    (None, 0, "at least 1"),
])
def test_contradictory_or_empty_requests_are_refused(address, workers, message):
    with pytest.raises(ValueError, match=message):
        image_task_runner(address, workers)


def test_every_submitted_task_pickles():
    """Dask sends each task object (with its cache-key function) to a worker process."""
    from tasks.steps.ingest import check_image_chunk
    from tasks.steps.simulation import render_images
    from tasks.steps.vision import calibrate, detect_chunk, poses

    for task in (check_image_chunk, detect_chunk, calibrate, poses, render_images):
        copy = pickle.loads(cloudpickle.dumps(task))
        assert copy.name == task.name and copy.cache_key_fn is task.cache_key_fn


def read_tables(root, campaign_id: str) -> dict[str, pd.DataFrame]:
    from tasks.lake.store import read_table

    out = {}
    for name in MEASURE_TABLES:
        df = read_table(name, root, campaign_id)
        keys = [c for c in ("image_id", "trial", "camera", "row", "col") if c in df.columns]
        out[name] = df.sort_values(keys, kind="stable").reset_index(drop=True)
    return out


@pytest.mark.flow
def test_measure_on_two_dask_workers_gives_identical_tables(prefect_harness, tmp_path):
    from distributed import Client, get_task_stream
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings

    from flows.measure import measure_campaign
    from tasks.simulation.simulate import write_campaign

    folder = write_campaign(tmp_path / "dask", "dask", seed=11, size="small", plan=PLAN)
    chunk_size = 6  # 7 detection chunks, so that both workers get some
    # a result storage of its own per run: the cache keys hash image contents, not the results root,
    # so a shared storage would serve the second run from the first's cache
    with temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: tmp_path / "storage-threads"}):
        threads = measure_campaign(str(folder), str(tmp_path / "threads"), chunk_size=chunk_size)
    storage = tmp_path / "storage-dask"
    with (local_dask_cluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
          Client(cluster) as client, get_task_stream(client) as stream,
          temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: storage})):
        runner = image_task_runner(dask_address=cluster.scheduler_address)
        dask = measure_campaign.with_options(task_runner=runner)(str(folder), str(tmp_path / "dask-results"),
                                                                 chunk_size=chunk_size)

    n = len(pd.read_csv(folder / "manifest.csv"))
    for summary in (threads, dask):
        assert summary["cached"] == {"detect": 0, "calibrate": 0, "poses": 0}
        assert summary["n_detected"] == n and summary["n_poses"] == n
    assert any(storage.iterdir())  # the workers persisted their results where this run told them
    workers = {t["worker"] for t in stream.data}
    assert len(workers) == 2, f"the image work ran on {workers}"

    expected, got = read_tables(tmp_path / "threads", "dask"), read_tables(tmp_path / "dask-results", "dask")
    for name in MEASURE_TABLES:
        assert len(expected[name]) > 0, name
        pd.testing.assert_frame_equal(got[name], expected[name], check_exact=True, obj=name)


@pytest.mark.flow
def test_fivecal_ingest_on_a_local_cluster_uses_one_prefect_server(prefect_harness, campaign_copy, tmp_path):
    """``fivecal ingest --dask-workers 2`` with Prefect's temporary server, as a user runs it: the
    command starts the cluster, its workers record their task runs on the command's temporary
    server (none starts one of its own), and the images table equals the thread runner's."""
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings

    from flows.ingest import run_ingest
    from tasks.lake.store import read_table

    campaign = campaign_copy("dasklocal")
    with temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: tmp_path / "storage-threads"}):
        threads = run_ingest(campaign, tmp_path / "threads")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"), PREFECT_LOCAL_STORAGE_PATH=str(tmp_path / "storage-dask"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false")
    run = subprocess.run([sys.executable, "-m", "fivecal.cli", "ingest", str(campaign), "--results",
                          str(tmp_path / "dask"), "--dask-workers", "2"], env=env, capture_output=True, text=True,
                         timeout=300)
    log = run.stdout + run.stderr
    assert run.returncode == 0, log[-3000:]
    assert log.count("Starting temporary server") == 1, log[-3000:]
    assert f"{threads['n_ok']} ok, 0 faults" in run.stdout and threads["chunks_cached"] == 0
    pd.testing.assert_frame_equal(read_table("images", tmp_path / "dask"), read_table("images", tmp_path / "threads"),
                                  check_exact=True)
