"""Commands that process scans: ``simulate``, ``inspect``, ``demo``."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import (
    ContourOption,
    DbOption,
    RegistrationOption,
    Scenario,
    _db_url,
    _fail,
    _settings,
    app,
)
from pipescan.core.errors import OptionError, PipescanError
from pipescan.core.wording import plural


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
    asset_id: Annotated[
        str | None, typer.Option(help="The archive's asset id [default: the scenario's].")
    ] = None,
    inspected_at: Annotated[
        str | None,
        typer.Option(
            help="The inspection's date, ISO 8601 (2026-05-14 or 2026-05-14T09:30:00Z; "
            "UTC unless it says) [default: the scenario's, 2024-05-14T09:30Z]."
        ),
    ] = None,
    deposit_growth: Annotated[
        float,
        typer.Option(
            metavar="RATIO_PER_YEAR",
            help="Grow the scenario's deposits by this share of the diameter a year, from "
            "the scenario's date to --inspected-at (0.02: 2 % of the diameter a year; "
            "negative: cleaned).",
        ),
    ] = 0.0,
    frame_coverage: Annotated[
        float | None,
        typer.Option(
            min=0.05,
            max=1.0,
            help="Share of the field of view one frame covers: below 1, a non-repetitive "
            "(rosette) pattern, as Livox's Avia and Mid series have (docs/instrument.md).",
        ),
    ] = None,
    water_depth: Annotated[
        float | None,
        typer.Option(help="Water in the invert, as a share of the diameter (e.g. 0.1)."),
    ] = None,
    layout: Annotated[
        str | None,
        typer.Option(
            help="frames (one file per frame), cloud (one registered cloud.laz with GPS "
            "time) or bag (a ROS 1 bag: PointCloud2, odometry, IMU); default: cloud for ring "
            "and static, frames otherwise."
        ),
    ] = None,
) -> None:
    """Simulate a crawler LiDAR scan of a pipe and write it as a scan archive with ground truth.

    Scenarios: paper, clean, long (a forward-looking Livox HAP-like sensor), ring (a 2D ring profiler, about 300 points a section, 15 mm noise), static (a terrestrial scanner at three stations). Every sensor and crawler effect (range noise, spurious returns, mixed pixels, vibration, odometer scale error and slip, IMU noise and dropouts) is on at a realistic default.
    """  # noqa: E501
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.growth import grow_deposits
    from pipescan.simulator.scan import Effects, get_scenario, simulate_scan

    if list_effects:
        for f in dataclasses.fields(Effects):
            typer.echo(f"{f.name} = {getattr(Effects(), f.name)!r}")
        return
    if out is None:
        _fail(ValueError("simulate needs OUT, the directory to write the archive to"))
        return
    from pipescan.simulator.sensors import WaterLevel

    overrides: dict[str, object] = {"travel_m": travel_m} if travel_m is not None else {}
    if asset_id is not None:
        overrides["asset_id"] = asset_id
    try:
        if effect or ideal:
            overrides["effects"] = _effects(effect or [], ideal, get_scenario(scenario.value))
        if water_depth is not None:
            overrides["water"] = WaterLevel(depth_ratio=water_depth)
        if frame_coverage is not None:
            overrides["frame_coverage_ratio"] = frame_coverage
        scene = get_scenario(scenario.value, **overrides)
        if inspected_at is not None:
            scene = grow_deposits(scene, deposit_growth, _parse_datetime(inspected_at))
        elif deposit_growth:
            raise ValueError("--deposit-growth needs --inspected-at, the date to grow them to")
        scan = simulate_scan(scene, seed=seed)
        total = len(scan.times_s)
        started = time.perf_counter()

        def progress(done: int, of: int) -> None:
            if done == of or done % max(1, of // 10) == 0:
                logging.getLogger("pipescan").info("simulated %d/%d frames", done, of)

        path = write_simulated_archive(scan, out, progress=progress, layout=layout)
    except (PipescanError, ValueError) as exc:
        _fail(exc)
    deposits = ", ".join(f"{100 * d.peak_height_ratio:.1f} %" for d in scene.deposits[:3])
    typer.echo(
        f"wrote {path} ({plural(total, 'frame')}, scenario {scenario.value}, seed {seed}; "
        f"asset {scene.asset_id}, inspected {scene.inspected_at.isoformat()}"
        + (f"; deposit height {deposits} of the diameter" if deposits else "")
        + f") in {time.perf_counter() - started:.1f} s; ground truth in {path / 'ground_truth'}"
    )


def _parse_datetime(text: str) -> datetime:
    """An ISO 8601 date or datetime; without an offset, UTC (ValueError naming the option)."""
    try:
        value = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"--inspected-at {text!r} is not an ISO 8601 date or datetime "
            "(e.g. 2026-05-14 or 2026-05-14T09:30:00Z)"
        ) from None
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def _effects(assignments: list[str], ideal: bool, scenario=None):
    """Effects from ``NAME=VALUE`` strings over the scenario's own (ValueError naming the
    bad one)."""
    from pipescan.simulator.scan import Effects

    fields = {f.name: f for f in dataclasses.fields(Effects)}
    base = Effects.ideal() if ideal else (scenario.effects if scenario else Effects())
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
            elif isinstance(default, tuple) or name == "spurious_range_ratio":
                # Pairs (slip_duration_s; spurious_range_ratio, None by default).
                values[name] = tuple(float(v) for v in raw.split(","))
            else:
                values[name] = float(raw)
        except ValueError:
            raise ValueError(
                f"--effect {text!r}: {name} needs a {type(default).__name__} like {default!r}"
            ) from None
    return dataclasses.replace(base, **values)  # type: ignore[arg-type]


def _check_contour(settings, contour: str | None) -> None:
    from pipescan.core.contour import CONTOUR_METHODS

    method = contour or settings.contour_method
    if method not in CONTOUR_METHODS:
        given = f"--contour {contour!r}" if contour else f"PIPESCAN_CONTOUR_METHOD={method!r}"
        raise OptionError(
            f"{given} is not a contour method", hint=f"use one of: {', '.join(CONTOUR_METHODS)}"
        )


def _checked_settings(contour: str | None, registration: str | None):
    """The settings, with every choice a run names checked against what this pipescan has:
    the contour method, the registration method and engine, the threshold table (the pipe
    class and the rest are checked as settings). A wrong one is one line, before Prefect
    starts."""
    settings = _settings()
    _check_contour(settings, contour)
    from pipescan.core.registration import REGISTRATION_METHODS, RegistrationParams

    reg = registration or settings.registration_method
    given = (
        f"--registration {registration!r}"
        if registration
        else f"PIPESCAN_REGISTRATION_METHOD={reg!r}"
    )
    if reg not in REGISTRATION_METHODS:
        raise OptionError(
            f"{given} is not a registration method",
            hint=f"use one of: {', '.join(REGISTRATION_METHODS)}",
        )
    try:
        RegistrationParams(method=reg, engine=settings.registration_engine)
    except ValueError as exc:
        raise OptionError(
            f"{given} with PIPESCAN_REGISTRATION_ENGINE={settings.registration_engine!r}: {exc}",
            hint="docs/registration.md lists the methods and engines that go together",
        ) from None
    from pipescan.core.errors import GradingError
    from pipescan.core.grading import load_table

    try:
        load_table(settings.threshold_table)
    except GradingError as exc:
        raise OptionError(f"PIPESCAN_THRESHOLD_TABLE={settings.threshold_table!r}: {exc}") from None
    return settings


def _refuse_secret_early(archive: str) -> None:
    """Refuse an archive URL holding a secret before anything is said or started (the check
    itself, with Prefect's import, only when fsspec's reading of the URL finds one)."""
    from pipescan.storage.input.urls import url_secret

    if url_secret(archive) is not None:
        from pipescan.flows.network import refuse_password_in_url

        refuse_password_in_url(archive, "archive")


def _first_look(archive: str, settings) -> None:
    """Open a local archive, check its metadata, layout and first and last point files, and
    say what it holds: the run's first lines, before Prefect starts (a bad archive fails here
    in a fraction of a second). A zip or tar is unpacked here once more (about 1 s per 80 MB).
    A remote archive is checked by the run, which copies it once."""
    from pipescan.cli._precheck import first_look

    log = logging.getLogger("pipescan")
    local = Path(archive.removeprefix("file://"))
    if local.is_file() and local.stat().st_size > 50_000_000:
        log.info(f"unpacking {archive} ({local.stat().st_size / 1e6:,.0f} MB) to check it")
    look = first_look(archive, settings)
    if look is None:
        from pipescan.storage.input.urls import without_secrets

        shown = without_secrets(archive)  # said before the URL's secrets are refused
        log.info(f"archive {shown}: a remote archive, copied and checked when the run starts")
        return
    log.info(look.found)
    if look.checked:
        log.info(look.checked)
    for warning in look.warnings:
        log.warning(f"warning: {warning}")


def _prefect_api_url() -> str | None:
    """The Prefect API the run will use, when one is set (PREFECT_API_URL, or the active
    profile's), read without importing Prefect; None: Prefect starts a local one."""
    if url := os.environ.get("PREFECT_API_URL", "").strip():
        return url
    import tomllib

    home = Path(os.environ.get("PREFECT_HOME", "~/.prefect")).expanduser()
    path = Path(os.environ.get("PREFECT_PROFILES_PATH", home / "profiles.toml")).expanduser()
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, ValueError):
        return None
    active = os.environ.get("PREFECT_PROFILE") or doc.get("active", "ephemeral")
    url = doc.get("profiles", {}).get(active, {}).get("PREFECT_API_URL")
    return str(url) if url else None


