"""The web app: pages for the network, a pipe, an inspection and the runs, and the JSON API
under ``/api/``, on one database opened read-only.

:func:`create_app` takes explicit arguments (the CLI reads the settings). The figures come
from the storage layer and the report's own context (:func:`pipescan.reports.build_context`,
with its matplotlib SVG charts); downloads are generated from the database into a private
temporary folder, never from a path a request names.
"""

from __future__ import annotations

import contextlib
import hmac
import logging
import math
import re
import tempfile
import threading
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from datetime import UTC, date, datetime
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlencode, urlsplit

import anyio
import numpy as np
import sqlalchemy as sa
from fastapi import FastAPI, HTTPException, Query, Request
from fastapi import Path as FastPath
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from pydantic import BaseModel, Field

import pipescan
from pipescan.core.errors import PipescanError
from pipescan.core.trends import (
    NO_SIGNIFICANT_CHANGE,
    change_thresholds,
    is_significant,
    measured_span_years,
    years,
)
from pipescan.core.wording import signed
from pipescan.reports.context import (
    STATUS_LABELS,
    fmt_bound_grade,
    fmt_bound_pct,
    fmt_clock,
    fmt_datetime,
    fmt_m,
    fmt_pct,
)
from pipescan.storage.database import web_queries
from pipescan.storage.database.db import StorageError, connect, session_scope
from pipescan.storage.database.models import Inspection
from pipescan.storage.database.network import gis_ids
from pipescan.storage.database.queries import defect_counts
from pipescan.storage.database.repository import (
    get_inspection,
    list_defects,
    list_inspections,
)
from pipescan.storage.database.trends import AssetTrend, asset_trend
from pipescan.web.figures import (
    GRADE_COLOURS,
    NO_GRADE_COLOUR,
    SURVEY_COLOURS,
    grade_colour,
    network_map_svg,
    pipe_href,
    profiles_svg,
    trend_point_svg,
)

__all__ = ["TOKEN_COOKIE", "WebConfig", "create_app"]

_log = logging.getLogger("pipescan.web")

HERE = Path(__file__).parent
TOKEN_COOKIE = "pipescan_token"
InspectionId = Annotated[int, FastPath(ge=1, le=2**31 - 1, description="An inspection's id")]
"""An inspection id as a request gives it: within the database's integer column."""
PAGE_ROWS = 50
"""Rows of the network table per page."""
RUNS_SHOWN = 20
"""Recent network runs on the Runs page."""
RUNS_TTL_S = 30.0
"""How long the runs read from Prefect's API are shown before they are asked again."""

_CSP = (
    "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; "
    "script-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'"
)


@dataclass(frozen=True)
class WebConfig:
    """What the app serves: ``database_url`` (opened read-only), the ``token`` every request
    must carry (None: none needed, for 127.0.0.1), a short label of the database for the
    page footer (never the URL: it may hold a password), and where recent runs come from."""

    database_url: str
    token: str | None = None
    database_label: str = ""
    tile_url: str | None = None
    """A basemap's tiles, ``https://host/{z}/{x}/{y}.png`` (Web Mercator, the usual XYZ
    scheme): the organisation's own tile server. None: the lines are drawn on their own."""
    runs: Callable[[int, str], list[Any]] | None = None
    """Recent network runs, newest first: ``runs(limit, read_only_database_url)`` returns
    :class:`pipescan.flows.runs.NetworkRun` records (``pipescan serve`` passes
    :func:`pipescan.flows.runs.recent_network_runs` when Prefect's API is set); None: no
    source of runs, and the Runs page says so."""


# ---------------------------------------------------------------------------------------------
# Formatting for templates (percentages exist only here and in templates)


def _pct(ratio: float | None, digits: int = 1) -> str:
    return fmt_pct(ratio, digits)


def _rate(ratio_per_year: float | None) -> str:
    if ratio_per_year is None or not math.isfinite(ratio_per_year):
        return "–"
    return f"{signed(100.0 * ratio_per_year, 2)} pt/yr"


def _verdict(ratio_per_year: float | None, span_years: float, threshold_ratio: float) -> str:
    significant = is_significant(ratio_per_year, span_years, threshold_ratio=threshold_ratio)
    if significant is None:
        return "needs two measured inspections far enough apart"
    if not significant:
        return NO_SIGNIFICANT_CHANGE
    return "growing" if (ratio_per_year or 0.0) > 0 else "shrinking"


def _grade_text(grade: int | None) -> str:
    return "not graded" if grade is None else str(grade)


