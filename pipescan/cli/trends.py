"""Commands over time: ``trend`` (one pipe across its inspections) and ``worst`` (the network).

Blockage is shown in percent and its change per year in percentage points a year (``pt/yr``):
a ratio of 0.05 a year is ``+5.0 pt/yr``. Unmeasured sections show as ``-`` (or their status),
never as 0. A change that adds up, over the years the surveys span, to less than what two
surveys of an unchanged pipe differ by (:data:`pipescan.core.trends.SIGNIFICANT_CHANGE_RATIO`)
is worded and drawn as "no significant change".
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer

from pipescan.cli._app import DbOption, _fail, _stored_db_url, app, output_format
from pipescan.core.errors import OutputError, PipescanError
from pipescan.core.trends import (
    NO_SIGNIFICANT_CHANGE,
    SIGNIFICANT_CHANGE_RATIO,
    change_thresholds,
    is_significant,
    measured_span_years,
    years,
)
from pipescan.core.wording import plural, signed

_MIN_SPAN_PCT = 5.0
"""A blockage axis spans at least this many percentage points (and always shows 0): two and
a half times the smallest significant change, so that noise looks as small as it is."""

if TYPE_CHECKING:
    from pipescan.storage.database.trends import AssetRanking, AssetTrend


class RankBy(StrEnum):
    growth = "growth"
    current = "current"


SinceOption = Annotated[
    datetime | None,
    typer.Option(
        formats=["%Y-%m-%d", "%Y-%m-%dT%H:%M:%S"],
        help="Only inspections on or after this date (UTC).",
    ),
]


def _since(value: datetime | None) -> datetime | None:
    return None if value is None else value.replace(tzinfo=UTC)


def _pct_number(ratio: float | None) -> str:
    """A ratio as a percentage figure, ``-`` when missing, never ``-0.0``."""
    if ratio is None or not math.isfinite(ratio):
        return "-"
    text = f"{100 * ratio:.1f}"
    return text.lstrip("-") if float(text) == 0.0 else text


def _pct(ratio: float | None) -> str:
    text = _pct_number(ratio)
    return text if text == "-" else f"{text} %"


def _rate(ratio_per_year: float | None) -> str:
    if ratio_per_year is None or not math.isfinite(ratio_per_year):
        return "-"
    return f"{signed(100 * ratio_per_year, 2)} pt/yr"


def _number(value: float) -> float | None:
    return None if not math.isfinite(value) else float(value)


def _verdict(
    ratio_per_year: float | None,
    span_years: float,
    threshold_ratio: float = SIGNIFICANT_CHANGE_RATIO,
) -> str:
    """``growing``, ``shrinking``, ``no significant change`` or ``-`` (no growth figure)."""
    significant = is_significant(ratio_per_year, span_years, threshold_ratio=threshold_ratio)
    if significant is None:
        return "-"
    if not significant:
        return NO_SIGNIFICANT_CHANGE
    return "growing" if ratio_per_year > 0 else "shrinking"  # type: ignore[operator]


def _change_line(
    ratio_per_year: float | None,
    span_years: float,
    threshold_ratio: float = SIGNIFICANT_CHANGE_RATIO,
) -> str:
    """``+4.93 pt/yr (+14.8 pp over 3.0 years): growing``."""
    if ratio_per_year is None or not math.isfinite(ratio_per_year):
        return "- (needs two measured inspections far enough apart)"
    over = f"{signed(100 * ratio_per_year * span_years)} pp over {span_years:.1f} years"
    verdict = _verdict(ratio_per_year, span_years, threshold_ratio)
    return f"{_rate(ratio_per_year)} ({over}): {verdict}"


@dataclass(frozen=True)
class _Spans:
    """What says whether a change is significant: the years between the first and the last
    survey measuring each cell and the peak, and each cell's threshold."""

    cell_years: np.ndarray
    peak_years: float
    cell_threshold_ratio: np.ndarray

    def cell_verdict(self, result: AssetTrend, k: int) -> str:
        return _verdict(
            _number(result.change_per_year[k]),
            float(self.cell_years[k]),
            float(self.cell_threshold_ratio[k]),
        )


