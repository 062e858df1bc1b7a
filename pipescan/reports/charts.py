"""Report figures: blockage along the pipe, as vector SVG.

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
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from pipescan.core.model import Defect, SectionMeasures

__all__ = ["blockage_chart_svg"]

_ADJACENT_TOL_M = 1e-6
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
}


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _runs(sections: Sequence[SectionMeasures], keep: Sequence[bool]) -> list[tuple[float, float]]:
    """(start, end) chainage spans of touching sections for which ``keep`` is true."""
    runs: list[list[float]] = []
    previous_end = None
    for s, k in zip(sections, keep, strict=True):
        if not k:
            previous_end = None
            continue
        if (
            runs
            and previous_end is not None
            and abs(s.chainage_start_m - previous_end) <= _ADJACENT_TOL_M
        ):
            runs[-1][1] = s.chainage_end_m
        else:
            runs.append([s.chainage_start_m, s.chainage_end_m])
        previous_end = s.chainage_end_m
    return [(a, b) for a, b in runs]


def _steps(sections: Sequence[SectionMeasures]) -> tuple[list[float], list[float]]:
    """Coverage % per section and the step edges, with NaN steps over chainage gaps."""
    if not sections:
        return [], [0.0]
    values: list[float] = []
    edges = [sections[0].chainage_start_m]
    for s in sections:
        if abs(s.chainage_start_m - edges[-1]) > _ADJACENT_TOL_M:
            values.append(math.nan)  # a gap: matplotlib leaves NaN steps undrawn
            edges.append(s.chainage_start_m)
        values.append(s.coverage_ratio * 100.0)
        edges.append(s.chainage_end_m)
    return values, edges


def blockage_chart_svg(
    sections: Sequence[SectionMeasures],
    defects: Sequence[Defect],
    *,
    blockage_threshold_ratio: float,
    width_in: float = 6.7,
    height_in: float = 3.3,
) -> str:
    """Blockage along the chainage, with flagged and unmeasured spans, as an SVG document.

    Measured (``ok``) sections are bars of blockage % over their chainage interval, red where
    the section lies in a flagged defect. The flag threshold is a dashed line; flagged spans
    are shaded. Sections that are not ``ok`` are a grey hatched band labelled "not measured",
    never bars at 0. A strip below shows each section's angular coverage %.

    Parameters
    ----------
    sections
        The inspection's sections (any order); chainages in metres.
    defects
        Flagged spans to shade.
    blockage_threshold_ratio
        Flag threshold as a fraction (0.10 is drawn at 10 %).
    width_in, height_in
        Figure size in inches (the default fits an A4 text width).

    Returns
    -------
    str
        A standalone SVG document (UTF-8 text).
    """
    ordered = sorted(sections, key=lambda s: s.chainage_start_m)
    measured = [s.is_ok and _finite(s.blockage_ratio) for s in ordered]
    unmeasured_runs = _runs(ordered, [not s.is_ok for s in ordered])
    x_min_m = min((s.chainage_start_m for s in ordered), default=0.0)
    x_max_m = max((s.chainage_end_m for s in ordered), default=1.0)
    threshold_pct = blockage_threshold_ratio * 100.0

    def in_defect(s: SectionMeasures) -> bool:
        mid = 0.5 * (s.chainage_start_m + s.chainage_end_m)
        return any(d.chainage_start_m <= mid < d.chainage_end_m for d in defects)

    with mpl.rc_context(_STYLE):  # type: ignore[arg-type]  # stubs want Literal keys
        fig = Figure(figsize=(width_in, height_in), layout="constrained")
        ax, ax_cov = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [4.2, 1.0]})

        bars = [s for s, m in zip(ordered, measured, strict=True) if m]
        values_pct = [s.blockage_ratio * 100.0 for s in bars]  # type: ignore[operator]
        y_top = max([threshold_pct * 1.6, *(v * 1.12 for v in values_pct)])
        y_bottom = min([0.0, *(v * 1.12 for v in values_pct)])
        ax.set_ylim(y_bottom, y_top)

        for number, d in enumerate(defects, start=1):
            ax.axvspan(
                d.chainage_start_m, d.chainage_end_m, color=_COLOUR_FLAG_SPAN, lw=0, zorder=0
            )
            # Number and code, as in the defects table: a span flagged on deposits or
            # deformation has no tall bar, and this says why it is shaded.
            ax.text(
                0.5 * (d.chainage_start_m + d.chainage_end_m),
                y_top,
                f"{number} {d.code}".strip(),
                ha="center",
                va="top",
                color=_COLOUR_THRESHOLD,
                fontsize=7,
                fontweight="bold",
                zorder=5,
            )
        for start_m, end_m in unmeasured_runs:
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
            if end_m - start_m >= 0.05 * (x_max_m - x_min_m):
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

        ax.bar(
            [s.chainage_start_m for s in bars],
            values_pct,
            width=[s.chainage_end_m - s.chainage_start_m for s in bars],
            align="edge",
            color=[_COLOUR_FLAGGED if in_defect(s) else _COLOUR_MEASURED for s in bars],
            linewidth=0,
            zorder=2,
        )
        ax.axhline(0.0, color="#333333", lw=0.6, zorder=3)
        ax.axhline(threshold_pct, color=_COLOUR_THRESHOLD, lw=1.0, ls="--", zorder=3)
        ax.set_ylabel("blockage (%)")
        ax.grid(axis="y", color="#dddddd", lw=0.5, zorder=0)
        ax.set_xlim(x_min_m, x_max_m)

        handles = [
            Patch(color=_COLOUR_MEASURED, label="blockage, measured section"),
            Patch(color=_COLOUR_FLAGGED, label="flagged section"),
            Patch(color=_COLOUR_FLAG_SPAN, label="flagged span (defect)"),
            Patch(
                facecolor="#ececec", edgecolor=_COLOUR_UNMEASURED, hatch="///", label="not measured"
            ),
            Line2D(
                [],
                [],
                color=_COLOUR_THRESHOLD,
                ls="--",
                label=f"flag threshold {threshold_pct:g} %",
            ),
        ]
        fig.legend(handles=handles, loc="outside upper center", ncols=3, frameon=False, fontsize=7)

        # Coverage is known for every section, measured or not: it shows why a band is grey.
        coverage_pct, edges_m = _steps(ordered)
        ax_cov.stairs(
            coverage_pct,
            edges_m,
            color="#2d7d46",
            lw=0.9,
            baseline=None,
            zorder=2,
        )
        ax_cov.set_ylim(0, 105)
        ax_cov.set_yticks([0, 50, 100])
        ax_cov.set_ylabel("coverage\n(%)")
        ax_cov.set_xlabel("chainage from upstream node (m)")
        ax_cov.grid(axis="y", color="#dddddd", lw=0.5, zorder=0)

        buffer = io.StringIO()
        fig.savefig(buffer, format="svg", metadata={"Date": None})
    return buffer.getvalue()