def _safe_name(text: str) -> str:
    """A file name from an asset id: letters, digits, ``-``, ``_`` and ``.`` only."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "pipe"


# ---------------------------------------------------------------------------------------------
# API models


class PipeOut(BaseModel):
    asset_id: str
    gis_id: str | None
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    material: str | None
    inspection_count: int
    last_inspection_id: int
    last_inspected_at: datetime
    condition_class: int | None = Field(
        description="Worst condition class of the latest inspection's measured sections "
        "(0 worst ... 4 best)"
    )
    peak_blockage_ratio: float | None
    peak_chainage_m: float | None
    growth_per_year_ratio: float | None = Field(
        description="Growth per year of the peak blockage over the pipe's scans (Theil-Sen)"
    )
    defect_count: int
    line: list[list[float]] | None = Field(description="The pipe's line, upstream first, in crs")
    crs: str | None


class PipePage(BaseModel):
    total: int
    offset: int
    limit: int
    items: list[PipeOut]


class InspectionOut(BaseModel):
    id: int
    asset_id: str
    inspected_at: datetime
    archive_uri: str
    software_version: str
    status: str
    threshold_table: str
    section_count: int
    measured_section_count: int
    mean_blockage_ratio: float | None
    peak_blockage_ratio: float | None
    peak_chainage_m: float | None
    scanned_length_m: float
    direction: str | None
    chainage_offset_m: float | None


class InspectionPage(BaseModel):
    offset: int
    limit: int
    items: list[InspectionOut]


class SectionOut(BaseModel):
    chainage_start_m: float
    chainage_end_m: float
    status: str
    blockage_ratio: float | None
    blockage_uncertainty_ratio: float | None
    ovality_ratio: float | None
    deformation_ratio: float | None
    deposit_height_ratio: float | None
    coverage_ratio: float
    point_count: int
    grade: int | None


class SectionPage(BaseModel):
    inspection_id: int
    offset: int
    limit: int
    items: list[SectionOut]
    next_offset: int | None


class DefectOut(BaseModel):
    code: str | None
    measure: str
    chainage_start_m: float
    chainage_end_m: float
    peak_chainage_m: float
    peak_value: float | None
    peak_blockage_ratio: float | None
    grade: int | None
    clock_from_h: float | None
    clock_to_h: float | None
    characterisation: str | None
    lower_bound: bool = False
    """Part of the feature stood in water that returned nothing: it is at least
    ``peak_value``, and its class at least as bad as ``grade``."""


class TrendSurvey(BaseModel):
    inspection_id: int
    inspected_at: datetime
    offset_m: float
    correlation: float | None
    is_reference: bool
    measured_section_count: int
    mean_blockage_ratio: float | None
    peak_blockage_ratio: float | None


class TrendCell(BaseModel):
    chainage_start_m: float
    chainage_end_m: float
    blockage_ratio: list[float | None]
    status: list[str | None]
    change_per_year: float | None
    noise_threshold_ratio: float = Field(
        description="The change over the surveys' span below which it is noise"
    )
    change: str


class TrendOut(BaseModel):
    asset_id: str
    step_m: float
    peak_change_per_year: float | None
    mean_change_per_year: float | None
    inspections: list[TrendSurvey]
    chainages: list[TrendCell]


def _finite(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def _inspection_out(r: Any) -> InspectionOut:
    return InspectionOut(
        id=r.id,
        asset_id=r.asset_id,
        inspected_at=r.inspected_at,
        archive_uri=_strip_credentials(r.archive_uri),
        software_version=r.software_version,
        status=r.status,
        threshold_table=r.threshold_table,
        section_count=r.section_count,
        measured_section_count=r.measured_section_count,
        mean_blockage_ratio=r.mean_blockage_ratio,
        peak_blockage_ratio=r.peak_blockage_ratio,
        peak_chainage_m=r.peak_chainage_m,
        scanned_length_m=r.scanned_length_m,
        direction=r.direction,
        chainage_offset_m=r.chainage_offset_m,
    )


def _strip_credentials(uri: str) -> str:
    from pipescan.core.sanitize import strip_credentials

    return strip_credentials(uri)


def _pipe_out(p: web_queries.PipeRow) -> PipeOut:
    return PipeOut(
        asset_id=p.asset_id,
        gis_id=p.gis_id,
        upstream_node=p.upstream_node,
        downstream_node=p.downstream_node,
        nominal_diameter_m=p.nominal_diameter_m,
        material=p.material,
        inspection_count=p.inspection_count,
        last_inspection_id=p.last_inspection_id,
        last_inspected_at=p.last_inspected_at,
        condition_class=p.worst_grade,
        peak_blockage_ratio=p.peak_blockage_ratio,
        peak_chainage_m=p.peak_chainage_m,
        growth_per_year_ratio=p.peak_change_per_year,
        defect_count=p.defect_count,
        line=None if p.line_xy is None else [list(v) for v in p.line_xy],
        crs=p.crs,
    )


# ---------------------------------------------------------------------------------------------
# The network table's filters and order


class SortKey(StrEnum):
    asset = "asset"
    grade = "class"
    peak = "peak"
    growth = "growth"
    last = "last"
    defects = "defects"


_SORT_KEYS: dict[SortKey, Callable[[web_queries.PipeRow], Any]] = {
    SortKey.asset: lambda p: p.asset_id,
    SortKey.grade: lambda p: 9 if p.worst_grade is None else p.worst_grade,
    SortKey.peak: lambda p: -math.inf if p.peak_blockage_ratio is None else p.peak_blockage_ratio,
    SortKey.growth: lambda p: (
        -math.inf if p.peak_change_per_year is None else p.peak_change_per_year
    ),
    SortKey.last: lambda p: p.last_inspected_at,
    SortKey.defects: lambda p: p.defect_count,
}
_DEFAULT_DESC = {SortKey.peak, SortKey.growth, SortKey.last, SortKey.defects}


@dataclass(frozen=True)
class NetworkFilter:
    q: str = ""
    grade: str = ""
    min_peak_pct: float | None = None
    min_growth_pt: float | None = None
    inspected_before: date | None = None
    inspected_since: date | None = None

    def keeps(self, p: web_queries.PipeRow) -> bool:
        if self.q:
            needle = self.q.casefold()
            names = (p.asset_id, p.gis_id or "", p.upstream_node or "", p.downstream_node or "")
            if not any(needle in n.casefold() for n in names):
                return False
        if self.grade:
            wanted = None if self.grade == "none" else int(self.grade)
            if p.worst_grade != wanted:
                return False
        if self.min_peak_pct is not None and (
            p.peak_blockage_ratio is None or 100.0 * p.peak_blockage_ratio < self.min_peak_pct
        ):
            return False
        if self.min_growth_pt is not None and (
            p.peak_change_per_year is None or 100.0 * p.peak_change_per_year < self.min_growth_pt
        ):
            return False
        day = p.last_inspected_at.astimezone(UTC).date()
        if self.inspected_before is not None and day >= self.inspected_before:
            return False
        return not (self.inspected_since is not None and day < self.inspected_since)


def filter_and_sort(
    pipes: list[web_queries.PipeRow], flt: NetworkFilter, sort: SortKey, descending: bool
) -> list[web_queries.PipeRow]:
    kept = [p for p in pipes if flt.keeps(p)]
    kept.sort(key=lambda p: p.asset_id)
    kept.sort(key=_SORT_KEYS[sort], reverse=descending)
    return kept


# ---------------------------------------------------------------------------------------------
# The app


class _Cache:
    """A few recent values, each valid while the database's fingerprint
    (:func:`web_queries.database_version`) is unchanged."""

    def __init__(self, size: int = 16) -> None:
        self._items: OrderedDict[Any, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._size = size

    def get(self, key: Any, build: Callable[[], Any]) -> Any:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = build()
        with self._lock:
            self._items[key] = value
            while len(self._items) > self._size:
                self._items.popitem(last=False)
        return value


class _Network:
    """The network page's rows (:func:`web_queries.network_pipes`), read once and read again
    in the background when the database changes (its :func:`web_queries.database_version`).

    Reading a large network takes seconds (the worst class of every latest inspection is an
    aggregate over its sections). The app reads it before it starts listening, so a request
    never waits for a read. Until a new read is done, requests get the previous one: the page
    may be one read behind a save, for as long as a read takes.
    """

    def __init__(self, engine: sa.Engine) -> None:
        self._engine = engine
        self._lock = threading.Lock()
        self._held: tuple[Any, list[web_queries.PipeRow]] | None = None
        self._building = False
        self._first = threading.Event()
        self._error: BaseException | None = None

    def rows(self) -> list[web_queries.PipeRow]:
        self._refresh(web_queries.database_version(self._engine))
        if not self._first.wait(timeout=300):
            raise StorageError("reading the network takes more than 5 minutes")
        with self._lock:
            held = self._held
        if held is None:
            raise StorageError(f"the network could not be read from the database: {self._error}")
        return held[1]

    def _refresh(self, version: Any) -> None:
        with self._lock:
            if (self._held is not None and self._held[0] == version) or self._building:
                return
            self._building = True
        threading.Thread(target=self._build, args=(version,), daemon=True).start()

    def _build(self, version: Any) -> None:
        try:
            rows = web_queries.network_pipes(self._engine)
            with self._lock:
                self._held = (version, rows)
        except Exception as exc:
            self._error = exc
            _log.exception("reading the network failed")
        finally:
            with self._lock:
                self._building = False
            self._first.set()


def _server_timing(request: Request, name: str, started: float) -> None:
    timings = getattr(request.state, "timings", [])
    timings.append(f"{name};dur={1000 * (time.perf_counter() - started):.1f}")
    request.state.timings = timings


def create_app(config: WebConfig) -> FastAPI:
    """The web app on ``config.database_url``, opened read-only.

    Raises
    ------
    StorageError
        The database cannot be opened read-only, or is not at the schema revision this
        pipescan needs (run ``pipescan db upgrade`` first).
    """
    if config.tile_url:
        check_tile_url(config.tile_url)
    read_only = web_queries.read_only_url(config.database_url)
    try:
        engine = connect(read_only)
    except StorageError as exc:
        if "readonly" in str(exc) or "read-only" in str(exc):
            raise StorageError(
                "the database is not at this pipescan's schema revision, and serve opens it "
                "read-only",
                hint="run `pipescan db upgrade` on it first (back it up first)",
            ) from exc
        raise

    @contextlib.asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        # The report's loader imports Prefect (seconds): not on the first inspection's request.
        threading.Thread(target=_import_report_loader, daemon=True).start()
        # The network is read before the server listens, so that no request waits for a read.
        started = time.perf_counter()
        rows = await anyio.to_thread.run_sync(network.rows)
        _log.info("read the network: %d pipes in %.1f s", len(rows), time.perf_counter() - started)
        yield
        engine.dispose()

    app = FastAPI(
        lifespan=lifespan,
        title="pipescan",
        version=pipescan.__version__,
        description="The pipescan database, read-only: pipes, inspections, sections, defects "
        "and trends. Ratios are fractions (0.235, not 23.5 %); unmeasured figures are null.",
        docs_url=None,  # FastAPI's pages load their scripts from a CDN: /api is ours
        redoc_url=None,
        openapi_url="/api/openapi.json",
    )
    app.state.engine = engine
    csp = _CSP
    if config.tile_url:
        tiles = _origin(config.tile_url)
        csp = _CSP.replace("img-src 'self' data:", f"img-src 'self' data: {tiles}")
    templates = Jinja2Templates(directory=str(HERE / "templates"))
    templates.env.globals.update(
        version=pipescan.__version__,
        database_label=config.database_label,
        grade_colours=GRADE_COLOURS,
        no_grade_colour=NO_GRADE_COLOUR,
        pipe_href=pipe_href,
        grade_colour=grade_colour,
        pct=_pct,
        rate=_rate,
        metres=fmt_m,
        when=fmt_datetime,
        grade_text=_grade_text,
    )
    app.mount("/static", StaticFiles(directory=str(HERE / "static")), name="static")
    cache = _Cache()

    def version() -> tuple[Any, ...]:
        return web_queries.database_version(engine)

    network = _Network(engine)

    def pipes() -> list[web_queries.PipeRow]:
        return network.rows()

    @app.middleware("http")
    async def guard(request: Request, call_next: Any) -> Response:
        started = time.perf_counter()
        if config.token is not None and request.url.path != "/favicon.ico":
            given = request.query_params.get("token")
            if given is not None and hmac.compare_digest(given.encode(), config.token.encode()):
                # Once, from a link: the token moves into a cookie and out of the address.
                query = urlencode([(k, v) for k, v in request.query_params.items() if k != "token"])
                target = request.url.path + (f"?{query}" if query else "")
                response: Response = RedirectResponse(target, status_code=303)
                response.set_cookie(
                    TOKEN_COOKIE, config.token, httponly=True, samesite="strict", secure=False
                )
                return _secure_headers(response, csp)
            bearer = request.headers.get("authorization", "")
            presented = request.cookies.get(TOKEN_COOKIE) or (
                bearer[7:] if bearer.lower().startswith("bearer ") else ""
            )
            if not hmac.compare_digest(presented.encode(), config.token.encode()):
                return _secure_headers(
                    Response(
                        "this pipescan server needs its token: open the link `pipescan serve` "
                        "printed (?token=...), or send Authorization: Bearer TOKEN\n",
                        status_code=401,
                        media_type="text/plain",
                    )
                )
        response = await call_next(request)
        timings = [*getattr(request.state, "timings", [])]
        timings.append(f"total;dur={1000 * (time.perf_counter() - started):.1f}")
        response.headers["Server-Timing"] = ", ".join(timings)
        return _secure_headers(response, csp)

    @app.exception_handler(StorageError)
    async def storage_error(request: Request, exc: StorageError) -> Response:
        status = 404 if getattr(exc, "reason", str(exc)).startswith("no ") else 400
        if request.url.path.startswith("/api/"):
            return JSONResponse({"detail": str(exc)}, status_code=status)
        return templates.TemplateResponse(
            request, "error.html", {"title": "Not found", "message": str(exc)}, status_code=status
        )

    @app.exception_handler(PipescanError)
    async def pipescan_error(request: Request, exc: PipescanError) -> Response:
        if request.url.path.startswith("/api/"):
            return JSONResponse({"detail": str(exc)}, status_code=400)
        return templates.TemplateResponse(
            request, "error.html", {"title": "Cannot do that", "message": str(exc)}, status_code=400
        )

    # -----------------------------------------------------------------------------------------
    # Pages

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def network_page(
        request: Request,
        q: Annotated[str, Query(max_length=100)] = "",
        grade: Annotated[str, Query(pattern="^(|[0-4]|none)$")] = "",
        min_peak: Annotated[str, Query(max_length=12)] = "",
        min_growth: Annotated[str, Query(max_length=12)] = "",
        since: Annotated[str, Query(max_length=10)] = "",
        before: Annotated[str, Query(max_length=10)] = "",
        sort: SortKey = SortKey.grade,
        order: Annotated[str, Query(pattern="^(|asc|desc)$")] = "",
        page: Annotated[int, Query(ge=1, le=100_000)] = 1,
    ) -> Response:
        started = time.perf_counter()
        everything = pipes()
        _server_timing(request, "network", started)
        flt = NetworkFilter(
            q=q.strip(),
            grade=grade,
            min_peak_pct=_number(min_peak, "min_peak"),
            min_growth_pt=_number(min_growth, "min_growth"),
            inspected_since=_day(since, "since"),
            inspected_before=_day(before, "before"),
        )
        descending = (order == "desc") if order else sort in _DEFAULT_DESC
        kept = filter_and_sort(everything, flt, sort, descending)
        pages = max(1, math.ceil(len(kept) / PAGE_ROWS))
        page = min(page, pages)
        shown = kept[(page - 1) * PAGE_ROWS : page * PAGE_ROWS]
        filtered = any((flt.q, flt.grade, min_peak, min_growth, since, before))
        drawn = network_map_svg(
            everything,
            highlighted={p.asset_id for p in kept} if filtered else None,
            tile_url=config.tile_url,
        )
        params = {
            "q": q,
            "grade": grade,
            "min_peak": min_peak,
            "min_growth": min_growth,
            "since": since,
            "before": before,
        }

        def link(**changes: Any) -> str:
            merged = {**params, "sort": sort.value, "order": "desc" if descending else "asc"}
            merged["page"] = str(page)
            merged.update({k: str(v) for k, v in changes.items()})
            return "/?" + urlencode({k: v for k, v in merged.items() if v not in ("", None)})

        def sort_link(key: str) -> str:
            wanted = SortKey(key)
            if wanted == sort:
                return link(sort=key, order="asc" if descending else "desc", page=1)
            return link(sort=key, order="desc" if wanted in _DEFAULT_DESC else "asc", page=1)

        grades = {g: sum(1 for p in everything if p.worst_grade == g) for g in range(5)}
        context = {
            "title": "Network",
            "pipes": shown,
            "total": len(everything),
            "kept": len(kept),
            "page": page,
            "pages": pages,
            "params": params,
            "sort": sort.value,
            "descending": descending,
            "link": link,
            "sort_link": sort_link,
            "map": drawn,
            "without_line": [p.asset_id for p in everything if p.line_xy is None],
            "grades": grades,
            "ungraded": sum(1 for p in everything if p.worst_grade is None),
            "filtered": filtered,
            "last_run": _last_run(recent_runs()[0]),
            "tile_host": _origin(config.tile_url) if config.tile_url else None,
        }
        return templates.TemplateResponse(request, "network.html", context)

    @app.get("/pipes/{asset_id}", response_class=HTMLResponse, include_in_schema=False)
    def pipe_page(
        request: Request,
        asset_id: str,
        at: Annotated[float | None, Query(ge=-1e6, le=1e6)] = None,
    ) -> Response:
        started = time.perf_counter()
        trend = asset_trend(engine, asset_id)
        records = list_inspections(engine, asset_id)
        counts = defect_counts(engine, [r.id for r in records])
        latest = records[-1]
        defects = list_defects(engine, latest.id)
        _server_timing(request, "queries", started)
        # This pipe's own head line, without reading the whole network.
        row = _PipeHead(
            gis_id=gis_ids(engine, [asset_id]).get(asset_id),
            worst_grade=web_queries.worst_grades(engine, [latest.id]).get(latest.id),
        )
        spans = _Spans.of(trend)
        cell = _cell(trend, at)
        colours = {
            s.inspection_id: SURVEY_COLOURS[(len(trend.surveys) - 1 - i) % len(SURVEY_COLOURS)]
            for i, s in enumerate(trend.surveys)
        }
        point = None
        if cell is not None:
            values = trend.blockage_ratio[:, cell]
            slope = _finite(float(trend.change_per_year[cell]))
            threshold = float(spans.cell_threshold_ratio[cell])
            point = {
                "start": float(trend.chainage_start_m[cell]),
                "end": float(trend.chainage_start_m[cell]) + trend.step_m,
                "svg": trend_point_svg(
                    [s.inspected_at for s in trend.surveys],
                    [float(v) for v in values],
                    inspection_ids=[s.inspection_id for s in trend.surveys],
                    noise_ratio=threshold,
                    slope_per_year=slope,
                ),
                "rows": [
                    {
                        "date": s.inspected_at.date().isoformat(),
                        "id": s.inspection_id,
                        "value": _pct(float(values[i])) if math.isfinite(values[i]) else None,
                        "status": trend.section_status[i, cell],
                        "status_label": STATUS_LABELS.get(
                            trend.section_status[i, cell], trend.section_status[i, cell]
                        ),
                    }
                    for i, s in enumerate(trend.surveys)
                ],
                "rate": _rate(slope),
                "noise": f"{100 * threshold:.1f} pp",
                "verdict": _verdict(slope, float(spans.cell_years[cell]), threshold),
                "span_years": float(spans.cell_years[cell]),
                "measured": int(trend.measured_count[cell]),
            }
        fastest = trend.fastest_growth()
        by_id = {r.id: r for r in records}
        context = {
            "title": f"Pipe {row.gis_id if row and row.gis_id else asset_id}",
            "asset_id": asset_id,
            "row": row,
            "trend": trend,
            "records": list(reversed(records)),
            "counts": counts,
            "latest": latest,
            "defects": [_defect_row(d) for d in defects],
            "profiles": profiles_svg(
                trend, selected_cell=cell, href_at=f"{pipe_href(asset_id)}?at="
            ),
            "colours": colours,
            "surveys": [
                {
                    "s": s,
                    "colour": colours[s.inspection_id],
                    "record": by_id.get(s.inspection_id),
                    "offset": "reference" if s.is_reference else f"{s.offset_m:+.2f} m",
                    "correlation": "" if s.correlation is None else f"{s.correlation:.2f}",
                }
                for s in reversed(trend.surveys)
            ],
            "point": point,
            "peaks_svg": trend_point_svg(
                [s.inspected_at for s in trend.surveys],
                [
                    math.nan if s.peak_blockage_ratio is None else s.peak_blockage_ratio
                    for s in trend.surveys
                ],
                inspection_ids=[s.inspection_id for s in trend.surveys],
                noise_ratio=spans.threshold_ratio,
                slope_per_year=trend.peak_change_per_year,
                label="The pipe's peak blockage over time",
            ),
            "at": at,
            "peak_rate": _rate(trend.peak_change_per_year),
            "peak_verdict": _verdict(
                trend.peak_change_per_year, spans.peak_years, spans.threshold_ratio
            ),
            "fastest": None if fastest is None else (fastest[0], _rate(fastest[1])),
            "range": (
                float(trend.chainage_start_m[0]) if trend.chainage_start_m.size else 0.0,
                float(trend.chainage_start_m[-1]) + trend.step_m
                if trend.chainage_start_m.size
                else 0.0,
            ),
        }
        return templates.TemplateResponse(request, "pipe.html", context)

    @app.get("/inspections/{inspection_id}", response_class=HTMLResponse, include_in_schema=False)
    def inspection_page(request: Request, inspection_id: InspectionId) -> Response:
        started = time.perf_counter()
        context = cache.get(
            ("inspection", inspection_id, version()),
            lambda: _report_context(read_only, inspection_id),
        )
        _server_timing(request, "report", started)
        record = get_inspection(engine, inspection_id)
        context = {
            **context,
            "title": f"Inspection {inspection_id}",
            "record": record,
            "downloads": [
                (kind.value, DOWNLOADS[kind][0], DOWNLOADS[kind][2]) for kind in DownloadKind
            ],
        }
        return templates.TemplateResponse(request, "inspection.html", context)

    @app.get("/inspections/{inspection_id}/download/{kind}", include_in_schema=False)
    def download(inspection_id: InspectionId, kind: DownloadKind) -> Response:
        record = get_inspection(engine, inspection_id)
        media_type = DOWNLOADS[kind][1]
        name = f"{_safe_name(record.asset_id)}_{record.inspected_at.date().isoformat()}"
        name += f"_inspection-{inspection_id}.{kind.value}"
        with tempfile.TemporaryDirectory(prefix="pipescan-web-") as folder:
            body = _generate(kind, engine, read_only, inspection_id, Path(folder))
        return Response(
            body,
            media_type=media_type,
            headers={"Content-Disposition": f'attachment; filename="{name}"'},
        )

    runs_held: dict[str, Any] = {}
    runs_lock = threading.Lock()

    def recent_runs() -> tuple[list[Any] | None, str | None]:
        """The recent runs and None, or None and why there are none; asked again at most
        every :data:`RUNS_TTL_S` seconds."""
        if config.runs is None:
            return None, None
        with runs_lock:
            held = runs_held.get("value")
            if held is not None and time.monotonic() - held[0] < RUNS_TTL_S:
                return held[1], held[2]
        try:
            value: tuple[list[Any] | None, str | None] = (config.runs(RUNS_SHOWN, read_only), None)
        except Exception as exc:  # Prefect's API down: the page says so, the rest works
            value = (None, f"Prefect's API did not answer ({type(exc).__name__})")
        with runs_lock:
            runs_held["value"] = (time.monotonic(), *value)
        return value

    @app.get("/runs", response_class=HTMLResponse, include_in_schema=False)
    def runs_page(request: Request) -> Response:
        runs, runs_error = recent_runs()
        tables = set(sa.inspect(engine).get_table_names())
        run_tables = sorted(t for t in tables if "run" in t.lower())
        statement = (
            sa.select(
                sa.func.min(Inspection.created_at),
                sa.func.max(Inspection.created_at),
                sa.func.count(),
                sa.func.count(sa.distinct(Inspection.asset_id)),
            )
            .group_by(sa.func.substr(sa.cast(Inspection.created_at, sa.String), 1, 10))
            .order_by(sa.func.max(Inspection.created_at).desc())
            .limit(30)
        )
        with session_scope(engine) as session:
            saves = session.execute(statement).all()
        context = {
            "title": "Runs",
            "runs": None if runs is None else [_run_row(r) for r in runs],
            "runs_error": runs_error,
            "runs_configured": config.runs is not None,
            "run_tables": run_tables,
            "saves": [
                {
                    "day": _as_utc(last).date().isoformat(),
                    "first": fmt_datetime(_as_utc(first)),
                    "last": fmt_datetime(_as_utc(last)),
                    "inspections": count,
                    "pipes": assets,
                }
                for first, last, count, assets in saves
            ],
        }
        return templates.TemplateResponse(request, "runs.html", context)

    @app.get("/api", response_class=HTMLResponse, include_in_schema=False)
    def api_page(request: Request) -> Response:
        schema = app.openapi()
        endpoints = []
        for path, methods in schema["paths"].items():
            for method, op in methods.items():
                endpoints.append(
                    {
                        "method": method.upper(),
                        "path": path,
                        "summary": op.get("summary", ""),
                        "description": op.get("description", ""),
                        "parameters": [
                            {
                                "name": p["name"],
                                "in": p["in"],
                                "required": p.get("required", False),
                                "description": p.get("description", ""),
                                "schema": _schema_words(p.get("schema", {})),
                            }
                            for p in op.get("parameters", [])
                        ],
                    }
                )
        return templates.TemplateResponse(
            request, "api.html", {"title": "API", "endpoints": endpoints, "info": schema["info"]}
        )

    # -----------------------------------------------------------------------------------------
    # JSON API

    @app.get("/api/pipes", response_model=PipePage, summary="The network's pipes")
    def api_pipes(
        q: Annotated[str, Query(max_length=100, description="Part of an asset or GIS id")] = "",
        condition_class: Annotated[
            str, Query(pattern="^(|[0-4]|none)$", description="0-4, or none (not graded)")
        ] = "",
        sort: SortKey = SortKey.asset,
        order: Annotated[str, Query(pattern="^(asc|desc)$")] = "asc",
        offset: Annotated[int, Query(ge=0, le=2**31 - 1)] = 0,
        limit: Annotated[int, Query(ge=1, le=web_queries.MAX_PAGE_SIZE)] = 100,
    ) -> PipePage:
        """Each pipe with its latest inspection's figures and its line, paginated."""
        kept = filter_and_sort(
            pipes(), NetworkFilter(q=q.strip(), grade=condition_class), sort, order == "desc"
        )
        return PipePage(
            total=len(kept),
            offset=offset,
            limit=limit,
            items=[_pipe_out(p) for p in kept[offset : offset + limit]],
        )

    @app.get("/api/pipes/{asset_id}", response_model=PipeOut, summary="One pipe")
    def api_pipe(asset_id: str) -> PipeOut:
        row = next((p for p in pipes() if p.asset_id == asset_id), None)
        if row is None:
            raise HTTPException(404, f"no asset {asset_id!r} with an inspection")
        return _pipe_out(row)

    @app.get("/api/pipes/{asset_id}/trend", response_model=TrendOut, summary="A pipe's trend")
    def api_trend(
        asset_id: str,
        chainage_m: Annotated[
            float | None,
            Query(ge=-1e6, le=1e6, description="Only this chainage (the reference survey's), m"),
        ] = None,
    ) -> TrendOut:
        """Blockage by aligned chainage across the pipe's inspections, with the change per
        year (Theil-Sen) and the change that noise alone can give, as `pipescan trend --json`."""
        trend = asset_trend(engine, asset_id)
        spans = _Spans.of(trend)
        cells = range(trend.chainage_start_m.size)
        if chainage_m is not None:
            cells = range(trend.cell_at(chainage_m), trend.cell_at(chainage_m) + 1)
        return TrendOut(
            asset_id=trend.asset_id,
            step_m=trend.step_m,
            peak_change_per_year=trend.peak_change_per_year,
            mean_change_per_year=trend.mean_change_per_year,
            inspections=[
                TrendSurvey(
                    inspection_id=s.inspection_id,
                    inspected_at=s.inspected_at,
                    offset_m=s.offset_m,
                    correlation=s.correlation,
                    is_reference=s.is_reference,
                    measured_section_count=s.measured_section_count,
                    mean_blockage_ratio=s.mean_blockage_ratio,
                    peak_blockage_ratio=s.peak_blockage_ratio,
                )
                for s in trend.surveys
            ],
            chainages=[
                TrendCell(
                    chainage_start_m=round(float(trend.chainage_start_m[k]), 3),
                    chainage_end_m=round(float(trend.chainage_start_m[k]) + trend.step_m, 3),
                    blockage_ratio=[_finite(float(v)) for v in trend.blockage_ratio[:, k]],
                    status=list(trend.section_status[:, k]),
                    change_per_year=_finite(float(trend.change_per_year[k])),
                    noise_threshold_ratio=float(spans.cell_threshold_ratio[k]),
                    change=_verdict(
                        _finite(float(trend.change_per_year[k])),
                        float(spans.cell_years[k]),
                        float(spans.cell_threshold_ratio[k]),
                    ),
                )
                for k in cells
            ],
        )

    @app.get("/api/inspections", response_model=InspectionPage, summary="Inspections")
    def api_inspections(
        asset_id: Annotated[str | None, Query(max_length=200)] = None,
        offset: Annotated[int, Query(ge=0, le=2**31 - 1)] = 0,
        limit: Annotated[int, Query(ge=1, le=web_queries.MAX_PAGE_SIZE)] = 100,
    ) -> InspectionPage:
        """Stored inspections (of one asset, or all) by asset, date and id, paginated."""
        records = web_queries.inspection_page(engine, asset_id=asset_id, offset=offset, limit=limit)
        return InspectionPage(
            offset=offset, limit=limit, items=[_inspection_out(r) for r in records]
        )

    @app.get(
        "/api/inspections/{inspection_id}", response_model=InspectionOut, summary="One inspection"
    )
    def api_inspection(inspection_id: InspectionId) -> InspectionOut:
        return _inspection_out(get_inspection(engine, inspection_id))

    @app.get(
        "/api/inspections/{inspection_id}/sections",
        response_model=SectionPage,
        summary="An inspection's sections",
    )
    def api_sections(
        inspection_id: InspectionId,
        offset: Annotated[int, Query(ge=0, le=2**31 - 1)] = 0,
        limit: Annotated[int, Query(ge=1, le=web_queries.MAX_PAGE_SIZE)] = 500,
    ) -> SectionPage:
        """Sections by chainage, without contours, `limit` at a time; figures of a section
        that is not measured (status other than ok) are null."""
        record = get_inspection(engine, inspection_id)
        sections = web_queries.section_page(engine, inspection_id, offset=offset, limit=limit)
        items = []
        for s in sections:
            ok = s.is_ok
            items.append(
                SectionOut(
                    chainage_start_m=s.chainage_start_m,
                    chainage_end_m=s.chainage_end_m,
                    status=str(s.status),
                    blockage_ratio=s.blockage_ratio if ok else None,
                    blockage_uncertainty_ratio=s.blockage_uncertainty_ratio if ok else None,
                    ovality_ratio=s.ovality_ratio if ok else None,
                    deformation_ratio=s.deformation_ratio if ok else None,
                    deposit_height_ratio=s.deposit_height_ratio if ok else None,
                    coverage_ratio=s.coverage_ratio,
                    point_count=s.point_count,
                    grade=s.grade if ok else None,
                )
            )
        following = offset + len(items)
        return SectionPage(
            inspection_id=inspection_id,
            offset=offset,
            limit=limit,
            items=items,
            next_offset=following if following < record.section_count else None,
        )

    @app.get(
        "/api/inspections/{inspection_id}/defects",
        response_model=list[DefectOut],
        summary="An inspection's defects",
    )
    def api_defects(inspection_id: InspectionId) -> list[DefectOut]:
        get_inspection(engine, inspection_id)
        return [
            DefectOut(
                code=d.code,
                measure=d.measure,
                chainage_start_m=d.chainage_start_m,
                chainage_end_m=d.chainage_end_m,
                peak_chainage_m=d.peak_chainage_m,
                peak_value=_finite(d.peak_value),
                peak_blockage_ratio=_finite(d.peak_blockage_ratio),
                grade=d.grade,
                clock_from_h=d.clock_from_h,
                clock_to_h=d.clock_to_h,
                characterisation=d.characterisation,
                lower_bound=d.lower_bound,
            )
            for d in list_defects(engine, inspection_id)
        ]

    return app


