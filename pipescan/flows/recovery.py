"""What a retried network run does first: close what its dead attempts left open.

When the process of a run dies (SIGKILL, OOM, a host crash), nothing marks the task runs and
sub-flow runs it was executing: Prefect leaves them Running for good, even after the run
itself is marked Crashed and retried (see :mod:`pipescan.flows.deploy` for the automations that
do that). A retried run knows that they belong to no living process, because it is the run
now: it marks them Crashed, so that no run of it stays Running.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

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


def close_earlier_attempts(flow_run_id: str, run_name: str) -> tuple[int, int]:
    """Mark Crashed the sub-flow runs and task runs of this flow run (and of its sub-flows) that
    are still active; call it before the run starts any of its own. Returns (sub-flow runs,
    task runs) marked."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterId,
        FlowRunFilterParentFlowRunId,
        TaskRunFilter,
        TaskRunFilterState,
        TaskRunFilterStateType,
    )
    from prefect.client.schemas.objects import StateType
    from prefect.states import Crashed

    active = [StateType.PENDING, StateType.RUNNING, StateType.CANCELLING, StateType.PAUSED]
    message = MESSAGE.format(run=run_name)
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
            client.set_task_run_state(task_run.id, Crashed(message=message), force=True)
        for subflow in open_subflows:
            client.set_flow_run_state(subflow.id, Crashed(message=message), force=True)
    return len(open_subflows), len(tasks)
