"""Report figures as vector SVG: blockage along the pipe, a defect's cross-section, the trend.

Figures are built on a bare :class:`matplotlib.figure.Figure` (no pyplot), so no global backend
or figure registry is touched and reports can be drawn from several threads; saving to SVG uses
matplotlib's vector SVG backend (raster Agg is never needed).
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from typing import Any

import matplotlib as mpl
import numpy as np
import shapely
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch
from shapely.geometry import LineString, Point

from pipescan.core.grading import flag_section
from pipescan.core.model import Defect, SectionMeasures
from pipescan.core.summary import adjacent_runs, touches

__all__ = ["blockage_chart_svg", "cross_section_svg", "trend_chart_svg"]

_COLOUR_MEASURED = "#3b6ea5"
_COLOUR_FLAGGED = "#c0392b"
_COLOUR_FLAG_SPAN = "#f6d5d1"
_COLOUR_UNMEASURED = "#9a9a9a"
_COLOUR_THRESHOLD = "#7a1f14"
_STYLE: dict[str, Any] = {
    "svg.fonttype": "none",  # keep text as text: smaller, sharper, searchable in the PDF
    "svg.hashsalt": "pipescan",  # stable ids, so the same input gives the same SVG
    "font.family": "DejaVu Sans",
    "font.size": 8,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "hatch.linewidth": 0.6,
    # Never "+2.349e1" above an axis: a reader takes the tick labels at their word.
    "axes.formatter.useoffset": False,
}


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _chainage_spans(
    sections: Sequence[SectionMeasures], keep: Sequence[bool]
) -> list[tuple[float, float]]:
    """(start, end) chainage spans of touching sections for which ``keep`` is true."""
    return [
        (sections[run.start].chainage_start_m, sections[run.stop - 1].chainage_end_m)
        for run in adjacent_runs(sections, keep)
    ]


def _steps(
    sections: Sequence[SectionMeasures], values: Sequence[float] | None = None
) -> tuple[list[float], list[float]]:
    """Step heights and edges over chainage-sorted sections, with NaN steps over chainage gaps.

    ``values`` are the heights, one per section (coverage % when not given).
    """
    if not sections:
        return [], [0.0]
    if values is None:
        values = [s.coverage_ratio * 100.0 for s in sections]
    heights: list[float] = []
    edges = [sections[0].chainage_start_m]
    for s, value in zip(sections, values, strict=True):
        if not touches(edges[-1], s.chainage_start_m):
            heights.append(math.nan)  # a gap: matplotlib leaves NaN steps undrawn
            edges.append(s.chainage_start_m)
        heights.append(value)
        edges.append(s.chainage_end_m)
    return heights, edges


def blockage_chart_svg(
    sections: Sequence[SectionMeasures],
    defects: Sequence[Defect],
    *,
    blockage_threshold_ratio: float,
    flag_grade: int = 2,
    min_coverage_ratio: float | None = None,
    width_in: float = 6.7,
    height_in: float = 3.3,
) -> str:
    """Blockage along the chainage, with flagged and unmeasured spans, as an SVG document.

    Measured (``ok``) sections are bars of blockage % over their chainage interval, red where
    the section itself is flagged (``pipescan.core.grading.flag_section``: the report's one
    rule). The flag threshold is a dashed line; flagged defects' spans are shaded. Sections
    that are not ``ok`` are a grey hatched band labelled "not measured", never bars at 0. A
    strip below shows each section's angular coverage %, with the coverage a section needs
    (``min_coverage_ratio``) as a dotted line.

    Parameters
    ----------
    sections
        The inspection's sections (any order); chainages in metres.
    defects
        Flagged spans to shade.
    blockage_threshold_ratio, flag_grade
        The flag rule: a blockage at or above this fraction (0.10 is drawn at 10 %), or a
        condition class this bad or worse.
    min_coverage_ratio
        The coverage a section needs to be measured, drawn on the coverage strip (None: not
        drawn).
    width_in, height_in
        Figure size in inches (the default fits an A4 text width).

    Returns
    -------
    str
        A standalone SVG document (UTF-8 text).
    """
    ordered = sorted(sections, key=lambda s: s.chainage_start_m)
    measured = [s.is_ok and _finite(s.blockage_ratio) for s in ordered]
    flagged = [
        flag_section(s, blockage_threshold_ratio=blockage_threshold_ratio, flag_grade=flag_grade)
        for s in ordered
    ]
    x_min_m = min((s.chainage_start_m for s in ordered), default=0.0)
    x_max_m = max((s.chainage_end_m for s in ordered), default=1.0)
    threshold_pct = blockage_threshold_ratio * 100.0

    with mpl.rc_context(_STYLE):  # type: ignore[arg-type]  # stubs want Literal keys
        fig = Figure(figsize=(width_in, height_in), layout="constrained")
        ax, ax_cov = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [4.2, 1.0]})
        values_pct = [
            s.blockage_ratio * 100.0  # type: ignore[operator]
            for s, m in zip(ordered, measured, strict=True)
            if m
        ]
        y_top = max([threshold_pct * 1.6, *(v * 1.12 for v in values_pct)])
        y_bottom = min([0.0, *(v * 1.12 for v in values_pct)])
        ax.set_ylim(y_bottom, y_top)
        _shade_defects(ax, defects, y_top)
        unmeasured_runs = _chainage_spans(ordered, [not s.is_ok for s in ordered])
        _shade_unmeasured(ax, ax_cov, unmeasured_runs, (y_bottom, y_top), x_max_m - x_min_m)
        _blockage_bars(ax, ordered, measured, flagged)
        ax.axhline(0.0, color="#333333", lw=0.6, zorder=3)
        ax.axhline(threshold_pct, color=_COLOUR_THRESHOLD, lw=1.0, ls="--", zorder=3)
        ax.set_ylabel("blockage (%)")
        ax.grid(axis="y", color="#dddddd", lw=0.5, zorder=0)
        ax.set_xlim(x_min_m, x_max_m)
        _blockage_legend(fig, threshold_pct)
        _coverage_strip(ax_cov, ordered, min_coverage_ratio, x_max_m)
        buffer = io.StringIO()
        fig.savefig(buffer, format="svg", metadata={"Date": None})
    return buffer.getvalue()


def _shade_defects(ax: Any, defects: Sequence[Defect], y_top: float) -> None:
    """Flagged defects' spans, shaded, each with its number and code at the top."""
    for number, d in enumerate(defects, start=1):
        ax.axvspan(d.chainage_start_m, d.chainage_end_m, color=_COLOUR_FLAG_SPAN, lw=0, zorder=0)
        # Number and code, as in the defects table: a span flagged on deposits or
        # deformation has no tall bar, and this says why it is shaded.
        ax.text(
            0.5 * (d.chainage_start_m + d.chainage_end_m),
            y_top,
            # With many defects the codes would run into each other: numbers only.
            f"{number} {d.code}".strip() if len(defects) <= 8 else str(number),
            ha="center",
            va="top",
            color=_COLOUR_THRESHOLD,
            fontsize=7,
            fontweight="bold",
            zorder=5,
        )