def _run_row(run: Any) -> dict[str, Any]:
    """A :class:`pipescan.flows.runs.NetworkRun` as the Runs page shows it."""
    took = ""
    if run.started is not None and run.finished is not None:
        seconds = (run.finished - run.started).total_seconds()
        took = f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"
    return {
        "name": run.name,
        "state": run.state_name,
        "green": run.green,
        "message": run.message or "",
        "started": fmt_datetime(_as_utc(run.started)) if run.started else "not started",
        "finished": fmt_datetime(_as_utc(run.finished)) if run.finished else "not finished",
        "took": took,
        "attempts": run.run_count,
        "store": _strip_credentials(run.store) if run.store else "",
        "counts": run.counts,
        "source": run.source,
        "notes": [
            {
                "kind": kind,
                "archive": note.archive,
                "why": note.why,
                "stored_since": note.stored_since,
            }
            for kind, notes in (("failed", run.failed), ("missing", run.missing))
            for note in notes
        ],
    }


def _last_run(runs: list[Any] | None) -> dict[str, Any] | None:
    """The latest run's archives that were not stored, for the network page."""
    if not runs:
        return None
    return _run_row(runs[0])


def _as_utc(value: datetime) -> datetime:
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def _origin(url: str) -> str:
    """``scheme://host[:port]`` of a URL."""
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}"


