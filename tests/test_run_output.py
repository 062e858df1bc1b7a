"""The cause is never lost: a scheduled run's process output (tracebacks, a fatal signal's
stack) goes to a named file, and the retried attempt finds the error its predecessor died of."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from pipescan.flows.recovery import last_error, run_output_path


def _attempt(path, attempt: int, body: str) -> subprocess.CompletedProcess:
    """A process standing for one attempt of a scheduled run: no pipe for its output (as a
    worker with ``stream_output`` off starts it), its output kept in ``path``."""
    code = textwrap.dedent(
        f"""
        from pathlib import Path
        from pipescan.flows.recovery import keep_output
        keep_output(Path({str(path)!r}), {attempt}, "cerise-lemming")
        """
    ) + textwrap.dedent(body)
    return subprocess.run(
        [sys.executable, "-c", code],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        timeout=60,
        check=False,
    )


def test_the_error_that_killed_an_attempt_is_in_its_output_file(tmp_path):
    path = run_output_path(tmp_path / "reports", "network-2026-12-07-cerise-lemming")
    assert path == tmp_path / "reports" / "logs" / "network-2026-12-07-cerise-lemming.log"
    died = _attempt(
        path,
        1,
        """
        print("[1/4] MH0-MH1 inspected")
        import sqlalchemy
        closed = Exception("server closed the connection")
        raise sqlalchemy.exc.OperationalError("SELECT 1", {}, closed)
        """,
    )
    assert died.returncode == 1
    text = path.read_text()
    assert "attempt 1 of run cerise-lemming" in text and "[1/4] MH0-MH1 inspected" in text
    assert last_error(path).startswith("sqlalchemy.exc.OperationalError: (builtins.Exception)")
    assert "server closed the connection" in last_error(path)

    # The next attempt appends; the error found is the latest attempt's only.
    assert _attempt(path, 2, 'print("fine")').returncode == 0
    assert "attempt 2 of run cerise-lemming" in path.read_text()
    assert last_error(path) is None


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_fatal_signal_leaves_its_stack(tmp_path):
    path = tmp_path / "logs" / "run.log"
    died = _attempt(path, 1, "import os, signal\nos.kill(os.getpid(), signal.SIGSEGV)\n")
    assert died.returncode != 0
    assert last_error(path) == "Fatal Python error: Segmentation fault"
    assert "Current thread" in path.read_text() or "Thread" in path.read_text()


def test_no_output_file_no_error(tmp_path):
    assert last_error(tmp_path / "none.log") is None


def test_a_sigterm_ends_the_run_while_an_archive_is_still_running(tmp_path):
    """A cancel is a SIGTERM from the worker. Prefect's handler raises in the main thread, which
    then waits for the pool thread inspecting an archive (here: 120 s of work); the process
    ends within seconds all the same, exit code 143, saying so in its output. (Prefect's API
    is away here: the closing of the sub-flow runs fails, and the process still ends.)"""
    path = tmp_path / "logs" / "run.log"
    code = textwrap.dedent(
        f"""
        import signal, threading, time
        from pathlib import Path
        from pipescan.flows.recovery import end_promptly_on_sigterm, keep_output

        class TerminationSignal(BaseException):
            pass

        def prefects(signum, frame):
            raise TerminationSignal()

        keep_output(Path({str(path)!r}), 1, "cerise-lemming")
        signal.signal(signal.SIGTERM, prefects)
        assert end_promptly_on_sigterm("0b1e", "cerise-lemming")
        archive = threading.Thread(target=time.sleep, args=(120,))
        archive.start()
        print("archive running", flush=True)
        try:
            time.sleep(120)
        finally:
            archive.join()  # as Prefect's thread pool does on the way out
        """
    )
    env = {**os.environ, "PREFECT_API_URL": "http://127.0.0.1:9/api"}
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not (path.exists() and "archive running" in path.read_text()):
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.1)
    signalled = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 143
    took_s = time.monotonic() - signalled
    assert took_s < 15, took_s
    assert "--- SIGTERM: the process ends now (" in path.read_text()  # and why