def _shade_unmeasured(
    ax: Any,
    ax_cov: Any,
    runs: Sequence[tuple[float, float]],
    y_range: tuple[float, float],
    x_span_m: float,
) -> None:
    """Unmeasured spans as grey hatched bands on both axes, the wide ones labelled."""
    y_bottom, y_top = y_range
    for start_m, end_m in runs:
        for axis in (ax, ax_cov):
            axis.axvspan(
                start_m,
                end_m,
                facecolor="#ececec",
                edgecolor=_COLOUR_UNMEASURED,
                hatch="///",
                lw=0,
                zorder=1,
            )
        # Label wide bands in place; narrow ones are explained by the legend.
        if end_m - start_m >= 0.05 * x_span_m:
            ax.text(
                0.5 * (start_m + end_m),
                y_bottom + 0.5 * (y_top - y_bottom),
                "not measured",
                rotation=90,
                ha="center",
                va="center",
                color="#555555",
                fontsize=7,
                bbox={"facecolor": "#ececec", "edgecolor": "none", "pad": 1.0},
                zorder=4,
            )


def _blockage_bars(
    ax: Any,
    ordered: Sequence[SectionMeasures],
    measured: Sequence[bool],
    flagged: Sequence[bool],
) -> None:
    """Measured sections' blockage as bars, red where the section is flagged.

    Two filled step outlines (one per colour), not one patch per section: a 100 m scan has
    1000 sections, and 1000 patches make the SVG slow to draw and to lay out in the PDF. A NaN
    step is not drawn, so unmeasured sections stay empty.
    """
    for colour, keep in (
        (_COLOUR_MEASURED, [m and not f for m, f in zip(measured, flagged, strict=True)]),
        (_COLOUR_FLAGGED, [m and f for m, f in zip(measured, flagged, strict=True)]),
    ):
        if not any(keep):
            continue
        heights, edges_m = _steps(
            ordered,
            [
                s.blockage_ratio * 100.0 if k else math.nan  # type: ignore[operator]
                for s, k in zip(ordered, keep, strict=True)
            ],
        )
        ax.stairs(heights, edges_m, fill=True, color=colour, lw=0, baseline=0.0, zorder=2)


