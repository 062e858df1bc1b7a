"""CSV and JSON Lines exports of stored sections and defects, on SQLite and PostgreSQL
(the ``engine`` fixture of tests/conftest.py)."""

from __future__ import annotations

import csv
import io
import json
import math
import sqlite3
from datetime import UTC, datetime
from typing import Any, ClassVar

import pytest
import sqlalchemy as sa

from pipescan.core.model import Defect, InspectionMeta, SectionMeasures, SectionStatus
from pipescan.exports import tables as export
from pipescan.storage.database import db, repository
from pipescan.storage.database.models import Section

DOCUMENTED_COLUMNS = (
    "asset_id,inspection_id,inspected_at,chainage_start_m,chainage_end_m,open_area_m2,"
    "nominal_area_m2,blockage_ratio,ovality_ratio,deformation_ratio,deposit_height_ratio,"
    "coverage_ratio,point_count,status,grade,blockage_uncertainty_ratio,"
    "ovality_uncertainty_ratio,deformation_uncertainty_ratio,deposit_height_uncertainty_ratio,"
    "water_depth_ratio,chainage_uncertainty_m,measured_inner_diameter_m,"
    "water_depth_uncertainty_ratio"
)
NOMINAL_AREA_M2 = math.pi * 0.6**2 / 4
MEASURED = SectionMeasures(
    chainage_start_m=12.3,
    chainage_end_m=12.4,
    nominal_area_m2=NOMINAL_AREA_M2,
    status=SectionStatus.OK,
    point_count=1500,
    coverage_ratio=0.9875,
    open_area_m2=0.2474,
    blockage_ratio=1 - 0.2474 / NOMINAL_AREA_M2,
    ovality_ratio=0.0123456789,
    deformation_ratio=0.0,
    deposit_height_ratio=0.1,
    grade=3,
    blockage_uncertainty_ratio=0.0061,
    ovality_uncertainty_ratio=0.004,
    deformation_uncertainty_ratio=0.005,
    deposit_height_uncertainty_ratio=0.012,
    water_depth_ratio=0.0,
    chainage_uncertainty_m=0.042,
)
# Figures computed but not trusted (only a fifth of the perimeter seen): stored for
# diagnosis, never exported as measured.
UNMEASURED = SectionMeasures(
    chainage_start_m=12.4,
    chainage_end_m=12.5,
    nominal_area_m2=NOMINAL_AREA_M2,
    status=SectionStatus.LOW_COVERAGE,
    point_count=12,
    coverage_ratio=0.2,
    open_area_m2=0.2,
    blockage_ratio=1 - 0.2 / NOMINAL_AREA_M2,
    ovality_ratio=0.05,
    deformation_ratio=0.02,
    deposit_height_ratio=0.0,
    blockage_uncertainty_ratio=0.3,
)
DEFECT = Defect(
    code="BBC",
    measure="deposit_height_ratio",
    chainage_start_m=12.3,
    chainage_end_m=12.4,
    peak_chainage_m=12.3,
    peak_value=0.1,
    peak_blockage_ratio=None,
    grade=3,
    clock_from_h=4.25,
    clock_to_h=7.75,
)


def _save(engine: sa.Engine, asset_id: str, year: int, content_hash: str) -> int:
    return repository.save_inspection(
        engine,
        repository.InspectionToSave(
            meta=InspectionMeta(
                asset_id=asset_id,
                inspected_at=datetime(year, 5, 17, 9, 30, tzinfo=UTC),
                nominal_diameter_m=0.6,
            ),
            archive_uri=f"/scans/{asset_id}-{year}.zip",
            content_hash=content_hash,
            params={"section_step_m": 0.1},
            software_version="0.1.0",
            sections=[MEASURED, UNMEASURED],
            defects=[DEFECT],
        ),
    )


def _save_three(engine: sa.Engine) -> dict[str, int]:
    # Saved out of order, to check the export's ordering.
    return {
        "B-2025": _save(engine, "B", 2025, "h3"),
        "A-2025": _save(engine, "A", 2025, "h2"),
        "A-2024": _save(engine, "A", 2024, "h1"),
    }


@pytest.fixture
def ids(engine: sa.Engine) -> dict[str, int]:
    return _save_three(engine)


def test_section_columns_are_the_design_names() -> None:
    assert ",".join(export.SECTION_CSV_COLUMNS) == DOCUMENTED_COLUMNS


