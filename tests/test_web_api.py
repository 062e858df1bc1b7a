"""The web view's JSON API and pages through FastAPI's TestClient, on a database of simulated
surveys (:func:`build_network`): figures equal the CLI's and the report's, pages bounded,
output escaped, the database opened read-only, no credentials shown."""

from __future__ import annotations

import math
import os
import re
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

from fastapi.testclient import TestClient

from pipescan.core.grading import grade_sections, load_table, merge_defects
from pipescan.core.model import InspectionMeta, SectionStatus
from pipescan.core.network import LayerPipe, NetworkLayer, PipeLine
from pipescan.core.summary import worst_grade
from pipescan.reports.sample import Feature, sample_sections
from pipescan.storage.database import db, repository, web_queries
from pipescan.storage.database.network import import_network_layer
from pipescan.storage.database.trends import asset_trend, worst_assets
from pipescan.web import WebConfig, create_app

CRS = "EPSG:25832"
HOSTILE_MATERIAL = "<script>alert('pipe')</script>"
T0 = datetime(2021, 5, 3, 9, 0, tzinfo=UTC)
YEARS = 3
"""Inspections per pipe, two years apart."""

# (asset id, upstream node, downstream node, upstream x, y, downstream x, y, features at the
# latest survey, growth factor per survey back in time, unmeasured spans)
PIPES = [
    ("MH1-MH2", "MH1", "MH2", 0.0, 0.0, 20.0, 0.0, [Feature("deposit", 6.0, 9.0, 0.40)], 0.6, []),
    ("MH2-MH3", "MH2", "MH3", 20.0, 0.0, 40.0, 5.0, [Feature("obstacle", 10.0, 11.4, 0.2)], 0.8,
     [(14.0, 15.0, SectionStatus.LOW_COVERAGE)]),
    ("MH3-MH4", "MH3", "MH4", 40.0, 5.0, 60.0, 5.0, [], 1.0, []),
    ("MH2-MH5", "MH2", "MH5", 20.0, 0.0, 20.0, -18.0, [Feature("deposit", 3.0, 5.0, 0.18)], 0.9,
     [(8.0, 8.6, SectionStatus.TOO_FEW_POINTS)]),
    ("MH5-MH6", "MH5", "MH6", None, None, None, None, [Feature("deposit", 2.0, 4.0, 0.25)], 0.7,
     []),
]  # fmt: skip
LENGTH_M = 18.0


def build_network(url: str, *, contours: bool = True) -> None:
    """Five simulated pipes, three surveys each two years apart, with growing features, unmeasured
    stretches, node positions for four of them (the fifth has none), a GIS layer line for one
    (bent, with its own id) and a material that is HTML."""
    if not url.startswith("sqlite"):
        db.upgrade(url)  # a server is migrated by its operator
    engine = db.connect(url)
    table = load_table("vsa-2023")
    try:
        items = []
        for n, (asset_id, up, down, ux, uy, dx, dy, features, back, gaps) in enumerate(PIPES):
            for k in range(YEARS):
                newest = k == YEARS - 1
                scale = back ** (YEARS - 1 - k)
                sections = grade_sections(
                    sample_sections(
                        LENGTH_M,
                        features=[replace(f, peak_ratio=f.peak_ratio * scale) for f in features],
                        unmeasured=[(a + 0.3 * k, b + 0.3 * k, st) for a, b, st in gaps],
                        seed=10 * n + k,
                        contours=contours and newest,
                    ),
                    table,
                )
                defects = merge_defects(sections, table)
                items.append(
                    repository.InspectionToSave(
                        meta=InspectionMeta(
                            asset_id=asset_id,
                            inspected_at=T0 + timedelta(days=730 * k + n),
                            nominal_diameter_m=0.5,
                            upstream_node=up,
                            downstream_node=down,
                            material=HOSTILE_MATERIAL if asset_id == "MH3-MH4" else "concrete",
                            upstream_node_xyz=None if ux is None else (ux, uy, 100.0),
                            downstream_node_xyz=None if dx is None else (dx, dy, 99.8),
                            crs=None if ux is None else CRS,
                        ),
                        archive_uri=f"s3://surveys/{asset_id}/{k}.tar.gz",
                        content_hash=f"sha256:{asset_id}:{k}",
                        params={"section_step_m": 0.1},
                        software_version="0.1.0",
                        sections=sections,
                        defects=defects,
                        threshold_table="vsa-2023",
                        scanned_length_m=LENGTH_M,
                    )
                )
        repository.save_inspections(engine, items)
        # One pipe's line from a GIS layer: bent, digitised downstream first, with its own id.
        bent = PipeLine(np.array([[40.0, 5.0], [50.0, 9.0], [60.0, 5.0]])[::-1].copy())
        import_network_layer(
            engine,
            NetworkLayer(
                pipes=(LayerPipe("GIS-0034", "MH3-MH4", "MH4", "MH3", bent),),
                crs=CRS,
                source="sewer.gpkg",
            ),
        )
    finally:
        engine.dispose()


