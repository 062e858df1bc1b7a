"""What a per-inspection report shows, computed from plain inputs.

The caller (a task reading the database) builds a :class:`ReportInput`; :func:`build_context`
turns it into the dictionary the Jinja2 template renders. All formatting lives here: ratios
stay fractions in the data and become percentages only in this module's output. A figure that
was not measured renders as ``"not measured"``, never as 0 or ``None``.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeGuard

from pipescan.core.grading import ThresholdTable
from pipescan.core.model import Defect, SectionMeasures, SectionStatus

__all__ = [
    "NOT_MEASURED",
    "ReportInput",
    "TableCitation",
    "build_context",
    "fmt_pct",
]

NOT_MEASURED = "not measured"
NOT_RECORDED = "not recorded"
WORST_SECTIONS = 10
# Spans listed per unmeasured reason in the summary before "and N more".
MAX_LISTED_SPANS = 6
_ADJACENT_TOL_M = 1e-6

STATUS_LABELS: dict[str, str] = {
    SectionStatus.OK: "measured",
    SectionStatus.LOW_COVERAGE: "low coverage",
    SectionStatus.TOO_FEW_POINTS: "too few points",
    SectionStatus.OUTSIDE_SCAN: "outside the scan",
    SectionStatus.NO_CONTOUR: "no closed contour",
}
STATUS_EXPLANATIONS: dict[str, str] = {
    SectionStatus.LOW_COVERAGE: "the scan saw too little of the pipe wall around the section",
    SectionStatus.TOO_FEW_POINTS: "too few LiDAR points fell in the section",
    SectionStatus.OUTSIDE_SCAN: "the section lies beyond the scanned length",
    SectionStatus.NO_CONTOUR: "no closed inner contour could be traced",
}
MEASURE_LABELS: dict[str, str] = {
    "blockage_ratio": "blockage",
    "deformation_ratio": "deformation",
    "deposit_height_ratio": "deposit height",
    "ovality_ratio": "ovality",
}
CODE_LABELS: dict[str, str] = {
    "BAA": "deformation",
    "BBB": "attached deposits",
    "BBC": "settled deposits",
    "BBE": "obstacle",
}


@dataclass(frozen=True)
class TableCitation:
    """The threshold table a report was graded with: its short name and full source."""

    name: str
    source: str


@dataclass(frozen=True)
class ReportInput:
    """Everything one inspection report needs, gathered by the caller from the database.

    Attributes
    ----------
    asset_id, upstream_node, downstream_node
        The pipe asset and its manhole ids (nodes may be None when not recorded).
    inspected_at
        When the scan was taken.
    nominal_diameter_m
        Design inner diameter in metres (None for non-circular pipes without one).
    material, pipe_shape
        As recorded in the archive metadata.
    inspection_id, archive_uri
        Database id of the inspection and where its scan archive lives.
    software_version
        pipescan version that produced the figures.
    threshold_table
        Name and source of the grading table (a :class:`ThresholdTable` also fits).
    blockage_threshold_ratio
        Blockage (a fraction) at or above which a section is flagged.
    point_count, frame_count
        Points in the registered cloud; LiDAR frames registered (0 for a pre-registered cloud).
    scanned_length_m
        Length of pipe covered by the scan, in metres.
    registration
        Registration quality: ``engine`` (str), ``mean_fitness`` (fraction of inliers),
        ``mean_rmse_m`` (metres), ``degenerate_frames`` (int). None or missing keys when the
        archive held a registered cloud.
    sections
        Graded sections, any order.
    defects
        Merged flagged spans (see :func:`pipescan.core.grading.merge_defects`).
    generated_at
        When the report was generated.
    flag_grade
        Condition class at or below which a section is flagged (default 2).
    pipe_class
        ``"rigid"`` or ``"flexible"``: which BAA rule graded deformation.
    """

    asset_id: str
    upstream_node: str | None
    downstream_node: str | None
    inspected_at: datetime
    nominal_diameter_m: float | None
    material: str | None
    pipe_shape: str
    inspection_id: str | int
    archive_uri: str
    software_version: str
    threshold_table: TableCitation | ThresholdTable
    blockage_threshold_ratio: float
    point_count: int
    frame_count: int
    scanned_length_m: float
    registration: Mapping[str, Any] | None
    sections: Sequence[SectionMeasures]
    defects: Sequence[Defect]
    generated_at: datetime
    flag_grade: int = 2
    pipe_class: str = "rigid"


# --- formatting -----------------------------------------------------------------------


def _finite(value: float | None) -> TypeGuard[float]:
    return value is not None and math.isfinite(value)


def fmt_pct(ratio: float | None, digits: int = 1, *, unit: bool = True) -> str:
    """A fraction as a percentage (``0.123`` -> ``"12.3 %"``); ``"not measured"`` if missing."""
    if not _finite(ratio):
        return NOT_MEASURED
    text = f"{ratio * 100.0:.{digits}f}"
    if text.lstrip("-").strip("0.") == "":  # "-0.0" -> "0.0"
        text = text.lstrip("-")
    # A no-break space keeps a figure and its unit on one line.
    return f"{text}\u00a0%" if unit else text


def fmt_m(value_m: float | None, digits: int = 2, *, unit: bool = True) -> str:
    """A length in metres, e.g. ``"12.30 m"``."""
    if not _finite(value_m):
        return NOT_MEASURED
    return f"{value_m:.{digits}f}\u00a0m" if unit else f"{value_m:.{digits}f}"


def fmt_span(start_m: float, end_m: float) -> str:
    """A chainage interval, e.g. ``"4.00–4.60 m"``."""
    return f"{start_m:.2f}–{end_m:.2f}\u00a0m"


def fmt_grade(grade: int | None) -> str:
    return str(grade) if grade is not None else "not graded"


def fmt_int(value: int | None) -> str:
    return f"{value:,}".replace(",", "\u202f") if value is not None else NOT_RECORDED


def fmt_datetime(value: datetime) -> str:
    text = value.strftime("%Y-%m-%d %H:%M")
    if value.tzinfo is not None:
        offset = value.strftime("%z")
        text += " UTC" if offset in ("+0000", "") else f" UTC{offset[:3]}:{offset[3:]}"
    return text


def _text(value: Any, missing: str = NOT_RECORDED) -> str:
    if value is None or (isinstance(value, str) and not value.strip()):
        return missing
    return str(value)


# --- helpers over sections ----------------------------------------------------------------


def _length_m(s: SectionMeasures) -> float:
    return s.chainage_end_m - s.chainage_start_m


def _spans(sections: Sequence[SectionMeasures]) -> list[tuple[float, float]]:
    """Merge chainage-sorted sections whose intervals touch into (start, end) spans."""
    spans: list[list[float]] = []
    for s in sections:
        if spans and abs(s.chainage_start_m - spans[-1][1]) <= _ADJACENT_TOL_M:
            spans[-1][1] = s.chainage_end_m
        else:
            spans.append([s.chainage_start_m, s.chainage_end_m])
    return [(a, b) for a, b in spans]


def _is_flagged_at(defects: Sequence[Defect], s: SectionMeasures) -> bool:
    mid = 0.5 * (s.chainage_start_m + s.chainage_end_m)
    return any(d.chainage_start_m <= mid < d.chainage_end_m for d in defects)


def _section_row(s: SectionMeasures, flagged: bool) -> dict[str, Any]:
    row: dict[str, Any] = {
        "start": fmt_m(s.chainage_start_m, unit=False),
        "end": fmt_m(s.chainage_end_m, unit=False),
        "coverage": fmt_pct(s.coverage_ratio, 0, unit=False),
        "points": fmt_int(s.point_count),
        "status": STATUS_LABELS.get(s.status, str(s.status)),
        "ok": s.is_ok,
        "flagged": flagged,
    }
    if s.is_ok:
        row.update(
            open_area=(f"{s.open_area_m2:.4f}" if _finite(s.open_area_m2) else NOT_MEASURED),
            blockage=fmt_pct(s.blockage_ratio, unit=False),
            ovality=fmt_pct(s.ovality_ratio, unit=False),
            deformation=fmt_pct(s.deformation_ratio, unit=False),
            deposit=fmt_pct(s.deposit_height_ratio, unit=False),
            grade=fmt_grade(s.grade),
        )
    else:
        # Figures computed for a section that is not trusted stay out of the report.
        row.update(reason=f"{NOT_MEASURED}: {STATUS_LABELS.get(s.status, str(s.status))}")
    return row


def _registration_rows(inp: ReportInput) -> list[tuple[str, str]]:
    reg = inp.registration or {}
    engine = reg.get("engine")
    if inp.frame_count == 0 and not engine:
        return [("registration", "none: the archive held one registered cloud")]
    fitness = reg.get("mean_fitness")
    rmse_m = reg.get("mean_rmse_m")
    degenerate = reg.get("degenerate_frames")
    rows = [
        ("frames registered", fmt_int(inp.frame_count)),
        ("registration engine", _text(engine)),
        (
            "mean ICP fitness",
            f"{fmt_pct(fitness)} of points matched" if _finite(fitness) else NOT_RECORDED,
        ),
        ("mean ICP residual", f"{rmse_m * 1000.0:.1f} mm" if _finite(rmse_m) else NOT_RECORDED),
    ]
    if degenerate is None:
        rows.append(("frames held to odometer", NOT_RECORDED))
    else:
        rows.append(
            (
                "frames held to odometer",
                f"{degenerate} of {inp.frame_count} (along-axis position from the odometer)"
                if degenerate
                else f"none of {inp.frame_count}",
            )
        )
    return rows


# --- the context --------------------------------------------------------------------------


def build_context(inp: ReportInput, *, chart: bool = True) -> dict[str, Any]:
    """Everything the inspection template shows, formatted.

    Parameters
    ----------
    inp
        The report's inputs.
    chart
        Draw the blockage chart (a matplotlib SVG, as a data URI). Tests of the context
        alone may skip it.

    Returns
    -------
    dict
        Keys used by ``templates/inspection.html.j2``: ``asset`` (cover facts), ``summary``
        (figures), ``grades`` (counts by class), ``unmeasured`` (metres by reason, with
        spans), ``worst`` (the worst ``ok`` sections by blockage), ``defects`` (rows),
        ``sections`` (appendix rows), ``chart_uri`` and ``table``.
    """
    sections = sorted(inp.sections, key=lambda s: s.chainage_start_m)
    defects = sorted(inp.defects, key=lambda d: d.chainage_start_m)
    ok = [s for s in sections if s.is_ok]
    total_length_m = sum(_length_m(s) for s in sections)
    ok_length_m = sum(_length_m(s) for s in ok)
    threshold_pct = fmt_pct(inp.blockage_threshold_ratio)
    flag_rule = f"blockage of {threshold_pct} or more, or condition class {inp.flag_grade} or worse"

    nominal = inp.nominal_diameter_m
    asset = {
        "asset_id": inp.asset_id,
        "upstream_node": _text(inp.upstream_node),
        "downstream_node": _text(inp.downstream_node),
        "inspected_at": fmt_datetime(inp.inspected_at),
        "nominal_size": (
            f"DN {round(nominal * 1000)} ({nominal:.3f} m inner diameter)"
            if _finite(nominal)
            else NOT_RECORDED
        ),
        "material": _text(inp.material),
        "pipe_shape": _text(inp.pipe_shape),
        "pipe_class": inp.pipe_class,
        "scanned_length": fmt_m(inp.scanned_length_m),
        "point_count": fmt_int(inp.point_count),
        "registration": _registration_rows(inp),
        "inspection_id": str(inp.inspection_id),
        "archive_uri": inp.archive_uri,
        "software_version": inp.software_version,
        "generated_at": fmt_datetime(inp.generated_at),
    }
    table = {"name": inp.threshold_table.name, "source": inp.threshold_table.source}

    # Counts by grade, over measured sections only.
    grades = []
    for grade in range(5):
        members = [s for s in ok if s.grade == grade]
        grades.append(
            {
                "grade": str(grade),
                "label": {0: "worst", 4: "best"}.get(grade, ""),
                "count": len(members),
                "length": fmt_m(sum(_length_m(s) for s in members), 1),
                "share": fmt_pct(
                    sum(_length_m(s) for s in members) / total_length_m if total_length_m else None,
                    0,
                ),
                "flag": grade <= inp.flag_grade,
            }
        )
    ungraded_ok = [s for s in ok if s.grade is None]

    # Unmeasured metres by reason, with the spans so an engineer can find them.
    unmeasured = []
    for status in SectionStatus:
        if status == SectionStatus.OK:
            continue
        members = [s for s in sections if s.status == status]
        if not members:
            continue
        spans = _spans(members)
        listed = [fmt_span(a, b) for a, b in spans[:MAX_LISTED_SPANS]]
        more = len(spans) - len(listed)
        unmeasured.append(
            {
                "reason": STATUS_LABELS.get(status, str(status)),
                "explanation": STATUS_EXPLANATIONS.get(status, ""),
                "count": len(members),
                "length": fmt_m(sum(_length_m(s) for s in members), 1),
                "spans": ", ".join(listed) + (f" and {more} more" if more else ""),
            }
        )
    unmeasured_length_m = total_length_m - ok_length_m

    # The worst measured sections by blockage.
    with_blockage = [s for s in ok if _finite(s.blockage_ratio)]
    worst_sections = sorted(
        with_blockage, key=lambda s: (-(s.blockage_ratio or 0.0), s.chainage_start_m)
    )[:WORST_SECTIONS]
    worst = [_section_row(s, _is_flagged_at(defects, s)) for s in worst_sections]

    defect_rows = []
    for d in defects:
        defect_rows.append(
            {
                "code": d.code or "—",
                "code_label": CODE_LABELS.get(d.code, ""),
                "measure": MEASURE_LABELS.get(d.measure, d.measure),
                "start": fmt_m(d.chainage_start_m, unit=False),
                "end": fmt_m(d.chainage_end_m, unit=False),
                "length": fmt_m(d.chainage_end_m - d.chainage_start_m, unit=False),
                "peak_at": fmt_m(d.peak_chainage_m, unit=False),
                "peak_value": fmt_pct(d.peak_value, unit=False),
                "peak_blockage": fmt_pct(d.peak_blockage_ratio, unit=False),
                "grade": fmt_grade(d.grade),
            }
        )

    peak = max(with_blockage, key=lambda s: s.blockage_ratio or 0.0, default=None)
    graded_ok = [s.grade for s in ok if s.grade is not None]
    summary = {
        "section_count": len(sections),
        "section_length": fmt_m(sections[0].chainage_end_m - sections[0].chainage_start_m, 2)
        if sections
        else NOT_RECORDED,
        "chainage_range": fmt_span(sections[0].chainage_start_m, sections[-1].chainage_end_m)
        if sections
        else NOT_RECORDED,
        "measured_count": len(ok),
        "measured_length": fmt_m(ok_length_m, 1),
        "measured_share": fmt_pct(ok_length_m / total_length_m if total_length_m else None, 0),
        "unmeasured_count": len(sections) - len(ok),
        "unmeasured_length": fmt_m(unmeasured_length_m, 1),
        "unmeasured_share": fmt_pct(
            unmeasured_length_m / total_length_m if total_length_m else None, 0
        ),
        "max_blockage": fmt_pct(peak.blockage_ratio) if peak else NOT_MEASURED,
        "max_blockage_at": fmt_m(peak.chainage_start_m) if peak else NOT_MEASURED,
        "mean_blockage": fmt_pct(
            sum(s.blockage_ratio or 0.0 for s in with_blockage) / len(with_blockage)
            if with_blockage
            else None
        ),
        "worst_grade": str(min(graded_ok)) if graded_ok else "not graded",
        "defect_count": len(defects),
        "flagged_length": fmt_m(sum(d.chainage_end_m - d.chainage_start_m for d in defects), 1),
        "ungraded_ok_count": len(ungraded_ok),
        "flag_rule": flag_rule,
        "threshold": threshold_pct,
        "flag_grade": inp.flag_grade,
        "has_negative_blockage": any((s.blockage_ratio or 0.0) < 0 for s in with_blockage),
    }

    chart_uri = None
    if chart and sections:
        # Imported here so that building a context without a chart needs no matplotlib.
        from pipescan.reports.charts import blockage_chart_svg

        svg = blockage_chart_svg(
            sections, defects, blockage_threshold_ratio=inp.blockage_threshold_ratio
        )
        chart_uri = "data:image/svg+xml;base64," + base64.b64encode(svg.encode()).decode("ascii")

    return {
        "title": f"Pipe condition report {inp.asset_id}",
        "asset": asset,
        "table": table,
        "summary": summary,
        "grades": grades,
        "unmeasured": unmeasured,
        "worst": worst,
        "defects": defect_rows,
        "sections": [_section_row(s, _is_flagged_at(defects, s)) for s in sections],
        "chart_uri": chart_uri,
        "not_measured": NOT_MEASURED,
    }