def test_sections_csv_values(engine: sa.Engine, ids: dict[str, int]) -> None:
    out = io.StringIO()
    written = export.export_sections_csv(engine, out, inspection_id=ids["A-2024"])
    lines = out.getvalue().splitlines()
    assert written == 2
    assert len(lines) == 3
    assert lines[0] == DOCUMENTED_COLUMNS
    measured, unmeasured = (
        dict(zip(export.SECTION_CSV_COLUMNS, r, strict=True)) for r in csv.reader(lines[1:])
    )
    assert measured == {
        "asset_id": "A",
        "inspection_id": str(ids["A-2024"]),
        "inspected_at": "2024-05-17T09:30:00+00:00",
        "chainage_start_m": "12.300",
        "chainage_end_m": "12.400",
        "open_area_m2": "0.2474",
        "nominal_area_m2": "0.282743",
        "blockage_ratio": f"{1 - 0.2474 / NOMINAL_AREA_M2:.6g}",
        "ovality_ratio": "0.0123457",
        "deformation_ratio": "0",  # a measured zero stays a zero
        "deposit_height_ratio": "0.1",
        "coverage_ratio": "0.9875",
        "point_count": "1500",
        "status": "ok",
        "grade": "3",
        "blockage_uncertainty_ratio": "0.0061",
        "ovality_uncertainty_ratio": "0.004",
        "deformation_uncertainty_ratio": "0.005",
        "deposit_height_uncertainty_ratio": "0.012",
        "water_depth_ratio": "0",
        "chainage_uncertainty_m": "0.042",
        "measured_inner_diameter_m": "",  # stored without one
        "water_depth_uncertainty_ratio": "",  # seen dry: no water, no ±
    }
    assert float(measured["blockage_ratio"]) == pytest.approx(0.125, abs=1e-3)
    # Unmeasured figures are empty, never 0.
    for name in (
        "open_area_m2",
        "blockage_ratio",
        "ovality_ratio",
        "deformation_ratio",
        "deposit_height_ratio",
        "grade",
        "blockage_uncertainty_ratio",
        "water_depth_ratio",  # not told: the invert's water was not measured there
    ):
        assert unmeasured[name] == "", name
    assert (unmeasured["status"], unmeasured["point_count"]) == ("low_coverage", "12")
    assert unmeasured["coverage_ratio"] == "0.2"
    # The database still holds the untrusted figures, for diagnosis.
    with engine.connect() as connection:
        stored = connection.execute(
            sa.select(Section.blockage_ratio).where(
                Section.inspection_id == ids["A-2024"], Section.status == "low_coverage"
            )
        ).scalar_one()
    assert stored == pytest.approx(UNMEASURED.blockage_ratio)


def test_sections_csv_selection_and_order(engine: sa.Engine, ids: dict[str, int]) -> None:
    out = io.StringIO()
    assert export.export_sections_csv(engine, out) == 6
    rows = list(csv.DictReader(io.StringIO(out.getvalue())))
    order = [(r["asset_id"], int(r["inspection_id"]), r["chainage_start_m"]) for r in rows]
    assert order == [
        ("A", ids["A-2024"], "12.300"),
        ("A", ids["A-2024"], "12.400"),
        ("A", ids["A-2025"], "12.300"),
        ("A", ids["A-2025"], "12.400"),
        ("B", ids["B-2025"], "12.300"),
        ("B", ids["B-2025"], "12.400"),
    ]
    assert export.export_sections_csv(engine, io.StringIO(), asset_id="A") == 4
    assert export.export_sections_csv(engine, io.StringIO(), asset_id="nobody") == 0
    assert (
        export.export_sections_csv(engine, io.StringIO(), asset_id="B", inspection_id=ids["A-2024"])
        == 0
    )


def test_defects_csv(engine: sa.Engine, ids: dict[str, int]) -> None:
    out = io.StringIO()
    assert export.export_defects_csv(engine, out, asset_id="B") == 1
    rows = list(csv.DictReader(io.StringIO(out.getvalue())))
    assert tuple(rows[0]) == export.DEFECT_CSV_COLUMNS
    assert rows == [
        {
            "asset_id": "B",
            "inspection_id": str(ids["B-2025"]),
            "inspected_at": "2025-05-17T09:30:00+00:00",
            "code": "BBC",
            "measure": "deposit_height_ratio",
            "chainage_start_m": "12.300",
            "chainage_end_m": "12.400",
            "peak_chainage_m": "12.300",
            "peak_value": "0.1",
            "peak_blockage_ratio": "",
            "grade": "3",
            "clock_from_h": "4.25",
            "clock_to_h": "7.75",
            "characterisation": "",
            "lower_bound": "false",
        }
    ]


def test_sections_jsonl(engine: sa.Engine, ids: dict[str, int]) -> None:
    out = io.StringIO()
    assert export.export_sections_jsonl(engine, out, inspection_id=ids["A-2025"]) == 2
    measured, unmeasured = (json.loads(line) for line in out.getvalue().splitlines())
    assert tuple(measured) == export.SECTION_CSV_COLUMNS
    assert measured["chainage_start_m"] == 12.3
    assert measured["ovality_ratio"] == 0.0123456789  # full precision
    assert measured["inspection_id"] == ids["A-2025"]
    assert measured["inspected_at"] == "2025-05-17T09:30:00+00:00"
    assert unmeasured["blockage_ratio"] is None
    assert unmeasured["grade"] is None
    assert unmeasured["status"] == "low_coverage"
    # Where the section sits is known to within this; unknown is null, never 0.
    assert measured["chainage_uncertainty_m"] == 0.042
    assert unmeasured["chainage_uncertainty_m"] is None