@pytest.fixture(scope="module")
def network_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("web") / "network.db"
    build_network(f"sqlite:///{path}")
    return path


@pytest.fixture(scope="module")
def client(network_db: Path) -> TestClient:
    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", database_label="sqlite"))
    with TestClient(app) as c:
        yield c


def test_pipes_carry_the_cli_figures(client: TestClient, network_db: Path) -> None:
    body = client.get("/api/pipes").json()
    assert body["total"] == len(PIPES)
    by_id = {p["asset_id"]: p for p in body["items"]}
    engine = db.connect(f"sqlite:///{network_db}")
    try:
        growth = {r.asset_id: r.peak_change_per_year for r in worst_assets(engine, by="current")}
        for asset_id, *_ in PIPES:
            latest = repository.list_inspections(engine, asset_id)[-1]
            sections = repository.list_sections(engine, latest.id)
            pipe = by_id[asset_id]
            assert pipe["last_inspection_id"] == latest.id
            assert pipe["condition_class"] == worst_grade(sections)  # the one rule, in SQL
            assert pipe["peak_blockage_ratio"] == pytest.approx(latest.peak_blockage_ratio)
            assert pipe["growth_per_year_ratio"] == pytest.approx(growth[asset_id])
            assert pipe["inspection_count"] == YEARS
            assert pipe["defect_count"] == len(repository.list_defects(engine, latest.id))
    finally:
        engine.dispose()
    assert by_id["MH1-MH2"]["line"][0][:2] == [0.0, 0.0]  # upstream first
    assert by_id["MH5-MH6"]["line"] is None
    gis = by_id["MH3-MH4"]
    assert gis["gis_id"] == "GIS-0034"
    assert gis["line"] == [[40.0, 5.0], [50.0, 9.0], [60.0, 5.0]]  # turned upstream first
    assert {p["condition_class"] for p in body["items"]} >= {4}
    assert min(p["condition_class"] for p in body["items"]) <= 1


def test_trend_is_the_cli_trend(client: TestClient, network_db: Path) -> None:
    body = client.get("/api/pipes/MH1-MH2/trend", params={"chainage_m": 7.5}).json()
    engine = db.connect(f"sqlite:///{network_db}")
    try:
        trend = asset_trend(engine, "MH1-MH2")
    finally:
        engine.dispose()
    cell = trend.cell_at(7.5)
    assert len(body["inspections"]) == YEARS
    (row,) = body["chainages"]
    assert row["chainage_start_m"] == pytest.approx(trend.chainage_start_m[cell])
    assert row["blockage_ratio"] == pytest.approx(list(trend.blockage_ratio[:, cell]))
    assert row["change_per_year"] == pytest.approx(trend.change_per_year[cell])
    assert row["change"] == "growing"
    assert row["noise_threshold_ratio"] >= 0.02
    assert body["peak_change_per_year"] == pytest.approx(trend.peak_change_per_year)
    whole = client.get("/api/pipes/MH1-MH2/trend").json()
    assert len(whole["chainages"]) == trend.chainage_start_m.size
    # A steady pipe's readings differ by noise only.
    steady = client.get("/api/pipes/MH3-MH4/trend", params={"chainage_m": 5}).json()
    assert steady["chainages"][0]["change"] == "no significant change"


