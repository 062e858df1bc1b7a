"""The network summary: a set of inspections (e.g. one scheduled run), a line per pipe,
ranked by worst condition and by growth since each pipe's previous inspection.

As for the inspection report, the caller gathers plain inputs (:class:`NetworkInput`) and
:func:`build_network_context` formats them; ratios become percentages only here, and a figure
that was not measured reads "not measured".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from pipescan.core.model import SectionMeasures
from pipescan.reports.context import (
    NOT_MEASURED,
    NOT_RECORDED,
    TableCitation,
    _finite,
    fmt_datetime,
    fmt_m,
    fmt_pct,
)

__all__ = ["NetworkInput", "PipeInspection", "PipeSummary", "build_network_context", "summarise"]

# Matched sections must start at the same chainage to the millimetre.
_MM = 1000.0


@dataclass(frozen=True)
class PipeInspection:
    """One pipe's inspection in a network summary, with its previous inspection if any.

    ``sections`` and ``previous_sections`` need no contours.
    """

    asset_id: str
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    material: str | None
    inspection_id: int | str
    inspected_at: datetime
    sections: Sequence[SectionMeasures]
    defect_count: int
    previous_inspection_id: int | str | None = None
    previous_inspected_at: datetime | None = None
    previous_sections: Sequence[SectionMeasures] = ()


@dataclass(frozen=True)
class NetworkInput:
    """Everything a network summary needs."""

    pipes: Sequence[PipeInspection]
    generated_at: datetime
    software_version: str
    blockage_threshold_ratio: float = 0.10
    flag_grade: int = 2
    threshold_tables: Sequence[TableCitation] = ()
    since: datetime | None = None
    title: str = "Network condition summary"


@dataclass(frozen=True)
class PipeSummary:
    """The figures of one pipe's line (fractions and metres; None when not measured).

    ``growth_ratio`` is the largest increase of blockage at one chainage since the previous
    inspection, over sections measured in both (matched on their start chainage, to the
    millimetre), and ``growth_at_m`` where; ``growth_per_year_ratio`` divides it by the years
    between the two inspections.
    """

    pipe: PipeInspection
    length_m: float
    measured_length_m: float
    worst_grade: int | None
    max_blockage_ratio: float | None
    max_blockage_at_m: float | None
    previous_max_blockage_ratio: float | None
    growth_ratio: float | None
    growth_at_m: float | None
    growth_per_year_ratio: float | None


def _peak(sections: Sequence[SectionMeasures]) -> tuple[float | None, float | None]:
    measured = [s for s in sections if s.is_ok and _finite(s.blockage_ratio)]
    if not measured:
        return None, None
    # Ties go to the upstream section.
    best = min(measured, key=lambda s: (-(s.blockage_ratio or 0.0), s.chainage_start_m))
    return best.blockage_ratio, best.chainage_start_m


def summarise(pipe: PipeInspection) -> PipeSummary:
    """The figures of one pipe's line in the network summary."""
    length_m = sum(s.chainage_end_m - s.chainage_start_m for s in pipe.sections)
    measured_m = sum(s.chainage_end_m - s.chainage_start_m for s in pipe.sections if s.is_ok)
    grades = [s.grade for s in pipe.sections if s.is_ok and s.grade is not None]
    peak, peak_at = _peak(pipe.sections)
    previous_peak, _ = _peak(pipe.previous_sections)
    growth = growth_at = per_year = None
    if pipe.previous_sections:
        before = {
            round(s.chainage_start_m * _MM): s.blockage_ratio
            for s in pipe.previous_sections
            if s.is_ok and _finite(s.blockage_ratio)
        }
        changes = [
            (s.blockage_ratio - before[key], s.chainage_start_m)  # type: ignore[operator]
            for s in pipe.sections
            if s.is_ok
            and _finite(s.blockage_ratio)
            and (key := round(s.chainage_start_m * _MM)) in before
        ]
        if changes:
            growth, growth_at = max(changes, key=lambda c: (c[0], -c[1]))
            if pipe.previous_inspected_at is not None:
                years = (pipe.inspected_at - pipe.previous_inspected_at).total_seconds() / (
                    365.25 * 86400.0
                )
                per_year = growth / years if years > 0.05 else None
    return PipeSummary(
        pipe=pipe,
        length_m=length_m,
        measured_length_m=measured_m,
        worst_grade=min(grades) if grades else None,
        max_blockage_ratio=peak,
        max_blockage_at_m=peak_at,
        previous_max_blockage_ratio=previous_peak,
        growth_ratio=growth,
        growth_at_m=growth_at,
        growth_per_year_ratio=per_year,
    )


def _points(ratio: float | None) -> str:
    """A change of a ratio in percentage points, signed (``+3.2``)."""
    if not _finite(ratio):
        return NOT_MEASURED
    text = f"{ratio * 100.0:+.1f}"
    return "0.0" if text in ("+0.0", "-0.0") else text