def _spans(result: AssetTrend) -> _Spans:
    times = np.array([years(s.inspected_at) for s in result.surveys])
    peaks = np.array([[_nan(s.peak_blockage_ratio)] for s in result.surveys])
    (peak_span,) = measured_span_years(times, peaks)
    return _Spans(
        cell_years=measured_span_years(times, result.blockage_ratio),
        peak_years=float(peak_span),
        cell_threshold_ratio=change_thresholds(result.blockage_ratio, result.step_m),
    )


def _nan(value: float | None) -> float:
    return math.nan if value is None else value


@app.command()
def trend(
    asset: Annotated[str, typer.Argument(help="The pipe asset id, e.g. MH1042-MH1043.")],
    chainage: Annotated[
        float | None,
        typer.Option(help="Only this chainage, in metres (the reference survey's chainage)."),
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option(
            help="Also draw the profiles and the change per year: PNG, PDF or SVG by the "
            "name's suffix (PNG without one)."
        ),
    ] = None,
    since: SinceOption = None,
    max_offset: Annotated[
        float,
        typer.Option(
            "--max-offset", min=0.0, help="Largest chainage shift between surveys to align, m."
        ),
    ] = 1.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of tables.")] = False,
    db: DbOption = None,
) -> None:
    """Blockage at each chainage across an asset's inspections, and its change per year.

    Surveys are aligned by cross-correlation; change per year is a Theil-Sen slope. A change
    smaller than two surveys of an unchanged pipe differ by (2 percentage points over the
    surveys' span; docs/measures.md) is "no significant change".

    Examples:

    \b
      pipescan trend MH1042-MH1043
      pipescan trend MH1042-MH1043 --chainage 41.5 --plot plots/MH1042.svg
    """
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.trends import asset_trend

    try:
        fmt = None
        if plot is not None:  # before the database: a wrong name is said at once
            fmt = output_format(
                plot, option="--plot", what="plot", formats=("png", "pdf", "svg"), bare="png"
            )
            from pipescan.reports.render import check_output_path

            check_output_path(plot, "plot", _FORMATS[fmt])
        engine = connect(_stored_db_url(db))
        try:
            result = asset_trend(engine, asset, max_offset_m=max_offset, since=_since(since))
        finally:
            engine.dispose()
        cell = None if chainage is None else result.cell_at(chainage)
        if plot is not None and fmt is not None:
            _plot_trend(result, plot, cell, fmt)
    except PipescanError as exc:
        _fail(exc)
        return
    if as_json:
        typer.echo(json.dumps(_trend_json(result, cell), indent=2))
    else:
        _print_trend(result, cell)
    if plot is not None:
        typer.echo(f"wrote {plot}", err=True)


