"""Prefect tasks and helpers that turn stored inspections into reports."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

import pipescan
from pipescan.core.grading import DEFAULT_TABLE, FlagRule, load_table, worst_defect
from pipescan.core.wording import plural
from pipescan.reports.context import (
    EarlierInspection,
    ReportInput,
    TableCitation,
    build_context,
    fmt_datetime,
)
from pipescan.reports.network import (
    EarlierScan,
    FailedArchive,
    NetworkInput,
    PipeInspection,
    build_network_context,
)
from pipescan.reports.render import render_network_pdf, render_pdf
from pipescan.storage.database.db import connect, session_scope
from pipescan.storage.database.network import placements
from pipescan.storage.database.queries import (
    defect_counts,
    defects_by_inspection,
    list_earlier_inspections,
    list_earlier_scans,
    list_network_inspections,
    section_profiles,
)
from pipescan.storage.database.repository import get_inspection, list_defects, list_sections
from pipescan.tasks.retries import IO_RETRY_OPTIONS

__all__ = [
    "load_network_input",
    "load_report_input",
    "network_message",
    "render_network_report",
    "render_network_report_task",
    "render_report",
    "report_message",
]

#: Earlier inspections of the asset loaded for the trend page.
TREND_HISTORY = 4


def _citation(table_name: str) -> TableCitation:
    try:
        table = load_table(table_name)
        return TableCitation(name=table.name, source=table.source)
    except Exception:  # a table removed since the run: still report, naming it
        return TableCitation(name=table_name, source="(table no longer installed)")


def load_report_input(database_url: str, inspection_id: int) -> ReportInput:
    """Gather one inspection's report input from the database, with the asset's earlier
    inspections (up to :data:`TREND_HISTORY`) for the trend page."""
    engine = connect(database_url)
    try:
        with session_scope(engine) as session:
            rec = get_inspection(session, inspection_id)
            sections = list_sections(session, inspection_id)
            defects = list_defects(session, inspection_id)
            earlier = list_earlier_inspections(session, inspection_id, limit=TREND_HISTORY)
            ids = [e.id for e in earlier]
            profiles = section_profiles(session, ids)
            counts = defect_counts(session, ids)
        reach = max((sec.chainage_end_m for sec in sections), default=None)
        placement = placements(engine, {rec.asset_id: reach})[rec.asset_id]
    finally:
        engine.dispose()
    params = rec.params or {}
    flag_rule = FlagRule.from_params(params)
    table_name = rec.threshold_table or params.get("threshold_table", DEFAULT_TABLE)
    return ReportInput(
        asset_id=rec.asset_id,
        upstream_node=rec.upstream_node,
        downstream_node=rec.downstream_node,
        inspected_at=rec.inspected_at,
        nominal_diameter_m=rec.nominal_diameter_m,
        material=rec.material,
        pipe_shape=rec.pipe_shape,
        inspection_id=rec.id,
        archive_uri=rec.archive_uri,
        software_version=rec.software_version,
        threshold_table=_citation(table_name),
        blockage_threshold_ratio=flag_rule.blockage_threshold_ratio,
        point_count=rec.point_count,
        frame_count=rec.frame_count,
        scanned_length_m=rec.scanned_length_m,
        registration=rec.registration,
        sections=sections,
        defects=defects,
        generated_at=datetime.now(UTC),
        flag_grade=flag_rule.flag_grade,
        pipe_class=params.get("pipe_class", "rigid"),
        pipe_class_reason=params.get("pipe_class_reason", "set for the run"),
        gis_id=placement.gis_id,
        length_note=placement.length_note,
        start_source=rec.start_source,
        measure_limits=params.get("measure"),
        history=[
            EarlierInspection(
                inspection_id=e.id,
                inspected_at=e.inspected_at,
                sections=profiles[e.id],
                defect_count=counts[e.id],
            )
            for e in earlier
        ],
    )


def load_network_input(
    database_url: str,
    *,
    since: datetime | None = None,
    inspection_ids: list[int] | None = None,
    failed: Sequence[FailedArchive] = (),
) -> NetworkInput:
    """Gather a network summary's input: the latest selected inspection of each asset, with
    the asset's earlier scans (their stored peak blockage) for its growth, and the run's
    archives that ``failed``."""
    engine = connect(database_url)
    try:
        with session_scope(engine) as session:
            records = list_network_inspections(session, since=since, inspection_ids=inspection_ids)
            ids = [r.id for r in records]
            history = list_earlier_scans(session, ids)
            profiles = section_profiles(session, ids)
            counts = defect_counts(session, ids)
            defects = defects_by_inspection(session, ids)
        placed = placements(
            engine,
            {
                r.asset_id: max((sec.chainage_end_m for sec in profiles[r.id]), default=None)
                for r in records
            },
        )
    finally:
        engine.dispose()
    pipes = []
    for r in records:
        pipes.append(
            PipeInspection(
                asset_id=r.asset_id,
                upstream_node=r.upstream_node,
                downstream_node=r.downstream_node,
                nominal_diameter_m=r.nominal_diameter_m,
                material=r.material,
                inspection_id=r.id,
                inspected_at=r.inspected_at,
                sections=profiles[r.id],
                defect_count=counts[r.id],
                worst_defect=worst_defect(defects[r.id]),
                earlier=[
                    EarlierScan(e.id, e.inspected_at, e.peak_blockage_ratio)
                    for e in reversed(history[r.id])
                ],
                gis_id=placed[r.asset_id].gis_id,
                length_note=placed[r.asset_id].length_note,
            )
        )
    network_rule = FlagRule.from_params((records[0].params or {}) if records else {})
    table_names = sorted({r.threshold_table or DEFAULT_TABLE for r in records})
    return NetworkInput(
        pipes=pipes,
        generated_at=datetime.now(UTC),
        software_version=pipescan.__version__,
        blockage_threshold_ratio=network_rule.blockage_threshold_ratio,
        flag_grade=network_rule.flag_grade,
        threshold_tables=[_citation(name) for name in table_names],
        since=since,
        failed=list(failed),
    )


@task(name="render-report", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def render_report(database_url: str, inspection_id: int, out_path: Path) -> Path:
    """Render one inspection's PDF condition report from the database."""
    return render_pdf(load_report_input(database_url, inspection_id), out_path)