def _blockage_legend(fig: Figure, threshold_pct: float) -> None:
    handles = [
        Patch(color=_COLOUR_MEASURED, label="blockage, measured section"),
        Patch(color=_COLOUR_FLAGGED, label="flagged section"),
        Patch(color=_COLOUR_FLAG_SPAN, label="flagged span (defect)"),
        Patch(facecolor="#ececec", edgecolor=_COLOUR_UNMEASURED, hatch="///", label="not measured"),
        Line2D(
            [], [], color=_COLOUR_THRESHOLD, ls="--", label=f"flag threshold {threshold_pct:g} %"
        ),
    ]
    fig.legend(handles=handles, loc="outside upper center", ncols=3, frameon=False, fontsize=7)


def _coverage_strip(
    ax_cov: Any,
    ordered: Sequence[SectionMeasures],
    min_coverage_ratio: float | None,
    x_max_m: float,
) -> None:
    """Each section's angular coverage, with the coverage a section needs dotted.

    Coverage is known for every section, measured or not: it shows why a band is grey.
    """
    coverage_pct, edges_m = _steps(ordered)
    ax_cov.stairs(coverage_pct, edges_m, color="#2d7d46", lw=0.9, baseline=None, zorder=2)
    if min_coverage_ratio is not None:
        ax_cov.axhline(100 * min_coverage_ratio, color="#2d7d46", lw=0.6, ls=":", zorder=1)
        ax_cov.text(
            x_max_m,
            100 * min_coverage_ratio,
            f" {100 * min_coverage_ratio:g} %",
            color="#2d7d46",
            fontsize=6,
            ha="left",
            va="center",
        )
    ax_cov.set_ylim(0, 105)
    ax_cov.set_yticks([0, 50, 100])
    ax_cov.set_ylabel("coverage\n(%)")
    ax_cov.set_xlabel("chainage from upstream node (m)")
    ax_cov.grid(axis="y", color="#dddddd", lw=0.5, zorder=0)


def _save_svg(fig: Figure) -> str:
    buffer = io.StringIO()
    fig.savefig(buffer, format="svg", metadata={"Date": None})
    return buffer.getvalue()


def _polygons(geometry: Any) -> list[shapely.Polygon]:
    """The polygons of a shapely geometry (a polygon, a multipolygon or a collection)."""
    if geometry.is_empty:
        return []
    if isinstance(geometry, shapely.Polygon):
        return [geometry]
    return [g for part in getattr(geometry, "geoms", []) for g in _polygons(part)]


