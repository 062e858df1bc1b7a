"""Prefect tasks and helpers that turn stored inspections into reports."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from prefect import task

from pipescan.core.grading import load_table
from pipescan.reports.context import ReportInput, TableCitation
from pipescan.reports.render import render_pdf
from pipescan.storage.db import connect
from pipescan.storage.repository import get_defects, get_inspection, get_sections

_IO_RETRIES = {"retries": 2, "retry_delay_seconds": [1, 5]}


def load_report_input(database_url: str, inspection_id: int) -> ReportInput:
    """Gather one inspection's report input from the database."""
    engine = connect(database_url)
    try:
        rec = get_inspection(engine, inspection_id)
        sections = get_sections(engine, inspection_id)
        defects = get_defects(engine, inspection_id)
    finally:
        engine.dispose()
    params = rec.params or {}
    table_name = rec.threshold_table or params.get("threshold_table", "vsa-2023")
    try:
        table = load_table(table_name)
        citation = TableCitation(name=table.name, source=table.source)
    except Exception:  # a table removed since the run: still report, naming it
        citation = TableCitation(name=table_name, source="(table no longer installed)")
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
        threshold_table=citation,
        blockage_threshold_ratio=params.get("blockage_threshold_ratio", 0.10),
        point_count=rec.point_count,
        frame_count=rec.frame_count,
        scanned_length_m=rec.scanned_length_m,
        registration=rec.registration,
        sections=sections,
        defects=defects,
        generated_at=datetime.now(UTC),
        flag_grade=params.get("flag_grade", 2),
        pipe_class=params.get("pipe_class", "rigid"),
    )


@task(name="render-report", **_IO_RETRIES)
def render_report(database_url: str, inspection_id: int, out_path: Path) -> Path:
    """Render one inspection's PDF condition report from the database."""
    return render_pdf(load_report_input(database_url, inspection_id), out_path)
