"""How every ``fivecal`` command ends: with its result, a clear message and exit 2, or promptly
on Ctrl-C / SIGTERM — never a traceback, never a process left behind.

:class:`GuardedTyper` is the CLI's ``typer.Typer``: each command it registers runs inside
:func:`guarded`, which

- turns an unexpected exception into ``error: <command> failed: <Type>: <message>`` on stderr and
  exit 2, and keeps Prefect from logging tracebacks meanwhile (``FIVECAL_DEBUG=1`` re-raises
  the exception and leaves Prefect's logs whole); typer's and click's own exits pass through;
- makes SIGTERM end the command as Ctrl-C does: a KeyboardInterrupt in the main thread (so that
  ``finally`` blocks run: a writer removes its staging folder), then the temporary Prefect servers
  are stopped and the process exits at once (``os._exit``: no waiting for threads busy with an
  image), 130 for SIGINT and 143 for SIGTERM. If the interrupt has not reached the command
  :data:`GRACE_S` seconds after the signal, or on a second signal, the same happens from a
  watchdog thread. Results are written atomically per partition
  (tasks/lake/store.py), so the lake is left as a kill would leave it: every partition whole.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import typer
from typer.exceptions import TyperException

from flows import server_guard

GRACE_S = 5.0
DEBUG_ENV = "FIVECAL_DEBUG"
_EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
_received: list[int] = []
# typer's exits and usage errors (TyperException: its vendored click's): typer reports them
_PASS_THROUGH = (typer.Exit, typer.Abort, TyperException, SystemExit)


class GuardedTyper(typer.Typer):
    """A ``typer.Typer`` whose commands run under :func:`guarded`."""

    def command(self, *args: Any, **kwargs: Any) -> Callable[[Callable], Callable]:
        register = super().command(*args, **kwargs)

        def decorator(f: Callable) -> Callable:
            register(guarded(f))
            return f  # the plain function stays callable from Python (e.g. demo calls calibrate)

        return decorator


def guarded(command: Callable) -> Callable:
    """``command`` ending as this module says."""

    @functools.wraps(command)
    def run(*args: Any, **kwargs: Any) -> Any:
        with _signals_end_the_command(), _prefect_logs_without_tracebacks():
            try:
                return command(*args, **kwargs)
            except _PASS_THROUGH:
                raise
            except Exception as e:
                if os.environ.get(DEBUG_ENV):
                    raise
                name = command.__name__.replace("_", "-")
                typer.echo(f"error: {name} failed: {type(e).__name__}: {e}\n(the results lake keeps every partition "
                           f"whole; {DEBUG_ENV}=1 shows the traceback)", err=True)
                raise typer.Exit(2) from None
            except BaseException as e:
                if not _is_interrupt(e):
                    raise
                signum = _received[-1] if _received else signal.SIGINT
                typer.echo(f"interrupted ({signal.Signals(signum).name}): stopped; every written partition of the "
                           "results lake is whole", err=True)
                if _received:  # a real signal: end now, as a kill would, without waiting for busy threads
                    _stop_now(signum)
                raise typer.Exit(_EXIT_CODES.get(signum, 130)) from None

    return run


def _is_interrupt(e: BaseException) -> bool:
    """Ctrl-C, or the exception Prefect's own SIGTERM handler raises while a flow runs (recognised
    by name: importing prefect here would slow every command down by a second)."""
    if type(e).__name__ == "TerminationSignal" and type(e).__module__.startswith("prefect"):
        if not _received:
            _received.append(signal.SIGTERM)
        return True
    return isinstance(e, KeyboardInterrupt)


def _on_signal(signum: int, frame: Any) -> None:
    if _received:  # a second signal: now
        _stop_now(signum)
    _received.append(signum)
    threading.Thread(target=_deadline, args=(signum,), name="stop-deadline", daemon=True).start()
    raise KeyboardInterrupt


def _deadline(signum: int) -> None:
    time.sleep(GRACE_S)
    _stop_now(signum)


def _stop_now(signum: int) -> None:
    """Stop the temporary Prefect servers and exit without waiting for busy threads."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    for process in server_guard.running_servers():
        with contextlib.suppress(OSError):
            process.terminate()
    os._exit(_EXIT_CODES.get(signum, 130))


@contextlib.contextmanager
def _prefect_logs_without_tracebacks() -> Iterator[None]:
    """Prefect logs a failed task or flow with its whole traceback (hundreds of lines); the command
    reports the error in one line instead. Unless $FIVECAL_DEBUG is set, records of Prefect's
    loggers are made without their traceback while the command runs."""
    if os.environ.get(DEBUG_ENV):
        yield
        return
    previous = logging.getLogRecordFactory()

    def factory(name, level, fn, lno, msg, args, exc_info, func=None, sinfo=None, **kwargs):
        if exc_info and name.startswith("prefect"):
            exc_info = None
            msg = f"{msg} (traceback hidden; {DEBUG_ENV}=1 shows it)"
        return previous(name, level, fn, lno, msg, args, exc_info, func, sinfo, **kwargs)

    logging.setLogRecordFactory(factory)
    try:
        yield
    finally:
        logging.setLogRecordFactory(previous)


@contextlib.contextmanager
def _signals_end_the_command() -> Iterator[None]:
    """SIGINT and SIGTERM handled by :func:`_on_signal` while the command runs (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _on_signal) for s in _EXIT_CODES}
    _received.clear()
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
