"""What a per-inspection report shows, computed from plain inputs.

The caller (a task reading the database) builds a :class:`ReportInput`; :func:`build_context`
turns it into the dictionary the Jinja2 template renders. All formatting lives here: ratios
stay fractions in the data and become percentages only in this module's output. A figure that
was not measured renders as ``"not measured"``, never as 0 or ``None``.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeGuard

from pipescan.core.grading import (
    FlagRule,
    ThresholdTable,
    flag_section,
    is_flagged,
    pipe_class_for_material,
)
from pipescan.core.model import Defect, SectionMeasures, SectionStatus
from pipescan.core.registration.metrics import (
    allows_unseen_slips,
    standstill_clause,
    unseen_slip_caveat,
    unseen_slips_clause,
)
from pipescan.core.sanitize import strip_credentials
from pipescan.core.summary import ADJACENT_TOL_M, adjacent_runs, blockage_summary, peak_blockage
from pipescan.core.trends import (
    MIN_YEARS_APART,
    NO_SIGNIFICANT_CHANGE,
    SECONDS_PER_YEAR,
    SIGNIFICANT_CHANGE_RATIO,
    growth_per_year,
    is_significant,
    years_between,
)

__all__ = [
    "APPENDIX_ALL_MAX_SECTIONS",
    "NOT_MEASURED",
    "EarlierInspection",
    "ReportInput",
    "TableCitation",
    "build_context",
    "fmt_pct",
]

NOT_MEASURED = "not measured"
NOT_RECORDED = "not recorded"
WORST_SECTIONS = 10
#: Up to this many sections the appendix lists every one; above it, a compact listing
#: (flagged sections, unmeasured spans, one measured section per metre).
APPENDIX_ALL_MAX_SECTIONS = 150
#: Chainage interval of the measured sections the compact appendix keeps, in metres.
APPENDIX_SAMPLE_EVERY_M = 1.0
#: Earlier inspections drawn on the trend page (the most recent ones).
TREND_MAX_EARLIER = 4
# Spans listed per unmeasured reason in the summary before "and N more".
MAX_LISTED_SPANS = 6

STATUS_LABELS: dict[str, str] = {
    SectionStatus.OK: "measured",
    SectionStatus.LOW_COVERAGE: "low coverage",
    SectionStatus.TOO_FEW_POINTS: "too few points",
    SectionStatus.OUTSIDE_SCAN: "outside the scan",
    SectionStatus.NO_CONTOUR: "no closed contour",
    SectionStatus.INVERT_UNDER_WATER: "invert under water",
    SectionStatus.WEAK_REGISTRATION: "weak registration",
    SectionStatus.SMEARED_WALL: "smeared wall",
}
STATUS_EXPLANATIONS: dict[str, str] = {
    SectionStatus.LOW_COVERAGE: "the scan saw too little of the pipe wall around the section",
    SectionStatus.TOO_FEW_POINTS: (
        "too few LiDAR points for the wall's scatter or its edges: the blockage is not known to "
        "within ±2.5 percentage points"
    ),
    SectionStatus.INVERT_UNDER_WATER: (
        "water hid the invert, where a deposit could lie; the water depth is measured"
    ),
    SectionStatus.OUTSIDE_SCAN: "the section lies beyond the scanned length",
    SectionStatus.NO_CONTOUR: "no closed inner contour could be traced",
    SectionStatus.WEAK_REGISTRATION: (
        "most frames that saw the section slid along the pipe (registered travel disagreed "
        "with the odometer beyond its error), or one had neither odometer nor geometry along "
        "the pipe, or the sensor covers only part of its view in one frame, whose "
        "registration is not yet trusted for figures"
    ),
    SectionStatus.SMEARED_WALL: (
        "the frames that saw the section disagree: the wall's points spread around the "
        "contour by more than the sensor's noise, or an object was seen where other frames "
        "saw the bare wall (registration may have slid along the pipe unseen)"
    ),
}


@dataclass(frozen=True)
class MeasureLimits:
    """The limits a section is measured under (from ``MeasureParams``): at least
    ``min_coverage_ratio`` of the wall seen, by angle, no unseen arc over ``max_gap_deg``, the
    blockage known to within ``max_uncertainty_ratio`` (95 %, ±), at least ``min_points``."""

    min_coverage_ratio: float
    max_gap_deg: float
    max_uncertainty_ratio: float
    min_points: int

    @classmethod
    def of(cls, given: Mapping[str, Any] | None) -> MeasureLimits:
        from pipescan.core.measures import MeasureParams

        default = MeasureParams()
        given = given or {}
        return cls(
            min_coverage_ratio=float(given.get("min_coverage_ratio", default.min_coverage_ratio)),
            max_gap_deg=float(given.get("max_gap_deg", default.max_gap_deg)),
            max_uncertainty_ratio=float(
                given.get("max_uncertainty_ratio", default.max_uncertainty_ratio)
            ),
            min_points=int(given.get("min_points", default.min_points)),
        )

    @property
    def coverage(self) -> str:
        return fmt_pct(self.min_coverage_ratio, 0)

    @property
    def uncertainty(self) -> str:
        return f"{100 * self.max_uncertainty_ratio:g}"


def status_words(s: SectionMeasures, limits: MeasureLimits) -> tuple[str, str]:
    """A section's status as a reader understands it: a label with its reason in a word
    (``"uncertain: wall scatter"``), and a sentence that gives the limit it missed.

    ``too_few_points`` is also what a section with thousands of points gets when its wall
    scatters too much for its blockage to be known (``MeasureParams.max_uncertainty_ratio``):
    it is named for that. ``low_coverage`` on a section that saw most of its wall is an unseen
    arc, not a low share.
    """
    if s.status == SectionStatus.LOW_COVERAGE:
        if not (_finite(s.coverage_ratio) and s.coverage_ratio >= limits.min_coverage_ratio):
            return "low coverage", (
                f"less than {limits.coverage} of the wall, by angle, was seen (a section is "
                f"measured from {limits.coverage} with no unseen arc over "
                f"{limits.max_gap_deg:g}°)"
            )
        return "low coverage: unseen arc", (
            f"{limits.coverage} or more of the wall was seen, but an unseen arc over "
            f"{limits.max_gap_deg:g}°, or unseen arcs together, leave the blockage uncertain by "
            f"more than ±{limits.uncertainty} points"
        )
    if s.status == SectionStatus.TOO_FEW_POINTS:
        if s.point_count < limits.min_points:
            return "too few points", f"fewer than {limits.min_points} points in the section"
        return "uncertain: wall scatter", (
            "the wall's points scatter too much, or its edges are too ragged, for the blockage "
            f"to be known within ±{limits.uncertainty} points (the section has enough points)"
        )
    if s.status == SectionStatus.WEAK_REGISTRATION:
        return "uncertain: registration", STATUS_EXPLANATIONS[s.status]
    if s.status == SectionStatus.SMEARED_WALL:
        return "uncertain: frames disagree", STATUS_EXPLANATIONS[s.status]
    return STATUS_LABELS.get(s.status, str(s.status)), STATUS_EXPLANATIONS.get(s.status, "")


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
CHARACTERISATIONS: dict[tuple[str, str], str] = {
    ("BAA", "A"): "vertical",
    ("BAA", "B"): "horizontal",
}


@dataclass(frozen=True)
class TableCitation:
    """The threshold table a report was graded with: its short name and full source."""

    name: str
    source: str


@dataclass(frozen=True)
class EarlierInspection:
    """An earlier inspection of the same asset, for the trend page.

    Attributes
    ----------
    inspection_id, inspected_at
        Its database id and date.
    sections
        Its sections (contours not needed), any order.
    defect_count
        How many defects it had (None when not known).
    """

    inspection_id: str | int
    inspected_at: datetime
    sections: Sequence[SectionMeasures]
    defect_count: int | None = None


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
        The coded defects, one per physical feature (see
        :func:`pipescan.core.grading.merge_defects`); those over the threshold are flagged.
    generated_at
        When the report was generated.
    flag_grade
        Condition class at or below which a section is flagged (default 2).
    pipe_class
        ``"rigid"`` or ``"flexible"``: which BAA rule graded deformation.
    pipe_class_reason
        Why that class (e.g. ``"from the material (PVC: flexible)"``); empty when not known.
    history
        Earlier inspections of the same asset, any order; a trend page is added when there
        is at least one.
    gis_id, length_note
        The pipe's id in an imported network layer, and the words saying that the scan's
        reach and the pipe's GIS length disagree (None when unknown or when they agree).
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
    pipe_class_reason: str = ""
    history: Sequence[EarlierInspection] = ()
    gis_id: str | None = None
    length_note: str | None = None
    start_source: str | None = None
    """Where the scan's start came from (``pipescan.core.start.START_SOURCES``)."""
    measure_limits: Mapping[str, Any] | None = None
    """The limits a section was measured under (the run's ``MeasureParams``, as stored:
    ``min_coverage_ratio``, ``max_gap_deg``, ``max_uncertainty_ratio``, ``min_points``); None:
    this pipescan's defaults. The report states them where it names a section's status."""


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