def _print_trend(result: AssetTrend, cell: int | None) -> None:
    size = f"DN {1000 * result.nominal_diameter_m:.0f}" if result.nominal_diameter_m else "DN ?"
    described = ", ".join(
        x
        for x in (
            f"{result.upstream_node or '?'} -> {result.downstream_node or '?'}",
            size,
            result.pipe_shape,
            result.material or "",
        )
        if x
    )
    reference = next(s for s in result.surveys if s.is_reference)
    spans = _spans(result)
    typer.echo(f"{result.asset_id} ({described}): {plural(len(result.surveys), 'inspection')}")
    typer.echo(
        f"chainages are those of inspection {reference.inspection_id} "
        f"({reference.inspected_at.date().isoformat()}), the reference survey"
    )
    typer.echo("")
    typer.echo(
        f"{'id':>6}  {'inspected':10}  {'measured':>8}  {'mean':>7}  {'peak':>7}  "
        f"{'at m':>7}  {'offset m':>8}  {'corr':>5}"
    )
    for s in result.surveys:
        at = "-" if s.peak_chainage_m is None else f"{s.peak_chainage_m + s.offset_m:.2f}"
        if s.is_reference:
            offset, correlation = "ref", ""
        else:
            offset = f"{s.offset_m:+.2f}"
            correlation = "-" if s.correlation is None else f"{s.correlation:.2f}"
        typer.echo(
            f"{s.inspection_id:>6}  {s.inspected_at.date().isoformat():10}  "
            f"{s.measured_section_count:>8}  {_pct(s.mean_blockage_ratio):>7}  "
            f"{_pct(s.peak_blockage_ratio):>7}  {at:>7}  {offset:>8}  {correlation:>5}"
        )
    typer.echo("")
    typer.echo(
        f"change per year (Theil-Sen); under {100 * SIGNIFICANT_CHANGE_RATIO:.0f} pp over the "
        f"surveys' span is {NO_SIGNIFICANT_CHANGE} (two surveys of an unchanged pipe differ "
        "that much):"
    )
    typer.echo(f"  peak blockage  {_change_line(result.peak_change_per_year, spans.peak_years)}")
    # The mean over the whole pipe averages its sections' noise away: the threshold, set
    # for one section, would call real changes of the mean noise. Its rate only.
    typer.echo(f"  mean blockage  {_rate(result.mean_change_per_year)}")
    fastest = result.fastest_growth()
    if fastest is not None:
        k = int(np.flatnonzero(np.isclose(result.chainage_start_m, fastest[0]))[0])
        if spans.cell_verdict(result, k) == "growing":
            typer.echo(f"  fastest-growing chainage: {fastest[0]:.2f} m, {_rate(fastest[1])}")
        else:
            typer.echo(
                f"  no chainage grew significantly (the fastest, {fastest[0]:.2f} m: "
                f"{_rate(fastest[1])})"
            )
    typer.echo("")
    if cell is not None:
        start = result.chainage_start_m[cell]
        typer.echo(f"at chainage {start:.2f}-{start + result.step_m:.2f} m:")
        for i, s in enumerate(result.surveys):
            value = result.blockage_ratio[i, cell]
            status = result.section_status[i, cell]
            if math.isfinite(value):
                shown = f"blockage {_pct(value)}"
            else:
                shown = "no section" if status is None else f"unmeasured ({status})"
            typer.echo(f"  {s.inspected_at.date().isoformat()}  {shown}")
        measured = plural(int(result.measured_count[cell]), "measured inspection")
        line = _change_line(
            _number(result.change_per_year[cell]),
            float(spans.cell_years[cell]),
            float(spans.cell_threshold_ratio[cell]),
        )
        typer.echo(f"  change per year: {line} ({measured})")
        return
    dates = [s.inspected_at.date().isoformat() for s in result.surveys]
    typer.echo("blockage by chainage, % (- = unmeasured):")
    typer.echo(
        f"{'chainage m':>10}  " + "  ".join(f"{d:>10}" for d in dates) + f"  {'pt/yr':>8}  change"
    )
    for k, start in enumerate(result.chainage_start_m):
        values = "  ".join(f"{_pct_number(v):>10}" for v in result.blockage_ratio[:, k])
        slope = _number(result.change_per_year[k])
        rate = "-" if slope is None else signed(100 * slope, 2)
        typer.echo(f"{start:>10.2f}  {values}  {rate:>8}  {spans.cell_verdict(result, k)}")


def _trend_json(result: AssetTrend, cell: int | None) -> dict[str, Any]:
    cells = range(result.chainage_start_m.size) if cell is None else [cell]
    spans = _spans(result)
    return {
        "asset_id": result.asset_id,
        "upstream_node": result.upstream_node,
        "downstream_node": result.downstream_node,
        "nominal_diameter_m": result.nominal_diameter_m,
        "pipe_shape": result.pipe_shape,
        "material": result.material,
        "step_m": result.step_m,
        "mean_change_per_year": result.mean_change_per_year,
        "peak_change_per_year": result.peak_change_per_year,
        "significant_change_ratio": SIGNIFICANT_CHANGE_RATIO,
        "peak_change": _verdict(result.peak_change_per_year, spans.peak_years),
        "inspections": [
            {
                "inspection_id": s.inspection_id,
                "inspected_at": s.inspected_at.isoformat(),
                "offset_m": s.offset_m,
                "correlation": s.correlation,
                "is_reference": s.is_reference,
                "measured_section_count": s.measured_section_count,
                "mean_blockage_ratio": s.mean_blockage_ratio,
                "peak_blockage_ratio": s.peak_blockage_ratio,
                "peak_chainage_m": s.peak_chainage_m,
            }
            for s in result.surveys
        ],
        "chainages": [
            {
                "chainage_start_m": round(float(result.chainage_start_m[k]), 3),
                "chainage_end_m": round(float(result.chainage_start_m[k]) + result.step_m, 3),
                "blockage_ratio": [_number(v) for v in result.blockage_ratio[:, k]],
                "status": list(result.section_status[:, k]),
                "change_per_year": _number(result.change_per_year[k]),
                "change": spans.cell_verdict(result, k),
                "measured_count": int(result.measured_count[k]),
            }
            for k in cells
        ],
    }


