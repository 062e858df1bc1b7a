"""Outputs are what was asked: a plot or report path's suffix chooses its format, or the
command refuses in one line before any work; every command makes the output's missing
folders (CSV, JSON lines and PDF did; ISYBAU XML and GeoPackage now too)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.storage.database.db import connect
from tests.test_cli_journey import cli, stored, write_archive  # noqa: F401  (a fixture)
from tests.test_trends import T0, YEAR, save, sections_from, survey

MAGIC = {"png": b"\x89PNG\r\n\x1a\n", "pdf": b"%PDF", "svg": b"<?xml"}


@pytest.fixture
def trend_db(tmp_path: Path) -> str:
    """Three yearly surveys of asset P1 in a SQLite file."""
    url = f"sqlite:///{tmp_path / 'trend.db'}"
    engine = connect(url)
    try:
        for year in range(3):
            save(engine, "P1", T0 + year * YEAR, sections_from(list(survey(year, 0.0))))
    finally:
        engine.dispose()
    return url


def _invoke(*args: str):
    return CliRunner().invoke(app, list(args))


@pytest.mark.parametrize("fmt", ["png", "pdf", "svg"])
def test_a_trend_plot_is_written_in_the_format_its_suffix_names(fmt, trend_db, tmp_path):
    out = tmp_path / "new" / "folder" / f"trend.{fmt}"
    result = _invoke("trend", "P1", "--plot", str(out), "--db", trend_db)
    assert result.exit_code == 0, result.output
    assert out.read_bytes().startswith(MAGIC[fmt])
    if fmt == "svg":
        assert b"<svg" in out.read_bytes()[:2000]
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no .part left


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("trend.jpg", ".jpg is not a format pipescan writes a plot in"),
        ("trend.PDF.txt", ".txt is not a format pipescan writes a plot in"),
    ],
)
def test_a_plot_of_another_suffix_is_one_line_before_any_work(name, expected, tmp_path):
    # No database at all: the name is refused before the command looks for one.
    run = cli("trend", "P1", "--plot", str(tmp_path / name), "--db",
              f"sqlite:///{tmp_path / 'none.db'}", cwd=tmp_path)  # fmt: skip
    line = run.one_line_error()
    assert expected in line and "(end the name in .png or .pdf or .svg)" in line
    assert not (tmp_path / name).exists()


def test_a_report_is_a_pdf_or_refused_in_one_line(tmp_path, stored):  # noqa: F811
    for name, expected in [
        ("out/report.png", "-o {}: a report is written as PDF only (end the name in .pdf"),
        ("out/report.docx", "-o {}: .docx is not a format pipescan writes a report in"),
    ]:
        path = tmp_path / name
        line = cli("report", "--inspection", "1", "--db", stored, "-o", str(path),
                   cwd=tmp_path).one_line_error()  # fmt: skip
        assert expected.format(path) in line, line
        assert not path.parent.exists()
    png = cli("report", "--inspection", "1", "--db", stored, "-o", "r.png", cwd=tmp_path)
    assert "`pdftoppm -png` turns its pages into PNG images" in png.one_line_error()
    archive = write_archive(tmp_path / "site7")
    line = cli("inspect", str(archive), "--report", str(tmp_path / "r.svg"), "--db",
               stored, cwd=tmp_path).one_line_error()  # fmt: skip
    assert "--report" in line and "a report is written as PDF only" in line


def test_the_exports_make_their_folders_as_the_others_do(tmp_path, stored):  # noqa: F811
    xml = tmp_path / "new" / "dir" / "p.xml"
    run = cli("export", "isybau", "--inspection", "1", "--db", stored, "-o", str(xml),
              cwd=tmp_path)  # fmt: skip
    assert run.code == 0, run.stderr
    assert xml.read_bytes().startswith(b"<?xml")
    gpkg = tmp_path / "other" / "dir" / "n.gpkg"
    run = cli("export", "gis", "--inspection", "1", "--db", stored, "-o", str(gpkg), cwd=tmp_path)
    # The stored pipe has no geometry (no network layer): what is refused is that, not the
    # folder; the folder was made.
    assert "folder does not exist" not in run.stderr, run.stderr
    assert gpkg.parent.is_dir()
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    line = cli("export", "isybau", "--inspection", "1", "--db", stored, "-o",
               str(blocker / "p.xml"), cwd=tmp_path).one_line_error()  # fmt: skip
    assert f"{blocker} is not a folder" in line
