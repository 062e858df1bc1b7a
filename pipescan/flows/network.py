"""The ``inspect-network`` flow: every scan archive of a store, each in its own sub-flow.

Work fans out on three levels: over archives (a bounded number of ``inspect-archive``
sub-flows at once, each named after its archive), and within each archive over frame chunks
and chainage windows, on a local pool or a Dask cluster. Tasks receive paths, ids and small
dataclasses, so nothing big crosses the wire to a Dask worker.

A failing archive fails alone: its error is recorded in the network summary and on its
sub-flow run, and the other archives go on. An archive that failed for a transient cause (the
database or Prefect's API unreachable, a concurrency slot not granted, its sub-flow taken for
crashed) is tried again later in the run, with backoff, for up to :data:`RETRY_WINDOW_S`
seconds; one that failed for its own content is not. Whatever is not stored at the end makes
the run end Failed, naming the archives (``missing``: the next run takes them first; ``failed``:
fix the archive). An archive whose content was already inspected under the same parameters is
not processed again (``reuse_stored``), so a run that was killed can simply be started again: it
finishes the remaining archives, and the database keeps one copy of each inspection. Two
archives of the same content (a folder and its zip) are one inspection, said once.
"""

from __future__ import annotations

import logging
import re
import time
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path

from prefect import flow, get_run_logger, tags, task
from prefect.cache_policies import NO_CACHE
from prefect.exceptions import Abort
from prefect.futures import as_completed
from prefect.runtime import flow_run
from prefect.settings import PREFECT_API_URL, temporary_settings
from prefect.states import Failed
from prefect.task_runners import ThreadPoolTaskRunner

from pipescan.core.contour.grid import GridParams
from pipescan.core.errors import PipescanError
from pipescan.core.measures import MeasureParams
from pipescan.core.registration import RegistrationParams
from pipescan.core.sanitize import strip_credentials, strip_credentials_in_text
from pipescan.core.wording import plural
from pipescan.flows.database import checked_database_url, in_deployment
from pipescan.flows.inspect import InspectionParams, InspectionSummary, inspect_archive
from pipescan.flows.notification import RUN_HOOKS
from pipescan.flows.recovery import (
    close_earlier_attempts,
    close_leftovers,
    close_task_runs_of,
    end_promptly_on_sigterm,
    keep_output,
    last_error,
    run_output_path,
)
from pipescan.flows.runners import make_task_runner
from pipescan.reports.network import FailedArchive
from pipescan.settings import get_settings, use_settings
from pipescan.tasks.network import (
    IO_RETRY_OPTIONS,
    archive_label,
    discover_archives,
    find_stored_archives,
    unstored_first,
)
from pipescan.tasks.retries import CONTENT, TRANSIENT, failure_cause

log = logging.getLogger("pipescan")

RETRY_WINDOW_S = 900.0
"""An archive that failed for a transient cause is tried again for up to this long after its
first failure (15 min: a database or Prefect server restarted, a short network outage)."""
RETRY_FIRST_DELAY_S = 15.0
"""The wait before an archive's second attempt; each next wait doubles, up to
:data:`RETRY_MAX_DELAY_S` (15, 30, 60, 120, 120... s)."""
RETRY_MAX_DELAY_S = 120.0
DATABASE_WAIT_S = 300.0
"""A scheduled run whose database does not answer at the start tries again for this long
(5, 10, 20, 40, 60, 60... s apart) before it fails: a blip at 02:00 does not cost the night."""
DATABASE_FIRST_DELAY_S = 5.0
DATABASE_MAX_DELAY_S = 60.0
STATUSES = ("inspected", "reused", "duplicate", "failed", "missing")
"""An archive's outcome in a network run, in the order summaries count them."""
OUTCOMES_ARTIFACT = "pipescan-network-outcomes"
"""Key of the table artifact where a run leaves each archive's outcome (``pipescan runs``)."""


def backoff_delay(first_s: float, max_s: float, retry: int) -> float:
    """The wait before retry number ``retry`` (1, 2...): ``first_s`` doubling each time, at
    most ``max_s``.

    >>> [backoff_delay(15, 120, n) for n in range(1, 6)]
    [15, 30, 60, 120, 120]
    """
    return min(first_s * 2 ** (retry - 1), max_s)


