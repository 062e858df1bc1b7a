"""Network runs: finding archives in a store, retrying only I/O, one bad archive failing alone,
re-runs reusing what is stored (one copy of each inspection), and the network summary."""

from __future__ import annotations

import fsspec
import pytest
import sqlalchemy as sa
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.core.errors import (
    ArchiveError,
    FetchError,
    GeometryError,
    MetadataError,
    PipescanError,
    RegistrationError,
    ScratchSpaceError,
)
from pipescan.flows.database import absolute_database_url
from pipescan.flows.network import (
    ArchiveOutcome,
    network_report_name,
    progress_line,
    refuse_password_in_url,
    worst_pipes,
)
from pipescan.storage.database.db import StorageError
from pipescan.tasks.network import StoreError, archive_label, find_archives
from pipescan.tasks.retries import is_transient_io_error

# --- the store ----------------------------------------------------------------------------------


def _touch(path, text="x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_find_archives_at_any_depth_in_natural_order(tmp_path):
    store = tmp_path / "store"
    _touch(store / "MH10-MH11" / "inspection.toml")
    _touch(store / "MH2-MH3" / "inspection.toml")
    _touch(store / "MH2-MH3" / "frames" / "stray.zip")  # inside an archive: content, not archive
    _touch(store / "2026-11" / "MH7-MH8.tar.gz")
    _touch(store / "2026-11" / "deep" / "MH9-MH10.ZIP")
    _touch(store / "2026-11" / "MH5-MH6" / "inspection.toml")
    _touch(store / "notes.txt")
    _touch(store / ".hidden.zip")
    _touch(store / "MH1.tgz")
    found = find_archives(str(store))
    rel = [p[len(str(store)) + 1 :] for p in found]
    assert rel == [
        "2026-11/deep/MH9-MH10.ZIP",
        "2026-11/MH5-MH6",
        "2026-11/MH7-MH8.tar.gz",
        "MH1.tgz",
        "MH2-MH3",
        "MH10-MH11",
    ]


def test_find_archives_in_an_fsspec_store():
    fs = fsspec.filesystem("memory")
    fs.pipe("/netstore-test/a/MH1-MH2/inspection.toml", b"x")
    fs.pipe("/netstore-test/a/MH3-MH4.zip", b"x")
    try:
        assert find_archives("memory://netstore-test/a") == [
            "memory:///netstore-test/a/MH1-MH2",
            "memory:///netstore-test/a/MH3-MH4.zip",
        ]
    finally:
        fs.rm("/netstore-test", recursive=True)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: None, "does not exist"),
        (lambda p: p.mkdir(), "holds no scan archive"),
        (lambda p: p.write_text("x"), "is a file"),
    ],
)
def test_a_missing_empty_or_file_store_is_a_clear_error(tmp_path, make, message):
    store = tmp_path / "store"
    make(store)
    with pytest.raises(StoreError, match=message) as info:
        find_archives(str(store))
    assert str(store) in str(info.value)


def test_archive_labels():
    assert archive_label("/s/2026/MH1042-MH1043.tar.gz") == "MH1042-MH1043"
    assert archive_label("s3://b/runs/MH1-MH2.zip") == "MH1-MH2"
    assert archive_label("/s/MH1-MH2/") == "MH1-MH2"
    assert archive_label("/s/x.tar") == "x"


def test_relative_sqlite_urls_are_made_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert absolute_database_url("sqlite:///p.db") == f"sqlite:///{tmp_path / 'p.db'}"
    assert absolute_database_url("sqlite:////abs/p.db") == "sqlite:////abs/p.db"
    url = "postgresql+psycopg://u:secret@h/db"
    assert absolute_database_url(url) == url


# --- what is retried ----------------------------------------------------------------------------


def _wrapped(outer_cls, inner: BaseException, **kw) -> BaseException:
    try:
        try:
            raise inner
        except BaseException as exc:
            raise outer_cls("wrapped", **kw) from exc
    except BaseException as outer:
        return outer


