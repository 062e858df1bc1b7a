"""Export stored sections and defects as CSV or JSON Lines, for asset systems and GIS.

Rows are streamed from the database in batches, so an export of a whole network does not
have to fit in memory. Column names are the names used end to end (docs/measures.md). A figure that
was not measured is an empty CSV cell (``null`` in JSON), never 0; so are the figures of a
section whose status is not ``ok`` (its coverage and point count stay, as the reason).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any, TextIO, TypeVar

import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.storage.database.models import DefectRow, Inspection, Section
from pipescan.storage.database.repository import mm_to_m

__all__ = [
    "DEFECT_CSV_COLUMNS",
    "SECTION_CSV_COLUMNS",
    "export_defects_csv",
    "export_defects_jsonl",
    "export_sections_csv",
    "export_sections_jsonl",
    "text_cell",
]

SECTION_CSV_COLUMNS: tuple[str, ...] = (
    "asset_id",
    "inspection_id",
    "inspected_at",
    "chainage_start_m",
    "chainage_end_m",
    "open_area_m2",
    "nominal_area_m2",
    "blockage_ratio",
    "ovality_ratio",
    "deformation_ratio",
    "deposit_height_ratio",
    "coverage_ratio",
    "point_count",
    "status",
    "grade",
    # Added later, so at the end: columns keep their places for existing readers.
    "blockage_uncertainty_ratio",
    "ovality_uncertainty_ratio",
    "deformation_uncertainty_ratio",
    "deposit_height_uncertainty_ratio",
    "water_depth_ratio",
    "chainage_uncertainty_m",
    "measured_inner_diameter_m",
    "water_depth_uncertainty_ratio",
)
"""Header of the sections CSV, in order. ``chainage_uncertainty_m`` bounds how far the
section's true place along the pipe may be from its chainage (empty when not known).
``measured_inner_diameter_m`` is the inner diameter the inspection measured on the clean
wall (``core.summary.measured_inner_diameter``; the same on every row of an inspection, empty
when it measured none): blockage is against the nominal diameter.
``water_depth_uncertainty_ratio`` is the 95 % ± of ``water_depth_ratio`` (empty where no
water was read, and for sections stored before it was recorded)."""

DEFECT_CSV_COLUMNS: tuple[str, ...] = (
    "asset_id",
    "inspection_id",
    "inspected_at",
    "code",
    "measure",
    "chainage_start_m",
    "chainage_end_m",
    "peak_chainage_m",
    "peak_value",
    "peak_blockage_ratio",
    "grade",
    "clock_from_h",
    "clock_to_h",
    "characterisation",
    "lower_bound",
)
"""Header of the defects CSV, in order."""

_MEASURE_COLUMNS = (
    "open_area_m2",
    "nominal_area_m2",
    "blockage_ratio",
    "ovality_ratio",
    "deformation_ratio",
    "deposit_height_ratio",
    "coverage_ratio",
)

_LATER_COLUMNS = (
    "blockage_uncertainty_ratio",
    "ovality_uncertainty_ratio",
    "deformation_uncertainty_ratio",
    "deposit_height_uncertainty_ratio",
    "water_depth_ratio",
    "chainage_uncertainty_m",
)

# Figures of a section that are empty in an export unless its status is ok. The water depth
# is not among them: it is measured where the invert is under water (and no other figure is).
_UNTRUSTED_UNLESS_OK = (
    "open_area_m2",
    "blockage_ratio",
    "ovality_ratio",
    "deformation_ratio",
    "deposit_height_ratio",
    "blockage_uncertainty_ratio",
    "ovality_uncertainty_ratio",
    "deformation_uncertainty_ratio",
    "deposit_height_uncertainty_ratio",
)

# Rows fetched per round trip while streaming.
_BATCH_ROWS = 1000


_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def text_cell(value: str | None) -> str:
    """A text cell that a spreadsheet shows as text, never runs as a formula.

    Text starting with ``=``, ``+``, ``-`` or ``@`` (or a tab or CR, which some spreadsheets
    skip before looking) gets a leading ``'``, the spreadsheet's own "this is text" mark:
    ``=HYPERLINK(...)`` in an asset id stays a string. Only text columns pass through here;
    figures are written by pipescan's own number formats, so a negative ratio such as
    ``-0.02`` stays a number a spreadsheet reads as -0.02.

    >>> text_cell("=HYPERLINK(1)"), text_cell("MH1-MH2"), text_cell("-12")
    ("'=HYPERLINK(1)", 'MH1-MH2', "'-12")
    """
    if value is None:
        return ""
    return "'" + value if value.startswith(_FORMULA_STARTS) else value


def _float_cell(value: float | None) -> str:
    # Six significant digits: 0.1 % of a ratio and 1 cm² of area are far below what a LiDAR
    # section resolves. Unmeasured (None) and NaN are empty, never "0".
    if value is None or not math.isfinite(value):
        return ""
    return f"{value:.6g}"


def _chainage_cell(value_m: float) -> str:
    return f"{value_m:.3f}"


def _bool_cell(value: bool | None) -> str:
    """``true``, ``false``, or empty when not recorded."""
    return "" if value is None else ("true" if value else "false")


def _int_cell(value: int | None) -> str:
    return "" if value is None else str(value)


# Bare Select: its type parameters differ between SQLAlchemy 2.0 and 2.1.
_SelectT = TypeVar("_SelectT", bound=sa.Select)


def _filtered(statement: _SelectT, asset_id: str | None, inspection_id: int | None) -> _SelectT:
    if asset_id is not None:
        statement = statement.where(Inspection.asset_id == asset_id)
    if inspection_id is not None:
        statement = statement.where(Inspection.id == inspection_id)
    return statement


def _stream(engine: Engine, statement: sa.Executable) -> Iterator[sa.Row[Any]]:
    with engine.connect() as connection:
        result = connection.execution_options(yield_per=_BATCH_ROWS).execute(statement)
        yield from result


def _section_rows(
    engine: Engine, asset_id: str | None, inspection_id: int | None
) -> Iterator[dict[str, Any]]:
    statement = sa.select(
        Inspection.asset_id,
        Inspection.id.label("inspection_id"),
        Inspection.inspected_at,
        Section.chainage_start_mm,
        Section.chainage_end_mm,
        *(getattr(Section, name) for name in _MEASURE_COLUMNS),
        Section.point_count,
        Section.status,
        Section.grade,
        *(getattr(Section, name) for name in _LATER_COLUMNS),
        Inspection.registration_json["measured_inner_diameter_m"]
        .as_float()
        .label("measured_inner_diameter_m"),
        Section.water_depth_uncertainty_ratio,
    ).join(Section, Section.inspection_id == Inspection.id)
    statement = _filtered(statement, asset_id, inspection_id).order_by(
        Inspection.asset_id, Inspection.inspected_at, Inspection.id, Section.chainage_start_mm
    )
    for row in _stream(engine, statement):
        record = row._asdict()
        record["chainage_start_m"] = mm_to_m(record.pop("chainage_start_mm"))
        record["chainage_end_m"] = mm_to_m(record.pop("chainage_end_mm"))
        if record["status"] != "ok":
            # The database keeps what could be computed, for diagnosis; an export never
            # presents it as measured. Coverage and point count stay: they are the reason.
            record.update(dict.fromkeys(_UNTRUSTED_UNLESS_OK))
        yield record


def _defect_rows(
    engine: Engine, asset_id: str | None, inspection_id: int | None
) -> Iterator[dict[str, Any]]:
    statement = sa.select(
        Inspection.asset_id,
        Inspection.id.label("inspection_id"),
        Inspection.inspected_at,
        DefectRow.code,
        DefectRow.measure,
        DefectRow.chainage_start_m,
        DefectRow.chainage_end_m,
        DefectRow.peak_chainage_m,
        DefectRow.peak_value,
        DefectRow.peak_blockage_ratio,
        DefectRow.grade,
        DefectRow.clock_from_h,
        DefectRow.clock_to_h,
        DefectRow.characterisation,
        DefectRow.lower_bound,
    ).join(DefectRow, DefectRow.inspection_id == Inspection.id)
    statement = _filtered(statement, asset_id, inspection_id).order_by(
        Inspection.asset_id,
        Inspection.inspected_at,
        Inspection.id,
        DefectRow.chainage_start_m,
        DefectRow.id,
    )
    for row in _stream(engine, statement):
        yield row._asdict()


def _section_csv_cells(record: Mapping[str, Any]) -> list[str]:
    return [
        text_cell(record["asset_id"]),
        str(record["inspection_id"]),
        record["inspected_at"].isoformat(),
        _chainage_cell(record["chainage_start_m"]),
        _chainage_cell(record["chainage_end_m"]),
        *(_float_cell(record[name]) for name in _MEASURE_COLUMNS),
        str(record["point_count"]),
        text_cell(record["status"]),
        _int_cell(record["grade"]),
        *(_float_cell(record[name]) for name in _LATER_COLUMNS),
        _float_cell(record["measured_inner_diameter_m"]),
        _float_cell(record["water_depth_uncertainty_ratio"]),
    ]


def _defect_csv_cells(record: Mapping[str, Any]) -> list[str]:
    return [
        text_cell(record["asset_id"]),
        str(record["inspection_id"]),
        record["inspected_at"].isoformat(),
        text_cell(record["code"]),
        text_cell(record["measure"]),
        _chainage_cell(record["chainage_start_m"]),
        _chainage_cell(record["chainage_end_m"]),
        _chainage_cell(record["peak_chainage_m"]),
        _float_cell(record["peak_value"]),
        _float_cell(record["peak_blockage_ratio"]),
        _int_cell(record["grade"]),
        _float_cell(record["clock_from_h"]),
        _float_cell(record["clock_to_h"]),
        text_cell(record["characterisation"]),
        _bool_cell(record["lower_bound"]),
    ]


def export_sections_csv(
    engine: Engine,
    out: TextIO,
    *,
    asset_id: str | None = None,
    inspection_id: int | None = None,
) -> int:
    """Write stored sections as CSV, one row per section, header :data:`SECTION_CSV_COLUMNS`.

    Parameters
    ----------
    engine
        From ``pipescan.storage.database.db.connect``.
    out
        A text stream; open files with ``newline=""`` (the csv module's convention). Rows end
        with ``\\n``.
    asset_id, inspection_id
        Restrict the export to one asset and/or one inspection; by default every section of
        every inspection is written.

    Returns
    -------
    int
        The number of data rows written (the header not counted).

    Notes
    -----
    Rows are ordered by asset, inspection date, inspection id and chainage. Chainages are in
    metres with three decimals (exact: they are stored in millimetres), ``inspected_at`` in
    ISO 8601 UTC, other figures with six significant digits; unmeasured figures are empty.
    """
    return _write_csv(
        out,
        SECTION_CSV_COLUMNS,
        _section_rows(engine, asset_id, inspection_id),
        _section_csv_cells,
    )


def export_defects_csv(
    engine: Engine,
    out: TextIO,
    *,
    asset_id: str | None = None,
    inspection_id: int | None = None,
) -> int:
    """Write stored defects as CSV, one row per defect, header :data:`DEFECT_CSV_COLUMNS`.

    Parameters and formatting are those of :func:`export_sections_csv`; ``peak_value`` is
    the worst value of the measure the defect is graded on, a ratio. ``code`` is the EN 13508-2
    main code (or ``unclassified``); ``clock_from_h`` and ``clock_to_h`` the arc it takes, in
    hours clockwise looking in the survey's direction (12 at the crown), empty for a
    deformation; ``characterisation`` the EN 13508-2 characterisation where the geometry tells
    it (docs/coding.md); ``lower_bound`` ``true`` where part of the defect stood in water
    that returned nothing, so that it is at least ``peak_value`` and its class at least as
    bad as ``grade`` (empty for a defect stored before this was recorded).

    Returns
    -------
    int
        The number of data rows written (the header not counted).
    """
    return _write_csv(
        out, DEFECT_CSV_COLUMNS, _defect_rows(engine, asset_id, inspection_id), _defect_csv_cells
    )


def _json_number(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else value


def _write_csv(
    out: TextIO,
    columns: Sequence[str],
    records: Iterable[Mapping[str, Any]],
    cells: Callable[[Mapping[str, Any]], list[str]],
) -> int:
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(columns)
    count = 0
    for record in records:
        writer.writerow(cells(record))
        count += 1
    return count


def _write_jsonl(
    out: TextIO,
    columns: Sequence[str],
    records: Iterable[Mapping[str, Any]],
    numbers: Sequence[str],
) -> int:
    """One JSON object per record; ``numbers`` are written as null when NaN or unknown."""
    count = 0
    for record in records:
        obj = {name: record[name] for name in columns}
        obj["inspected_at"] = record["inspected_at"].isoformat()
        for name in numbers:
            obj[name] = _json_number(record[name])
        out.write(json.dumps(obj, ensure_ascii=False, allow_nan=False))
        out.write("\n")
        count += 1
    return count


def export_sections_jsonl(
    engine: Engine,
    out: TextIO,
    *,
    asset_id: str | None = None,
    inspection_id: int | None = None,
) -> int:
    """Write stored sections as JSON Lines: one object per line, keys
    :data:`SECTION_CSV_COLUMNS`.

    Numbers are written at full precision, unmeasured figures as ``null``, ``inspected_at``
    as ISO 8601 UTC text. Selection and order are those of :func:`export_sections_csv`.

    Returns
    -------
    int
        The number of lines written.
    """
    return _write_jsonl(
        out,
        SECTION_CSV_COLUMNS,
        _section_rows(engine, asset_id, inspection_id),
        (
            *_MEASURE_COLUMNS,
            *_LATER_COLUMNS,
            "measured_inner_diameter_m",
            "water_depth_uncertainty_ratio",
        ),
    )


def export_defects_jsonl(
    engine: Engine,
    out: TextIO,
    *,
    asset_id: str | None = None,
    inspection_id: int | None = None,
) -> int:
    """Write stored defects as JSON Lines: one object per line, keys
    :data:`DEFECT_CSV_COLUMNS`.

    Numbers are written at full precision, unknown figures (``peak_blockage_ratio``,
    ``grade``, the clock positions of a deformation or of a defect stored before coding, a
    missing ``characterisation``, a ``lower_bound`` stored before it was recorded) as
    ``null``, ``inspected_at`` as ISO 8601 UTC text.
    Selection and order are those of :func:`export_defects_csv`.

    Returns
    -------
    int
        The number of lines written.
    """
    return _write_jsonl(
        out,
        DEFECT_CSV_COLUMNS,
        _defect_rows(engine, asset_id, inspection_id),
        ("peak_blockage_ratio", "clock_from_h", "clock_to_h"),
    )