@dataclass(frozen=True)
class ArchiveOutcome:
    """What became of one archive of a network run.

    ``status`` is ``inspected`` (processed and stored now), ``reused`` (already stored under
    the same content and parameters), ``duplicate`` (the same content as the archive
    ``same_as``, whose inspection it is), ``failed`` (for its own content, ``cause``
    ``content``, or a defect, ``error``: not tried again; nothing stored) or ``missing`` (a
    transient cause, still failing when the run's retries ran out: the next run takes it
    first). ``error`` says why; ``attempts`` counts the tries in this run.
    """

    archive: str
    label: str
    status: str
    wall_time_s: float
    inspection_id: int | None = None
    asset_id: str | None = None
    section_count: int | None = None
    sections_ok: int | None = None
    defect_count: int | None = None
    max_blockage_ratio: float | None = None
    max_blockage_chainage_m: float | None = None
    report_path: str | None = None
    error: str | None = None
    error_type: str | None = None
    cause: str | None = None
    attempts: int = 1
    same_as: str | None = None
    subflow_run_id: str | None = None
    """The failed attempt's sub-flow run."""

    @property
    def stored(self) -> bool:
        return self.status in ("inspected", "reused", "duplicate")

    @classmethod
    def from_summary(cls, archive: str, label: str, summary: InspectionSummary, wall_s: float):
        return cls(
            archive=strip_credentials(archive),
            label=label,
            status="reused" if summary.reused else "inspected",
            wall_time_s=wall_s,
            inspection_id=summary.inspection_id,
            asset_id=summary.asset_id,
            section_count=summary.section_count,
            sections_ok=summary.sections_ok,
            defect_count=summary.defect_count,
            max_blockage_ratio=summary.max_blockage_ratio,
            max_blockage_chainage_m=summary.max_blockage_chainage_m,
            report_path=summary.report_path,
        )


@dataclass(frozen=True)
class NetworkSummary:
    """The result of a network run: one outcome per archive (in store order), the worst
    pipes by blockage, and the network report if one was written."""

    store: str
    executor: str
    outcomes: list[ArchiveOutcome]
    worst: list[ArchiveOutcome]
    wall_time_s: float
    network_report_path: str | None = None
    network_report_error: str | None = None
    counts: dict[str, int] = field(default_factory=dict)

    retry_window_s: float = RETRY_WINDOW_S

    @property
    def failures(self) -> list[ArchiveOutcome]:
        """The archives not stored: ``failed`` and ``missing``."""
        return [o for o in self.outcomes if not o.stored]

    @property
    def missing(self) -> list[ArchiveOutcome]:
        """The archives left out for a transient cause: the next run takes them first."""
        return [o for o in self.outcomes if o.status == "missing"]

    @property
    def duplicates(self) -> list[ArchiveOutcome]:
        return [o for o in self.outcomes if o.status == "duplicate"]

    @property
    def inspection_ids(self) -> list[int]:
        return [o.inspection_id for o in self.outcomes if o.inspection_id is not None]


# --- helpers ----------------------------------------------------------------------------------


def params_from_settings(settings, *, contour: str | None = None, registration: str | None = None):
    """The inspection parameters that ``PIPESCAN_*`` settings (or a ``.env``) give, with the
    CLI's ``--contour`` and ``--registration`` overriding them.

    Raises
    ------
    PipescanError
        When the settings combine a registration method and engine that do not go together.
    """
    method = registration or settings.registration_method
    try:
        registration_params = RegistrationParams(method=method, engine=settings.registration_engine)
    except ValueError as exc:
        raise PipescanError(
            str(exc),
            field="PIPESCAN_REGISTRATION_METHOD, PIPESCAN_REGISTRATION_ENGINE",
            hint="set them together; docs/registration.md lists the combinations",
        ) from exc
    return InspectionParams(
        registration=registration_params,
        measure=MeasureParams(
            method=contour or settings.contour_method,
            grid=GridParams(k=settings.grid_k, s_threshold_rad=settings.grid_s_threshold_rad),
        ),
        step_m=settings.step_m,
        window_m=settings.window_m,
        chunk_frames=settings.chunk_frames,
        frame_stride=settings.frame_stride,
        placed_share=settings.placed_share,
        threshold_table=settings.threshold_table,
        pipe_class=settings.pipe_class,
        blockage_threshold_ratio=settings.blockage_threshold_ratio,
        flag_grade=settings.flag_grade,
    )


def absolute_location(location: str) -> str:
    """A local path made absolute (workers may run elsewhere); a URL unchanged."""
    if "://" in location:
        return location
    return str(Path(location).expanduser().resolve())


def refuse_password_in_url(location: str, what: str = "store") -> None:
    """Refuse a URL with a secret in it (``s3://KEY:SECRET@bucket/...``, a token as the user
    ``https://TOKEN@host/...``, in any link of an fsspec chain, or a pre-signed
    ``?X-Amz-Signature=...``) before it becomes a flow or deployment parameter, which Prefect
    keeps and shows.

    Raises
    ------
    PipescanError
        Naming the URL without its secrets.
    """
    from pipescan.storage.input.urls import url_secret, without_secrets

    if url_secret(location) is None:  # each link of a chain, as fsspec reads it
        return
    shown = without_secrets(location)
    raise PipescanError(
        f"the {what} URL {shown} holds a secret, which Prefect would keep with the run's "
        "parameters",
        hint="give the credentials to the machines that read it instead: for s3://, "
        "AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY or ~/.aws/credentials, see "
        "docs/operations.md",
    )


def _api_url_for_workers(uses_dask: bool) -> str | None:
    """The API a Dask worker must report its task runs to, when the flow runs on a temporary
    (ephemeral) Prefect server. Without it, each worker process would start a server of its
    own; with ``PREFECT_API_URL`` set, the setting travels with each task already."""
    if not uses_dask or PREFECT_API_URL.value():
        return None
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        return str(client.api_url)