_FORMATS = {"png": "PNG", "pdf": "PDF", "svg": "SVG"}


def _plot_trend(result: AssetTrend, path: Path, cell: int | None, fmt: str = "png") -> None:
    """Draw :func:`_trend_figure` in ``fmt`` (``png``, ``pdf`` or ``svg``) at exactly
    ``path`` (its folder created; written under a temporary name and renamed into place).
    matplotlib would add ``.png`` to a name without a suffix, and the command then said it
    wrote a file that was not there.

    Raises
    ------
    OutputError
        ``path`` is a folder, or its folder cannot be made or written to.
    """
    import matplotlib.pyplot as plt

    from pipescan.reports.render import check_output_path
    from pipescan.storage.atomic import atomic_file

    check_output_path(path, "plot", _FORMATS[fmt])
    figure = _trend_figure(result, cell)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path) as fh:  # a new file of a random name: no link followed
            figure.savefig(fh, dpi=110, format=fmt)
    except OSError as exc:
        raise OutputError(
            f"cannot write the plot: {exc.strerror or exc}",
            file=str(path),
            hint=f"give the path of a {_FORMATS[fmt]} file in a folder you can write to",
        ) from exc
    finally:
        plt.close(figure)


def _trend_figure(result: AssetTrend, cell: int | None):
    """The profiles of every survey, the change per year at each chainage, and (with a
    chainage) that chainage over time, as a matplotlib figure.

    Drawn to show change, not noise: no offset notation on any axis; blockage axes start at
    0 and span at least :data:`_MIN_SPAN_PCT`; the change-per-year axis spans at least the
    band of "no significant change", which is drawn, with the bars inside it in grey; earlier
    surveys are drawn wider, under the later ones, so that identical surveys stay visible.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    spans = _spans(result)
    times = np.array([years(s.inspected_at) for s in result.surveys])
    survey_span = float(times.max() - times.min()) if times.size else 0.0
    count = len(result.surveys)
    centres = result.chainage_start_m + result.step_m / 2
    panels = 3 if cell is not None else 2
    with plt.rc_context({"axes.formatter.useoffset": False, "font.size": 9}):
        figure, axes = plt.subplots(
            panels, 1, figsize=(10, 2.8 * panels + 0.8), constrained_layout=True
        )
        top, middle = axes[0], axes[1]
        colours = plt.get_cmap("viridis")
        for i, s in enumerate(result.surveys):
            label = s.inspected_at.date().isoformat()
            if not s.is_reference and s.offset_m:
                label += f" (shifted {s.offset_m:+.2f} m)"
            older = count - 1 - i  # 0 for the latest survey
            # NaN breaks the line: unmeasured sections are gaps, not zeros.
            top.plot(
                centres,
                100 * result.blockage_ratio[i],
                color=colours(0.85 * i / max(count - 1, 1)),
                lw=1.3 + 2.2 * older,
                alpha=1.0 if older == 0 else 0.75,
                solid_capstyle="butt",
                zorder=2 + i,
                label=label,
            )
        _blockage_limits(top, 100 * result.blockage_ratio)
        top.set_ylabel("blockage (%)")
        top.set_title(f"{result.asset_id}: blockage along the pipe, by inspection")
        top.legend(
            fontsize="small",
            ncols=min(count, 3),
            loc="best",
            title="earlier surveys drawn wider, beneath",
            title_fontsize="x-small",
        )
        top.grid(alpha=0.3)

        rates = 100 * result.change_per_year
        band = 100 * SIGNIFICANT_CHANGE_RATIO / survey_span if survey_span > 0 else math.inf
        significant = np.array(
            [spans.cell_verdict(result, k) in ("growing", "shrinking") for k in range(rates.size)],
            dtype=bool,
        )
        colour = np.where(significant, np.where(rates > 0, "tab:red", "tab:blue"), "#9a9a9a")
        middle.bar(centres, np.nan_to_num(rates), width=result.step_m, color=colour, alpha=0.9)
        middle.axhline(0, color="black", lw=0.6)
        finite = np.abs(rates[np.isfinite(rates)])
        largest = float(finite.max()) if finite.size else 0.0
        if math.isfinite(band):
            middle.axhspan(-band, band, color="#d9d9d9", alpha=0.6, lw=0, zorder=0)
            half = max(1.15 * largest, 1.6 * band)
        else:
            half = max(1.15 * largest, 1.0)
        middle.set_ylim(-half, half)
        middle.set_ylabel("change (pt/yr)")
        middle.set_xlabel("chainage (m, reference survey)")
        middle.set_title("change per year at each chainage (Theil-Sen)")
        handles = [
            Patch(color="tab:red", label="growing"),
            Patch(color="tab:blue", label="shrinking"),
            Patch(
                color="#9a9a9a",
                label=f"{NO_SIGNIFICANT_CHANGE}: under {100 * SIGNIFICANT_CHANGE_RATIO:.0f} pp "
                f"over the surveys' {survey_span:.1f} years (grey band; more on a steep profile)",
            ),
        ]
        middle.legend(handles=handles, fontsize="small", loc="upper left", ncols=3)
        middle.grid(alpha=0.3)
        for axis in (top, middle):
            axis.set_xlim(centres[0] - result.step_m, centres[-1] + result.step_m)
        if cell is not None:
            start = result.chainage_start_m[cell]
            for axis in (top, middle):
                axis.axvspan(start, start + result.step_m, color="orange", alpha=0.3, zorder=0)
            _plot_cell(axes[2], result, cell, spans.cell_verdict(result, cell))
        figure.canvas.draw()  # lay the ticks out under these rc settings
    return figure


def _blockage_limits(axis, values_pct: np.ndarray) -> None:
    """From 0 (or below, where the pipe is wider than nominal) to above the largest value,
    spanning at least :data:`_MIN_SPAN_PCT`."""
    finite = values_pct[np.isfinite(values_pct)]
    low = min(0.0, float(finite.min())) if finite.size else 0.0
    high = float(finite.max()) if finite.size else 0.0
    margin = 0.08 * max(high - low, _MIN_SPAN_PCT)
    low = low - margin if low < 0 else 0.0
    axis.set_ylim(low, max(high + margin, low + _MIN_SPAN_PCT))


def _plot_cell(axis, result: AssetTrend, cell: int, verdict: str) -> None:
    """One chainage's blockage over time, its Theil-Sen line and what it amounts to."""
    start = result.chainage_start_m[cell]
    dates = [s.inspected_at for s in result.surveys]
    values = 100 * result.blockage_ratio[:, cell]
    axis.plot(dates, values, "o", color="tab:orange", ms=6, zorder=3, label="measured")
    rate = _number(result.change_per_year[cell])
    measured = np.isfinite(values)
    if rate is not None and measured.sum() >= 2:
        # The Theil-Sen line: its slope, through the median of (value - slope * time).
        t = np.array([years(d) for d in dates])
        level = float(np.median(values[measured] - 100 * rate * t[measured]))
        seen = [d for d, m in zip(dates, measured, strict=True) if m]
        ends = [min(seen), max(seen)]
        line = [level + 100 * rate * years(d) for d in ends]
        axis.plot(ends, line, "--", color="tab:orange", lw=1, zorder=2, label="Theil-Sen")
    _blockage_limits(axis, values)
    axis.set_ylabel("blockage (%)")
    title = f"at chainage {start:.2f}-{start + result.step_m:.2f} m"
    if rate is not None:
        title += f": {_rate(rate)}, {verdict}"
    axis.set_title(title)
    axis.legend(fontsize="small", loc="best")
    axis.grid(alpha=0.3)


