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
storage path) travel with each task (prefect-dask serialises the calling context). When the
caller runs Prefect's temporary server (no ``PREFECT_API_URL`` set), the tasks carry its address,
so that the workers record their task runs there instead of each starting a temporary server of
its own (about 15 s and 250 MB per worker); that server listens on 127.0.0.1, so workers on other
machines need ``PREFECT_API_URL`` set to a server they can reach.

A flow's runner is fixed when it is called, so a subflow that should use its parent's workers is
called as ``subflow.with_options(task_runner=subflow_task_runner())`` (see flows/measure.py).
"""

from __future__ import annotations

import functools
import os
import sys
from typing import Any

from prefect.context import FlowRunContext
from prefect.settings import PREFECT_API_URL, temporary_settings
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
    runner_class = dask_task_runner_class()
    if dask_address:
        return runner_class(address=dask_address)
    # processes: detection and decoding hold the GIL in places; one thread per worker process
    # keeps a worker's memory to one image at a time. No dashboard (no port, no bokeh needed).
    return runner_class(cluster_class=local_dask_cluster,
                        cluster_kwargs={"n_workers": dask_workers, "threads_per_worker": 1, "processes": True,
                                        "dashboard_address": None})


def local_dask_cluster(**kwargs: Any):
    """``distributed.LocalCluster(**kwargs)`` whose workers keep glibc's own malloc trim policy.

    Dask starts workers with MALLOC_TRIM_THRESHOLD_=65536 so that freed memory goes back to the
    system at once; every large buffer is then a fresh mmap, and dot detection on full-size images
    costs about 1.6× the CPU time (≈130 against ≈85 ms per image measured here). Without it a
    worker keeps some freed memory for re-use, a bounded amount that does not grow with the campaign.
    """
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return LocalCluster(**kwargs)


@functools.cache
def dask_task_runner_class() -> type[TaskRunner]:
    """The DaskTaskRunner subclass used here (defined on first use: importing Dask takes about 1 s).

    Its tasks carry the caller's Prefect API address, temporary server included: prefect-dask sends
    each task with the caller's settings, which with Prefect's temporary server hold no API URL, and
    a worker would then start a temporary server of its own. Here the URL of the server that the
    caller's client talks to is added to the settings each task is sent with.
    """
    from prefect_dask import DaskTaskRunner

    class CallerApiDaskTaskRunner(DaskTaskRunner):
        _api_url: str | None = None

        def submit(self, task: Any, parameters: dict[str, Any], wait_for: Any = None, dependencies: Any = None):
            if PREFECT_API_URL.value():
                return super().submit(task, parameters, wait_for, dependencies)
            if self._api_url is None:  # the running flow's client (not to be closed here)
                from prefect.client.orchestration import get_client

                context = FlowRunContext.get()
                self._api_url = str((context.client if context else get_client(sync_client=True)).api_url)
            with temporary_settings(updates={PREFECT_API_URL: self._api_url}):
                return super().submit(task, parameters, wait_for, dependencies)

    return CallerApiDaskTaskRunner


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
    if "prefect_dask" in sys.modules:  # else the runner cannot be a Dask one
        from prefect_dask import DaskTaskRunner

        if isinstance(runner, DaskTaskRunner):
            return dask_task_runner_class()(address=runner.client.scheduler.address)
    return runner.duplicate()
