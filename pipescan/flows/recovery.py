"""What a scheduled network run does so that nothing of a crash is lost: its process's output
goes to a named file (:func:`keep_output`), and a retried attempt first closes what its dead
attempts left open and says why the last one died (:func:`last_error`).

When the process of a run dies (SIGKILL, OOM, a host crash), nothing marks the task runs and
sub-flow runs it was executing: Prefect leaves them Running for good, even after the run
itself is marked Crashed and retried (see :mod:`pipescan.flows.deploy` for the automations that
do that). A retried run knows that they belong to no living process, because it is the run
now: it marks them Crashed, so that no run of it stays Running. At its end, a run marks
Crashed what an outage of Prefect's API or database left active of it
(:func:`close_leftovers`); on SIGTERM (a cancel), it closes what it was running and ends at
once (:func:`end_promptly_on_sigterm`).
"""

from __future__ import annotations

import faulthandler
import os
import re
import sys
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

RUN_LOGS = "logs"
"""The folder, in the reports folder, of the scheduled runs' process output."""
TAIL_BYTES = 65536
"""How much of the end of an output file :func:`last_error` reads."""
# The last line of a Python traceback: ``package.module.SomeError: message``.
_ERROR_LINE = re.compile(
    r"^(?:[A-Za-z_][\w.]*\.)?[A-Z]\w*(?:Error|Exception|Exit|Interrupt|Run)\b.*"
)
PAGE = 200
"""Runs read per request (the server's default cap)."""
MESSAGE = "left running by an earlier attempt of {run}, whose process died"


def _pages(read: Callable[..., list[Any]], **filters: Any) -> Iterator[Any]:
    offset = 0
    while True:
        page = read(**filters, limit=PAGE, offset=offset)
        yield from page
        if len(page) < PAGE:
            return
        offset += PAGE


def close_earlier_attempts(
    flow_run_id: str, run_name: str, died_of: str | None = None
) -> tuple[int, int]:
    """Mark Crashed the sub-flow runs and task runs of this flow run (and of its sub-flows) that
    are still active, their message naming the error the earlier attempt ``died_of`` if known;
    call it before the run starts any of its own. Returns (sub-flow runs, task runs) marked."""
    message = MESSAGE.format(run=run_name) + (f": {died_of}" if died_of else "")
    return close_open_runs(flow_run_id, message)


def _active_states() -> list:
    """The states of a run that has not ended."""
    from prefect.client.schemas.objects import StateType

    return [StateType.PENDING, StateType.RUNNING, StateType.CANCELLING, StateType.PAUSED]


def close_open_runs(flow_run_id: str, message: str, *, cancelled: bool = False) -> tuple[int, int]:
    """Mark Crashed (or Cancelled) the sub-flow runs and task runs of this flow run (and of its
    sub-flows) that are still active, with ``message``. Returns (sub-flow runs, task runs)
    marked."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterId,
        FlowRunFilterParentFlowRunId,
        TaskRunFilter,
        TaskRunFilterState,
        TaskRunFilterStateType,
    )
    from prefect.states import Cancelled, Crashed

    active = _active_states()
    final = Cancelled if cancelled else Crashed
    with get_client(sync_client=True) as client:
        subflows = list(
            _pages(
                client.read_flow_runs,
                flow_run_filter=FlowRunFilter(
                    parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[flow_run_id])
                ),
            )
        )
        run_ids = [flow_run_id, *(str(r.id) for r in subflows)]
        tasks = list(
            _pages(
                client.read_task_runs,
                flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=run_ids)),
                task_run_filter=TaskRunFilter(
                    state=TaskRunFilterState(type=TaskRunFilterStateType(any_=active))
                ),
            )
        )
        open_subflows = [r for r in subflows if r.state is not None and r.state.type in active]
        for task_run in tasks:
            client.set_task_run_state(task_run.id, final(message=message), force=True)
        for subflow in open_subflows:
            client.set_flow_run_state(subflow.id, final(message=message), force=True)
    return len(open_subflows), len(tasks)


SIGTERM_END_S = 10.0
"""At most this long after a SIGTERM, a scheduled run's process ends."""
STALE_S = 30.0
"""A task run of a finished network run still active in Prefect after this long lost its
later states (:func:`close_leftovers`)."""