def worst_pipes(outcomes: list[ArchiveOutcome], count: int) -> list[ArchiveOutcome]:
    """The ``count`` inspections with the highest peak blockage (unmeasured ones left out)."""
    measured = [o for o in outcomes if o.max_blockage_ratio is not None]
    return sorted(measured, key=lambda o: (-o.max_blockage_ratio, o.label))[:count]


def _pct(ratio: float | None) -> str:
    return "not measured" if ratio is None else f"{100 * ratio:.1f} %"


def progress_line(done: int, total: int, outcome: ArchiveOutcome) -> str:
    """One line of per-archive progress, e.g. ``[3/20] MH1-MH2 inspected in 12.3 s: ...``."""
    head = f"[{done}/{total}] {outcome.label}"
    if outcome.status == "failed":
        return f"{head} FAILED after {outcome.wall_time_s:.1f} s: {outcome.error}"
    if outcome.status == "missing":
        return f"{head} MISSING after {plural(outcome.attempts, 'attempt')}: {outcome.error}"
    what = (
        f"reused inspection {outcome.inspection_id} (already stored)"
        if outcome.status == "reused"
        else f"inspected in {outcome.wall_time_s:.1f} s as inspection {outcome.inspection_id}"
    )
    worst = (
        f", worst blockage {_pct(outcome.max_blockage_ratio)}"
        f" at {outcome.max_blockage_chainage_m:.1f} m"
        if outcome.max_blockage_chainage_m is not None
        else ""
    )
    defects = plural(outcome.defect_count or 0, "defect")
    return f"{head} {what}: asset {outcome.asset_id}, {defects}{worst}"


def retry_line(outcome: ArchiveOutcome, delay_s: float) -> str:
    """The line of an archive that failed for a transient cause and is tried again."""
    return (
        f"{outcome.label}: attempt {outcome.attempts} failed for a transient cause, trying "
        f"again in {delay_s:.0f} s: {outcome.error}"
    )


def counts_line(counts: dict[str, int]) -> str:
    """``2 inspected, 1 reused (already stored), ...``: the statuses a run had."""
    words = {
        "reused": "reused (already stored)",
        "duplicate": "the same content as another archive",
        "missing": "missing (to be taken first next time)",
    }
    parts = [f"{counts.get(k, 0)} {words.get(k, k)}" for k in STATUSES[:2]]
    parts += [f"{counts[k]} {words.get(k, k)}" for k in STATUSES[2:] if counts.get(k)]
    if not counts.get("failed") and not counts.get("missing"):
        parts.append("0 failed")
    return ", ".join(parts)


def incomplete_message(summary: NetworkSummary) -> str:
    """The Failed state's message of a run that left archives unstored: which ones, and why."""
    parts = []
    if summary.missing:
        parts.append(
            f"missing after {summary.retry_window_s / 60:.0f} min of retries (a transient "
            "cause; the next run takes them first): "
            + ", ".join(f"{o.label} ({o.error})" for o in summary.missing)
        )
    failed = [o for o in summary.failures if o.status == "failed"]
    bad = [o for o in failed if o.cause == CONTENT]
    if bad:
        parts.append(
            "failed for their own content (not retried; fix the archive): "
            + ", ".join(f"{o.label} ({o.error})" for o in bad)
        )
    erred = [o for o in failed if o.cause != CONTENT]
    if erred:
        parts.append(
            "failed on an error in pipescan (not retried; please report it): "
            + ", ".join(f"{o.label} ({o.error})" for o in erred)
        )
    count = len(summary.failures)
    return f"{count} of {plural(len(summary.outcomes), 'archive')} not stored: " + "; ".join(parts)


def format_network_summary(summary: NetworkSummary) -> list[str]:
    """The network summary as text lines (printed by the CLI, logged to the Prefect run)."""
    lines = [
        f"network run over {summary.store}: {plural(len(summary.outcomes), 'archive')} "
        f"in {summary.wall_time_s:.1f} s on {summary.executor}",
        f"  {counts_line(summary.counts)}",
    ]
    if summary.duplicates:
        lines.append("  the same content under two names (one inspection each, listed once):")
        lines += [
            f"    {o.label} = {o.same_as} (inspection {o.inspection_id})"
            for o in summary.duplicates
        ]
    if summary.missing:
        lines.append(
            f"  MISSING, a transient cause outlasted {summary.retry_window_s / 60:.0f} min of "
            "retries (nothing stored; the next run takes them first):"
        )
        lines += [
            f"    {o.label}: {plural(o.attempts, 'attempt')}, {o.error}" for o in summary.missing
        ]
    bad = [o for o in summary.failures if o.status == "failed"]
    if bad:
        lines.append("  failed for their own content (nothing stored, not retried; fix them):")
        lines += [f"    {o.label}: {o.error}" for o in bad]
    if summary.worst:
        lines.append("  worst pipes by peak blockage:")
        for rank, o in enumerate(summary.worst, 1):
            lines.append(
                f"    {rank}. {o.asset_id}  {_pct(o.max_blockage_ratio)} at "
                f"{o.max_blockage_chainage_m:.1f} m, {plural(o.defect_count or 0, 'defect')} "
                f"(inspection {o.inspection_id}, {o.label})"
            )
    if summary.network_report_path:
        lines.append(f"  network report: {summary.network_report_path}")
    if summary.network_report_error:
        lines.append(f"  network report NOT written: {summary.network_report_error}")
    return lines