def test_defects_jsonl(engine: sa.Engine, ids: dict[str, int]) -> None:
    out = io.StringIO()
    assert export.export_defects_jsonl(engine, out, asset_id="A") == 2
    first, second = (json.loads(line) for line in out.getvalue().splitlines())
    assert tuple(first) == export.DEFECT_CSV_COLUMNS
    assert (first["inspection_id"], second["inspection_id"]) == (ids["A-2024"], ids["A-2025"])
    assert first == {
        "asset_id": "A",
        "inspection_id": ids["A-2024"],
        "inspected_at": "2024-05-17T09:30:00+00:00",
        "code": "BBC",
        "measure": "deposit_height_ratio",
        "chainage_start_m": 12.3,
        "chainage_end_m": 12.4,
        "peak_chainage_m": 12.3,
        "peak_value": 0.1,
        "peak_blockage_ratio": None,  # unknown, not 0
        "grade": 3,
        "clock_from_h": 4.25,
        "clock_to_h": 7.75,
        "characterisation": None,
        "lower_bound": False,
    }


def test_cli_export_to_files(engine: sa.Engine, db_url: str, ids: dict[str, int], tmp_path) -> None:
    from typer.testing import CliRunner

    from pipescan.cli import app

    for what, fmt, rows in (("sections", "csv", 6), ("defects", "jsonl", 3)):
        target = tmp_path / f"{what}.{fmt}"
        result = CliRunner().invoke(
            app, ["export", what, "--format", fmt, "-o", str(target), "--db", db_url]
        )
        assert result.exit_code == 0, result.output
        lines = target.read_text().splitlines()
        assert len(lines) == rows + (fmt == "csv")
        assert f"wrote {rows} rows to {target}" in result.output


class _CountingCursor(sqlite3.Cursor):
    fetch_sizes: ClassVar[list[int]] = []
    fetchall_calls: ClassVar[int] = 0

    def fetchmany(self, size: int | None = None) -> list[Any]:
        rows = super().fetchmany(size) if size is not None else super().fetchmany()
        _CountingCursor.fetch_sizes.append(len(rows))
        return rows

    def fetchall(self) -> list[Any]:
        _CountingCursor.fetchall_calls += 1
        return super().fetchall()


class _CountingConnection(sqlite3.Connection):
    def cursor(self, factory: Any = _CountingCursor) -> sqlite3.Cursor:
        return super().cursor(factory)


def test_export_streams_in_batches(sqlite_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    engine = db.connect(sqlite_url)
    _save_three(engine)
    engine.dispose()
    # An engine whose driver cursors count what is fetched: with batches of 2 rows, the 6
    # rows arrive in several fetches of at most 2, never in one fetchall.
    counting = sa.create_engine(sqlite_url, connect_args={"factory": _CountingConnection})
    monkeypatch.setattr(export, "_BATCH_ROWS", 2)
    _CountingCursor.fetch_sizes.clear()
    _CountingCursor.fetchall_calls = 0
    out = io.StringIO()
    try:
        assert export.export_sections_csv(counting, out) == 6
    finally:
        counting.dispose()
    assert _CountingCursor.fetchall_calls == 0
    assert sum(_CountingCursor.fetch_sizes) == 6
    assert max(_CountingCursor.fetch_sizes) == 2
    assert len(out.getvalue().splitlines()) == 7


def test_sections_carry_the_inspection_s_measured_inner_diameter(engine: sa.Engine) -> None:
    """Blockage is against the nominal diameter: the diameter the wall measured goes beside
    it on every row of the inspection (empty where the inspection measured none)."""
    measured = repository.save_inspection(
        engine,
        repository.InspectionToSave(
            meta=InspectionMeta(
                asset_id="M", inspected_at=datetime(2025, 1, 2, tzinfo=UTC), nominal_diameter_m=0.6
            ),
            archive_uri="/scans/m.zip",
            content_hash="hm",
            params={},
            software_version="0.1.0",
            sections=[MEASURED, UNMEASURED],
            defects=[],
            registration={"measured_inner_diameter_m": 0.5893},
        ),
    )
    unmeasured = _save(engine, "N", 2025, "hn")
    out = io.StringIO()
    export.export_sections_csv(engine, out)
    rows = list(csv.DictReader(io.StringIO(out.getvalue())))
    by_inspection = {(r["inspection_id"], r["measured_inner_diameter_m"]) for r in rows}
    assert by_inspection == {(str(measured), "0.5893"), (str(unmeasured), "")}
    out = io.StringIO()
    export.export_sections_jsonl(engine, out, inspection_id=measured)
    assert {
        json.loads(line)["measured_inner_diameter_m"] for line in out.getvalue().splitlines()
    } == {0.5893}