def test_sections_are_paginated_and_bounded(client: TestClient) -> None:
    inspection_id = client.get("/api/pipes/MH2-MH3").json()["last_inspection_id"]
    first = client.get(f"/api/inspections/{inspection_id}/sections", params={"limit": 100}).json()
    assert len(first["items"]) == 100 and first["next_offset"] == 100
    rest = client.get(
        f"/api/inspections/{inspection_id}/sections", params={"offset": 100, "limit": 1000}
    ).json()
    assert len(rest["items"]) == round(LENGTH_M / 0.1) - 100 and rest["next_offset"] is None
    starts = [s["chainage_start_m"] for s in first["items"] + rest["items"]]
    assert starts == sorted(starts)
    unmeasured = [s for s in first["items"] + rest["items"] if s["status"] != "ok"]
    assert unmeasured and all(s["blockage_ratio"] is None for s in unmeasured)
    for bad in ({"limit": 1001}, {"limit": 0}, {"offset": -1}):
        assert (
            client.get(f"/api/inspections/{inspection_id}/sections", params=bad).status_code == 422
        )
    assert client.get("/api/pipes", params={"limit": 5000}).status_code == 422
    assert client.get("/api/inspections", params={"limit": 5000}).status_code == 422
    page = client.get("/api/inspections", params={"limit": 4, "offset": 2}).json()
    assert len(page["items"]) == 4


def test_defects_and_inspections(client: TestClient) -> None:
    inspection_id = client.get("/api/pipes/MH1-MH2").json()["last_inspection_id"]
    defects = client.get(f"/api/inspections/{inspection_id}/defects").json()
    assert defects and defects[0]["code"] == "BBC"
    assert defects[0]["clock_from_h"] is not None
    one = client.get(f"/api/inspections/{inspection_id}").json()
    assert one["asset_id"] == "MH1-MH2" and one["section_count"] == round(LENGTH_M / 0.1)
    listed = client.get("/api/inspections", params={"asset_id": "MH1-MH2"}).json()["items"]
    assert [i["inspected_at"] for i in listed] == sorted(i["inspected_at"] for i in listed)
    assert client.get("/api/inspections/999999").status_code == 404
    for path in (  # ids and offsets beyond the database's integers, chainages that are no number
        "/api/inspections/99999999999999999999",
        "/inspections/99999999999999999999",
        "/inspections/99999999999999999999/download/pdf",
        "/api/inspections?offset=99999999999999999999",
        "/api/pipes/MH1-MH2/trend?chainage_m=nan",
        "/pipes/MH1-MH2?at=inf",
    ):
        assert client.get(path).status_code == 422, path
    assert client.get("/api/pipes/NOPE").status_code == 404
    assert client.get("/api/pipes/NOPE/trend").status_code == 404


def test_openapi_and_its_page_work_offline(client: TestClient) -> None:
    schema = client.get("/api/openapi.json").json()
    for path in (
        "/api/pipes",
        "/api/pipes/{asset_id}/trend",
        "/api/inspections/{inspection_id}/sections",
        "/api/inspections/{inspection_id}/defects",
    ):
        assert path in schema["paths"]
    page = client.get("/api").text
    assert "/api/inspections/{inspection_id}/sections" in page
    assert client.get("/docs").status_code == 404  # FastAPI's page would load a CDN's scripts
    for path in ("/", "/api", "/runs", "/pipes/MH1-MH2"):
        html = client.get(path).text
        assert "http://" not in html.replace('xmlns="http://www.w3.org/2000/svg"', "")
        assert "https://" not in html