def fmt_points(ratio: float | None) -> str:
    """A change of a ratio in percentage points, signed (``+3.2``); never ``-0.0``."""
    if not _finite(ratio):
        return NOT_MEASURED
    text = f"{ratio * 100.0:+.1f}"
    return "0.0" if text in ("+0.0", "-0.0") else text


def fmt_growth(ratio_per_year: float | None, span_years: float) -> dict[str, str]:
    """A growth per year for a table cell: ``{"value": "+3.2", "note": ""}``, with the note
    ``"no significant change"`` when, over the ``span_years`` the inspections cover, it is
    within the measurement's noise (:func:`pipescan.core.trends.is_significant`); the value
    is ``"–"`` without a growth figure."""
    if ratio_per_year is None or not math.isfinite(ratio_per_year):
        return {"value": "–", "note": ""}
    significant = is_significant(ratio_per_year, span_years)
    return {
        "value": fmt_points(ratio_per_year),
        "note": "" if significant else NO_SIGNIFICANT_CHANGE,
    }


def measured_span_years(dates: Sequence[datetime], values: Sequence[float | None]) -> float:
    """Years between the first and the last date whose value was measured (0 if under two)."""
    seen = [d for d, v in zip(dates, values, strict=True) if _finite(v)]
    return years_between(max(seen), min(seen)) if len(seen) >= 2 else 0.0


def fmt_m(value_m: float | None, digits: int = 2, *, unit: bool = True) -> str:
    """A length in metres, e.g. ``"12.30 m"``."""
    if not _finite(value_m):
        return NOT_MEASURED
    return f"{value_m:.{digits}f}\u00a0m" if unit else f"{value_m:.{digits}f}"


def fmt_span(start_m: float, end_m: float) -> str:
    """A chainage interval, e.g. ``"4.00–4.60 m"``."""
    return f"{start_m:.2f}–{end_m:.2f}\u00a0m"


def _fmt_share(ratio: float | None) -> str:
    """A share in whole per cent, but "<1 %" rather than "0 %" for a small non-zero share."""
    if _finite(ratio) and 0.0 < ratio < 0.005:
        return "<1\u00a0%"
    return fmt_pct(ratio, 0)


def fmt_grade(grade: int | None) -> str:
    return str(grade) if grade is not None else "not graded"


