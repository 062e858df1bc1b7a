"""Commands over time: ``trend`` (one pipe across its inspections) and ``worst`` (the network).

Blockage is shown in percent and its change per year in percentage points a year (``pt/yr``):
a ratio of 0.05 a year is ``+5.0 pt/yr``. Unmeasured sections show as ``-`` (or their status),
never as 0.
"""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from pipescan.cli._app import DbOption, _db_url, _fail, app
from pipescan.core.errors import PipescanError

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


def _pct(ratio: float | None) -> str:
    return "-" if ratio is None or not math.isfinite(ratio) else f"{100 * ratio:.1f} %"


def _rate(ratio_per_year: float | None) -> str:
    if ratio_per_year is None or not math.isfinite(ratio_per_year):
        return "-"
    return f"{100 * ratio_per_year:+.2f} pt/yr"


def _number(value: float) -> float | None:
    return None if not math.isfinite(value) else float(value)


@app.command()
def trend(
    asset: Annotated[str, typer.Argument(help="The pipe asset id, e.g. MH1042-MH1043.")],
    chainage: Annotated[
        float | None,
        typer.Option(help="Only this chainage, in metres (the reference survey's chainage)."),
    ] = None,
    plot: Annotated[
        Path | None, typer.Option(help="Also draw the profiles and the change per year (PNG).")
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

    Surveys are aligned by cross-correlation; change per year is a Theil-Sen slope.
    """
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.trends import asset_trend

    try:
        engine = connect(_db_url(db))
        try:
            result = asset_trend(engine, asset, max_offset_m=max_offset, since=_since(since))
        finally:
            engine.dispose()
        cell = None if chainage is None else result.cell_at(chainage)
        if plot is not None:
            _plot_trend(result, plot, cell)
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
    typer.echo(f"{result.asset_id} ({described}): {len(result.surveys)} inspections")
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
        f"change per year (Theil-Sen): mean blockage {_rate(result.mean_change_per_year)}, "
        f"peak blockage {_rate(result.peak_change_per_year)}"
    )
    fastest = result.fastest_growth()
    if fastest is not None:
        typer.echo(f"fastest-growing chainage: {fastest[0]:.2f} m, {_rate(fastest[1])}")
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
        typer.echo(
            f"  change per year: {_rate(_number(result.change_per_year[cell]))} "
            f"({int(result.measured_count[cell])} measured inspections)"
        )
        return
    dates = [s.inspected_at.date().isoformat() for s in result.surveys]
    typer.echo("blockage by chainage, % (- = unmeasured):")
    typer.echo(f"{'chainage m':>10}  " + "  ".join(f"{d:>10}" for d in dates) + "     pt/yr")
    for k, start in enumerate(result.chainage_start_m):
        values = "  ".join(
            f"{'-' if not math.isfinite(v) else f'{100 * v:.1f}':>10}"
            for v in result.blockage_ratio[:, k]
        )
        slope = result.change_per_year[k]
        rate = "-" if not math.isfinite(slope) else f"{100 * slope:+.2f}"
        typer.echo(f"{start:>10.2f}  {values}  {rate:>8}")


def _trend_json(result: AssetTrend, cell: int | None) -> dict[str, Any]:
    cells = range(result.chainage_start_m.size) if cell is None else [cell]
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
                "measured_count": int(result.measured_count[k]),
            }
            for k in cells
        ],
    }


def _plot_trend(result: AssetTrend, path: Path, cell: int | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 3 if cell is not None else 2
    figure, axes = plt.subplots(
        panels, 1, figsize=(10, 2.6 * panels + 0.6), constrained_layout=True
    )
    top, middle = axes[0], axes[1]
    colours = plt.get_cmap("viridis")
    count = len(result.surveys)
    centres = result.chainage_start_m + result.step_m / 2
    for i, s in enumerate(result.surveys):
        label = s.inspected_at.date().isoformat()
        if not s.is_reference and s.offset_m:
            label += f" (shifted {s.offset_m:+.2f} m)"
        # NaN breaks the line: unmeasured sections are gaps, not zeros.
        top.plot(
            centres,
            100 * result.blockage_ratio[i],
            color=colours(i / max(count - 1, 1)),
            lw=1.2,
            label=label,
        )
    top.set_ylabel("blockage (%)")
    top.set_title(f"{result.asset_id}: blockage along the pipe, by inspection")
    top.legend(fontsize="small", ncols=min(count, 3), loc="upper left")
    top.grid(alpha=0.3)
    middle.bar(
        centres, 100 * result.change_per_year, width=result.step_m, color="tab:red", alpha=0.8
    )
    middle.axhline(0, color="black", lw=0.6)
    middle.set_ylabel("change (pt/yr)")
    middle.set_xlabel("chainage (m, reference survey)")
    middle.set_title("change per year at each chainage (Theil-Sen)")
    middle.grid(alpha=0.3)
    for axis in (top, middle):
        axis.set_xlim(centres[0] - result.step_m, centres[-1] + result.step_m)
    if cell is not None:
        start = result.chainage_start_m[cell]
        for axis in (top, middle):
            axis.axvspan(start, start + result.step_m, color="orange", alpha=0.3)
        bottom = axes[2]
        dates = [s.inspected_at for s in result.surveys]
        values = 100 * result.blockage_ratio[:, cell]
        bottom.plot(dates, values, "o-", color="tab:orange")
        bottom.set_ylabel("blockage (%)")
        bottom.set_title(f"at chainage {start:.2f}-{start + result.step_m:.2f} m")
        bottom.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


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
        engine = connect(_db_url(db))
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
        f"{'mean':>7}  {'peak/yr':>12}  {'mean/yr':>12}"
    )
    for rank, r in enumerate(rows, 1):
        at = "-" if r.current_peak_chainage_m is None else f"{r.current_peak_chainage_m:.2f}"
        typer.echo(
            f"{rank:>3}  {pipe_label(r.asset_id, names):24} {r.inspection_count:>4}  "
            f"{r.last_inspected_at.date().isoformat():10}  "
            f"{_pct(r.current_peak_blockage_ratio):>7}  {at:>7}  "
            f"{_pct(r.current_mean_blockage_ratio):>7}  {_rate(r.peak_change_per_year):>12}  "
            f"{_rate(r.mean_change_per_year):>12}"
        )


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
    }