def merge_duplicates(outcomes: list[ArchiveOutcome]) -> list[ArchiveOutcome]:
    """Archives stored as the same inspection (the same asset, content and parameters under
    two names, e.g. a folder and its zip): the first keeps its outcome (``inspected`` if
    either was processed now), the others become ``duplicate`` of it. Order is kept."""
    first: dict[int, ArchiveOutcome] = {}
    for o in outcomes:
        if o.inspection_id is None:
            continue
        kept = first.setdefault(o.inspection_id, o)
        if kept is not o and o.status == "inspected" and kept.status == "reused":
            first[o.inspection_id] = replace(kept, status="inspected")
    merged = []
    for o in outcomes:
        kept = first.get(o.inspection_id) if o.inspection_id is not None else None
        if kept is None:
            merged.append(o)
        elif kept.archive == o.archive:
            merged.append(kept)
        else:
            merged.append(replace(o, status="duplicate", same_as=kept.label))
    return merged


class NetworkIncomplete(PipescanError):
    """A network run ended with archives not stored; ``summary`` has the whole run."""

    def __init__(self, message: str, summary: NetworkSummary | None = None) -> None:
        super().__init__(message)
        self.summary = summary

    def __reduce__(self):
        return (type(self), (self.reason, self.summary))


def failed_reason(outcome: ArchiveOutcome, retry_window_s: float) -> str:
    """Why an archive is not stored, for the network report: what to do comes first, as a
    database outage asks for nothing but the next run, a bad archive for a person."""
    if outcome.status == "missing":
        return (
            f"not reached: a transient cause (the database or the Prefect server not answering) "
            f"outlasted {retry_window_s / 60:.0f} min of retries; the archive is probably fine "
            f"and the next run takes it first. {outcome.error}"
        )
    if outcome.cause == "content":
        return f"the archive itself (fix it; it is not retried): {outcome.error}"
    return f"an error of pipescan (report it with the run's log): {outcome.error}"


def _write_network_report(
    database_url: str,
    out_path: Path,
    inspection_ids: list[int],
    failed: list[ArchiveOutcome],
    retry_window_s: float = RETRY_WINDOW_S,
) -> tuple[str | None, str | None]:
    """Render the network report (listing the ``failed`` archives with their reasons) if
    this pipescan has one; returns (path, error)."""
    from pipescan.tasks import reporting

    render = getattr(reporting, "render_network_report", None)
    if render is None:
        log.info("no network report renderer in this pipescan: skipped")
        return None, None
    # A task of the run, so that the UI shows it; it writes a file, so I/O is retried.
    render_task = task(render, name="network-report", **IO_RETRY_OPTIONS)
    try:
        written = render_task(
            database_url,
            out_path,
            inspection_ids=inspection_ids,
            failed=[FailedArchive(o.label, failed_reason(o, retry_window_s)) for o in failed],
        )
    except Exception as exc:  # the inspections are stored; a report failure must not hide that
        log.warning("the network report failed: %s", exc)
        return None, f"{type(exc).__name__}: {exc}"
    return str(written), None


# --- the per-archive task and the flow --------------------------------------------------------


@task(name="archive", cache_policy=NO_CACHE)
def inspect_one_archive(
    archive: str,
    label: str,
    database_url: str,
    params: InspectionParams,
    work_dir: str,
    runner_kind: str,
    workers: int,
    report_path: str | None,
    reuse_stored: bool,
) -> ArchiveOutcome:
    """Run the ``inspect-archive`` sub-flow for one archive, named after it, its chunk and
    window tasks on a local pool of ``workers``; an error of this archive becomes a
    ``failed`` outcome instead of stopping the network run.

    On Dask, this task is the unit sent to a worker: an archive path in, a small outcome out.
    The database URL is a task argument (Prefect keeps no task arguments; a Dask worker gets it
    with the task) and reaches the sub-flow as a setting, never as a flow parameter.
    """
    started = time.perf_counter()
    subflow = inspect_archive.with_options(
        flow_run_name=label, task_runner=make_task_runner(runner_kind, workers)
    )
    state = None
    try:
        # The network run resolved the URL (and any Secret block's password) already.
        with use_settings(database_url=database_url, database_password_block=""):
            state = subflow(
                archive=archive,
                report_path=report_path,
                params=params,
                work_dir=work_dir,
                reuse_stored=reuse_stored,
                return_state=True,
            )
        summary = state.result()
    except (Exception, Abort) as exc:  # Abort: Prefect took the sub-flow for crashed
        outcome = failed_outcome(archive, label, exc, time.perf_counter() - started)
        if state is not None:
            outcome = replace(outcome, subflow_run_id=str(state.state_details.flow_run_id))
        return outcome
    return ArchiveOutcome.from_summary(archive, label, summary, time.perf_counter() - started)