_SAID = {"prefect": False}


def _say_prefect_starts() -> None:
    """Say, once a command, that Prefect's local API is starting (when no server is set):
    before Prefect is imported, for the ten seconds of silence that follow."""
    if not _SAID["prefect"] and _prefect_api_url() is None:
        logging.getLogger("pipescan").info(PREFECT_STARTING_LINE)
    _SAID["prefect"] = True


PREFECT_STARTING_LINE = (
    "starting Prefect's local API (about 10 s; set PREFECT_API_URL to a running server to "
    "skip this)"
)


def _inspection_params(contour: str | None, registration: str | None, settings=None):
    """The run's parameters from the settings and the options, each choice checked first
    (:func:`_checked_settings`)."""
    settings = settings or _checked_settings(contour, registration)
    from pipescan.flows.network import params_from_settings

    return params_from_settings(settings, contour=contour, registration=registration)


def _run_inspection(archive: str, db_url: str, report: Path | None, params):
    """Run the flow, its stages as progress bars on a terminal (lines elsewhere)."""
    from pipescan.cli._progress import run_progress

    log = logging.getLogger("pipescan")
    _say_prefect_starts()
    with run_progress(log):
        return _run_flow(archive, db_url, report, params)


def _run_flow(archive: str, db_url: str, report: Path | None, params):
    from pipescan.flows.database import checked_database_url
    from pipescan.flows.inspect import inspect_archive
    from pipescan.flows.network import refuse_password_in_url
    from pipescan.flows.runners import make_task_runner
    from pipescan.settings import use_settings

    s = _settings()
    runner = make_task_runner(s.task_runner, s.workers)
    flow = inspect_archive.with_options(task_runner=runner)
    # The database is a setting of this process, never a flow parameter (Prefect keeps those);
    # it is checked before the archive is processed.
    refuse_password_in_url(archive, "archive")  # a flow parameter: Prefect keeps it
    with use_settings(database_url=db_url):
        checked_database_url()
        _start_engines_ahead(s, runner)
        return flow(
            archive=archive,
            report_path=str(report) if report else None,
            params=params,
            work_dir=str(s.work_dir),
        )