@pytest.mark.parametrize(
    ("exc", "transient"),
    [
        (ConnectionResetError("peer reset"), True),
        (TimeoutError("read timed out"), True),
        (OSError(5, "Input/output error"), True),
        (_wrapped(FetchError, OSError(104, "reset"), archive="s3://b/a.zip"), True),
        (_wrapped(FetchError, FileNotFoundError(2, "no such key"), archive="s3://b/a"), False),
        # About the input: never retried, even when an OSError is underneath (a member name
        # too long for the file system, a full work directory).
        (_wrapped(ArchiveError, OSError(36, "File name too long"), archive="a.zip"), False),
        (_wrapped(ScratchSpaceError, OSError(28, "No space left on device")), False),
        (_wrapped(StorageError, sa.exc.OperationalError("INSERT", {}, "database is locked")), True),
        (StorageError("no inspection with id 4"), False),
        (GeometryError("no points in the window"), False),
        (_wrapped(GeometryError, OSError(5, "io")), False),
        (RegistrationError("ICP diverged"), False),
        (MetadataError("missing inspected_at"), False),
        (ArchiveError("the archive does not exist"), False),
        (FileNotFoundError(2, "No such file"), False),
        (PermissionError(13, "denied"), False),
        (ValueError("bad value"), False),
    ],
)
def test_only_transient_io_errors_are_retried(exc, transient):
    assert is_transient_io_error(exc) is transient


def test_progress_and_worst_pipes():
    ok = ArchiveOutcome(
        archive="/s/MH1-MH2",
        label="MH1-MH2",
        status="inspected",
        wall_time_s=12.34,
        inspection_id=7,
        asset_id="A1",
        defect_count=2,
        max_blockage_ratio=0.167,
        max_blockage_chainage_m=2.8,
    )
    bad = ArchiveOutcome(
        archive="/s/X", label="X", status="failed", wall_time_s=0.5, error="archive /s/X: broken"
    )
    low = ArchiveOutcome(**{**ok.__dict__, "label": "L", "max_blockage_ratio": 0.02})
    assert progress_line(3, 20, ok) == (
        "[3/20] MH1-MH2 inspected in 12.3 s as inspection 7: asset A1, 2 defects, "
        "worst blockage 16.7 % at 2.8 m"
    )
    assert progress_line(4, 20, bad) == "[4/20] X FAILED after 0.5 s: archive /s/X: broken"
    assert worst_pipes([low, bad, ok], 5) == [ok, low]
    assert worst_pipes([low, bad, ok], 1) == [ok]


def test_settings_give_the_inspection_parameters(monkeypatch):
    from pipescan.flows.network import params_from_settings
    from pipescan.settings import Settings

    monkeypatch.setenv("PIPESCAN_GRID_K", "8")
    monkeypatch.setenv("PIPESCAN_GRID_S_THRESHOLD_RAD", "0.7")
    monkeypatch.setenv("PIPESCAN_REGISTRATION_METHOD", "point_to_plane")
    monkeypatch.setenv("PIPESCAN_REGISTRATION_ENGINE", "open3d")
    params = params_from_settings(Settings(), contour="grid")
    assert params.measure.method == "grid"
    assert (params.measure.grid.k, params.measure.grid.s_threshold_rad) == (8, 0.7)
    assert (params.registration.method, params.registration.engine) == ("point_to_plane", "open3d")
    monkeypatch.setenv("PIPESCAN_GRID_K", "2")
    with pytest.raises(ValueError, match="grid_k"):
        Settings()


def test_default_settings_give_the_default_inspection_parameters(monkeypatch):
    """The settings and the parameters' own defaults agree (both from core.defaults)."""
    import os

    from pipescan.flows.inspect import InspectionParams
    from pipescan.flows.network import params_from_settings
    from pipescan.settings import Settings

    for name in [k for k in os.environ if k.startswith("PIPESCAN_")]:
        monkeypatch.delenv(name)
    assert params_from_settings(Settings(_env_file=None)) == InspectionParams()


