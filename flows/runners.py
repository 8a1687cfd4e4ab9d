"""Where the image work runs: the task runner of the image flows (ingest, measure, simulate).

SYNOPSIS::

    from flows.ingest import ingest_campaign
    from flows.runners import image_task_runner

    runner = image_task_runner(dask_workers=2)             # a local Dask cluster of 2 processes
    runner = image_task_runner(dask_address="tcp://sched:8786")  # an existing Dask cluster
    runner = image_task_runner()                           # threads of this process (the default)
    ingest_campaign.with_options(task_runner=runner)("data/campaigns/demo")

The flows themselves run in the calling process (they read the manifest, assemble and write the
tables); only their submitted tasks — image checks, dot detection, camera calibration, poses,
rendering — go to the runner. On Dask each task runs in a worker process, which needs this
package installed and the campaign folder, the results root and Prefect's result storage
(``PREFECT_LOCAL_STORAGE_PATH``) at the same paths as the caller; Prefect's settings (API URL,
storage path) travel with each task (prefect-dask serialises the calling context).

A flow's runner is fixed when it is called, so a subflow that should use its parent's workers is
called as ``subflow.with_options(task_runner=subflow_task_runner())`` (see flows/measure.py).
"""

from __future__ import annotations

import os
import sys

from prefect.context import FlowRunContext
from prefect.task_runners import TaskRunner, ThreadPoolTaskRunner

LOCAL_THREADS = os.cpu_count() or 2  # threads of the default runner


def image_task_runner(dask_address: str | None = None, dask_workers: int | None = None) -> TaskRunner:
    """The task runner for image work.

    dask_address: scheduler address of an existing Dask cluster (e.g. ``tcp://10.0.0.5:8786``);
        the flow connects a client to it and leaves the cluster running afterwards.
    dask_workers: number of worker processes of a local Dask cluster (one thread each) that the
        flow starts when it begins and stops when it ends (a few seconds of start-up).
    Neither: a ThreadPoolTaskRunner of :data:`LOCAL_THREADS` threads in the calling process.
    Raises ValueError when both are given or dask_workers < 1.
    """
    if dask_address and dask_workers is not None:
        raise ValueError("give a Dask scheduler address (existing cluster) or a number of local Dask workers, "
                         "not both")
    if dask_workers is not None and dask_workers < 1:
        raise ValueError(f"the number of local Dask workers must be at least 1 (got {dask_workers})")
    if not dask_address and dask_workers is None:
        return ThreadPoolTaskRunner(max_workers=LOCAL_THREADS)
    from prefect_dask import DaskTaskRunner

    if dask_address:
        return DaskTaskRunner(address=dask_address)
    # processes: detection and decoding hold the GIL in places; one thread per worker process
    # keeps a worker's memory to one image at a time. No dashboard (no port, no bokeh needed).
    return DaskTaskRunner(cluster_class="distributed.LocalCluster",
                          cluster_kwargs={"n_workers": dask_workers, "threads_per_worker": 1, "processes": True,
                                          "dashboard_address": None})


def subflow_task_runner() -> TaskRunner:
    """A task runner for a subflow that uses the same workers as the running flow.

    Dask: a runner connected to the running flow's cluster (a local cluster is not started twice).
    Otherwise a copy of the running flow's runner; outside a flow the default of
    :func:`image_task_runner`.
    """
    context = FlowRunContext.get()
    if context is None or context.task_runner is None:
        return image_task_runner()
    runner = context.task_runner
    if "prefect_dask" in sys.modules:
        from prefect_dask import DaskTaskRunner

        if isinstance(runner, DaskTaskRunner):
            return DaskTaskRunner(address=runner.client.scheduler.address)
    return runner.duplicate()