@app.command()
def worst(
    by: Annotated[
        RankBy,
        typer.Option(
            help="growth: fastest-growing peak blockage; current: highest peak blockage now."
        ),
    ] = RankBy.growth,
    limit: Annotated[int, typer.Option(min=1, help="How many pipes to list.")] = 10,
    since: SinceOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    db: DbOption = None,
) -> None:
    """The network's worst pipes, by blockage growth per year or by current blockage."""
    from pipescan.cli.exchange import gis_names, pipe_label
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.trends import worst_assets

    try:
        engine = connect(_stored_db_url(db))
        try:
            rows = worst_assets(engine, by=by.value, limit=limit, since=_since(since))
            names = gis_names(engine, [r.asset_id for r in rows])
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
        return
    if as_json:
        typer.echo(
            json.dumps(
                [_ranking_json(r) | {"gis_id": names.get(r.asset_id)} for r in rows], indent=2
            )
        )
        return
    if not rows:
        from pipescan.core.trends import MIN_YEARS_APART, SECONDS_PER_YEAR

        days = MIN_YEARS_APART * SECONDS_PER_YEAR / 86400.0
        apart = f"two inspections at least {days:.0f} days apart"
        needs = apart if by == RankBy.growth else "one"
        typer.echo(f"no pipe has {needs} with measured sections yet")
        return
    typer.echo(
        f"{'#':>3}  {'pipe':24} {'insp':>4}  {'last':10}  {'peak':>7}  {'at m':>7}  "
        f"{'mean':>7}  {'peak/yr':>12}  {'mean/yr':>12}  peak change"
    )
    for rank, r in enumerate(rows, 1):
        at = "-" if r.current_peak_chainage_m is None else f"{r.current_peak_chainage_m:.2f}"
        typer.echo(
            f"{rank:>3}  {pipe_label(r.asset_id, names):24} {r.inspection_count:>4}  "
            f"{r.last_inspected_at.date().isoformat():10}  "
            f"{_pct(r.current_peak_blockage_ratio):>7}  {at:>7}  "
            f"{_pct(r.current_mean_blockage_ratio):>7}  {_rate(r.peak_change_per_year):>12}  "
            f"{_rate(r.mean_change_per_year):>12}  "
            f"{_verdict(r.peak_change_per_year, _ranking_span(r))}"
        )
    if by == RankBy.growth:
        typer.echo(
            f"(peak change: under {100 * SIGNIFICANT_CHANGE_RATIO:.0f} pp over the years "
            f"between a pipe's first and last inspection is {NO_SIGNIFICANT_CHANGE})"
        )


def _ranking_span(r: AssetRanking) -> float:
    return years(r.last_inspected_at) - years(r.first_inspected_at)


def _ranking_json(r: AssetRanking) -> dict[str, Any]:
    return {
        "asset_id": r.asset_id,
        "upstream_node": r.upstream_node,
        "downstream_node": r.downstream_node,
        "nominal_diameter_m": r.nominal_diameter_m,
        "inspection_count": r.inspection_count,
        "first_inspected_at": r.first_inspected_at.isoformat(),
        "last_inspected_at": r.last_inspected_at.isoformat(),
        "last_inspection_id": r.last_inspection_id,
        "current_peak_blockage_ratio": r.current_peak_blockage_ratio,
        "current_peak_chainage_m": r.current_peak_chainage_m,
        "current_mean_blockage_ratio": r.current_mean_blockage_ratio,
        "peak_change_per_year": r.peak_change_per_year,
        "mean_change_per_year": r.mean_change_per_year,
        "peak_change": _verdict(r.peak_change_per_year, _ranking_span(r)),
    }
