"""Commands that process scans: ``simulate``, ``inspect``, ``demo``."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import ContourOption, DbOption, Scenario, _db_url, _fail, _settings, app
from pipescan.core.errors import OptionError, PipescanError


@app.command()
def simulate(
    out: Annotated[
        Path | None, typer.Argument(help="Directory to write the archive to.", show_default=False)
    ] = None,
    scenario: Annotated[Scenario, typer.Option(help="Scene and sensor preset.")] = Scenario.paper,
    seed: Annotated[int, typer.Option(help="Random seed (same seed, same scan).")] = 0,
    travel_m: Annotated[float | None, typer.Option(help="Override the crawler's travel.")] = None,
    effect: Annotated[
        list[str] | None,
        typer.Option(
            metavar="NAME=VALUE",
            help="Set a sensor or crawler effect (repeatable), e.g. "
            "spurious_return_ratio=0.02 or slip_duration_s=0.5,2. Names: see --list-effects.",
        ),
    ] = None,
    ideal: Annotated[
        bool, typer.Option(help="Switch every effect off (then --effect switches some on).")
    ] = False,
    list_effects: Annotated[
        bool, typer.Option(help="List the effects with their defaults, and exit.")
    ] = False,
) -> None:
    """Simulate a crawler LiDAR scan of a pipe and write it as a scan archive with ground truth.

    Every sensor and crawler effect (range noise, spurious returns, mixed pixels, vibration, odometer scale error and slip, IMU noise and dropouts) is on at a realistic default.
    """  # noqa: E501
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import Effects, get_scenario, simulate_scan

    if list_effects:
        for f in dataclasses.fields(Effects):
            typer.echo(f"{f.name} = {getattr(Effects(), f.name)!r}")
        return
    if out is None:
        _fail(ValueError("simulate needs OUT, the directory to write the archive to"))
        return
    overrides: dict[str, object] = {"travel_m": travel_m} if travel_m is not None else {}
    try:
        overrides["effects"] = _effects(effect or [], ideal)
        scan = simulate_scan(get_scenario(scenario.value, **overrides), seed=seed)
        total = len(scan.times_s)
        started = time.perf_counter()

        def progress(done: int, of: int) -> None:
            if done == of or done % max(1, of // 10) == 0:
                logging.getLogger("pipescan").info("simulated %d/%d frames", done, of)

        path = write_simulated_archive(scan, out, progress=progress)
    except (PipescanError, ValueError) as exc:
        _fail(exc)
    typer.echo(
        f"wrote {path} ({total} frames, scenario {scenario.value}, seed {seed}) "
        f"in {time.perf_counter() - started:.1f} s; ground truth in {path / 'ground_truth'}"
    )


def _effects(assignments: list[str], ideal: bool):
    """Effects from ``NAME=VALUE`` strings (ValueError naming the bad one)."""
    from pipescan.simulator.scan import Effects

    fields = {f.name: f for f in dataclasses.fields(Effects)}
    base = Effects.ideal() if ideal else Effects()
    values: dict[str, object] = {}
    for text in assignments:
        name, sep, raw = text.partition("=")
        name = name.strip()
        if not sep or name not in fields:
            raise ValueError(
                f"--effect {text!r}: expected NAME=VALUE with NAME one of {', '.join(fields)}"
            )
        default = getattr(base, name)
        try:
            if isinstance(default, bool):
                if raw.strip().lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError
                values[name] = raw.strip().lower() in ("true", "1", "yes")
            elif isinstance(default, tuple):
                values[name] = tuple(float(v) for v in raw.split(","))
            else:
                values[name] = float(raw)
        except ValueError:
            raise ValueError(
                f"--effect {text!r}: {name} needs a {type(default).__name__} like {default!r}"
            ) from None
    return dataclasses.replace(base, **values)  # type: ignore[arg-type]


def _inspection_params(contour: str | None, registration: str | None):
    """The run's parameters from the settings and the options; a contour method that is not
    registered is refused here, before Prefect starts."""
    from pipescan.core.contour import CONTOUR_METHODS

    settings = _settings()
    method = contour or settings.contour_method
    if method not in CONTOUR_METHODS:
        given = f"--contour {contour!r}" if contour else f"PIPESCAN_CONTOUR_METHOD={method!r}"
        raise OptionError(
            f"{given} is not a contour method", hint=f"use one of: {', '.join(CONTOUR_METHODS)}"
        )
    from pipescan.flows.network import params_from_settings

    return params_from_settings(settings, contour=contour, registration=registration)


def _run_inspection(archive: str, db_url: str, report: Path | None, params):
    from pipescan.flows.inspect import inspect_archive
    from pipescan.flows.runners import make_task_runner

    s = _settings()
    flow = inspect_archive.with_options(task_runner=make_task_runner(s.task_runner, s.workers))
    return flow(
        archive=archive,
        database_url=db_url,
        report_path=str(report) if report else None,
        params=params,
        work_dir=str(s.work_dir),
    )


def _print_summary(summary) -> None:
    pct = lambda r: "not measured" if r is None else f"{100 * r:.1f} %"  # noqa: E731
    typer.echo(
        f"inspection {summary.inspection_id}: asset {summary.asset_id}, {summary.inspected_at}"
    )
    typer.echo(
        f"  {summary.frame_count} frames, {summary.point_count:,} points, "
        f"{summary.scanned_length_m:.1f} m scanned"
    )
    typer.echo(f"  {summary.section_count} sections, {summary.sections_ok} measured (status ok)")
    for status, n in sorted(summary.unmeasured_by_status.items()):
        typer.echo(f"    {n} unmeasured: {status}")
    if summary.max_blockage_chainage_m is not None:
        typer.echo(
            f"  worst blockage {pct(summary.max_blockage_ratio)} "
            f"at {summary.max_blockage_chainage_m:.1f} m"
        )
    typer.echo(
        f"  {summary.defect_count} defects coded, {summary.flagged_defect_count} over the "
        "flagging threshold"
    )
    reg = summary.registration
    if reg.get("frames"):
        typer.echo(
            f"  registration: {reg['engine']}, mean fitness {reg['mean_fitness']:.2f}, "
            f"RMSE {1000 * reg['mean_rmse_m']:.1f} mm; along the axis, "
            f"{reg['degenerate_frames']} of {reg['frames']} frames held to the "
            f"{reg.get('along_axis_prior', 'odometer').replace('_', ' ')} (smooth pipe)"
        )
        if reg.get("warning"):
            typer.secho(f"  warning: {reg['warning']}", fg=typer.colors.YELLOW)
    if summary.report_path:
        typer.echo(f"  report: {summary.report_path}")
    typer.echo(f"  done in {summary.wall_time_s:.1f} s")


@app.command()
def inspect(
    archive: Annotated[str, typer.Argument(help="Archive: directory, .zip, .tar, .tar.gz or URL.")],
    db: DbOption = None,
    report: Annotated[Path | None, typer.Option(help="Also write the PDF report here.")] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print a machine-readable summary.")
    ] = False,
    contour: ContourOption = None,
    registration: Annotated[
        str | None,
        typer.Option(help="gicp (default), point_to_plane, or the paper's point_to_point."),
    ] = None,
) -> None:
    """Process one scan archive: register, measure, grade, store (and report)."""
    try:
        summary = _run_inspection(
            archive, _db_url(db), report, _inspection_params(contour, registration)
        )
    except PipescanError as exc:
        _fail(exc)
    if as_json:
        typer.echo(json.dumps(dataclasses.asdict(summary), indent=2, default=str))
    else:
        _print_summary(summary)


@app.command()
def demo(
    out: Annotated[
        Path, typer.Option(help="Folder for the demo's archive, database and PDF.")
    ] = Path("pipescan-demo"),
    seed: int = 0,
    db: DbOption = None,
) -> None:
    """Simulate the paper's scenario, inspect it and write the PDF report, printing each stage."""
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan

    log = logging.getLogger("pipescan")
    out.mkdir(parents=True, exist_ok=True)
    archive = out / "archive-paper"
    db_url = db or f"sqlite:///{(out / 'pipescan.db').resolve()}"
    pdf = out / "report.pdf"
    started = time.perf_counter()
    try:
        log.info("1/3 simulating the paper scenario (0.5 m pipe, Livox HAP-like sensor)")
        scan = simulate_scan(get_scenario("paper"), seed=seed)
        # Replaces an earlier demo's archive, and refuses any other folder of that name.
        write_simulated_archive(scan, archive)
        log.info("    archive: %s (%d frames)", archive, len(scan.times_s))
        log.info("2/3 inspecting: registration, axis, sections, measures, grading, storage")
        summary = _run_inspection(str(archive), db_url, pdf, _inspection_params(None, None))
        log.info("3/3 report written")
    except PipescanError as exc:
        _fail(exc)
    _print_summary(summary)
    typer.echo(f"\ndemo finished in {time.perf_counter() - started:.0f} s")
    typer.echo(f"PDF report: {pdf.resolve()}")
    typer.echo(f"database:   {db_url}")