def _chord_mm(
    polygon: shapely.Polygon, start: tuple[float, float], end: tuple[float, float]
) -> tuple[float, float] | None:
    """The piece of the line start-end inside ``polygon`` that holds the centre (or the
    longest piece if none does), as (from, to) positions along that line's varying axis."""
    pieces = [
        g
        for g in [polygon.intersection(LineString([start, end]))]
        for g in (getattr(g, "geoms", None) or [g])
        if isinstance(g, LineString) and not g.is_empty
    ]
    if not pieces:
        return None
    centre = Point(0.0, 0.0)
    piece = next(
        (p for p in pieces if p.distance(centre) < 1e-6), max(pieces, key=lambda p: p.length)
    )
    axis = 0 if start[1] == end[1] else 1
    values = sorted(c[axis] for c in piece.coords)
    return values[0], values[-1]


def cross_section_svg(
    contour_m: np.ndarray,
    *,
    nominal_diameter_m: float | None,
    blockage_ratio: float | None = None,
    title: str = "",
    clock_arc_h: tuple[float, float] | None = None,
    width_in: float = 3.3,
    height_in: float = 3.1,
) -> str:
    """One section's measured contour against the nominal circle, to scale, as SVG.

    (Over 80 lines for this docstring only: the body draws its parts, ``_draw_open_and_lost``,
    ``_clear_height``, ``_clear_width``, ``_nominal_diameter_line``, ``_clock_marks``.)

    The section is drawn as seen looking in the survey's direction (the way clock positions
    are read: 12 at the crown, 3 on the right), with the clock positions 12, 3, 6 and 9 marked
    around it; ``clock_arc_h``, a defect's ``(from, to)`` clock positions, is drawn as a thick
    arc outside the wall, clockwise from ``from`` to ``to``.

    The open area inside the measured contour is pale blue; the part of the nominal circle
    that is not open (lost to deposits, obstacles or deformation) is shaded red. Dimension
    lines give the nominal diameter, the clear height and width through the pipe centre, and
    the loss at the invert and the crown when there is one. Both axes are in millimetres at
    the same scale. The figure has no legend: the report gives one key for all of them
    (measured contour: solid blue; nominal circle: dashed; lost area: red hatching).

    Parameters
    ----------
    contour_m
        The section's inner contour, shape (M, 2), M >= 3, in metres, in the section plane
        with the pipe centre at the origin: first column across (right), second up.
    nominal_diameter_m
        Design inner diameter; None draws the contour alone (no nominal circle, no loss).
    blockage_ratio
        The section's stored blockage (a fraction), written in the top right corner.
    title
        Drawn above the figure.

    Returns
    -------
    str
        A standalone SVG document.

    Raises
    ------
    ValueError
        If ``contour_m`` is not an (M, 2) array of finite numbers with M >= 3.
    """
    contour = np.asarray(contour_m, dtype=np.float64)
    if contour.ndim != 2 or contour.shape[1] != 2 or len(contour) < 3:
        raise ValueError(f"contour_m must have shape (M, 2) with M >= 3, not {contour.shape}")
    if not np.isfinite(contour).all():
        raise ValueError("contour_m holds non-finite values")
    # The section plane's first axis (PipeAxis.right, up x direction) points to the left of
    # someone looking in the survey's direction: mirror it, so the figure is their view.
    contour_mm = contour * np.array([-1000.0, 1000.0])
    polygon = shapely.Polygon(contour_mm)
    if not polygon.is_valid:
        parts = _polygons(shapely.make_valid(polygon))
        polygon = max(parts, key=lambda p: p.area) if parts else polygon
    radius_mm = nominal_diameter_m * 500.0 if _finite(nominal_diameter_m) else None
    extent_mm = max(float(np.abs(contour_mm).max()), radius_mm or 0.0)

    with mpl.rc_context(_STYLE):  # type: ignore[arg-type]
        # Fixed margins, not constrained layout: the figures are all alike, and measuring the
        # layout of each one doubled its drawing time.
        fig = Figure(figsize=(width_in, height_in))
        ax = fig.add_axes((0.19, 0.12, 0.78, 0.8))
        ax.set_aspect("equal")
        _draw_open_and_lost(ax, polygon, radius_mm)
        _clear_height(ax, polygon, radius_mm, extent_mm)
        _clear_width(ax, polygon, extent_mm)
        if radius_mm is not None:
            _nominal_diameter_line(ax, radius_mm)
        _clock_marks(ax, radius_mm or extent_mm, clock_arc_h)
        limit = extent_mm * 1.3
        ax.set_xlim(-limit, limit)
        ax.set_ylim(-limit, limit)
        ax.set_xlabel("across (mm), looking in the survey's direction")
        ax.set_ylabel("up (mm)")
        ax.tick_params(labelsize=6.5)
        ax.grid(color="#e4e4e4", lw=0.4, zorder=0)
        if title:
            # Figure text, not an axes title: placing an axes title measures every artist
            # above the axes (here the dimension lines), which took most of the drawing time.
            fig.text(
                0.02, 0.985, title, fontsize=8, fontweight="bold", color=_COLOUR_THRESHOLD,
                ha="left", va="top",
            )  # fmt: skip
        if _finite(blockage_ratio):
            fig.text(
                0.98, 0.985, f"blockage {blockage_ratio * 100:.1f} %", fontsize=6.5,
                color=_COLOUR_THRESHOLD, ha="right", va="top",
            )  # fmt: skip
        # No legend in the figure: the report gives one key for all of them.
        return _save_svg(fig)