def close_leftovers(flow_run_id: str, stale_s: float = STALE_S) -> tuple[int, int]:
    """At the end of a network run, mark Crashed what Prefect still holds active of it though
    it is over: its sub-flow runs (every sub-flow it started has returned), the task runs of
    its sub-flows that did not complete, and its own task runs whose state is older than
    ``stale_s`` seconds (one just finished may still be on its way through Prefect's event
    pipeline). Such runs lost their final state while Prefect's API or database did not answer
    (seen: PostgreSQL stopped for 20 s left a sub-flow Running and task runs Pending). Returns
    (sub-flow runs, task runs) marked; an API that does not answer marks none."""
    from datetime import timedelta

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterId,
        FlowRunFilterParentFlowRunId,
        TaskRunFilter,
        TaskRunFilterState,
        TaskRunFilterStateType,
    )
    from prefect.states import Crashed

    if not flow_run_id:  # not a run (the flow's function called as such)
        return 0, 0
    active = _active_states()
    message = "left active when Prefect's API or database did not answer; the run is over"
    try:
        with get_client(sync_client=True) as client:
            subflows = list(
                _pages(
                    client.read_flow_runs,
                    flow_run_filter=FlowRunFilter(
                        parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[flow_run_id])
                    ),
                )
            )
            open_subflows = [r for r in subflows if r.state is None or r.state.type in active]
            unfinished = {
                str(r.id) for r in subflows if r.state is None or not r.state.is_completed()
            }
            tasks = list(
                _pages(
                    client.read_task_runs,
                    flow_run_filter=FlowRunFilter(
                        id=FlowRunFilterId(any_=[flow_run_id, *(str(r.id) for r in subflows)])
                    ),
                    task_run_filter=TaskRunFilter(
                        state=TaskRunFilterState(type=TaskRunFilterStateType(any_=active))
                    ),
                )
            )
            now = datetime.now(UTC)
            stale = [
                t
                for t in tasks
                if str(t.flow_run_id) in unfinished
                or t.state is None
                or now - t.state.timestamp > timedelta(seconds=stale_s)
            ]
            for task_run in stale:
                client.set_task_run_state(task_run.id, Crashed(message=message), force=True)
            for subflow in open_subflows:
                client.set_flow_run_state(subflow.id, Crashed(message=message), force=True)
        abandoned = close_abandoned_runs(flow_run_id)
    except Exception:  # the API is away: nothing to do about it now
        return 0, 0
    return len(open_subflows) + abandoned[0], len(stale) + abandoned[1]


ABANDONED_AFTER_S = 1800.0
"""An earlier run that ended Crashed or Cancelled this long ago has no process left (a live run
the silent-run automation took for dead is back within minutes; a crashed one is retried
after 30 s)."""
LOOK_BACK_S = 7 * 86400.0
"""How far back :func:`close_abandoned_runs` looks."""


def close_abandoned_runs(
    flow_run_id: str, abandoned_after_s: float = ABANDONED_AFTER_S
) -> tuple[int, int]:
    """Close what earlier runs of this run's deployment left active: a run that ended Crashed
    (on its last attempt) or Cancelled (its host dead) between :data:`LOOK_BACK_S` and
    ``abandoned_after_s`` seconds ago has no process left, and its sub-flow and task runs
    still active are marked Cancelled or Crashed, as the run ended. No automation does it: a
    sub-flow sends no end event, so the silent-run automation does not watch sub-flows
    (:mod:`pipescan.flows.deploy`). Returns (sub-flow runs, task runs) marked."""
    from datetime import timedelta

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        DeploymentFilter,
        DeploymentFilterId,
        FlowRunFilter,
        FlowRunFilterEndTime,
        FlowRunFilterState,
        FlowRunFilterStateType,
    )
    from prefect.client.schemas.objects import StateType

    with get_client(sync_client=True) as client:
        deployment_id = client.read_flow_run(flow_run_id).deployment_id
        if deployment_id is None:
            return 0, 0
        now = datetime.now(UTC)
        ended = client.read_flow_runs(
            deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment_id])),
            flow_run_filter=FlowRunFilter(
                state=FlowRunFilterState(
                    type=FlowRunFilterStateType(any_=[StateType.CRASHED, StateType.CANCELLED])
                ),
                end_time=FlowRunFilterEndTime(
                    after_=now - timedelta(seconds=LOOK_BACK_S),
                    before_=now - timedelta(seconds=abandoned_after_s),
                ),
            ),
            limit=PAGE,
        )
    closed = (0, 0)
    for run in ended:
        cancelled = run.state is not None and run.state.is_cancelled()
        more = close_open_runs(
            str(run.id),
            f"left active by run {run.name}, which ended "
            f"{'Cancelled' if cancelled else 'Crashed'} with no process left",
            cancelled=cancelled,
        )
        closed = (closed[0] + more[0], closed[1] + more[1])
    return closed