def _start_engines_ahead(settings, runner) -> None:
    """Start the registration engines' worker processes now, if the flow will use them: their
    imports (about 2 s of CPU each) then overlap the start of Prefect's API instead of the
    first chunks (the flow stops them again for a registered cloud, which needs none)."""
    from pipescan.flows.runners import engine_processes, limit_library_threads
    from pipescan.tasks import enginepool

    workers = engine_processes(settings.engine_processes, runner)
    if workers:
        limit_library_threads(settings.library_threads)  # the workers inherit the limit
        enginepool.prestart(workers, ahead=True)


def _stored_inspection_ids(db_url: str) -> set[int]:
    """The ids of the inspections stored before a run: a run that stores one of them again
    (the same archive under the same parameters) replaced its rows. Empty for a database
    that does not exist yet or has no tables; nothing is created here."""
    import sqlalchemy as sa

    from pipescan.storage.database.db import create_engine_for, parse_database_url

    try:
        url = parse_database_url(db_url)
        database = url.database or ""
        if url.get_backend_name() == "sqlite" and (
            database in ("", ":memory:") or not Path(database).expanduser().exists()
        ):
            return set()
        engine = create_engine_for(db_url)
    except PipescanError:
        return set()  # the run says what is wrong with the URL
    try:
        with engine.connect() as connection:
            rows = connection.execute(sa.text("SELECT id FROM inspections"))
            return {int(row[0]) for row in rows}
    except sa.exc.SQLAlchemyError:
        return set()
    finally:
        engine.dispose()


def _raw_unmeasured_lines(summary) -> list[str]:
    return [
        f"    {n} not measured ({status.replace('_', ' ')})"
        for status, n in sorted(summary.unmeasured_by_status.items())
    ]