def test_pages_escape_what_the_database_holds(client: TestClient) -> None:
    for path in ("/", "/pipes/MH3-MH4"):
        html = client.get(path).text
        assert HOSTILE_MATERIAL not in html
    assert "&lt;script&gt;" in client.get("/pipes/MH3-MH4").text
    inspection_id = client.get("/api/pipes/MH3-MH4").json()["last_inspection_id"]
    html = client.get(f"/inspections/{inspection_id}").text
    assert HOSTILE_MATERIAL not in html and "&lt;script&gt;" in html
    search = client.get("/", params={"q": "<b>x</b>"}).text
    assert "<b>x</b>" not in search
    assert "script-src 'self'" in client.get("/").headers["content-security-policy"]


def test_network_page_sorts_filters_and_searches(client: TestClient) -> None:
    def order(**params: str) -> list[str]:
        html = client.get("/", params=params).text
        return [part.split('"', 1)[0] for part in html.split('<tr data-asset="')[1:]]

    assert order(sort="asset", order="asc") == sorted(p[0] for p in PIPES)
    peaks = {
        p["asset_id"]: p["peak_blockage_ratio"] for p in client.get("/api/pipes").json()["items"]
    }
    assert order(sort="peak", order="desc") == sorted(peaks, key=lambda a: -peaks[a])
    assert order(q="mh5") == ["MH2-MH5", "MH5-MH6"]
    assert order(q="GIS-0034") == ["MH3-MH4"]
    assert order(grade="4") == ["MH3-MH4"]
    high = order(min_peak="20")
    assert high and all(100 * peaks[a] >= 20 for a in high)
    assert order(since="2099-01-01") == []
    assert client.get("/", params={"min_peak": "lots"}).status_code == 400
    assert client.get("/", params={"sort": "nonsense"}).status_code == 422


def test_map_draws_each_located_pipe_in_its_class_colour(client: TestClient) -> None:
    from pipescan.web.figures import grade_colour

    html = client.get("/").text
    pipes = {p["asset_id"]: p for p in client.get("/api/pipes").json()["items"]}
    for asset_id, pipe in pipes.items():
        marker = f'data-asset="{asset_id}"'
        if pipe["line"] is None:
            assert marker not in html.split("<table")[0]
            continue
        polyline = html.split(marker)[0].rsplit("<polyline", 1)[1]
        assert f'stroke="{grade_colour(pipe["condition_class"])}"' in polyline
    assert "Not on the map (no line): MH5-MH6" in html


def test_pipe_page_shows_a_reading_per_inspection(client: TestClient) -> None:
    html = client.get("/pipes/MH1-MH2", params={"at": 7.5}).text
    # One reading per inspection at the chainage, and one per inspection of the pipe's peak.
    at_chainage = html.split('class="chart small at-chainage"')[1].split("</figure>")[0]
    assert at_chainage.count('class="reading"') == YEARS
    peaks = html.split('class="chart small peaks"')[1].split("</figure>")[0]
    assert peaks.count('class="reading"') == YEARS
    assert html.count('class="profile"') >= YEARS
    assert "growing" in html
    gaps = client.get("/pipes/MH2-MH3").text
    assert 'class="unmeasured"' in gaps
    assert client.get("/pipes/MH1-MH2", params={"at": 500}).status_code == 400
    assert client.get("/pipes/NOPE").status_code == 404


def test_inspection_page_is_the_report(client: TestClient) -> None:
    inspection_id = client.get("/api/pipes/MH1-MH2").json()["last_inspection_id"]
    html = client.get(f"/inspections/{inspection_id}").text
    assert "data:image/svg+xml" in html  # the report's own charts
    assert "Cross-sections at each defect" in html
    assert "BBC" in html and "not measured" in html
    for kind in ("pdf", "csv", "jsonl", "xml", "gpkg"):
        assert f"/inspections/{inspection_id}/download/{kind}" in html