def fmt_clock(from_h: float | None, to_h: float | None, code: str = "") -> str:
    """A defect's clock positions, ``"10.3–1.7"`` (clockwise, hours); ``"whole ring"`` for a
    deformation, which has none; ``"—"`` when they were not recorded.

    >>> fmt_clock(10.34, 1.66), fmt_clock(None, None, "BAA"), fmt_clock(None, None, "BBE")
    ('10.3–1.7', 'whole ring', '—')
    """
    if not (_finite(from_h) and _finite(to_h)):
        return "whole ring" if code == "BAA" else "\u2014"
    return f"{from_h:.1f}\u2013{to_h:.1f}"


def _code_words(d: Defect) -> str:
    """The code's family in words, with its characterisation where there is one."""
    words = CODE_LABELS.get(d.code, "")
    extra = CHARACTERISATIONS.get((d.code, d.characterisation or ""), "")
    return f"{words}, {extra}" if words and extra else words


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
    return [
        (sections[run.start].chainage_start_m, sections[run.stop - 1].chainage_end_m)
        for run in adjacent_runs(sections)
    ]


CHAINAGE_UNCERTAINTY_SHOWN_M = 0.05
"""A section's chainage uncertainty is printed in its row from half a section (5 cm): below,
the range the appendix's lead gives says all a reader needs."""


def _uncertainty(s: SectionMeasures) -> str:
    """The section's chainage uncertainty, where it is worth a reader's attention
    (:data:`CHAINAGE_UNCERTAINTY_SHOWN_M`); empty otherwise."""
    u = s.chainage_uncertainty_m
    shown = u is not None and _finite(u) and u >= CHAINAGE_UNCERTAINTY_SHOWN_M
    return fmt_m(u, unit=False) if shown else ""


def _section_row(s: SectionMeasures, flagged: bool, limits: MeasureLimits) -> dict[str, Any]:
    row: dict[str, Any] = {
        "start": fmt_m(s.chainage_start_m, unit=False),
        "end": fmt_m(s.chainage_end_m, unit=False),
        "uncertainty": _uncertainty(s),
        "coverage": fmt_pct(s.coverage_ratio, 0, unit=False),
        "points": fmt_int(s.point_count),
        "status": status_words(s, limits)[0],
        "ok": s.is_ok,
        "flagged": flagged,
    }
    if s.is_ok:
        row.update(
            open_area=(f"{s.open_area_m2:.4f}" if _finite(s.open_area_m2) else NOT_MEASURED),
            blockage=_with_uncertainty(s.blockage_ratio, s.blockage_uncertainty_ratio),
            ovality=fmt_pct(s.ovality_ratio, unit=False),
            deformation=fmt_pct(s.deformation_ratio, unit=False),
            deposit=fmt_pct(s.deposit_height_ratio, unit=False),
            grade=fmt_grade(s.grade),
        )
    else:
        # Figures computed for a section that is not trusted stay out of the report.
        reason = NOT_MEASURED
        if _finite(s.water_depth_ratio) and s.water_depth_ratio:
            depth, u = fmt_pct(s.water_depth_ratio, 0), s.water_depth_uncertainty_ratio
            if _finite(u):
                depth = _with_uncertainty(s.water_depth_ratio, u) + "\u00a0%"
            reason += f" (water {depth} of the diameter deep)"
        row.update(reason=reason)
    return row


def _with_uncertainty(ratio: float | None, uncertainty: float | None) -> str:
    """A measured percentage with its 95 % uncertainty: ``"12.3 ± 0.4"``; an uncertainty that
    would round to 0.0 reads ``"± <0.05"``, never ``"± 0.0"``.

    >>> _with_uncertainty(0.123, 0.004).split(), _with_uncertainty(0.235, 0.0002).split()
    (['12.3', '±', '0.4'], ['23.5', '±', '<0.05'])
    """
    text = fmt_pct(ratio, unit=False)
    if not _finite(ratio) or not _finite(uncertainty):
        return text
    points = abs(uncertainty) * 100.0
    return f"{text}\u00a0±\u00a0" + ("<0.05" if points < 0.05 else f"{points:.1f}")


def _registration_rows(inp: ReportInput) -> list[tuple[str, str]]:
    """The registration appendix: how the frames were placed along the pipe, for an engineer
    who wants to know why the chainage can be trusted as far as the cover says."""
    from pipescan.core.start import START_SOURCES

    start = (
        [("scan start", START_SOURCES.get(inp.start_source, inp.start_source))]
        if inp.start_source
        else []
    )
    return start + _registration_only_rows(inp) + _sensor_rows(inp)


def _sensor_rows(inp: ReportInput) -> list[tuple[str, str]]:
    """The sensor as the run used it: its blind zone, noise and share of the view, each from
    the inspection's ``[sensor]`` profile or estimated from the scan (the limits the sections
    were held to follow from them). None for an inspection stored before they were read."""
    described = (inp.registration or {}).get("instrument")
    if not described:
        return []
    parts = [part for part in described.split("; ") if part != "sensor unknown"]
    return [
        (
            "sensor",
            "; ".join(parts) + ". The smear and blind-zone limits the sections were held to "
            "follow from these",
        )
    ]


def _stride_reason(reason: str) -> str:
    """The stride's reason without the clause naming which bound chose it (a developer's
    word: the figures before it say the same)."""
    return "; ".join(part for part in reason.split("; ") if not part.startswith("bound by"))


_MATCHING_WORDS = {
    "gicp": "generalised ICP (GICP)",
    "point_to_plane": "point-to-plane ICP",
    "point_to_point": "point-to-point ICP",
}


def _matching_words(engine: str | None) -> str:
    """``"small_gicp gicp"`` as ``"generalised ICP (GICP), by small_gicp"``."""
    if not engine:
        return NOT_RECORDED
    library, _, method = engine.partition(" ")
    words = _MATCHING_WORDS.get(method.strip())
    return f"{words}, by {library}" if words else engine