def _row(rank: int, p: PipeSummary, flag_grade: int) -> dict[str, Any]:
    pipe = p.pipe
    nodes = " → ".join(n for n in (pipe.upstream_node, pipe.downstream_node) if n)
    return {
        "rank": rank,
        "asset_id": pipe.asset_id,
        "nodes": nodes or NOT_RECORDED,
        "size": (
            f"DN {round(pipe.nominal_diameter_m * 1000)}"
            if _finite(pipe.nominal_diameter_m)
            else NOT_RECORDED
        ),
        "material": pipe.material or NOT_RECORDED,
        "inspection_id": str(pipe.inspection_id),
        "inspected_at": fmt_datetime(pipe.inspected_at)[:10],
        "length": fmt_m(p.length_m, 1, unit=False),
        "measured": fmt_pct(
            p.measured_length_m / p.length_m if p.length_m else None, 0, unit=False
        ),
        "worst_grade": str(p.worst_grade) if p.worst_grade is not None else "not graded",
        "flag": p.worst_grade is not None and p.worst_grade <= flag_grade,
        "max_blockage": fmt_pct(p.max_blockage_ratio, unit=False),
        "max_blockage_at": fmt_m(p.max_blockage_at_m, unit=False)
        if p.max_blockage_at_m is not None
        else "",
        "defects": str(pipe.defect_count),
        "previous_at": (
            fmt_datetime(pipe.previous_inspected_at)[:10]
            if pipe.previous_inspected_at is not None
            else "first inspection"
        ),
        "previous_max_blockage": fmt_pct(p.previous_max_blockage_ratio, unit=False)
        if pipe.previous_sections
        else "–",
        "growth": _points(p.growth_ratio),
        "growth_at": fmt_m(p.growth_at_m, unit=False) if p.growth_at_m is not None else "",
        "growth_per_year": _points(p.growth_per_year_ratio),
    }


def build_network_context(inp: NetworkInput) -> dict[str, Any]:
    """Everything the network template shows, formatted.

    Returns
    -------
    dict
        ``by_grade`` (every pipe, worst condition first: worst grade, then largest blockage;
        ungraded pipes last), ``by_growth`` (pipes with a previous inspection, fastest growth
        first), ``first_inspections`` (asset ids without one), ``totals`` and ``grade_counts``.
    """
    summaries = [summarise(p) for p in inp.pipes]
    by_grade = sorted(
        summaries,
        key=lambda p: (
            p.worst_grade if p.worst_grade is not None else 99,
            -(p.max_blockage_ratio if p.max_blockage_ratio is not None else -math.inf),
            p.pipe.asset_id,
        ),
    )
    with_growth = [p for p in summaries if p.growth_ratio is not None]
    by_growth = sorted(with_growth, key=lambda p: (-(p.growth_ratio or 0.0), p.pipe.asset_id))
    total_m = sum(p.length_m for p in summaries)
    measured_m = sum(p.measured_length_m for p in summaries)
    dates = [p.pipe.inspected_at for p in summaries]
    grade_counts = []
    for grade in range(5):
        grade_counts.append(
            {
                "grade": str(grade),
                "count": sum(1 for p in summaries if p.worst_grade == grade),
                "flag": grade <= inp.flag_grade,
            }
        )
    ungraded = sum(1 for p in summaries if p.worst_grade is None)
    return {
        "title": inp.title,
        "generated_at": fmt_datetime(inp.generated_at),
        "software_version": inp.software_version,
        "since": fmt_datetime(inp.since) if inp.since is not None else None,
        "tables": [{"name": t.name, "source": t.source} for t in inp.threshold_tables],
        "flag_rule": (
            f"blockage of {fmt_pct(inp.blockage_threshold_ratio)} or more, "
            f"or condition class {inp.flag_grade} or worse"
        ),
        "totals": {
            "pipes": len(summaries),
            "first_date": fmt_datetime(min(dates))[:10] if dates else NOT_RECORDED,
            "last_date": fmt_datetime(max(dates))[:10] if dates else NOT_RECORDED,
            "length": fmt_m(total_m, 1),
            "measured": fmt_m(measured_m, 1),
            "measured_share": fmt_pct(measured_m / total_m if total_m else None, 0),
            "defects": sum(p.pipe.defect_count for p in summaries),
            "flagged_pipes": sum(
                1
                for p in summaries
                if p.worst_grade is not None and p.worst_grade <= inp.flag_grade
            ),
            "with_previous": len(with_growth),
            "ungraded": ungraded,
        },
        "grade_counts": grade_counts,
        "flag_grade": inp.flag_grade,
        "by_grade": [_row(i, p, inp.flag_grade) for i, p in enumerate(by_grade, start=1)],
        "by_growth": [_row(i, p, inp.flag_grade) for i, p in enumerate(by_growth, start=1)],
        "first_inspections": sorted(p.pipe.asset_id for p in summaries if p.growth_ratio is None),
    }