def failed_outcome(
    archive: str, label: str, exc: BaseException, wall_s: float, attempts: int = 1
) -> ArchiveOutcome:
    """A ``failed`` outcome, with its cause (:func:`pipescan.tasks.retries.failure_cause`)."""
    return ArchiveOutcome(
        archive=strip_credentials(archive),
        label=label,
        status="failed",
        wall_time_s=wall_s,
        error=strip_credentials_in_text(str(exc)) or type(exc).__name__,
        error_type=type(exc).__name__,
        cause=failure_cause(exc),
        attempts=attempts,
    )


# The hooks e-mail a failed run and follow a deployment's run's last heartbeat.
@flow(name="inspect-network", **RUN_HOOKS)
def inspect_network(
    store: str,
    params: InspectionParams | None = None,
    work_dir: str | None = None,
    concurrency: int | None = None,
    dask_address: str | None = None,
    task_runner: str | None = None,
    workers: int | None = None,
    reports_dir: str | None = None,
    network_report_path: str | None = None,
    write_network_report: bool = True,
    reuse_stored: bool = True,
    worst_count: int = 5,
    retry_window_s: float | None = None,
    startup_wait_s: float | None = None,
) -> NetworkSummary:
    """Inspect every archive of a store; end with a network summary (and the network report).

    The database is the one of the settings where the flow runs (``PIPESCAN_DATABASE_URL``,
    with ``PIPESCAN_DATABASE_PASSWORD_BLOCK``; :func:`pipescan.settings.use_settings`), never
    a parameter. It is checked once (reachable, migrated, writable) before any archive.

    The stages: :func:`_announce_attempt`, :func:`_plan_run` (the settings, the database),
    ``discover_archives``, :func:`_inspect_archives` (the archives' tasks, retries),
    :func:`_summarise` (the summary, the network report). (Over 80 lines for this docstring
    only, the parameters' reference that Prefect's UI shows: the body is its stages.)

    Parameters
    ----------
    store
        A local directory or fsspec URL holding the archives (see
        :func:`pipescan.tasks.network.find_archives`).
    work_dir, concurrency, dask_address, task_runner, workers
        None: from the settings (``PIPESCAN_WORK_DIR``, ``PIPESCAN_NETWORK_CONCURRENCY``,
        ``PIPESCAN_DASK_ADDRESS``, ``PIPESCAN_TASK_RUNNER``, ``PIPESCAN_WORKERS``) of the
        process that runs the flow, e.g. a deployment's worker. ``concurrency`` archives are
        processed at once (default 2, or on Dask the cluster's worker threads). With a Dask
        address, each archive is one task on the cluster (whose workers must see the store,
        the work folder and the database); within an archive, its chunk and window tasks run
        on a local pool (``task_runner``: threads or processes) of ``workers``.
    params
        None: from the settings, as ``pipescan inspect`` does.
    reports_dir
        If given, each inspection's PDF report is written there as ``<archive>.pdf``, and the
        network report too (unless ``network_report_path`` names another place).
    network_report_path, write_network_report
        Where to write the network report when this pipescan can render one; default
        ``<reports_dir or PIPESCAN_REPORTS_DIR>/network-<date>-<run name>.pdf``, so that each
        run keeps its own.
    reuse_stored
        Skip (and summarise) archives already stored with the same content and parameters;
        False processes every archive again (each inspection is still stored once).
    worst_count
        How many of the worst pipes the summary lists.
    retry_window_s
        How long after its first failure an archive that failed for a transient cause is
        tried again (None: :data:`RETRY_WINDOW_S`, 15 min; 0: never).
    startup_wait_s
        How long the database check at the start is repeated while the database does not
        answer (None: :data:`DATABASE_WAIT_S`, 5 min, in a deployment's run; 0 otherwise,
        where a person waits for the answer).

    Returns
    -------
    NetworkSummary
        When every archive is stored. Otherwise the run ends Failed, its message naming the
        archives not stored, and calling the flow raises :class:`NetworkIncomplete`, whose
        ``summary`` is the whole run's.

    Raises
    ------
    StorageError
        The database is unreachable (for ``startup_wait_s``), not migrated or refuses writes;
        or, in a scheduled run, the worker names no database (one error, before any archive).
    StoreError
        The store does not exist or holds no archive. A failing archive does not raise.
    NetworkIncomplete
        Archives were left unstored (see Returns).
    """
    started = time.perf_counter()
    run_log = get_run_logger()
    s = get_settings()
    _announce_attempt(s, reports_dir, reuse_stored, run_log)
    plan = _plan_run(
        s,
        run_log,
        params=params,
        work_dir=work_dir,
        concurrency=concurrency,
        dask_address=dask_address,
        task_runner=task_runner,
        workers=workers,
        reports_dir=reports_dir,
        network_report_path=network_report_path,
        write_network_report=write_network_report,
        reuse_stored=reuse_stored,
        retry_window_s=retry_window_s,
        startup_wait_s=startup_wait_s,
    )
    archives = discover_archives(absolute_location(store))
    outcomes = _inspect_archives(plan, store, archives, s, run_log)
    summary = _summarise(plan, store, [outcomes[a] for a in archives], worst_count, started)
    for line in format_network_summary(summary):
        run_log.info(line)
    _leave_outcomes(summary)
    if summary.failures:
        # Not green: Prefect's list, its UI and the automations see a Failed run, with the
        # archives not stored in its message; the caller gets them with the summary.
        message = incomplete_message(summary)
        return Failed(message=message, data=NetworkIncomplete(message, summary))
    return summary