def _unmeasured_lines(db_url: str, summary) -> list[str]:
    """The unmeasured sections by the report's words for their status ("uncertain: wall
    scatter", not "too_few_points" on thousands of points), read back from the stored
    sections; the stored status names if they cannot be read."""
    raw = _raw_unmeasured_lines(summary)
    if not summary.unmeasured_by_status:
        return []
    try:
        from collections import Counter

        from pipescan.reports.context import MeasureLimits, status_words
        from pipescan.storage.database.db import connect, session_scope
        from pipescan.storage.database.repository import get_inspection, list_sections

        engine = connect(db_url)
        try:
            with session_scope(engine) as session:
                record = get_inspection(session, summary.inspection_id)
                sections = list_sections(session, summary.inspection_id)
        finally:
            engine.dispose()
        limits = MeasureLimits.of((record.params or {}).get("measure"))
        counts = Counter(status_words(s, limits)[0] for s in sections if not s.is_ok)
    except Exception:  # the summary is said anyway: the stored names
        return raw
    return [f"    {n} not measured ({label})" for label, n in sorted(counts.items())]


def _print_summary(summary, replaced: bool = False, unmeasured: list[str] | None = None) -> None:
    pct = lambda r: "not measured" if r is None else f"{100 * r:.1f} %"  # noqa: E731
    typer.echo(
        f"inspection {summary.inspection_id}: asset {summary.asset_id}, {summary.inspected_at}"
    )
    if replaced:
        typer.echo(
            f"  replaced the stored rows of inspection {summary.inspection_id} (this archive, "
            "under the same parameters, was stored before)"
        )
    # A frames archive has at least one frame; none is a registered cloud.
    content = plural(summary.frame_count, "frame") if summary.frame_count else "registered cloud"
    stride = (summary.registration or {}).get("frame_stride", 1)
    if summary.frame_count and stride > 1:
        read = summary.registration.get("frames", summary.frame_count)
        closer = summary.registration.get("frames_looked_closer")
        more = f", and {closer:,} where ICP disagreed with the odometer" if closer else ""
        tracked = summary.registration.get("frames_tracked")
        others = f"; {tracked:,} tracked between them" if tracked else ""
        content += f" ({read:,} registered: every {stride}{more}{others})"
    share = (summary.registration or {}).get("placed_share")
    points = f"{summary.point_count:,} points"
    if share is not None and share < 1.0:
        points += f" placed ({100 * share:.0f} % of each frame's, at random)"
    typer.echo(f"  {content}, {points}, {summary.scanned_length_m:.1f} m scanned")
    typer.echo(f"  {plural(summary.section_count, 'section')}, {summary.sections_ok} measured")
    for line in unmeasured if unmeasured is not None else _raw_unmeasured_lines(summary):
        typer.echo(line)  # under the sections' line they break down
    if summary.measured_inner_diameter_m is not None:
        typer.echo(
            f"  inner diameter measured {summary.measured_inner_diameter_m:.3f} m "
            "(blockage is against the nominal diameter)"
        )
    if (summary.registration or {}).get("instrument"):
        typer.echo(f"  instrument: {summary.registration['instrument']}")
    if summary.max_blockage_chainage_m is not None:
        typer.echo(
            f"  worst blockage {pct(summary.max_blockage_ratio)} "
            f"at {summary.max_blockage_chainage_m:.1f} m"
        )
    typer.echo(
        f"  {plural(summary.defect_count, 'defect')} coded, {summary.flagged_defect_count} over "
        "the flagging threshold"
    )
    if summary.start_source:
        from pipescan.core.start import START_SOURCES

        typer.echo(f"  scan start: {START_SOURCES.get(summary.start_source, summary.start_source)}")
    reg = summary.registration
    if reg.get("frames"):
        typer.echo(
            f"  registration: {reg['engine']}, mean fitness {reg['mean_fitness']:.2f}, "
            f"RMSE {1000 * reg['mean_rmse_m']:.1f} mm"
        )
        prior = reg.get("along_axis_prior", "odometer").replace("_", " ")
        line = (
            f"  along the axis: {reg['degenerate_frames']} of {reg['frames']} frames rested on "
            f"the {prior} (the geometry along the pipe was weaker evidence)"
        )
        if "slides" in reg:
            line += f", {plural(reg['slides'], 'frame')} slid"
        if reg.get("chainage_uncertainty_m") is not None:
            line += f"; chainage within ±{100 * reg['chainage_uncertainty_m']:.1f} cm at the end"
        typer.echo(line)
        if slips := reg.get("odometer_slips_caught_m"):
            times = {1: "once", 2: "twice"}.get(len(slips), f"{len(slips)} times")
            line = (
                f"  the odometer slipped {times} where features were in view "
                f"(up to {100 * max(slips):.0f} cm)"
            )
            from pipescan.core.registration.metrics import unseen_slips_clause

            if clause := unseen_slips_clause(reg):
                line += f"; {clause}"
            typer.echo(line)
        from pipescan.core.registration.metrics import standstill_clause, unseen_slip_caveat

        if stood := standstill_clause(reg):
            typer.echo(f"  {stood}")
        if caveat := unseen_slip_caveat(reg):
            typer.echo(f"  {caveat}")
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
    registration: RegistrationOption = None,
) -> None:
    """Process one scan archive: register, measure, grade, store (and report).

    The archive's metadata and layout, its first and last point files (units, NaN, empty, the
    diameter's scale) and every option are checked before Prefect starts, in about a second.

    Examples:

    \b
      pipescan inspect runs/MH1042-MH1043.zip --report reports/MH1042.pdf
      pipescan inspect site7.zip --db postgresql+psycopg://db.example/pipescan
    """
    _SAID["prefect"] = False
    try:
        settings = _settings()
        _check_contour(settings, contour)  # cheap: before the archive
        if report is not None:  # not after the whole run
            from pipescan.cli._app import output_format
            from pipescan.reports.render import check_report_path

            output_format(report, option="--report", what="report", formats=("pdf",), bare="pdf")
            check_report_path(report)
        _refuse_secret_early(archive)  # before any line names the archive
        _first_look(archive, settings)  # the first lines: before the checks that load scipy
        checked = _checked_settings(contour, registration)
        _say_prefect_starts()  # the next import is Prefect's
        params = _inspection_params(contour, registration, checked)
        db_url = _db_url(db)
        stored_before = _stored_inspection_ids(db_url)
        summary = _run_inspection(archive, db_url, report, params)
    except PipescanError as exc:
        _fail(exc)
    replaced = summary.inspection_id in stored_before
    if as_json:
        if replaced:  # said on stderr too: stdout is the JSON
            logging.getLogger("pipescan").info(
                f"replaced the stored rows of inspection {summary.inspection_id}"
            )
        typer.echo(
            json.dumps(dataclasses.asdict(summary) | {"replaced": replaced}, indent=2, default=str)
        )
    else:
        _print_summary(summary, replaced, _unmeasured_lines(db_url, summary))