def check_tile_url(url: str) -> str:
    """A tile URL template as given, or a StorageError saying what is wrong with it."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise StorageError(f"tile URL {url!r} is not an http(s) address", field="--tile-url")
    if parts.username or parts.password:
        raise StorageError(
            "the tile URL holds credentials, which every browser would be sent",
            field="--tile-url",
            hint="use a tile server the browsers may reach without them",
        )
    missing = [p for p in ("{z}", "{x}", "{y}") if p not in url]
    if missing:
        raise StorageError(
            f"tile URL {url!r} lacks {', '.join(missing)}",
            field="--tile-url",
            hint="give a template such as https://tiles.example/{z}/{x}/{y}.png",
        )
    return url


def _secure_headers(response: Response, csp: str = _CSP) -> Response:
    response.headers["Content-Security-Policy"] = csp
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = "no-referrer"
    response.headers["X-Frame-Options"] = "DENY"
    response.headers.setdefault("Cache-Control", "no-store")
    return response


def _number(text: str, name: str) -> float | None:
    if not text.strip():
        return None
    try:
        value = float(text)
    except ValueError:
        raise StorageError(f"{name} must be a number, not {text!r}", field=name) from None
    if not math.isfinite(value):
        raise StorageError(f"{name} must be a finite number", field=name)
    return value


def _day(text: str, name: str) -> date | None:
    if not text.strip():
        return None
    try:
        return date.fromisoformat(text.strip())
    except ValueError:
        raise StorageError(f"{name} must be a date YYYY-MM-DD, not {text!r}", field=name) from None


def _schema_words(schema: dict[str, Any]) -> str:
    if "anyOf" in schema:
        return " or ".join(_schema_words(s) for s in schema["anyOf"])
    words = schema.get("type", schema.get("$ref", "").rsplit("/", 1)[-1])
    bounds = [f"{k} {schema[k]}" for k in ("minimum", "maximum", "maxLength") if k in schema]
    if "pattern" in schema:
        bounds.append(f"pattern {schema['pattern']}")
    return words + (f" ({', '.join(bounds)})" if bounds else "")


@dataclass(frozen=True)
class _PipeHead:
    gis_id: str | None
    worst_grade: int | None


@dataclass(frozen=True)
class _Spans:
    """What says whether a change is significant (as ``pipescan trend``): the years between
    the first and the last survey measuring each cell and the peak, and each cell's noise
    threshold (:func:`pipescan.core.trends.change_thresholds`)."""

    cell_years: np.ndarray
    peak_years: float
    cell_threshold_ratio: np.ndarray
    threshold_ratio: float

    @classmethod
    def of(cls, trend: AssetTrend) -> _Spans:
        from pipescan.core.trends import SIGNIFICANT_CHANGE_RATIO

        times = np.array([years(s.inspected_at) for s in trend.surveys])
        peaks = np.array(
            [
                [math.nan if s.peak_blockage_ratio is None else s.peak_blockage_ratio]
                for s in trend.surveys
            ]
        )
        (peak_span,) = measured_span_years(times, peaks)
        return cls(
            cell_years=measured_span_years(times, trend.blockage_ratio),
            peak_years=float(peak_span),
            cell_threshold_ratio=change_thresholds(trend.blockage_ratio, trend.step_m),
            threshold_ratio=SIGNIFICANT_CHANGE_RATIO,
        )


def _cell(trend: AssetTrend, at: float | None) -> int | None:
    """The chosen chainage's cell; without a choice, the peak of the reference survey."""
    if trend.chainage_start_m.size == 0:
        return None
    if at is not None:
        return trend.cell_at(at)
    reference = next((i for i, s in enumerate(trend.surveys) if s.is_reference), None)
    if reference is None:
        return None
    row = trend.blockage_ratio[reference]
    if not np.isfinite(row).any():
        return None
    return int(np.nanargmax(row))


