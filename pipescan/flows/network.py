"""The ``inspect-network`` flow: every scan archive of a store, each in its own sub-flow.

Work fans out on three levels: over archives (a bounded number of ``inspect-archive``
sub-flows at once, each named after its archive), and within each archive over frame chunks
and chainage windows, on a local pool or a Dask cluster. Tasks receive paths, ids and small
dataclasses, so nothing big crosses the wire to a Dask worker.

A failing archive fails alone: its error is recorded in the network summary and on its
sub-flow run, and the other archives go on. An archive whose content was already inspected
under the same parameters is not processed again (``reuse_stored``), so a run that was killed
can simply be started again: it finishes the remaining archives, and the database keeps one
copy of each inspection.
"""

from __future__ import annotations

import logging
import re
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from urllib.parse import urlsplit

from prefect import flow, get_run_logger, tags, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed
from prefect.runtime import flow_run
from prefect.settings import PREFECT_API_URL, temporary_settings
from prefect.task_runners import ThreadPoolTaskRunner

from pipescan.core.contour.grid import GridParams
from pipescan.core.errors import PipescanError
from pipescan.core.measures import MeasureParams
from pipescan.core.registration import RegistrationParams
from pipescan.core.sanitize import REDACTED, strip_credentials
from pipescan.core.wording import plural
from pipescan.flows.database import checked_database_url, in_deployment
from pipescan.flows.inspect import InspectionParams, InspectionSummary, inspect_archive
from pipescan.flows.recovery import close_earlier_attempts
from pipescan.flows.runners import make_task_runner
from pipescan.reports.network import FailedArchive
from pipescan.settings import get_settings, use_settings
from pipescan.tasks.network import IO_RETRY_OPTIONS, archive_label, discover_archives

log = logging.getLogger("pipescan")