@app.command()
def demo(
    out: Annotated[
        Path, typer.Option(help="Folder for the demo's archive, database and PDF.")
    ] = Path("pipescan-demo"),
    seed: int = 0,
    db: DbOption = None,
) -> None:
    """Simulate the paper's scenario, inspect it and write the PDF report, printing each stage."""
    from pipescan.core.errors import OutputError
    from pipescan.settings import as_database_url
    from pipescan.simulator.archive import file_in_the_way, write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan

    log = logging.getLogger("pipescan")
    _SAID["prefect"] = False
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file of that name, or one on its way
        _fail(
            OutputError(
                f"cannot make the demo's folder: {file_in_the_way(out) or exc.strerror or exc}",
                file=str(out),
                hint="choose another --out",
            )
        )
    archive = out / "archive-paper"
    db_url = as_database_url(db) if db else f"sqlite:///{(out / 'pipescan.db').resolve()}"
    pdf = out / "report.pdf"
    started = time.perf_counter()
    try:
        log.info("1/3 simulating the paper scenario (0.5 m pipe, Livox HAP-like sensor)")
        scan = simulate_scan(get_scenario("paper"), seed=seed)
        # Replaces an earlier demo's archive, and refuses any other folder of that name.
        write_simulated_archive(scan, archive)
        log.info("    archive: %s (%d frames)", archive, len(scan.times_s))
        log.info("2/3 inspecting: registration, axis, sections, measures, grading, storage")
        params = _inspection_params(None, None)
        stored_before = _stored_inspection_ids(db_url)
        summary = _run_inspection(str(archive), db_url, pdf, params)
        log.info("3/3 report written")
    except PipescanError as exc:
        _fail(exc)
    _print_summary(
        summary, summary.inspection_id in stored_before, _unmeasured_lines(db_url, summary)
    )
    typer.echo(f"\ndemo finished in {time.perf_counter() - started:.0f} s")
    typer.echo(f"PDF report: {pdf.resolve()}")
    typer.echo(f"database:   {db_url}")
