"""The network summary: a set of inspections (e.g. one scheduled run), a line per pipe,
ranked by worst condition and by growth.

As for the inspection report, the caller gathers plain inputs (:class:`NetworkInput`) and
:func:`build_network_context` formats them; ratios become percentages only here, and a figure
that was not measured reads "not measured". A pipe's largest blockage and its growth per year
are the core's one definitions (:func:`pipescan.core.summary.peak_blockage`,
:func:`pipescan.core.trends.growth_per_year`), the same figures as ``pipescan worst --by
growth`` and ``pipescan trend`` give.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from pipescan.core.flags import FlagRule
from pipescan.core.model import Defect, SectionMeasures
from pipescan.core.summary import peak_blockage, worst_grade
from pipescan.core.trends import (
    MIN_YEARS_APART,
    SECONDS_PER_YEAR,
    SIGNIFICANT_CHANGE_RATIO,
    growth_per_year,
)
from pipescan.reports.context import (
    NOT_RECORDED,
    TableCitation,
    _finite,
    fmt_clock,
    fmt_datetime,
    fmt_grade,
    fmt_growth,
    fmt_m,
    fmt_pct,
    fmt_points,
    measured_span_years,
)

__all__ = [
    "EarlierScan",
    "FailedArchive",
    "NetworkInput",
    "PipeInspection",
    "PipeSummary",
    "build_network_context",
    "summarise",
]


@dataclass(frozen=True)
class EarlierScan:
    """An earlier scan of a pipe (one per archive): when, and its peak blockage (None when
    nothing was measured), as stored with the inspection."""

    inspection_id: int | str
    inspected_at: datetime
    peak_blockage_ratio: float | None


@dataclass(frozen=True)
class PipeInspection:
    """One pipe's inspection in a network summary, with the pipe's earlier scans.

    ``sections`` need no contours. ``earlier`` are the asset's earlier scans (each archive
    once), in date order; the last is the previous inspection. ``gis_id`` is the pipe's id in
    an imported network layer; ``length_note`` says when the scan's reach and the pipe's GIS
    length disagree. ``worst_defect`` is the defect
    that sets the pipe's condition (:func:`pipescan.core.grading.worst_defect`), shown with its
    code and clock positions.
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
    earlier: Sequence[EarlierScan] = ()
    worst_defect: Defect | None = None
    gis_id: str | None = None
    length_note: str | None = None

    @property
    def name(self) -> str:
        """What the report calls the pipe: its GIS id when a network layer was imported."""
        return self.gis_id or self.asset_id

    @property
    def previous(self) -> EarlierScan | None:
        return self.earlier[-1] if self.earlier else None


@dataclass(frozen=True)
class FailedArchive:
    """An archive of the run that failed (nothing was stored for it): its label in the run
    and the one-line reason."""

    label: str
    reason: str


@dataclass(frozen=True)
class NetworkInput:
    """Everything a network summary needs. ``failed`` are the archives of the run the summary
    covers that failed (a summary of the database alone has none)."""

    pipes: Sequence[PipeInspection]
    generated_at: datetime
    software_version: str
    blockage_threshold_ratio: float = FlagRule.blockage_threshold_ratio
    flag_grade: int = FlagRule.flag_grade
    threshold_tables: Sequence[TableCitation] = ()
    since: datetime | None = None
    title: str = "Network condition summary"
    failed: Sequence[FailedArchive] = ()


@dataclass(frozen=True)
class PipeSummary:
    """The figures of one pipe's line (fractions and metres; None when not measured).

    ``growth_per_year_ratio`` is the pipe's growth: the growth per year of its peak blockage
    over the earlier scans and this one (:func:`pipescan.core.trends.growth_per_year`);
    ``growth_span_years`` the years between the first and the last of them that measured a
    peak (what says whether the growth is significant). ``change_ratio`` is the peak blockage
    now less the previous inspection's.
    """

    pipe: PipeInspection
    length_m: float
    measured_length_m: float
    worst_grade: int | None
    max_blockage_ratio: float | None
    max_blockage_at_m: float | None
    previous_max_blockage_ratio: float | None
    change_ratio: float | None
    growth_per_year_ratio: float | None
    growth_span_years: float = 0.0