@pytest.mark.parametrize(
    ("kind", "starts"),
    [
        ("csv", b"asset_id,inspection_id"),
        ("jsonl", b'{"asset_id": "MH1-MH2"'),
        ("xml", b"<?xml"),
        ("gpkg", b"SQLite format 3"),
        ("pdf", b"%PDF"),
    ],
)
def test_downloads_come_from_the_database(client: TestClient, kind: str, starts: bytes) -> None:
    inspection_id = client.get("/api/pipes/MH1-MH2").json()["last_inspection_id"]
    response = client.get(f"/inspections/{inspection_id}/download/{kind}")
    assert response.status_code == 200
    assert response.content.startswith(starts)
    disposition = response.headers["content-disposition"]
    assert disposition.startswith('attachment; filename="MH1-MH2_')
    assert disposition.endswith(f'_inspection-{inspection_id}.{kind}"')


def test_downloads_take_no_path(client: TestClient) -> None:
    for path in (
        "/inspections/1/download/..%2F..%2Fetc%2Fpasswd",
        "/inspections/1/download/pdf%2F..",
        "/inspections/1/download/txt",
    ):
        assert client.get(path).status_code in (404, 422)
    assert client.get("/static/../app.py").status_code == 404


def test_the_database_is_opened_read_only(network_db: Path) -> None:
    url = web_queries.read_only_url(f"sqlite:///{network_db}")
    engine = db.create_engine_for(url)
    try:
        with pytest.raises(sa.exc.OperationalError, match="readonly"), engine.begin() as c:
            c.execute(sa.text("DELETE FROM sections"))
    finally:
        engine.dispose()
    pg = web_queries.read_only_url("postgresql+psycopg://u:secret@db.example/pipescan")
    assert "default_transaction_read_only" in pg
    with pytest.raises(db.StorageError, match="no database"):
        web_queries.read_only_url(f"sqlite:///{network_db}.missing")


def test_read_only_on_postgresql(postgres_url: str) -> None:
    build_network(postgres_url, contours=False)
    app = create_app(WebConfig(database_url=postgres_url))
    with TestClient(app) as c:
        assert c.get("/api/pipes").json()["total"] == len(PIPES)
        assert c.get("/pipes/MH1-MH2").status_code == 200
        engine = app.state.engine
        with pytest.raises(sa.exc.InternalError, match="read-only"), engine.begin() as conn:
            conn.execute(sa.text("DELETE FROM sections"))


def test_no_credentials_in_any_page(network_db: Path) -> None:
    from pipescan.cli.serve import _label

    password = "s3cr3t-pa55word"
    label = _label(f"postgresql+psycopg://pipescan:{password}@db.example:5432/network")
    assert label == "postgresql network"  # what the footer shows of a database
    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", database_label=label))
    with TestClient(app) as c:
        inspection_id = c.get("/api/pipes/MH1-MH2").json()["last_inspection_id"]
        paths = ["/", "/runs", "/api", "/api/openapi.json", "/pipes/MH1-MH2", "/api/pipes"]
        paths += [f"/inspections/{inspection_id}", "/api/inspections"]
        for path in paths:
            body = c.get(path).text
            assert password not in body and str(network_db) not in body


def test_a_token_guards_every_request(network_db: Path) -> None:
    token = "t" * 24
    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", token=token))
    with TestClient(app) as c:
        assert c.get("/api/pipes").status_code == 401
        assert c.get("/", params={"token": "wrong" * 5}).status_code == 401
        assert c.get("/", params={"token": "é" * 24}).status_code == 401  # not a crash
        bearer = c.get("/api/pipes", headers={"Authorization": f"Bearer {token}"})
        assert bearer.status_code == 200
        first = c.get("/", params={"token": token, "q": "MH1"}, follow_redirects=False)
        assert first.status_code == 303 and "token" not in first.headers["location"]
        assert c.get(first.headers["location"]).status_code == 200  # the cookie now


def test_serve_refuses_the_network_without_a_token(network_db: Path) -> None:
    from typer.testing import CliRunner

    from pipescan.cli import app

    result = CliRunner().invoke(app, ["serve", "--host", "0.0.0.0", "--db", str(network_db)])
    assert result.exit_code == 2
    assert "needs" not in result.output or "token" in result.output
    assert "without a token" in result.output