def _defect_row(d: Any) -> dict[str, Any]:
    return {
        "code": d.code or "—",
        "measure": d.measure,
        "clock": fmt_clock(d.clock_from_h, d.clock_to_h, d.code or ""),
        "start": fmt_m(d.chainage_start_m, unit=False),
        "end": fmt_m(d.chainage_end_m, unit=False),
        "peak_at": fmt_m(d.peak_chainage_m, unit=False),
        "peak_value": fmt_bound_pct(d, unit=True),
        "peak_blockage": fmt_pct(d.peak_blockage_ratio),
        "grade": fmt_bound_grade(d),
        "grade_value": d.grade,
    }


def _import_report_loader() -> None:
    import pipescan.tasks.reporting  # noqa: F401


def _report_context(url: str, inspection_id: int) -> dict[str, Any]:
    """The inspection report's own context (figures, tables, charts), as the PDF has it."""
    from pipescan.reports.context import build_context
    from pipescan.tasks.reporting import load_report_input

    return build_context(load_report_input(url, inspection_id))


# ---------------------------------------------------------------------------------------------
# Downloads


class DownloadKind(StrEnum):
    pdf = "pdf"
    csv = "csv"
    jsonl = "jsonl"
    xml = "xml"
    gpkg = "gpkg"


DOWNLOADS: dict[DownloadKind, tuple[str, str, str]] = {
    DownloadKind.pdf: ("PDF report", "application/pdf", "the condition report, as printed"),
    DownloadKind.csv: ("Sections, CSV", "text/csv; charset=utf-8", "every section"),
    DownloadKind.jsonl: (
        "Sections, JSON Lines",
        "application/x-ndjson; charset=utf-8",
        "every section",
    ),
    DownloadKind.xml: (
        "ISYBAU XML 2013",
        "application/xml",
        "condition data, validated against the schema",
    ),
    DownloadKind.gpkg: ("GeoPackage", "application/geopackage+sqlite3", "pipe, defects, sections"),
}