# --- the flow's stages ------------------------------------------------------------------------


@dataclass(frozen=True)
class _RunPlan:
    """How a network run works: its parameters, with the settings filling what they left
    unset (:func:`_plan_run`)."""

    database_url: str
    params: InspectionParams
    work_dir: str
    reports_dir: str | None
    report_out: Path | None
    reuse_stored: bool
    retry_window_s: float
    concurrency: int | None
    dask_address: str | None
    runner_kind: str
    workers: int

    @property
    def executor(self) -> str:
        """Where the archives run, in words (``local threads x2 per archive``)."""
        local = f"{self.runner_kind} x{self.workers} per archive"
        return f"dask {self.dask_address} ({local})" if self.dask_address else f"local {local}"


def _announce_attempt(settings, reports_dir: str | None, reuse_stored: bool, run_log) -> None:
    """Keep a scheduled run's output (:func:`_keep_scheduled_output`); in a run retried after
    a crash (:mod:`pipescan.flows.deploy`), close its earlier attempts' runs and say so."""
    died_of = _keep_scheduled_output(settings, reports_dir, run_log)
    if flow_run.run_count <= 1:
        return
    closed = close_earlier_attempts(flow_run.id, flow_run.name, died_of)
    _progress(
        run_log,
        f"attempt {flow_run.run_count} of this run: {closed[0]} sub-flow and {closed[1]} "
        "task runs of the earlier attempts marked Crashed"
        + ("; archives already stored are reused" if reuse_stored else "")
        + (f"; the earlier attempt died of: {died_of}" if died_of else ""),
        failed=bool(died_of),
    )


def _plan_run(
    s,
    run_log,
    *,
    params: InspectionParams | None,
    work_dir: str | None,
    concurrency: int | None,
    dask_address: str | None,
    task_runner: str | None,
    workers: int | None,
    reports_dir: str | None,
    network_report_path: str | None,
    write_network_report: bool,
    reuse_stored: bool,
    retry_window_s: float | None,
    startup_wait_s: float | None,
) -> _RunPlan:
    """The run's plan from the flow's parameters and the settings ``s``, once the database
    answers (:func:`wait_for_database`)."""
    if startup_wait_s is None:
        startup_wait_s = DATABASE_WAIT_S if in_deployment() else 0.0
    database_url = wait_for_database(s, startup_wait_s, run_log)
    report_out = None
    if write_network_report:
        reports = Path(reports_dir) if reports_dir else s.reports_dir
        report_out = _network_report_out(network_report_path, reports)
    runner_kind = task_runner or s.task_runner
    if runner_kind == "dask":  # the chunk and window tasks run beside their archive's task
        runner_kind = "threads"
    return _RunPlan(
        database_url=database_url,
        params=params or params_from_settings(s),
        work_dir=absolute_location(str(work_dir or s.work_dir)),
        reports_dir=reports_dir,
        report_out=report_out,
        reuse_stored=reuse_stored,
        retry_window_s=RETRY_WINDOW_S if retry_window_s is None else retry_window_s,
        concurrency=concurrency,
        dask_address=dask_address or s.dask_address,
        runner_kind=runner_kind,
        workers=workers or s.workers,
    )


def _inspect_archives(
    plan: _RunPlan, store: str, archives: list[str], s, run_log
) -> dict[str, ArchiveOutcome]:
    """Each archive's outcome: its ``archive`` task submitted to the run's pool, archives
    without a stored inspection first, transient failures tried again (:func:`_run_archives`)."""
    labels = dict(zip(archives, _unique_labels(archives), strict=True))
    # Archives with no stored inspection go first: those an earlier run left missing (and
    # new ones), so that a short night still catches up.
    order = unstored_first(archives, find_stored_archives(plan.database_url))
    # On Dask each archive is one task on a worker (its chunks and windows on the worker's
    # own pool): Prefect's overhead per Dask task run (~0.15 s) would otherwise eat a large
    # share of a register-chunk or measure-window task (see docs/orchestration.md).
    pool = (
        make_task_runner("dask", dask_address=plan.dask_address)
        if plan.dask_address
        else ThreadPoolTaskRunner(max_workers=plan.concurrency or s.network_concurrency or 2)
    )
    api_url = _api_url_for_workers(bool(plan.dask_address))
    api = temporary_settings({PREFECT_API_URL: api_url}) if api_url else nullcontext()
    # The sub-flows carry this run's tags (a deployment's), which its recovery automations
    # look for (pipescan.flows.deploy).
    with api, pool, tags(*(flow_run.tags or [])):
        concurrency = plan.concurrency or s.network_concurrency
        if not concurrency:
            concurrency = sum(pool.client.nthreads().values()) if plan.dask_address else 2
        _progress(
            run_log,
            f"{len(archives)} archives in {strip_credentials(store)}; "
            f"{concurrency} at a time on {plan.executor}",
        )

        def submit(archive: str):
            label = labels[archive]
            return pool.submit(
                inspect_one_archive.with_options(task_run_name=f"archive {label}"),
                parameters={
                    "archive": archive,
                    "label": label,
                    "database_url": plan.database_url,
                    "params": plan.params,
                    "work_dir": plan.work_dir,
                    "runner_kind": plan.runner_kind,
                    "workers": plan.workers,
                    "report_path": (
                        str(Path(plan.reports_dir) / f"{label}.pdf") if plan.reports_dir else None
                    ),
                    "reuse_stored": plan.reuse_stored,
                },
            )

        return _run_archives(
            order, labels, submit, concurrency, plan.retry_window_s, run_log, len(archives)
        )


