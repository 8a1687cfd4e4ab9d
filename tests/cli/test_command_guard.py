"""How a fivecal command ends (fivecal/command_guard.py, flows/server_guard.py): a failure is a
clear message and exit 2, SIGTERM/SIGINT stop it promptly, and Prefect's temporary server is
started under a watchdog that ends it when the command dies, SIGKILL included.

The signal and watchdog tests run small child processes (no Prefect server: a stub ASGI app under
the watchdog stands for it); each is bounded in time and killed in a ``finally``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from fivecal.command_guard import DEBUG_ENV, GuardedTyper
from flows import server_guard

runner = CliRunner()
REPO = Path(__file__).resolve().parents[2]


def failing_app() -> GuardedTyper:
    app = GuardedTyper()

    @app.command()
    def boom(kind: str) -> None:
        if kind == "index":
            [][1]
        if kind == "exit":
            raise typer.Exit(3)
        raise typer.BadParameter("nope", param_hint="--kind")

    @app.command()
    def other() -> None:
        pass

    return app


def test_an_unexpected_error_is_one_line_and_exit_2_not_a_traceback(monkeypatch):
    monkeypatch.delenv(DEBUG_ENV, raising=False)
    result = runner.invoke(failing_app(), ["boom", "index"])
    assert result.exit_code == 2
    assert result.output.startswith("error: boom failed: IndexError: list index out of range\n")
    assert "Traceback" not in result.output


def test_typer_exits_and_usage_errors_pass_through_and_debug_re_raises(monkeypatch):
    app = failing_app()
    assert runner.invoke(app, ["boom", "exit"]).exit_code == 3
    usage = runner.invoke(app, ["boom", "usage"])
    assert usage.exit_code == 2 and "Invalid value for --kind: nope" in usage.output
    monkeypatch.setenv(DEBUG_ENV, "1")
    debug = runner.invoke(app, ["boom", "index"])
    assert debug.exit_code == 1 and isinstance(debug.exception, IndexError)


def test_every_fivecal_command_is_guarded():
    from fivecal.cli import app

    assert isinstance(app, GuardedTyper)
    assert all(c.callback.__wrapped__ is not None for c in app.registered_commands)


def spawn(code: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)


BUSY_COMMAND = """
    import threading, time
    from fivecal.command_guard import GuardedTyper
    app = GuardedTyper()

    @app.command()
    def busy(seconds: float = 120.0) -> None:
        worker = threading.Thread(target=time.sleep, args=(seconds,))  # a thread busy with an image
        worker.start()
        print("started", flush=True)
        worker.join()

    @app.command()
    def other() -> None:
        pass

    app()
"""


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_stops_a_busy_command_promptly(signum, code):
    proc = spawn(BUSY_COMMAND.replace("app()", "app(['busy'])"))
    try:
        assert proc.stdout.readline().strip() == "started"
        start = time.monotonic()
        proc.send_signal(signum)
        proc.wait(timeout=30)
        elapsed = time.monotonic() - start
        assert proc.returncode == code, proc.stderr.read()
        assert elapsed < 3.0, elapsed  # not the 120 s the busy thread would take
        assert f"interrupted ({signal.Signals(signum).name})" in proc.stderr.read()
    finally:
        proc.kill()
        proc.wait()


STUB_SERVER = """
    import os, subprocess, sys, time
    from flows import server_guard
    # what Prefect's SubprocessASGIServer runs, through the guarded subprocess module
    child = server_guard._GuardedSubprocess().Popen(
        [sys.executable, "-m", "uvicorn", "--app-dir", {app_dir!r}, "stub_asgi:app", "--port", "0",
         "--log-level", "error"])
    print(child.pid, flush=True)
    time.sleep(120)
"""


def test_the_server_watchdog_ends_the_server_when_its_parent_is_killed(tmp_path):
    (tmp_path / "stub_asgi.py").write_text("async def app(scope, receive, send):\n    pass\n")
    parent = spawn(STUB_SERVER.format(app_dir=str(tmp_path)))
    child = None
    try:
        child = int(parent.stdout.readline())
        time.sleep(1.0)
        assert _running(child), _stderr_of(parent)  # the server runs while its parent lives
        cmdline = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        assert cmdline[1:4] == [b"-m", b"fivecal.server_watchdog", str(parent.pid).encode()]
        parent.kill()  # SIGKILL: no atexit, no finally
        parent.wait(timeout=10)
        deadline = time.monotonic() + 15
        while _running(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _running(child), "the server outlived the killed command"
    finally:
        parent.kill()
        parent.wait()
        if child is not None and _running(child):
            os.kill(child, signal.SIGKILL)


def _stderr_of(proc: subprocess.Popen) -> str:
    proc.kill()
    return proc.communicate(timeout=10)[1]


def _running(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def test_the_guard_is_installed_in_prefects_server_module_by_the_flows_package():
    from prefect.server.api import server

    import flows  # noqa: F401

    assert isinstance(server.subprocess, server_guard._GuardedSubprocess)
    assert server.subprocess.TimeoutExpired is subprocess.TimeoutExpired  # everything else unchanged


def test_prefect_log_records_lose_their_traceback_unless_debugging(monkeypatch):
    import logging

    monkeypatch.delenv(DEBUG_ENV, raising=False)
    seen = []
    app = GuardedTyper()

    @app.command()
    def log() -> None:
        try:
            [][1]
        except IndexError:
            for name in ("prefect.flow_runs", "fivecal.other"):
                seen.append(logging.getLogger(name).makeRecord(name, logging.ERROR, "f", 1, "failed", (),
                                                               sys.exc_info()))

    @app.command()
    def other() -> None:
        pass

    assert runner.invoke(app, ["log"]).exit_code == 0
    prefect_record, other_record = seen
    assert prefect_record.exc_info is None and prefect_record.msg.endswith(f"{DEBUG_ENV}=1 shows it)")
    assert other_record.exc_info is not None
    monkeypatch.setenv(DEBUG_ENV, "1")
    seen.clear()
    runner.invoke(app, ["log"])
    assert seen[0].exc_info is not None
