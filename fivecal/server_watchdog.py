"""``python -m fivecal.server_watchdog <parent pid> <uvicorn arguments>``: run uvicorn as
``python -m uvicorn <uvicorn arguments>`` would, and end it when the parent process is gone.

A thread checks every :data:`POLL_S` seconds whether this process still has the parent it was
started by (a killed parent's children are handed to another process); when not, it asks uvicorn
to shut down (SIGTERM) and, :data:`GRACE_S` seconds later, exits regardless. See
flows/server_guard.py.
"""

from __future__ import annotations

import os
import runpy
import signal
import sys
import threading
import time

POLL_S = 0.5
GRACE_S = 5.0


def _watch(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(POLL_S)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(GRACE_S)
    os._exit(1)


def main() -> None:
    parent = int(sys.argv[1])
    sys.argv = ["uvicorn", *sys.argv[2:]]
    threading.Thread(target=_watch, args=(parent,), name="parent-watchdog", daemon=True).start()
    runpy.run_module("uvicorn", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