def _summarise(
    plan: _RunPlan, store: str, outcomes: list[ArchiveOutcome], worst_count: int, started: float
) -> NetworkSummary:
    """The run's summary, with the network report written (when the run asks for one and
    stored anything), from its archives' outcomes in the store's order."""
    ordered = merge_duplicates(outcomes)
    report_path = report_error = None
    ids = list(dict.fromkeys(o.inspection_id for o in ordered if o.inspection_id is not None))
    if plan.report_out is not None and ids:
        not_stored = [o for o in ordered if not o.stored]
        report_path, report_error = _write_network_report(
            plan.database_url, plan.report_out, ids, not_stored, plan.retry_window_s
        )
    return NetworkSummary(
        store=strip_credentials(store),
        executor=plan.executor,
        outcomes=ordered,
        worst=worst_pipes([o for o in ordered if o.status != "duplicate"], worst_count),
        wall_time_s=time.perf_counter() - started,
        network_report_path=report_path,
        network_report_error=report_error,
        counts={k: sum(o.status == k for o in ordered) for k in STATUSES},
        retry_window_s=plan.retry_window_s,
    )


def _run_archives(
    order: list[str],
    labels: dict[str, str],
    submit,
    concurrency: int,
    retry_window_s: float,
    run_log,
    total: int,
) -> dict[str, ArchiveOutcome]:
    """Run each archive's task, ``concurrency`` at a time; an archive that fails for a
    transient cause is submitted again after a backoff while its window lasts, and is
    ``missing`` when the window closes. Returns each archive's last outcome."""
    queue: list[tuple[float, str]] = [(0.0, a) for a in order]  # (not before, archive)
    attempts: dict[str, int] = {}
    first_failed: dict[str, float] = {}
    outcomes: dict[str, ArchiveOutcome] = {}
    pending: dict = {}
    left_open: list[str] = []  # sub-flow runs of transient failures
    while queue or pending:
        now = time.monotonic()
        for due, archive in [q for q in queue if q[0] <= now]:
            if len(pending) >= max(1, concurrency):
                break
            queue.remove((due, archive))
            attempts[archive] = attempts.get(archive, 0) + 1
            pending[submit(archive)] = archive
        next_due = min((q[0] for q in queue), default=None)
        wait_s = None if next_due is None else max(0.05, next_due - time.monotonic())
        if not pending:
            time.sleep(wait_s or 0.05)
            continue
        try:
            finished = next(iter(as_completed(list(pending), timeout=wait_s)))
        except TimeoutError:  # a retry is due and a slot may be free
            continue
        archive = pending.pop(finished)
        started = time.monotonic()
        try:
            outcome = replace(finished.result(), attempts=attempts[archive])
        except (Exception, Abort) as exc:  # the task itself did not finish (its API calls)
            outcome = failed_outcome(archive, labels[archive], exc, 0.0, attempts[archive])
        if outcome.status == "failed" and outcome.cause == TRANSIENT:
            if outcome.subflow_run_id:
                left_open.append(outcome.subflow_run_id)
            first = first_failed.setdefault(archive, started)
            delay = backoff_delay(RETRY_FIRST_DELAY_S, RETRY_MAX_DELAY_S, attempts[archive])
            if started + delay - first <= retry_window_s:
                queue.append((started + delay, archive))
                _progress(run_log, retry_line(outcome, delay), failed=True)
                continue
            outcome = replace(outcome, status="missing")
        outcomes[archive] = outcome
        line = progress_line(len(outcomes), total, outcome)
        _progress(run_log, line, failed=not outcome.stored)
    # A sub-flow that failed for a transient cause can leave a task run Pending for good (seen:
    # a concurrency slot refused after a Prefect server outage). Closed now, not when it failed:
    # task-run states reach Prefect's database through its event pipeline, later.
    for subflow_run_id in left_open:
        close_task_runs_of(
            subflow_run_id, "its sub-flow failed for a transient cause; the archive was tried again"
        )
    close_leftovers(flow_run.id)  # what an outage of Prefect's database left active
    return outcomes