_ARROW = {
    "arrowstyle": "<|-|>",
    "color": "#222222",
    "lw": 0.7,
    "shrinkA": 0,
    "shrinkB": 0,
    "mutation_scale": 6,
}
"""A cross-section's dimension lines."""
_LABEL_BOX = {"facecolor": "white", "edgecolor": "none", "pad": 0.6, "alpha": 0.85}
"""Behind a dimension's label."""


def _draw_open_and_lost(ax: Any, polygon: shapely.Polygon, radius_mm: float | None) -> None:
    """The open area (pale blue), the nominal circle (dashed) and what of it is lost (red
    hatching), and the measured contour (solid blue)."""
    # Outlines are simplified to 0.3 mm (far below what the printed figure resolves): the
    # PDF renderer parses every vertex, and a report draws one figure per defect.
    outline = polygon.simplify(_DRAW_TOLERANCE_MM)
    ax.fill(*outline.exterior.xy, color="#dce9f5", lw=0, zorder=1)
    if radius_mm is not None:
        circle = Point(0.0, 0.0).buffer(radius_mm, quad_segs=64)
        # The measured contour wanders a millimetre or two either side of a sound wall,
        # which cuts the circle's difference into a hundred slivers. They are noise, not
        # lost area: an opening (erode, then dilate) removes anything thinner than
        # 2 * _SLIVER_MM, and specks under _MIN_LOST_MM2 are dropped.
        lost_area = (
            circle.difference(polygon)
            .buffer(-_SLIVER_MM, quad_segs=2)
            .buffer(_SLIVER_MM, quad_segs=2)
            .simplify(_DRAW_TOLERANCE_MM)
        )
        for lost in (p for p in _polygons(lost_area) if p.area >= _MIN_LOST_MM2):
            ax.fill(
                *lost.exterior.xy,
                facecolor="#f3c4bd",
                edgecolor=_COLOUR_FLAGGED,
                hatch="////",
                lw=0,
                zorder=2,
            )
        ax.add_patch(
            Circle((0.0, 0.0), radius_mm, fill=False, ec="#333333", lw=0.9, ls=(0, (4, 2)))
        )
    ax.plot(*outline.exterior.xy, color=_COLOUR_MEASURED, lw=1.4, zorder=4)