def end_promptly_on_sigterm(flow_run_id: str, run_name: str) -> bool:
    """In a scheduled run's process: on SIGTERM (the worker's way to cancel a run, or a person
    stopping the process), mark the run's active sub-flow and task runs Cancelled (Crashed when
    the run is not being cancelled) and end the process at once, within
    :data:`SIGTERM_END_S` seconds. Call it from the flow's function, in the main thread,
    where Prefect's own SIGTERM handler is installed: it calls that handler too. Returns
    whether it was installed (not outside the main thread).

    Without it, Prefect's handler stops the run from starting more archives, but the archive
    being inspected runs in a pool thread that nothing can stop, and the pool waits for it on
    the way out: the process lived on until its archive was done or until the worker killed it
    30 s after its SIGTERM (Prefect 3.8's fixed grace), leaving that archive's sub-flow
    Running (cancels took 25-34 s). The archive is taken first by the next run.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return False
    previous = signal.getsignal(signal.SIGTERM)

    def end() -> None:
        deadline = threading.Timer(  # whatever Prefect's API does
            SIGTERM_END_S,
            _exit_now,
            args=(
                f"--- SIGTERM: the process ends now (Prefect's API gave no answer in "
                f"{SIGTERM_END_S:g} s)",
            ),
        )
        deadline.daemon = True
        deadline.start()
        try:
            cancelled = _is_cancelling(flow_run_id)
            closed = close_open_runs(
                flow_run_id,
                f"{'cancelled' if cancelled else 'stopped'} with run {run_name}, whose process "
                "ended on SIGTERM",
                cancelled=cancelled,
            )
            said = (
                f"--- SIGTERM: run {run_name} {'cancelled' if cancelled else 'stopped'}; "
                f"{closed[0]} sub-flow and {closed[1]} task runs marked "
                f"{'Cancelled' if cancelled else 'Crashed'}; the process ends now"
            )
        except Exception as exc:  # the API is away: end all the same
            said = f"--- SIGTERM: the process ends now ({type(exc).__name__}: {exc})"
        _exit_now(said)

    def handler(signum, frame) -> None:
        signal.signal(signal.SIGTERM, previous)  # a second SIGTERM: Prefect's way
        threading.Thread(target=end, name="pipescan-sigterm", daemon=True).start()
        if callable(previous):
            previous(signum, frame)  # raises in this thread: no more archives start

    signal.signal(signal.SIGTERM, handler)
    return True


def _is_cancelling(flow_run_id: str) -> bool:
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.objects import StateType

    with get_client(sync_client=True) as client:
        state = client.read_flow_run(flow_run_id).state
    return state is not None and state.type in (StateType.CANCELLING, StateType.CANCELLED)


def _exit_now(said: str) -> None:
    print(said, flush=True)
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    os._exit(128 + 15)  # as a SIGTERM would have ended it


def run_output_path(reports_dir: Path, file_stem: str) -> Path:
    """Where a scheduled run's process writes its output: ``<reports>/logs/<stem>.log``, beside
    the run's network report (``<stem>.pdf``), so that one name finds both."""
    return reports_dir / RUN_LOGS / f"{file_stem}.log"


def keep_output(path: Path, attempt: int, run_name: str) -> Path:
    """Send this process's standard output and error (file descriptors 1 and 2: Python's
    tracebacks, Prefect's console lines, a native library's messages, a fatal signal's stack
    through :mod:`faulthandler`) to the end of ``path``, line by line.

    A worker runs a scheduled run's process without a pipe (``stream_output`` off, so that
    the run outlives its worker), which sends that output nowhere: the error that killed a
    run would be lost.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o640)
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None:
            reconfigure(line_buffering=True)
    faulthandler.enable(file=sys.stderr, all_threads=True)
    print(
        f"--- {datetime.now(UTC):%Y-%m-%d %H:%M:%S} UTC: attempt {attempt} of run {run_name}, "
        f"process {os.getpid()}",
        flush=True,
    )
    return path


def last_error(path: Path) -> str | None:
    """The last error line (a traceback's last line, or a fatal signal's) of the latest
    attempt in an output file that :func:`keep_output` wrote, or None. Call it before this
    attempt's :func:`keep_output`."""
    try:
        with path.open("rb") as f:
            f.seek(max(0, path.stat().st_size - TAIL_BYTES))
            tail = f.read().decode("utf-8", "replace")
    except OSError:
        return None
    lines = tail.splitlines()
    # Only the latest attempt: from its header on.
    headers = [i for i, line in enumerate(lines) if line.startswith("--- ")]
    if headers:
        lines = lines[headers[-1] :]
    found = None
    for line in lines:
        stripped = line.strip()
        if stripped.startswith("Fatal Python error") or _ERROR_LINE.match(stripped):
            found = stripped
    return found[:500] if found else None


def close_task_runs_of(flow_run_id: str, message: str) -> int:
    """Mark Crashed the task runs of one flow run that are still active: a sub-flow that failed
    for a transient cause (Prefect's API gone, a concurrency slot not granted) can leave a task
    run Pending for good. Returns how many were marked; an API that does not answer marks none.
    """
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterId,
        TaskRunFilter,
        TaskRunFilterState,
        TaskRunFilterStateType,
    )
    from prefect.states import Crashed

    active = _active_states()
    try:
        with get_client(sync_client=True) as client:
            tasks = list(
                _pages(
                    client.read_task_runs,
                    flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id])),
                    task_run_filter=TaskRunFilter(
                        state=TaskRunFilterState(type=TaskRunFilterStateType(any_=active))
                    ),
                )
            )
            for task_run in tasks:
                client.set_task_run_state(task_run.id, Crashed(message=message), force=True)
    except Exception:  # the API is still away: the next attempt's sub-flow is a new run anyway
        return 0
    return len(tasks)
