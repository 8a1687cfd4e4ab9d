"""Prefect's temporary server ends with the process that started it, however that process ends.

Without a ``PREFECT_API_URL`` Prefect 3 starts a temporary API server as a child process
(``prefect.server.api.server.SubprocessASGIServer``: ``python -m uvicorn ...``) and stops it from
an ``atexit`` hook — which never runs when the command is killed (SIGKILL, ``os._exit``, a crash),
leaving the server running as an orphan. :func:`install` makes that child start through
:mod:`fivecal.server_watchdog` instead, which runs the same uvicorn command and ends it as soon as
its parent process is gone. Installed when the ``flows`` package is imported.
"""

from __future__ import annotations

import os
import subprocess
import sys
from typing import Any

WATCHDOG_MODULE = "fivecal.server_watchdog"


class _GuardedSubprocess:
    """The ``subprocess`` module as Prefect's server module sees it: the same, except that a
    ``python -m uvicorn`` child is started under the watchdog, told this process' pid."""

    def __getattr__(self, name: str) -> Any:
        return getattr(subprocess, name)

    @staticmethod
    def Popen(args: Any, *rest: Any, **kwargs: Any) -> subprocess.Popen:
        if isinstance(args, list) and args[1:3] == ["-m", "uvicorn"]:
            args = [args[0], "-m", WATCHDOG_MODULE, str(os.getpid()), *args[3:]]
        return subprocess.Popen(args, *rest, **kwargs)


def install() -> None:
    """Start Prefect's temporary servers under the watchdog from now on (idempotent)."""
    from prefect.server.api import server

    if not isinstance(server.subprocess, _GuardedSubprocess):
        server.subprocess = _GuardedSubprocess()


def running_servers() -> list[subprocess.Popen]:
    """The temporary server processes this process started and has not stopped (if any)."""
    server = sys.modules.get("prefect.server.api.server")
    if server is None:
        return []
    return [s.server_process for s in list(server.SubprocessASGIServer._instances.values())
            if s.server_process is not None]