def _generate(
    kind: DownloadKind, engine: sa.Engine, url: str, inspection_id: int, folder: Path
) -> bytes:
    """One download, written by pipescan's own exporter into ``folder`` (private to this
    request) under a fixed name, and read back."""
    if kind is DownloadKind.pdf:
        from pipescan.reports.render import render_pdf
        from pipescan.tasks.reporting import load_report_input

        return render_pdf(load_report_input(url, inspection_id), folder / "report.pdf").read_bytes()
    if kind in (DownloadKind.csv, DownloadKind.jsonl):
        from pipescan.exports.tables import export_sections_csv, export_sections_jsonl

        write = export_sections_csv if kind is DownloadKind.csv else export_sections_jsonl
        target = folder / "sections"
        with target.open("w", encoding="utf-8", newline="") as out:
            write(engine, out, inspection_id=inspection_id)
        return target.read_bytes()
    if kind is DownloadKind.xml:
        from pipescan.exports.isybau import IsybauHeader, created_today, export_isybau

        target = folder / "isybau.xml"
        export_isybau(
            engine,
            target,
            IsybauHeader(created_on=created_today(), property_number="", property_name=""),
            inspection_id=inspection_id,
        )
        return target.read_bytes()
    from pipescan.exports.gis import export_gis

    target = folder / "pipe.gpkg"
    export_gis(engine, target, fmt="gpkg", inspection_id=inspection_id, with_sections=True)
    return target.read_bytes()