def _ordinal(n: int) -> str:
    """``3`` as ``"3rd"``.

    >>> [_ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22)]
    ['1st', '2nd', '3rd', '4th', '11th', '12th', '13th', '21st', '22nd']
    """
    last = {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{'th' if 11 <= n % 100 <= 13 else last}"


def _registration_only_rows(inp: ReportInput) -> list[tuple[str, str]]:
    reg = inp.registration or {}
    engine = reg.get("engine")
    if inp.frame_count == 0 and (not engine or engine.startswith("none")):
        return [("registration", "none: the archive held one registered cloud")]
    fitness = reg.get("mean_fitness")
    rmse_m = reg.get("mean_rmse_m")
    degenerate = reg.get("degenerate_frames")
    registered = reg.get("frames", inp.frame_count)
    stride = reg.get("frame_stride", 1)
    closer = reg.get("frames_looked_closer")
    frame_rows = [("frames used", f"all {fmt_int(inp.frame_count)}")]
    if stride > 1:
        more = f", and {fmt_int(closer)} more where the scan and the odometer disagreed"
        reason = _stride_reason(reg.get("frame_stride_reason", "set for the run"))
        chosen = (
            f"{fmt_int(registered)} of {fmt_int(inp.frame_count)}: every {_ordinal(stride)}"
            f"{more if closer else ''} ({reason})"
        )
        # Inspections stored before every frame was placed used only the frames registered.
        frame_rows = [("frames used", chosen)]
        if "frames_tracked" in reg:
            lost = reg.get("frames_not_tracked") or 0
            placed = (
                f"all {fmt_int(inp.frame_count)}: the {fmt_int(reg['frames_tracked'])} between "
                "registered ones aligned to the map"
                + (f"; {fmt_int(lost)} that could not be are left out" if lost else "")
            )
            frame_rows = [("frames registered", chosen), ("frames placed", placed)]
    share, per_section = reg.get("placed_share"), reg.get("points_per_section")
    if _finite(share) and share < 1.0:
        kept = reg.get("section_points")
        of = (
            f": an inner section gets about {fmt_int(int(round(share * per_section, -3)))} of its "
            f"{fmt_int(int(round(per_section, -3)))} and measures from {fmt_int(kept)} of them"
            if _finite(per_section) and kept
            else ""
        )
        frame_rows.append(("points placed", f"{fmt_pct(share, 0)} of each frame's, at random{of}"))
    rows = [
        *frame_rows,
        ("scan matching", _matching_words(engine)),
        (
            "points matched",
            f"{fmt_pct(fitness)} of each frame's points, on average, matched the frames before"
            if _finite(fitness)
            else NOT_RECORDED,
        ),
        (
            "match residual",
            f"{rmse_m * 1000.0:.1f} mm, the mean distance between matched points"
            if _finite(rmse_m)
            else NOT_RECORDED,
        ),
    ]
    if degenerate is None:
        rows.append(("placed by the odometer", NOT_RECORDED))
    else:
        rows.append(
            (
                "placed by the odometer",
                f"{degenerate} of {registered} frames: where the pipe's shape gave no hold "
                "along its axis, their place along the pipe is the odometer's"
                if degenerate
                else f"none of {registered}: every frame was placed by the pipe's shape",
            )
        )
    uncertainty_m = reg.get("chainage_uncertainty_m")
    if _finite(uncertainty_m):
        if degenerate == 0:
            # Every frame was placed against features: the ± is registration's own error.
            what = "registration's own error: no frame rested on the odometer"
        elif (
            (reg.get("odometer_slips_caught_m") or reg.get("odometer_slip_stated_m"))
            and allows_unseen_slips(reg)
        ) or reg.get("odometer_stood_frames"):
            what = "the odometer's error over the travel it placed, and its possible slips"
        else:
            what = "the odometer's error over the travel it placed"
        rows.append(("chainage uncertainty", f"up to ±{fmt_m(uncertainty_m)} at the end ({what})"))
    if stood := standstill_clause(reg):
        rows.append(("odometer standstills", stood[0].upper() + stood[1:]))
    if caveat := unseen_slip_caveat(reg):
        rows.append(("unseen odometer slips", caveat))
    caught = reg.get("odometer_slips_caught_m")
    if caught:
        clause = unseen_slips_clause(reg)
        allowed = f"; {clause}" if clause else ""
        rows.append(
            (
                "odometer slips caught",
                f"{len(caught)} with features in view, up to {fmt_m(max(caught))}{allowed}",
            )
        )
    slides = reg.get("slides")
    if slides:
        rows.append(
            ("slides caught", f"{slides} frame(s) put back on the odometer; their sections "
             "are not measured")
        )  # fmt: skip
    return rows


def _measured_diameter(inp) -> str | None:
    """The wall's inner diameter as the run measured it (``core.summary.
    measured_inner_diameter``, stored with the registration summary); None before it was."""
    measured = (inp.registration or {}).get("measured_inner_diameter_m")
    if not _finite(measured):
        return None
    return f"{measured:.3f} m (the wall's median)"


def _trust_rows(
    inp: ReportInput, sections: Sequence[SectionMeasures], limits: MeasureLimits
) -> list[tuple[str, str]]:
    """The cover's two answers: can the chainage be trusted, and the figures, and how far.
    The details are the registration appendix's."""
    reg = inp.registration or {}
    engine = reg.get("engine")
    if inp.frame_count == 0 and (not engine or engine.startswith("none")):
        chainage = "as the registered cloud gives it (pipescan did not register it)"
    elif _finite(u := reg.get("chainage_uncertainty_m")):
        chainage = f"within ±{fmt_m(u)} at the end of the scan, less before it"
        if unseen_slip_caveat(reg):
            chainage += "; more where the odometer may have slipped unseen"
        if slides := reg.get("slides"):
            chainage += f"; {slides} frame(s) slid, their sections are not measured"
    else:
        chainage = "not estimated"
    ok = sum(s.is_ok for s in sections)
    figures = (
        f"each measured blockage within ±{limits.uncertainty} points (95 %); "
        f"{ok} of {len(sections)} sections measured, the others carry no figure"
        if sections
        else "no sections"
    )
    rows = [("chainage", chainage), ("figures", figures)]
    if reg.get("warning"):
        rows.append(("caution", str(reg["warning"])))
    return rows


def _pipe_class_note(inp: ReportInput) -> str:
    """A caution when the material's usual class differs from the class graded with."""
    usual = pipe_class_for_material(inp.material)
    if usual is None or usual == inp.pipe_class:
        return ""
    return (
        f"{inp.material} pipes are usually {usual}; this inspection was graded as a "
        f"{inp.pipe_class} pipe, so deformation (BAA) was judged on the {inp.pipe_class} thresholds"
    )


def _svg_uri(svg: str) -> str:
    return "data:image/svg+xml;base64," + base64.b64encode(svg.encode()).decode("ascii")


def _unmeasured_run_row(run: Sequence[SectionMeasures], limits: MeasureLimits) -> dict[str, Any]:
    """One appendix row for touching unmeasured sections of one status."""
    first, last = run[0], run[-1]
    status = status_words(first, limits)[0]
    coverages = [s.coverage_ratio for s in run]
    coverage = (
        fmt_pct(coverages[0], 0, unit=False)
        if len(run) == 1
        else f"{fmt_pct(min(coverages), 0, unit=False)}–{fmt_pct(max(coverages), 0, unit=False)}"
    )
    count = f" ({len(run)} sections)" if len(run) > 1 else ""
    return {
        "start": fmt_m(first.chainage_start_m, unit=False),
        "end": fmt_m(last.chainage_end_m, unit=False),
        "uncertainty": _uncertainty(max(run, key=lambda s: s.chainage_uncertainty_m or 0.0)),
        "coverage": coverage,
        "points": fmt_int(sum(s.point_count for s in run)),
        "status": status,
        "ok": False,
        "flagged": False,
        "reason": f"{NOT_MEASURED}{count}",
    }


def _appendix(
    sections: Sequence[SectionMeasures],
    is_flagged_section: Callable[[SectionMeasures], bool],
    limits: MeasureLimits,
) -> tuple[list[dict[str, Any]], bool]:
    """The appendix rows, and whether the listing is complete.

    Up to :data:`APPENDIX_ALL_MAX_SECTIONS` sections, every section is a row. Beyond that,
    laying out a row per section makes the PDF slow to render and long to read, so the rows
    are: every flagged section, one row per span of touching unmeasured sections of one
    status, and the measured section starting on each whole metre
    (:data:`APPENDIX_SAMPLE_EVERY_M`). The CSV export holds every section.
    """
    if len(sections) <= APPENDIX_ALL_MAX_SECTIONS:
        return [_section_row(s, is_flagged_section(s), limits) for s in sections], True
    unmeasured = adjacent_runs(
        sections,
        [not s.is_ok for s in sections],
        same=lambda s: status_words(s, limits)[0],
    )
    run_at = {run.start: run for run in unmeasured}
    rows: list[dict[str, Any]] = []
    for i, s in enumerate(sections):
        if i in run_at:
            rows.append(_unmeasured_run_row(sections[run_at[i].start : run_at[i].stop], limits))
        if not s.is_ok:
            continue
        flagged = is_flagged_section(s)
        in_metres = s.chainage_start_m / APPENDIX_SAMPLE_EVERY_M
        on_metre = abs(in_metres - round(in_metres)) <= ADJACENT_TOL_M
        if flagged or on_metre:
            rows.append(_section_row(s, flagged, limits))
    return rows, False


def _section_at(sections: Sequence[SectionMeasures], chainage_m: float) -> SectionMeasures | None:
    return next(
        (
            s
            for s in sections
            if s.chainage_start_m - ADJACENT_TOL_M <= chainage_m < s.chainage_end_m - ADJACENT_TOL_M
        ),
        None,
    )


def _defect_figures(
    inp: ReportInput, sections: Sequence[SectionMeasures], defects: Sequence[Defect]
) -> list[dict[str, Any]]:
    """A cross-section figure at each defect's peak (an SVG data URI, or why there is none)."""
    from pipescan.reports.charts import cross_section_svg

    figures = []
    for number, d in enumerate(defects, start=1):
        s = _section_at(sections, d.peak_chainage_m)
        figure: dict[str, Any] = {
            "number": number,
            "code": d.code or "—",
            "code_label": _code_words(d),
            "clock": fmt_clock(d.clock_from_h, d.clock_to_h, d.code),
            "at": fmt_m(d.peak_chainage_m),
            "measure": MEASURE_LABELS.get(d.measure, d.measure),
            "value": fmt_bound_pct(d, unit=True),
            "grade": fmt_bound_grade(d),
            "uri": None,
            "missing": "",
        }
        if s is None or s.contour_m is None or len(s.contour_m) < 3:
            figure["missing"] = "the contour of this section was not stored"
        else:
            figure["blockage"] = fmt_pct(s.blockage_ratio)
            figure["open_area"] = (
                f"{s.open_area_m2:.4f}\u00a0m²" if _finite(s.open_area_m2) else NOT_MEASURED
            )
            figure["uri"] = _svg_uri(
                cross_section_svg(
                    s.contour_m,
                    nominal_diameter_m=inp.nominal_diameter_m,
                    blockage_ratio=s.blockage_ratio,
                    title=f"{number} {d.code} at {d.peak_chainage_m:.2f} m",
                    clock_arc_h=(
                        (d.clock_from_h, d.clock_to_h)
                        if _finite(d.clock_from_h) and _finite(d.clock_to_h)
                        else None
                    ),
                )
            )
        figures.append(figure)
    return figures


def _peak_blockage_in(
    sections: Sequence[SectionMeasures], start_m: float, end_m: float
) -> tuple[float | None, bool]:
    """Largest measured blockage over sections whose middle lies in ``[start_m, end_m)``,
    and whether any section there was not measured."""
    inside = [
        s for s in sections if start_m <= 0.5 * (s.chainage_start_m + s.chainage_end_m) < end_m
    ]
    peak = peak_blockage(inside)
    return (None if peak is None else peak.blockage_ratio), any(not s.is_ok for s in inside)


def _inspection_summary_row(
    inspection_id: str | int,
    inspected_at: datetime,
    sections: Sequence[SectionMeasures],
    defect_count: int | None,
    *,
    current: bool,
) -> dict[str, Any]:
    total_m = sum(_length_m(s) for s in sections)
    ok_m = sum(_length_m(s) for s in sections if s.is_ok)
    peak = peak_blockage(sections)
    grades = [s.grade for s in sections if s.is_ok and s.grade is not None]
    return {
        "inspection_id": str(inspection_id),
        "inspected_at": fmt_datetime(inspected_at),
        "current": current,
        "measured": f"{fmt_m(ok_m, 1)} ({fmt_pct(ok_m / total_m if total_m else None, 0)})",
        "max_blockage": fmt_pct(peak.blockage_ratio) if peak else NOT_MEASURED,
        "max_blockage_at": fmt_m(peak.chainage_start_m) if peak else "",
        "defects": str(defect_count) if defect_count is not None else NOT_RECORDED,
        "worst_grade": str(min(grades)) if grades else "not graded",
    }


def _trend(
    inp: ReportInput,
    sections: Sequence[SectionMeasures],
    defects: Sequence[Defect],
    *,
    chart: bool,
) -> dict[str, Any] | None:
    """The trend page: earlier inspections of the asset against this one, by chainage."""
    earlier = sorted(
        (h for h in inp.history if h.inspected_at <= inp.inspected_at),
        key=lambda h: h.inspected_at,
        reverse=True,
    )
    if not earlier:
        return None
    shown = earlier[:TREND_MAX_EARLIER]
    inspections = [
        _inspection_summary_row(
            inp.inspection_id, inp.inspected_at, sections, len(defects), current=True
        )
    ] + [
        _inspection_summary_row(
            h.inspection_id, h.inspected_at, h.sections, h.defect_count, current=False
        )
        for h in earlier
    ]
    # Each defect of this inspection, and the largest blockage over its span in each earlier
    # inspection: comparing spans, not single sections, tolerates the few centimetres by which
    # two scans' chainages can disagree. Its growth per year is the one definition
    # (pipescan.core.trends.growth_per_year) over this and the earlier inspections shown.
    columns = shown[:3]
    dates = [inp.inspected_at] + [h.inspected_at for h in shown]
    changes = []
    for number, d in enumerate(defects, start=1):
        span = (d.chainage_start_m, d.chainage_end_m)
        now, _ = _peak_blockage_in(sections, *span)
        peaks = [now] + [_peak_blockage_in(h.sections, *span)[0] for h in shown]
        cells = []
        for h in columns:
            value, partly = _peak_blockage_in(h.sections, *span)
            text = fmt_pct(value, unit=False) if value is not None else NOT_MEASURED
            if value is not None and partly:
                text += "*"
            cells.append(text)
        previous = peaks[1]
        change_text = fmt_points(now - previous if _finite(now) and _finite(previous) else None)
        growth = growth_per_year(dates, peaks)
        rate_text = fmt_growth(growth, measured_span_years(dates, peaks))
        changes.append(
            {
                "number": number,
                "code": d.code or "—",
                "span": f"{d.chainage_start_m:.2f}–{d.chainage_end_m:.2f}",
                "now": fmt_pct(now, unit=False),
                "earlier": cells,
                "change": change_text,
                "rate": rate_text,
            }
        )
    chart_uri = None
    if chart:
        from pipescan.reports.charts import trend_chart_svg

        chart_uri = _svg_uri(
            trend_chart_svg(
                sections,
                [(fmt_datetime(h.inspected_at)[:10], h.sections) for h in shown],
                defects,
                label=f"{fmt_datetime(inp.inspected_at)[:10]} (this inspection)",
                blockage_threshold_ratio=inp.blockage_threshold_ratio,
            )
        )
    return {
        "inspections": inspections,
        "columns": [fmt_datetime(h.inspected_at)[:10] for h in columns],
        "previous_date": fmt_datetime(shown[0].inspected_at)[:10],
        "changes": changes,
        "chart_uri": chart_uri,
        "shown_count": len(shown),
        "earlier_count": len(earlier),
        "any_partly": any("*" in c for row in changes for c in row["earlier"]),
        "min_days_apart": round(MIN_YEARS_APART * SECONDS_PER_YEAR / 86400.0),
        "significant_points": f"{100 * SIGNIFICANT_CHANGE_RATIO:g}",
    }


# --- the context --------------------------------------------------------------------------


def build_context(inp: ReportInput, *, chart: bool = True) -> dict[str, Any]:
    """Everything the inspection template shows, formatted.

    Parameters
    ----------
    inp
        The report's inputs.
    chart
        Draw the figures (matplotlib SVGs, as data URIs): the blockage chart, the defects'
        cross-sections and the trend chart. Tests of the context alone may skip them.

    Returns
    -------
    dict
        Keys used by ``templates/inspection.html.j2``: ``asset`` (cover facts), ``summary``
        (figures), ``grades`` (counts by class), ``unmeasured`` (metres by reason, with
        spans), ``worst`` (the worst ``ok`` sections by blockage), ``defects`` (rows),
        ``figures`` (a cross-section at each defect's peak), ``trend`` (None without earlier
        inspections), ``sections`` (appendix rows) with ``appendix`` (whether the listing is
        complete, and the export command), ``chart_uri`` and ``table``.
    """
    sections = sorted(inp.sections, key=lambda s: s.chainage_start_m)
    defects = sorted(inp.defects, key=lambda d: d.chainage_start_m)
    # Every coded defect is listed; those over the report's threshold are flagged, and only
    # they are shaded on the chart and marked in the section tables.
    flags = FlagRule(inp.blockage_threshold_ratio, inp.flag_grade).kwargs()
    flagged = [d for d in defects if is_flagged(d, **flags)]
    limits = MeasureLimits.of(inp.measure_limits)

    def section_flagged(s: SectionMeasures) -> bool:
        # The one rule, on the section's own figures: a section inside a flagged defect but
        # itself under the rule is not flagged.
        return flag_section(s, **flags)

    ok = [s for s in sections if s.is_ok]
    total_length_m = sum(_length_m(s) for s in sections)
    # The worst measured sections by blockage.
    worst_sections = sorted(
        [s for s in ok if _finite(s.blockage_ratio)],
        key=lambda s: (-(s.blockage_ratio or 0.0), s.chainage_start_m),
    )[:WORST_SECTIONS]
    appendix_rows, appendix_complete = _appendix(sections, section_flagged, limits)
    return {
        "title": f"Pipe condition report {inp.asset_id}",
        "asset": _asset_facts(inp, sections, limits),
        "table": {"name": inp.threshold_table.name, "source": inp.threshold_table.source},
        "summary": _summary(inp, sections, defects, flagged),
        "grades": _grade_rows(ok, total_length_m, inp.flag_grade),
        "unmeasured": _unmeasured_rows(sections, limits),
        "worst": [_section_row(s, section_flagged(s), limits) for s in worst_sections],
        "defects": [_defect_row(d, is_flagged(d, **flags)) for d in defects],
        "lower_bound_note": LOWER_BOUND_NOTE if any(d.lower_bound for d in defects) else "",
        "sections": appendix_rows,
        "appendix": {
            "complete": appendix_complete,
            "row_count": len(appendix_rows),
            "section_count": len(sections),
            "every_m": fmt_m(APPENDIX_SAMPLE_EVERY_M, 0),
            "export_command": (
                f"pipescan export sections --inspection {inp.inspection_id} -o sections.csv"
            ),
        },
        "figures": _defect_figures(inp, sections, defects) if chart else [],
        "trend": _trend(inp, sections, defects, chart=chart),
        "chart_uri": _chart_uri(inp, sections, flagged, limits) if chart and sections else None,
        "not_measured": NOT_MEASURED,
        "limits": {
            "coverage": limits.coverage,
            "gap_deg": f"{limits.max_gap_deg:g}",
            "uncertainty": limits.uncertainty,
            "min_points": limits.min_points,
        },
        "registration": _registration_rows(inp),
        "chainage_uncertainty": _chainage_uncertainty_range(sections),
    }


def _asset_facts(
    inp: ReportInput, sections: Sequence[SectionMeasures], limits: MeasureLimits
) -> dict[str, Any]:
    """The cover's facts: the pipe, the scan, what it can be trusted for, the run."""
    nominal = inp.nominal_diameter_m
    return {
        "asset_id": inp.asset_id,
        "upstream_node": _text(inp.upstream_node),
        "downstream_node": _text(inp.downstream_node),
        "inspected_at": fmt_datetime(inp.inspected_at),
        "nominal_size": (
            f"DN {round(nominal * 1000)} ({nominal:.3f} m inner diameter)"
            if _finite(nominal)
            else NOT_RECORDED
        ),
        "measured_diameter": _measured_diameter(inp),
        "material": _text(inp.material),
        "pipe_shape": _text(inp.pipe_shape),
        "pipe_class": inp.pipe_class,
        "pipe_class_reason": inp.pipe_class_reason,
        "pipe_class_note": _pipe_class_note(inp),
        "scanned_length": fmt_m(inp.scanned_length_m),
        "point_count": fmt_int(inp.point_count),
        "trust": _trust_rows(inp, sections, limits),
        "inspection_id": str(inp.inspection_id),
        "archive_uri": strip_credentials(inp.archive_uri),
        "software_version": inp.software_version,
        "generated_at": fmt_datetime(inp.generated_at),
        "gis_id": inp.gis_id,
        "length_note": inp.length_note,
    }


def _grade_rows(
    ok: Sequence[SectionMeasures], total_length_m: float, flag_grade: int
) -> list[dict[str, Any]]:
    """Counts by condition class, over measured sections only."""
    grades = []
    for grade in range(5):
        members = [s for s in ok if s.grade == grade]
        grades.append(
            {
                "grade": str(grade),
                "label": {0: "worst", 4: "best"}.get(grade, ""),
                "count": len(members),
                "length": fmt_m(sum(_length_m(s) for s in members), 1),
                "share": _fmt_share(
                    sum(_length_m(s) for s in members) / total_length_m if total_length_m else None
                ),
                "flag": grade <= flag_grade,
            }
        )
    return grades


def _unmeasured_rows(
    sections: Sequence[SectionMeasures], limits: MeasureLimits
) -> list[dict[str, Any]]:
    """Unmeasured metres by reason, with the spans so an engineer can find them: one row per
    status as the reader reads it ("low coverage" and "low coverage: unseen arc" are two rows,
    each with the limit it missed)."""
    by_words: dict[tuple[str, str], list[SectionMeasures]] = {}
    for status in SectionStatus:
        for s in sections:
            if s.status == status and status != SectionStatus.OK:
                by_words.setdefault(status_words(s, limits), []).append(s)
    unmeasured = []
    for (label, explanation), members in by_words.items():
        spans = _spans(members)
        listed = [fmt_span(a, b) for a, b in spans[:MAX_LISTED_SPANS]]
        more = len(spans) - len(listed)
        unmeasured.append(
            {
                "reason": label,
                "explanation": explanation,
                "count": len(members),
                "length": fmt_m(sum(_length_m(s) for s in members), 1),
                "spans": ", ".join(listed) + (f" and {more} more" if more else ""),
            }
        )
    return unmeasured


LOWER_BOUND_NOTE = (
    "A value marked ≥ stood in water that returned nothing: the part under the water was not "
    "seen, so the defect is at least that large and its class at least that bad."
)
"""What a lower bound's ``≥`` means, under the defects table of the report and the web view
(present only where a defect is one)."""


def fmt_bound_pct(d: Defect, *, unit: bool = False) -> str:
    """A defect's peak value in per cent, ``≥`` before it when it is a lower bound.

    >>> from pipescan.core.model import Defect
    >>> fmt_bound_pct(Defect("BBE", "blockage_ratio", 2.6, 2.9, 2.7, 0.169, None, 3,
    ...                      lower_bound=True))
    '≥\xa016.9'
    """
    text = fmt_pct(d.peak_value, unit=unit)
    return f"\u2265\u00a0{text}" if d.lower_bound and _finite(d.peak_value) else text


def fmt_bound_grade(d: Defect) -> str:
    """A defect's class, ``"3 or worse"`` when it is a lower bound (0 is the worst)."""
    text = fmt_grade(d.grade)
    return f"{text} or worse" if d.lower_bound and d.grade is not None and d.grade > 0 else text


def _defect_row(d: Defect, flagged: bool) -> dict[str, Any]:
    """One row of the defects table."""
    return {
        "code": d.code or "—",
        "code_label": _code_words(d),
        "clock": fmt_clock(d.clock_from_h, d.clock_to_h, d.code),
        "flagged": flagged,
        "measure": MEASURE_LABELS.get(d.measure, d.measure),
        "start": fmt_m(d.chainage_start_m, unit=False),
        "end": fmt_m(d.chainage_end_m, unit=False),
        "length": fmt_m(d.chainage_end_m - d.chainage_start_m, unit=False),
        "peak_at": fmt_m(d.peak_chainage_m, unit=False),
        "peak_value": fmt_bound_pct(d),
        "peak_blockage": fmt_pct(d.peak_blockage_ratio, unit=False),
        "grade": fmt_bound_grade(d),
    }


def _summary(
    inp: ReportInput,
    sections: Sequence[SectionMeasures],
    defects: Sequence[Defect],
    flagged: Sequence[Defect],
) -> dict[str, Any]:
    """The summary's figures: what was measured, the blockage, the grades and the defects."""
    ok = [s for s in sections if s.is_ok]
    total_length_m = sum(_length_m(s) for s in sections)
    ok_length_m = sum(_length_m(s) for s in ok)
    unmeasured_length_m = total_length_m - ok_length_m
    blockage = blockage_summary(sections)
    graded_ok = [s.grade for s in ok if s.grade is not None]
    threshold_pct = fmt_pct(inp.blockage_threshold_ratio)
    return {
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
        "max_blockage": fmt_pct(blockage.peak_blockage_ratio),
        "max_blockage_at": fmt_m(blockage.peak_chainage_m),
        "mean_blockage": fmt_pct(blockage.mean_blockage_ratio),
        "worst_grade": str(min(graded_ok)) if graded_ok else "not graded",
        "defect_count": len(defects),
        "flagged_count": len(flagged),
        "flagged_length": fmt_m(sum(d.chainage_end_m - d.chainage_start_m for d in flagged), 1),
        "ungraded_ok_count": sum(s.grade is None for s in ok),
        "flag_rule": (
            f"blockage of {threshold_pct} or more, or condition class {inp.flag_grade} or worse"
        ),
        "threshold": threshold_pct,
        "flag_grade": inp.flag_grade,
        "has_negative_blockage": any(
            (s.blockage_ratio or 0.0) < 0 for s in ok if _finite(s.blockage_ratio)
        ),
    }


def _chart_uri(
    inp: ReportInput,
    sections: Sequence[SectionMeasures],
    flagged: Sequence[Defect],
    limits: MeasureLimits,
) -> str:
    """The blockage chart along the pipe, as a data URI."""
    # Imported here so that building a context without a chart needs no matplotlib.
    from pipescan.reports.charts import blockage_chart_svg

    return _svg_uri(
        blockage_chart_svg(
            sections,
            flagged,
            blockage_threshold_ratio=inp.blockage_threshold_ratio,
            flag_grade=inp.flag_grade,
            min_coverage_ratio=limits.min_coverage_ratio,
        )
    )


def _chainage_uncertainty_range(sections: Sequence[SectionMeasures]) -> str:
    """How far the sections' chainages may be off, first to last: ``"±0.01 m at 0.40 m to
    ±0.03 m at 6.60 m"``; empty when not known."""
    known = [s for s in sections if _finite(s.chainage_uncertainty_m)]
    if not known:
        return ""
    first, last = known[0], known[-1]
    a, b = first.chainage_uncertainty_m or 0.0, last.chainage_uncertainty_m or 0.0
    if fmt_m(a) == fmt_m(b):
        return f"within ±{fmt_m(b)}"
    return (
        f"within ±{fmt_m(a)} at {fmt_m(first.chainage_start_m)} to ±{fmt_m(b)} at "
        f"{fmt_m(last.chainage_end_m)}"
    )