def summarise(pipe: PipeInspection) -> PipeSummary:
    """The figures of one pipe's line in the network summary."""
    length_m = sum(s.chainage_end_m - s.chainage_start_m for s in pipe.sections)
    measured_m = sum(s.chainage_end_m - s.chainage_start_m for s in pipe.sections if s.is_ok)
    peak = peak_blockage(pipe.sections)
    peak_ratio = None if peak is None else peak.blockage_ratio
    previous = pipe.previous
    previous_peak = None if previous is None else previous.peak_blockage_ratio
    dates = [e.inspected_at for e in pipe.earlier] + [pipe.inspected_at]
    peaks = [e.peak_blockage_ratio for e in pipe.earlier] + [peak_ratio]
    growth = growth_per_year(dates, peaks)
    return PipeSummary(
        pipe=pipe,
        length_m=length_m,
        measured_length_m=measured_m,
        worst_grade=worst_grade(pipe.sections),
        max_blockage_ratio=peak_ratio,
        max_blockage_at_m=None if peak is None else peak.chainage_start_m,
        previous_max_blockage_ratio=previous_peak,
        change_ratio=(
            peak_ratio - previous_peak
            if peak_ratio is not None and previous_peak is not None
            else None
        ),
        growth_per_year_ratio=growth,
        growth_span_years=measured_span_years(dates, peaks),
    )


def _defect_words(d: Defect | None) -> str:
    """``"BBC 3.8–8.2, class 2"``: a defect's code, clock positions and class, in brief."""
    if d is None:
        return ""
    clock = fmt_clock(d.clock_from_h, d.clock_to_h, d.code)
    where = "" if clock == "\u2014" else f" {clock}"
    return f"{d.code}{where}, class {fmt_grade(d.grade)}"


def _row(rank: int, p: PipeSummary, flag_grade: int) -> dict[str, Any]:
    pipe = p.pipe
    nodes = " → ".join(n for n in (pipe.upstream_node, pipe.downstream_node) if n)
    return {
        "rank": rank,
        "asset_id": pipe.asset_id,
        "pipe": pipe.name,
        "asset_note": (
            f"asset {pipe.asset_id}" if pipe.gis_id and pipe.gis_id != pipe.asset_id else ""
        ),
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
        "worst_defect": _defect_words(pipe.worst_defect),
        "previous_at": (
            fmt_datetime(pipe.previous.inspected_at)[:10]
            if pipe.previous is not None
            else "first inspection"
        ),
        "previous_max_blockage": fmt_pct(p.previous_max_blockage_ratio, unit=False)
        if pipe.previous is not None
        else "–",
        "inspections": str(len(pipe.earlier) + 1),
        "change": fmt_points(p.change_ratio),
        "growth_per_year": fmt_growth(p.growth_per_year_ratio, p.growth_span_years),
    }


def build_network_context(inp: NetworkInput) -> dict[str, Any]:
    """Everything the network template shows, formatted.

    Returns
    -------
    dict
        ``by_grade`` (every pipe, worst condition first: worst grade, then largest blockage;
        ungraded pipes last), ``by_growth`` (pipes with a growth figure, fastest first),
        ``first_inspections`` (asset ids without an earlier scan), ``without_growth`` (asset
        ids with one but no growth figure), ``failed`` (the run's archives that failed, with
        their reasons), ``totals`` and ``grade_counts``.
    """
    summaries = [summarise(p) for p in inp.pipes]
    by_grade = sorted(
        summaries,
        key=lambda p: (
            p.worst_grade if p.worst_grade is not None else 99,
            -(p.max_blockage_ratio if p.max_blockage_ratio is not None else -math.inf),
            p.pipe.name,
        ),
    )
    # The order of ``pipescan worst --by growth``: fastest growth first, then by asset id.
    with_growth = [p for p in summaries if p.growth_per_year_ratio is not None]
    by_growth = sorted(with_growth, key=lambda p: (-(p.growth_per_year_ratio or 0.0), p.pipe.name))
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
            "with_previous": sum(1 for p in summaries if p.pipe.earlier),
            "ungraded": ungraded,
        },
        "grade_counts": grade_counts,
        "flag_grade": inp.flag_grade,
        "min_days_apart": round(MIN_YEARS_APART * SECONDS_PER_YEAR / 86400.0),
        "significant_points": f"{100 * SIGNIFICANT_CHANGE_RATIO:g}",
        "by_grade": [_row(i, p, inp.flag_grade) for i, p in enumerate(by_grade, start=1)],
        "by_growth": [_row(i, p, inp.flag_grade) for i, p in enumerate(by_growth, start=1)],
        "failed": [{"label": f.label, "reason": f.reason} for f in inp.failed],
        "first_inspections": sorted(p.pipe.name for p in summaries if not p.pipe.earlier),
        "without_growth": sorted(
            p.pipe.name for p in summaries if p.pipe.earlier and p.growth_per_year_ratio is None
        ),
        "length_notes": [
            {"pipe": p.pipe.name, "note": p.pipe.length_note}
            for p in sorted(summaries, key=lambda p: p.pipe.name)
            if p.pipe.length_note
        ],
    }