@dataclass(frozen=True)
class ArchiveOutcome:
    """What became of one archive of a network run.

    ``status`` is ``inspected`` (processed and stored now), ``reused`` (already stored under
    the same content and parameters) or ``failed`` (``error`` says why; nothing was stored).
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

    @property
    def failures(self) -> list[ArchiveOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]

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
    """Refuse a URL with a secret in it (``s3://KEY:SECRET@bucket/...``, or a pre-signed
    ``?X-Amz-Signature=...``) before it becomes a flow or deployment parameter, which Prefect
    keeps and shows.

    Raises
    ------
    PipescanError
        Naming the URL without its secrets.
    """
    if "://" not in location:
        return
    try:
        password = urlsplit(location).password
    except ValueError:  # an unparseable port: not ours to judge
        password = None
    shown = strip_credentials(location)
    secret_query = f"={REDACTED}" in shown and f"={REDACTED}" not in location
    if password is None and not secret_query:
        return
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


def format_network_summary(summary: NetworkSummary) -> list[str]:
    """The network summary as text lines (printed by the CLI, logged to the Prefect run)."""
    c = summary.counts
    lines = [
        f"network run over {summary.store}: {plural(len(summary.outcomes), 'archive')} "
        f"in {summary.wall_time_s:.1f} s on {summary.executor}",
        f"  {c.get('inspected', 0)} inspected, {c.get('reused', 0)} reused (already stored), "
        f"{c.get('failed', 0)} failed",
    ]
    if summary.failures:
        lines.append("  failed archives (nothing stored for them):")
        lines += [f"    {o.label}: {o.error}" for o in summary.failures]
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


def _write_network_report(
    database_url: str, out_path: Path, inspection_ids: list[int], failed: list[ArchiveOutcome]
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
            failed=[FailedArchive(o.label, o.error or "failed") for o in failed],
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
    try:
        # The network run resolved the URL (and any Secret block's password) already.
        with use_settings(database_url=database_url, database_password_block=""):
            summary = subflow(
                archive=archive,
                report_path=report_path,
                params=params,
                work_dir=work_dir,
                reuse_stored=reuse_stored,
            )
    except Exception as exc:
        return ArchiveOutcome(
            archive=strip_credentials(archive),
            label=label,
            status="failed",
            wall_time_s=time.perf_counter() - started,
            error=str(exc),
            error_type=type(exc).__name__,
        )
    return ArchiveOutcome.from_summary(archive, label, summary, time.perf_counter() - started)


@flow(name="inspect-network")
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
) -> NetworkSummary:
    """Inspect every archive of a store; end with a network summary (and the network report).

    The database is the one of the settings where the flow runs (``PIPESCAN_DATABASE_URL``,
    with ``PIPESCAN_DATABASE_PASSWORD_BLOCK``; :func:`pipescan.settings.use_settings`), never
    a parameter. It is checked once (reachable, migrated, writable) before any archive.

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
        If given, each inspection's PDF report is written there as ``<archive>.pdf``.
    network_report_path, write_network_report
        Where to write the network report when this pipescan can render one; default
        ``<PIPESCAN_REPORTS_DIR>/network-<date>-<run name>.pdf``, so that each run keeps its own.
    reuse_stored
        Skip (and summarise) archives already stored with the same content and parameters;
        False processes every archive again (each inspection is still stored once).
    worst_count
        How many of the worst pipes the summary lists.

    Raises
    ------
    StorageError
        The database is unreachable, not migrated or refuses writes; or, in a scheduled run,
        the worker names no database (one error, before any archive).
    StoreError
        The store does not exist or holds no archive. A failing archive does not raise.
    """
    started = time.perf_counter()
    run_log = get_run_logger()
    if flow_run.run_count > 1:  # retried after a crash (pipescan.flows.deploy)
        closed = close_earlier_attempts(flow_run.id, flow_run.name)
        _progress(
            run_log,
            f"attempt {flow_run.run_count} of this run: {closed[0]} sub-flow and {closed[1]} "
            "task runs of the earlier attempts marked Crashed"
            + ("; archives already stored are reused" if reuse_stored else ""),
        )
    s = get_settings()
    database_url = checked_database_url(s)
    params = params or params_from_settings(s)
    work_dir = absolute_location(str(work_dir or s.work_dir))
    report_out = (
        _network_report_out(network_report_path, s.reports_dir) if write_network_report else None
    )
    dask_address = dask_address or s.dask_address
    runner_kind = task_runner or s.task_runner
    if runner_kind == "dask":  # the chunk and window tasks run beside their archive's task
        runner_kind = "threads"
    workers = workers or s.workers
    local = f"{runner_kind} x{workers} per archive"
    executor = f"dask {dask_address} ({local})" if dask_address else f"local {local}"

    archives = discover_archives(absolute_location(store))
    total = len(archives)
    labels = _unique_labels(archives)
    # On Dask each archive is one task on a worker (its chunks and windows on the worker's
    # own pool): Prefect's overhead per Dask task run (~0.15 s) would otherwise eat a large
    # share of a register-chunk or measure-window task (see docs/orchestration.md).
    pool = (
        make_task_runner("dask", dask_address=dask_address)
        if dask_address
        else ThreadPoolTaskRunner(max_workers=concurrency or s.network_concurrency or 2)
    )
    api_url = _api_url_for_workers(bool(dask_address))
    settings = temporary_settings({PREFECT_API_URL: api_url}) if api_url else nullcontext()
    outcomes: dict[str, ArchiveOutcome] = {}
    # The sub-flows carry this run's tags (a deployment's), which its recovery automations
    # look for (pipescan.flows.deploy).
    with settings, pool, tags(*(flow_run.tags or [])):
        if not concurrency:
            concurrency = s.network_concurrency or (
                sum(pool.client.nthreads().values()) if dask_address else 2
            )
        _progress(
            run_log,
            f"{total} archives in {strip_credentials(store)}; "
            f"{concurrency} at a time on {executor}",
        )
        queue = list(zip(archives, labels, strict=True))
        pending: dict = {}
        while queue or pending:
            while queue and len(pending) < max(1, concurrency):
                archive, label = queue.pop(0)
                future = pool.submit(
                    inspect_one_archive.with_options(task_run_name=f"archive {label}"),
                    parameters={
                        "archive": archive,
                        "label": label,
                        "database_url": database_url,
                        "params": params,
                        "work_dir": work_dir,
                        "runner_kind": runner_kind,
                        "workers": workers,
                        "report_path": (
                            str(Path(reports_dir) / f"{label}.pdf") if reports_dir else None
                        ),
                        "reuse_stored": reuse_stored,
                    },
                )
                pending[future] = archive
            finished = next(iter(as_completed(list(pending))))
            outcome = finished.result()
            outcomes[pending.pop(finished)] = outcome
            line = progress_line(len(outcomes), total, outcome)
            _progress(run_log, line, failed=outcome.status == "failed")

    ordered = [outcomes[a] for a in archives]
    counts = {k: sum(o.status == k for o in ordered) for k in ("inspected", "reused", "failed")}
    report_path = report_error = None
    ids = [o.inspection_id for o in ordered if o.inspection_id is not None]
    if report_out is not None and ids:
        failed = [o for o in ordered if o.status == "failed"]
        report_path, report_error = _write_network_report(database_url, report_out, ids, failed)
    summary = NetworkSummary(
        store=strip_credentials(store),
        executor=executor,
        outcomes=ordered,
        worst=worst_pipes(ordered, worst_count),
        wall_time_s=time.perf_counter() - started,
        network_report_path=report_path,
        network_report_error=report_error,
        counts=counts,
    )
    for line in format_network_summary(summary):
        run_log.info(line)
    return summary


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