def test_worst_grade_in_sql_is_the_core_rule(network_db: Path) -> None:
    engine = db.connect(f"sqlite:///{network_db}")
    try:
        ids = [r.id for r in repository.list_inspections(engine)]
        grades = web_queries.worst_grades(
            engine, sa.select(sa.literal_column("id")).select_from(sa.table("inspections"))
        )
        for inspection_id in ids:
            expected = worst_grade(repository.list_sections(engine, inspection_id))
            assert grades.get(inspection_id) == expected
    finally:
        engine.dispose()


def test_runs_page_says_what_it_shows(client: TestClient) -> None:
    html = client.get("/runs").text
    assert "failed archive" in html and "What was stored, by day" in html
    assert str(len(PIPES) * YEARS) in html


def test_runs_from_prefect_are_shown_with_why_archives_failed(network_db: Path) -> None:
    from pipescan.flows.runs import ArchiveNote, NetworkRun

    asked: list[tuple[int, str]] = []

    def runs(limit: int, url: str) -> list[NetworkRun]:
        asked.append((limit, url))
        return [
            NetworkRun(
                id="1",
                name="nightly-<b>07</b>",
                state="COMPLETED",
                state_name="Completed",
                message=None,
                started=datetime(2026, 12, 7, 2, 0, tzinfo=UTC),
                finished=datetime(2026, 12, 7, 2, 40, tzinfo=UTC),
                run_count=1,
                store="s3://surveys/",
                counts={"inspected": 14, "reused": 3, "duplicate": 0, "failed": 1, "missing": 1},
                failed=[ArchiveNote("MH9-MH10.zip", "inspection.toml: no 'inspected_at'")],
                missing=[ArchiveNote("MH11-MH12.zip", "database unreachable", stored_since=True)],
            )
        ]

    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", runs=runs))
    with TestClient(app) as c:
        page = c.get("/runs").text
        assert "14 inspected" in page and "1 failed" in page and "1 missing" in page
        assert "MH9-MH10.zip" in page and "no &#39;inspected_at&#39;" in page
        assert "nightly-&lt;b&gt;07&lt;/b&gt;" in page  # escaped
        network = c.get("/").text
        assert "Latest network run" in network and "MH9-MH10.zip" in network
    assert asked and asked[0][1].endswith("mode=ro&uri=true")  # the database read-only

    def down(limit: int, url: str) -> list[NetworkRun]:
        raise OSError("connection refused")

    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", runs=down))
    with TestClient(app) as c:
        assert "Prefect&#39;s API did not answer" in c.get("/runs").text
        assert c.get("/").status_code == 200