def _clear_height(
    ax: Any, polygon: shapely.Polygon, radius_mm: float | None, extent_mm: float
) -> None:
    """The clear height through the centre, and the loss at the invert and the crown."""
    far = 2.0 * extent_mm
    height = _chord_mm(polygon, (0.0, -far), (0.0, far))
    if height is None:
        return
    low, high = height
    ax.annotate("", (0.0, low), (0.0, high), arrowprops=_ARROW, zorder=5)
    ax.text(
        0.03 * extent_mm,
        0.5 * (low + high) + 0.2 * extent_mm,
        f"clear height\n{high - low:.0f} mm",
        fontsize=6.5,
        ha="left",
        va="center",
        bbox=_LABEL_BOX,
        zorder=6,
    )
    if radius_mm is None:
        return
    for a, b in ((-radius_mm, low), (high, radius_mm)):
        if b - a > 0.02 * radius_mm:
            ax.annotate(
                "", (0.0, a), (0.0, b), arrowprops={**_ARROW, "color": _COLOUR_FLAGGED}, zorder=5
            )
            ax.text(
                -4.0,
                0.5 * (a + b),
                f"{b - a:.0f} mm",
                color=_COLOUR_THRESHOLD,
                fontsize=6.5,
                ha="right",
                va="center",
                bbox=_LABEL_BOX,
                zorder=6,
            )


def _clear_width(ax: Any, polygon: shapely.Polygon, extent_mm: float) -> None:
    """The clear width through the centre."""
    far = 2.0 * extent_mm
    width = _chord_mm(polygon, (-far, 0.0), (far, 0.0))
    if width is None:
        return
    left, right = width
    ax.annotate("", (left, 0.0), (right, 0.0), arrowprops=_ARROW, zorder=5)
    # Below the line and left of the centre: the clear height's label sits above, right.
    ax.text(
        left + 0.06 * extent_mm,
        -0.06 * extent_mm,
        f"clear width\n{right - left:.0f} mm",
        fontsize=6.5,
        ha="left",
        va="top",
        bbox=_LABEL_BOX,
        zorder=6,
    )


def _nominal_diameter_line(ax: Any, radius_mm: float) -> None:
    """The nominal diameter's dimension line above the section."""
    y_dim = radius_mm * 1.2
    ax.annotate("", (-radius_mm, y_dim), (radius_mm, y_dim), arrowprops=_ARROW, zorder=5)
    for x in (-radius_mm, radius_mm):
        ax.plot([x, x], [0.0, y_dim * 1.03], color="#999999", lw=0.4, zorder=0)
    ax.text(
        0.0,
        y_dim,
        f"nominal \u2300 {2 * radius_mm:.0f} mm",
        fontsize=6.5,
        ha="center",
        va="bottom",
        zorder=6,
    )


def _clock_marks(ax: Any, radius_mm: float, arc_h: tuple[float, float] | None) -> None:
    """Clock positions 12, 3, 6 and 9 around the wall, and a defect's arc outside it (in the
    figure's view, clock ``h`` lies at the angle ``90° − 30° h`` from the x axis)."""
    for hours in (12, 3, 6, 9):
        angle = math.radians(90.0 - 30.0 * hours)
        ax.text(
            1.1 * radius_mm * math.cos(angle), 1.1 * radius_mm * math.sin(angle), str(hours),
            fontsize=6, color="#777777", ha="center", va="center", zorder=6,
        )  # fmt: skip
    if arc_h is None or not all(_finite(h) for h in arc_h):
        return
    start, end = arc_h
    span = (end - start) % 12.0 or 12.0
    hours = start + np.linspace(0.0, span, 120)
    angles = np.radians(90.0 - 30.0 * hours)
    ring = 1.035 * radius_mm
    ax.plot(
        ring * np.cos(angles), ring * np.sin(angles), color=_COLOUR_FLAGGED, lw=3.0,
        solid_capstyle="butt", zorder=5,
    )  # fmt: skip


_DRAW_TOLERANCE_MM = 0.3
_SLIVER_MM = 1.5
_MIN_LOST_MM2 = 50.0
_TREND_COLOURS = ("#e08a2c", "#8a6bb8", "#6a9a58", "#b0b0b0")


def _profile_xy(sections: Sequence[SectionMeasures]) -> tuple[list[float], list[float]]:
    """Measured blockage % at each section's middle, with NaN (a break in the line) wherever
    a section is not measured or the chainage has a gap."""
    xs: list[float] = []
    ys: list[float] = []
    previous_end = None
    for s in sorted(sections, key=lambda s: s.chainage_start_m):
        if previous_end is not None and not touches(previous_end, s.chainage_start_m):
            xs.append(math.nan)
            ys.append(math.nan)
        xs.append(0.5 * (s.chainage_start_m + s.chainage_end_m))
        measured = s.is_ok and _finite(s.blockage_ratio)
        ys.append(s.blockage_ratio * 100.0 if measured else math.nan)  # type: ignore[operator]
        previous_end = s.chainage_end_m
    return xs, ys