def render_network_report(
    database_url: str,
    out_path: Path,
    *,
    since: datetime | None = None,
    inspection_ids: list[int] | None = None,
    failed: Sequence[FailedArchive] = (),
) -> Path:
    """Render the network summary PDF of a set of inspections.

    Parameters
    ----------
    database_url
        The pipescan database.
    out_path
        Where to write the PDF (written atomically; its folder is created).
    since
        Only inspections taken at or after this time.
    inspection_ids
        Only these inspections (e.g. those of one network run); with neither filter, the
        latest inspection of every asset.
    failed
        The run's archives that failed, listed with their reasons.

    Returns
    -------
    Path
        ``out_path``.

    Raises
    ------
    StorageError
        If an id in ``inspection_ids`` is not stored.
    """
    inp = load_network_input(
        database_url, since=since, inspection_ids=inspection_ids, failed=failed
    )
    return render_network_pdf(inp, out_path)


#: :func:`render_network_report` as a Prefect task, for flows that want it retried and logged.
render_network_report_task = task(name="render-network-report", **IO_RETRY_OPTIONS)(
    render_network_report
)


def report_message(inp: ReportInput) -> tuple[str, str]:
    """Subject and text of the e-mail that carries an inspection report."""
    ctx = build_context(inp, chart=False)
    summary = ctx["summary"]
    date = fmt_datetime(inp.inspected_at)[:10]
    count = summary["defect_count"]
    verdict = f"{count} defect{'s' if count != 1 else ''}" if count else "no defects"
    subject = f"Pipe condition report {inp.asset_id} ({date}): {verdict}"
    if count:
        subject += f", worst class {summary['worst_grade']}"
    lines = [
        f"Pipe condition report of {inp.asset_id}, inspected {fmt_datetime(inp.inspected_at)}.",
        "",
        f"Defects: {verdict}"
        + (f", {summary['flagged_length']} of pipe flagged" if count else "")
        + f" ({summary['flag_rule']}).",
        f"Worst condition class: {summary['worst_grade']}.",
        f"Largest blockage: {summary['max_blockage']}"
        + (
            f" at {summary['max_blockage_at']}."
            if summary["max_blockage_at"] != "not measured"
            else "."
        ),
        f"Measured: {summary['measured_length']} ({summary['measured_share']});"
        f" not measured: {summary['unmeasured_length']}.",
        "",
        "The full report is attached. pipescan inspection id: " + str(inp.inspection_id) + ".",
    ]
    return subject, "\n".join(line.replace("\u00a0", " ") for line in lines) + "\n"


def network_message(inp: NetworkInput) -> tuple[str, str]:
    """Subject and text of the e-mail that carries a network summary."""
    ctx = build_network_context(inp)
    totals = ctx["totals"]
    subject = (
        f"Network condition summary: {plural(totals['pipes'], 'pipe')}, "
        f"{totals['flagged_pipes']} with sections of class {inp.flag_grade} or worse"
    )
    lines = [
        f"{plural(totals['pipes'], 'pipe')} inspected {totals['first_date']} to "
        f"{totals['last_date']}.",
        f"Defects: {totals['defects']}. Pipes flagged: {totals['flagged_pipes']}.",
        "",
        "Worst five pipes:",
        *(
            f"  {r['rank']}. {r['asset_id']}: class {r['worst_grade']}, largest blockage "
            f"{r['max_blockage']}{'' if r['max_blockage'] == 'not measured' else ' %'}, "
            f"{plural(int(r['defects']), 'defect')}"
            for r in ctx["by_grade"][:5]
        ),
        "",
        *(
            [
                f"{plural(len(inp.failed), 'archive')} failed (nothing stored):",
                *(f"  {f.label}: {f.reason}" for f in inp.failed),
                "",
            ]
            if inp.failed
            else []
        ),
        "The full summary is attached.",
    ]
    return subject, "\n".join(line.replace("\u00a0", " ") for line in lines) + "\n"
