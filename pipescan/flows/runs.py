"""What became of recent network runs, from Prefect's API and the database (``pipescan runs``).

Each ``inspect-network`` run leaves a table of its archives' outcomes as an artifact
(:data:`pipescan.flows.network.OUTCOMES_ARTIFACT`). A run that never got to write it (it
crashed, or is still running) is described by its sub-flow runs instead, one per archive
attempt. The database says which of the archives a run left unstored have been stored since.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from pipescan.flows.network import OUTCOMES_ARTIFACT, STATUSES

FLOW_NAME = "inspect-network"


@dataclass(frozen=True)
class ArchiveNote:
    """An archive a run did not store: its label, why, and whether it is stored by now
    (None: the database was not asked or did not answer)."""

    archive: str
    why: str
    uri: str | None = None
    stored_since: bool | None = None


@dataclass(frozen=True)
class NetworkRun:
    """One ``inspect-network`` run as ``pipescan runs`` shows it.

    ``counts`` has a count per outcome (``inspected``, ``reused``, ``duplicate``, ``failed``,
    ``missing``); ``source`` says where they come from: ``outcomes`` (the run's own table)
    or ``sub-flows`` (its sub-flow runs, for a run that did not finish: ``missing`` then
    counts the archives whose last attempt did not end Completed).
    """

    id: str
    name: str
    state: str
    state_name: str
    message: str | None
    started: datetime | None
    finished: datetime | None
    run_count: int
    store: str | None
    counts: dict[str, int]
    failed: list[ArchiveNote] = field(default_factory=list)
    missing: list[ArchiveNote] = field(default_factory=list)
    source: str = "outcomes"

    @property
    def green(self) -> bool:
        return self.state == "COMPLETED" and not self.failed and not self.missing


def outcomes_from_rows(rows: list[dict[str, Any]]) -> tuple[dict, list, list]:
    """Counts, failed and missing archives from a run's outcome table."""
    counts = {k: sum(r.get("status") == k for r in rows) for k in STATUSES}
    notes: dict[str, list[ArchiveNote]] = {"failed": [], "missing": []}
    for r in rows:
        if r.get("status") in notes:
            notes[r["status"]].append(
                ArchiveNote(r.get("archive") or "?", r.get("error") or "", r.get("uri"))
            )
    return counts, notes["failed"], notes["missing"]


def outcomes_from_subflows(subflows: list[Any]) -> tuple[dict, list, list]:
    """Counts, failed and missing archives from a run's sub-flow runs (the last attempt of
    each archive; sub-flow runs are named after their archive)."""
    last: dict[str, Any] = {}
    for sub in sorted(subflows, key=lambda r: r.expected_start_time or r.created):
        last[sub.name] = sub
    counts = dict.fromkeys(STATUSES, 0)
    missing = []
    for name, sub in last.items():
        state = sub.state.type.value if sub.state else "UNKNOWN"
        if state == "COMPLETED":
            counts["inspected"] += 1  # or reused: a sub-flow's result is not kept
        else:
            counts["missing"] += 1
            why = (sub.state.message if sub.state else None) or state.lower()
            missing.append(ArchiveNote(name, f"{state.lower()}: {why}"))
    return counts, [], missing


def recent_network_runs(limit: int = 10, database_url: str | None = None) -> list[NetworkRun]:
    """The ``limit`` most recent ``inspect-network`` runs that started, newest first.

    Raises
    ------
    httpx.HTTPError
        Prefect's API does not answer.
    """
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowFilter,
        FlowFilterName,
        FlowRunFilter,
        FlowRunFilterStartTime,
    )
    from prefect.client.schemas.sorting import FlowRunSort

    with get_client(sync_client=True) as client:
        flow_runs = client.read_flow_runs(
            flow_filter=FlowFilter(name=FlowFilterName(any_=[FLOW_NAME])),
            flow_run_filter=FlowRunFilter(start_time=FlowRunFilterStartTime(is_null_=False)),
            sort=FlowRunSort.START_TIME_DESC,
            limit=limit,
        )
        tables = _outcome_tables(client, [r.id for r in flow_runs])
        runs = [_network_run(client, r, tables.get(str(r.id))) for r in flow_runs]
    if database_url and any(run.failed or run.missing for run in runs):
        from pipescan.core.errors import PipescanError
        from pipescan.tasks.network import stored_archive_uris

        try:
            stored = stored_archive_uris(database_url)
        except PipescanError:  # the runs are still worth showing
            return runs
        runs = [with_stored_since(run, stored) for run in runs]
    return runs


def _outcome_tables(client: Any, flow_run_ids: list[Any]) -> dict[str, Any]:
    """Each run's outcome table (:data:`OUTCOMES_ARTIFACT`), by run id: the latest, as a
    retried run writes one per attempt that finished."""
    from prefect.client.schemas.filters import (
        ArtifactFilter,
        ArtifactFilterFlowRunId,
        ArtifactFilterKey,
    )

    if not flow_run_ids:
        return {}
    artifacts = client.read_artifacts(
        artifact_filter=ArtifactFilter(
            flow_run_id=ArtifactFilterFlowRunId(any_=flow_run_ids),
            key=ArtifactFilterKey(any_=[OUTCOMES_ARTIFACT]),
        )
    )
    tables: dict[str, Any] = {}
    for artifact in sorted(artifacts, key=lambda a: a.created):
        tables[str(artifact.flow_run_id)] = artifact
    return tables


def _network_run(client: Any, r: Any, table: Any | None) -> NetworkRun:
    """One run, its archives' outcomes from its outcome table, or (a run that left none: it
    died) from its sub-flow runs."""
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterParentFlowRunId

    if table is not None:
        rows = table.data if isinstance(table.data, list) else json.loads(table.data)
        counts, failed, missing = outcomes_from_rows(rows)
        source = "outcomes"
    else:
        subflows = client.read_flow_runs(
            flow_run_filter=FlowRunFilter(
                parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[r.id])
            ),
            limit=200,
        )
        counts, failed, missing = outcomes_from_subflows(subflows)
        source = "sub-flows"
    return NetworkRun(
        id=str(r.id),
        name=r.name,
        state=r.state.type.value if r.state else "UNKNOWN",
        state_name=r.state.name if r.state else "Unknown",
        message=r.state.message if r.state else None,
        started=r.start_time,
        finished=r.end_time,
        run_count=r.run_count,
        store=(r.parameters or {}).get("store"),
        counts=counts,
        failed=failed,
        missing=missing,
        source=source,
    )


def with_stored_since(run: NetworkRun, stored: set[str]) -> NetworkRun:
    """``run`` with each archive it left unstored marked as stored since (by a later run) or
    not, given the archive URIs the database has inspections of."""
    from dataclasses import replace

    def mark(notes: list[ArchiveNote]) -> list[ArchiveNote]:
        return [replace(n, stored_since=n.uri in stored) if n.uri is not None else n for n in notes]

    return replace(run, failed=mark(run.failed), missing=mark(run.missing))