def trend_chart_svg(
    sections: Sequence[SectionMeasures],
    earlier: Sequence[tuple[str, Sequence[SectionMeasures]]],
    defects: Sequence[Defect],
    *,
    label: str,
    blockage_threshold_ratio: float,
    width_in: float = 6.7,
    height_in: float = 3.0,
) -> str:
    """Blockage by chainage in this inspection and earlier ones, as an SVG document.

    Each inspection is a line through its measured sections' middles; where a section was
    not measured the line breaks (no figure, never zero). Earlier inspections are drawn wider
    and beneath, so that one that reads the same as a later one stays visible. This
    inspection's defects are shaded.

    Parameters
    ----------
    sections
        This inspection's sections.
    earlier
        ``(label, sections)`` of earlier inspections, most recent first.
    defects
        This inspection's defects (shaded spans).
    label
        Legend label of this inspection.
    blockage_threshold_ratio
        Flag threshold (a fraction), drawn as a dashed line.
    """
    threshold_pct = blockage_threshold_ratio * 100.0
    with mpl.rc_context(_STYLE):  # type: ignore[arg-type]
        fig = Figure(figsize=(width_in, height_in), layout="constrained")
        ax = fig.subplots()
        for d in defects:
            ax.axvspan(
                d.chainage_start_m, d.chainage_end_m, color=_COLOUR_FLAG_SPAN, lw=0, zorder=0
            )
        values: list[float] = [threshold_pct * 1.5]
        lows: list[float] = [0.0]
        # Older inspections are drawn wider, beneath the newer ones: where two inspections
        # read the same, the older still shows as a band around the newer line.
        for number, (text, earlier_sections) in reversed(list(enumerate(earlier))):
            xs, ys = _profile_xy(earlier_sections)
            ax.plot(
                xs,
                ys,
                color=_TREND_COLOURS[number % len(_TREND_COLOURS)],
                lw=1.2 + 1.6 * (number + 1),
                alpha=0.8,
                solid_capstyle="butt",
                label=text,
                zorder=2 + (len(earlier) - number) * 0.1,
            )
            values += [y for y in ys if math.isfinite(y)]
        xs, ys = _profile_xy(sections)
        ax.plot(xs, ys, color=_COLOUR_MEASURED, lw=1.2, label=label, zorder=3)
        finite = [y for y in ys if math.isfinite(y)]
        values += finite
        lows += [min(finite, default=0.0)]
        all_sections = [*sections, *(s for _, ss in earlier for s in ss)]
        ax.set_xlim(
            min((s.chainage_start_m for s in all_sections), default=0.0),
            max((s.chainage_end_m for s in all_sections), default=1.0),
        )
        ax.set_ylim(min(lows) * 1.15 - 0.5, max(values) * 1.12)
        ax.axhline(0.0, color="#333333", lw=0.6, zorder=1)
        ax.axhline(threshold_pct, color=_COLOUR_THRESHOLD, lw=1.0, ls="--", zorder=1)
        ax.set_ylabel("blockage (%)")
        ax.set_xlabel("chainage from upstream node (m)")
        ax.grid(axis="y", color="#dddddd", lw=0.5, zorder=0)
        handles, _ = ax.get_legend_handles_labels()
        # This inspection first, then the earlier ones newest first.
        handles = [handles[-1], *reversed(handles[:-1])]
        handles += [
            Patch(color=_COLOUR_FLAG_SPAN, label="defect of this inspection"),
            Line2D(
                [],
                [],
                color=_COLOUR_THRESHOLD,
                ls="--",
                label=f"flag threshold {threshold_pct:g} %",
            ),
        ]
        fig.legend(handles=handles, loc="outside upper center", ncols=3, frameon=False, fontsize=7)
        return _save_svg(fig)