def wait_for_database(settings, wait_s: float, run_log) -> str:
    """The run's database (:func:`checked_database_url`), checked again while it does not
    answer (a transient cause), for up to ``wait_s`` seconds, with backoff.

    Raises
    ------
    StorageError
        What is wrong with the database, once the wait is over or at once when it is not
        transient (a refused login, a missing schema, a scheduled run without a database).
    """
    started = time.monotonic()
    retry = 0
    while True:
        try:
            return checked_database_url(settings)
        except PipescanError as exc:  # also a Secret block that Prefect's API did not give
            retry += 1
            delay = backoff_delay(DATABASE_FIRST_DELAY_S, DATABASE_MAX_DELAY_S, retry)
            waited = time.monotonic() - started
            if failure_cause(exc) != TRANSIENT or waited + delay > wait_s:
                if retry > 1:
                    raise type(exc)(
                        f"{exc.reason} (still so after {waited:.0f} s of trying)",
                        field=exc.field,
                        hint=exc.hint,
                    ) from exc
                raise
            line = (
                f"the database does not answer, trying again in {delay:.0f} s (for up to "
                f"{wait_s:.0f} s in all): {exc}"
            )
            if run_log is log:  # the command line's check, before any run
                log.warning(line)
            else:
                _progress(run_log, line, failed=True)
            time.sleep(delay)


def _leave_outcomes(summary: NetworkSummary) -> None:
    """Each archive's outcome as a table artifact of the run, where the UI shows it and
    ``pipescan runs`` reads it. A failure to write it is logged, not fatal."""
    from prefect.artifacts import create_table_artifact

    rows = [
        {
            "archive": o.label,
            "uri": o.archive,
            "status": o.status,
            "inspection": o.inspection_id,
            "attempts": o.attempts,
            "cause": o.cause,
            "same_as": o.same_as,
            "error": o.error,
        }
        for o in summary.outcomes
    ]
    try:
        create_table_artifact(
            table=rows,
            key=OUTCOMES_ARTIFACT,
            description=counts_line(summary.counts),
        )
    except Exception as exc:  # the API may be down; the log has the same lines
        log.warning("the run's outcome table was not written to Prefect: %s", exc)


def _keep_scheduled_output(settings, reports_dir: str | None, run_log) -> str | None:
    """In a deployment's run, send the process's output to its file in the reports folder
    (``logs/network-<date>-<run>.log``, :func:`pipescan.flows.recovery.keep_output`), and
    return the error the earlier attempt of a retried run died of, if its output says."""
    if not in_deployment():
        return None
    folder = (Path(reports_dir) if reports_dir else settings.reports_dir).expanduser()
    if not folder.is_absolute():  # the run fails on it shortly, saying so
        return None
    stem = network_report_name(flow_run.name, flow_run.scheduled_start_time).removesuffix(".pdf")
    path = run_output_path(folder, stem)
    died_of = last_error(path) if flow_run.run_count > 1 else None
    try:
        keep_output(path, flow_run.run_count, flow_run.name)
    except OSError as exc:
        run_log.warning(f"this run's process output goes nowhere: cannot write {path}: {exc}")
        return died_of
    run_log.info(f"this run's process output (errors included): {path} on the worker")
    end_promptly_on_sigterm(flow_run.id, flow_run.name)  # a cancel ends it in seconds
    return died_of


def _progress(run_log, line: str, *, failed: bool = False) -> None:
    """A progress line: to the run's log in Prefect (its UI shows how far a run is, also for a
    scheduled run) and to the ``pipescan`` logger for the terminal only (Prefect's handler on
    that logger would send the line to the run's log a second time)."""
    level = logging.WARNING if failed else logging.INFO
    run_log.log(level, line)
    log.log(level, line, extra={"send_to_api": False})


def network_report_name(run_name: str | None, when: datetime) -> str:
    """The network report's file name for a run: by date and run, so that each run keeps its
    own, e.g. ``network-2026-11-24-cerise-lemming.pdf``."""
    run = re.sub(r"[^A-Za-z0-9_.-]+", "-", run_name or "run").strip("-.") or "run"
    return f"network-{when:%Y-%m-%d}-{run}.pdf"


def _network_report_out(explicit: str | None, reports_dir: Path) -> Path:
    """Where this run writes its network report.

    Raises
    ------
    PipescanError
        In a scheduled run with a relative reports folder: it would be resolved in the run's
        temporary folder and deleted with it.
    """
    if explicit:
        return Path(absolute_location(explicit))
    if in_deployment() and not reports_dir.expanduser().is_absolute():
        raise PipescanError(
            f"the worker's reports folder {str(reports_dir)!r} is relative, which a scheduled "
            "run would resolve in its temporary folder",
            field="PIPESCAN_REPORTS_DIR",
            hint="set it to an absolute folder in the worker's environment (docs/operations.md)",
        )
    name = network_report_name(flow_run.name, flow_run.scheduled_start_time)
    return Path(absolute_location(str(reports_dir))) / name


def _unique_labels(archives: list[str]) -> list[str]:
    """Archive labels, made unique with a counter where two archives share a name."""
    seen: dict[str, int] = {}
    labels = []
    for archive in archives:
        label = archive_label(archive)
        seen[label] = seen.get(label, 0) + 1
        labels.append(label if seen[label] == 1 else f"{label}-{seen[label]}")
    return labels