# --- no password in a parameter Prefect keeps ---------------------------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ["inspect-network", "s3://AKIAKEY:Sup3r-Secret@bucket/2026-11"],
        ["inspect", "s3://AKIAKEY:Sup3r-Secret@bucket/2026-11/MH1-MH2.zip"],
        ["deploy", "--store", "s3://AKIAKEY:Sup3r-Secret@bucket/x", "--cron", "0 2 * * *"],
    ],
)
def test_a_url_with_a_password_is_refused_before_it_becomes_a_parameter(args):
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    [line] = result.output.strip().splitlines()
    assert "URL s3://bucket/" in line and "holds a secret" in line
    assert "Sup3r-Secret" not in result.output and "AKIAKEY" not in result.output


def test_a_presigned_url_is_refused_too():
    with pytest.raises(PipescanError, match="holds a secret") as err:
        refuse_password_in_url("https://host/x.zip?versionId=4&X-Amz-Signature=abc123")
    assert "abc123" not in str(err.value)


def test_urls_without_a_password_pass():
    from pipescan.storage.input.urls import url_secret

    for url in ("/data/scans", "s3://bucket/x", "ftp://user@host/x", "memory://a/b"):
        assert url_secret(url) is None, url
        assert refuse_password_in_url(url) is None


# --- the database of a run: from the settings where it runs ------------------------------------


def test_use_settings_sets_settings_for_its_block_only(monkeypatch):
    from pipescan.settings import get_settings, use_settings

    monkeypatch.setenv("PIPESCAN_DATABASE_URL", "sqlite:////env.db")
    with use_settings(database_url="sqlite:////given.db", work_dir=None):
        assert get_settings().database_url == "sqlite:////given.db"
        with use_settings(step_m=0.2):  # nested: adds to the outer block
            assert (get_settings().database_url, get_settings().step_m) == (
                "sqlite:////given.db",
                0.2,
            )
    assert get_settings().database_url == "sqlite:////env.db"


def test_a_scheduled_run_refuses_a_database_the_worker_would_lose(monkeypatch, tmp_path):
    from pipescan.flows import database
    from pipescan.settings import Settings

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(database, "in_deployment", lambda: True)
    with pytest.raises(StorageError, match="no database for this scheduled run") as implicit:
        database.run_database_url(Settings())
    assert implicit.value.field == "PIPESCAN_DATABASE_URL"
    with pytest.raises(StorageError, match="relative SQLite path"):
        database.run_database_url(Settings(database_url="sqlite:///network.db"))
    url = "postgresql+psycopg://pipescan:pw@db/pipescan"
    assert database.run_database_url(Settings(database_url=url)) == url
    # Outside a deployment the default is the command's working folder, as always.
    monkeypatch.setattr(database, "in_deployment", lambda: False)
    assert database.run_database_url(Settings()) == f"sqlite:///{tmp_path / 'pipescan.db'}"


def test_the_flows_take_no_database_url_parameter():
    from pipescan.flows.inspect import inspect_archive
    from pipescan.flows.network import inspect_network

    for flow in (inspect_archive, inspect_network):
        assert not any("database" in name for name in flow.parameters.properties), flow.name


def test_network_reports_are_named_by_date_and_run(monkeypatch, tmp_path):
    from datetime import datetime

    from pipescan.core.errors import PipescanError
    from pipescan.flows import network

    when = datetime(2026, 11, 24, 2, 0)
    assert network_report_name("cerise-lemming", when) == "network-2026-11-24-cerise-lemming.pdf"
    assert network_report_name("../a b", when) == "network-2026-11-24-a-b.pdf"
    assert network_report_name(None, when) == "network-2026-11-24-run.pdf"
    # A scheduled run with a relative reports folder would write into its temporary folder.
    monkeypatch.setattr(network, "in_deployment", lambda: True)
    with pytest.raises(PipescanError, match="PIPESCAN_REPORTS_DIR"):
        network._network_report_out(None, tmp_path.relative_to(tmp_path.parent))
    assert network._network_report_out(str(tmp_path / "n.pdf"), tmp_path) == tmp_path / "n.pdf"