def test_serve_starts_on_loopback_and_answers(network_db: Path) -> None:
    import socket
    import subprocess
    import sys
    import time

    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    command = [sys.executable, "-m", "pipescan.cli", "serve", "--db", str(network_db)]
    process = subprocess.Popen(
        [*command, "--port", str(port)],
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PREFECT_API_URL": ""},
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                response = httpx.get(f"http://127.0.0.1:{port}/api/pipes", timeout=5)
                break
            except httpx.TransportError:
                assert process.poll() is None, process.stderr.read() if process.stderr else ""
                assert time.monotonic() < deadline, "serve did not answer in 120 s"
                time.sleep(0.3)
        assert response.status_code == 200 and response.json()["total"] == len(PIPES)
        assert "server" not in response.headers  # uvicorn's banner is off
    finally:
        process.terminate()
        _, err = process.communicate(timeout=30)
    assert f"http://127.0.0.1:{port}/ (this machine only; read-only)" in err
    assert f"read the network: {len(PIPES)} pipes in" in err  # before it listened


def _utm_forward(lat_deg: float, lon_deg: float, zone: int) -> tuple[float, float]:
    """Latitude and longitude to UTM by Krüger's forward series (the inverse's counterpart,
    written out here independently of it)."""
    f = 1 / 298.257223563
    n = f / (2 - f)
    a_rect = 6378137.0 / (1 + n) * (1 + n**2 / 4 + n**4 / 64)
    alpha = (n / 2 - 2 * n**2 / 3 + 5 * n**3 / 16, 13 * n**2 / 48 - 3 * n**3 / 5, 61 * n**3 / 240)
    phi, dl = math.radians(lat_deg), math.radians(lon_deg - (zone * 6 - 183))
    c = 2 * math.sqrt(n) / (1 + n)
    t = math.sinh(math.atanh(math.sin(phi)) - c * math.atanh(c * math.sin(phi)))
    xi, eta = math.atan(t / math.cos(dl)), math.atanh(math.sin(dl) / math.sqrt(1 + t * t))
    terms = list(enumerate(alpha, start=1))
    e = eta + sum(a * math.cos(2 * j * xi) * math.sinh(2 * j * eta) for j, a in terms)
    nn = xi + sum(a * math.sin(2 * j * xi) * math.cosh(2 * j * eta) for j, a in terms)
    return 500_000 + 0.9996 * a_rect * e, 0.9996 * a_rect * nn + (10_000_000 if lat_deg < 0 else 0)


def test_utm_to_web_mercator() -> None:
    from pipescan.web.figures import _utm_to_lonlat, web_mercator

    # On the central meridian the northing is 0.9996 times the meridian arc: 4,984,944.378 m
    # from the equator to 45 degrees on WGS 84.
    lon, lat = _utm_to_lonlat(np.array([500_000.0]), np.array([0.9996 * 4_984_944.378]), 32, False)
    assert lon[0] == pytest.approx(9.0) and lat[0] == pytest.approx(45.0, abs=1e-7)
    for lat_deg, lon_deg, zone in [(48.85837, 2.294481, 31), (60.1, 13.5, 32), (-33.9, 18.4, 34)]:
        e, n = _utm_forward(lat_deg, lon_deg, zone)
        lon, lat = _utm_to_lonlat(np.array([e]), np.array([n]), zone, lat_deg < 0)
        assert (lat[0], lon[0]) == pytest.approx((lat_deg, lon_deg), abs=1e-7)  # a centimetre
    e, n = _utm_forward(50.0, 7.0, 32)
    x, y = web_mercator("EPSG:25832", np.array([[e, n]]))[0]
    assert x == pytest.approx(6378137.0 * math.radians(7.0), abs=0.01)
    assert y == pytest.approx(
        6378137.0 * math.log(math.tan(math.pi / 4 + math.radians(25))), abs=0.01
    )
    assert web_mercator("EPSG:2056", np.array([[2_600_000.0, 1_200_000.0]])) is None


def test_a_basemap_from_the_configured_tile_server(network_db: Path) -> None:
    tiles = "http://127.0.0.1:9/tiles/{z}/{x}/{y}.png"
    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", tile_url=tiles))
    with TestClient(app) as c:
        response = c.get("/")
        html = response.text
        hrefs = re.findall(r'<image href="([^"]+)"', html)
        assert hrefs and all(h.startswith("http://127.0.0.1:9/tiles/") for h in hrefs)
        z = {h.split("/")[4] for h in hrefs}
        assert len(z) == 1 and 17 <= int(z.pop()) <= 19  # a 60 m network: street-level tiles
        assert (
            "img-src 'self' data: http://127.0.0.1:9;"
            in response.headers["content-security-policy"]
        )
        assert "Basemap: tiles from http://127.0.0.1:9" in html
        assert 'data-asset="MH1-MH2"' in html  # the lines are still there
    for bad in (
        "ftp://x/{z}/{x}/{y}",
        "https://tiles.example/{z}/{x}.png",
        "https://u:p@h/{z}/{x}/{y}",
    ):
        with pytest.raises(db.StorageError):
            create_app(WebConfig(database_url=f"sqlite:///{network_db}", tile_url=bad))
