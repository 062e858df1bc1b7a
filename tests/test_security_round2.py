"""Security, round 2 (issue 56): no reader fetches anything, every expansion is bounded by what
was read, no credential passes in any URL form fsspec accepts, temporary files are created
exclusively, and parsing is bounded. The crafted inputs that fit the corpus are in
``tests/hostile.py`` (run by ``tests/test_hostile_inputs.py``); the ones that need a server, a
second process or a planted file are here."""

from __future__ import annotations

import http.server
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import ClassVar

import pytest

from pipescan.core.errors import PointFileError
from pipescan.storage.input.archive import open_archive, validate_archive
from tests import test_gis
from tests.hostile import e57_doctype, e57_shared_section, in_cloud
from tests.test_hostile_inputs import time_limit

ROOT = Path(__file__).resolve().parents[1]


class _Recorder(http.server.BaseHTTPRequestHandler):
    hits: ClassVar[list[str]] = []

    def do_GET(self) -> None:
        self.hits.append(self.path)
        self.send_response(200)
        self.end_headers()
        self.wfile.write(b'<!ENTITY % leak "x">')

    def log_message(self, *args) -> None:
        pass


@pytest.fixture
def http_server():
    """A local HTTP server that records every request (served from a thread of this process:
    the reader runs in a child, since libE57 holds the GIL while it parses)."""
    _Recorder.hits = []
    server = http.server.HTTPServer(("127.0.0.1", 0), _Recorder)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


_VALIDATE = """
import sys
from pipescan.core.errors import PipescanError
from pipescan.storage.input.archive import open_archive, validate_archive
try:
    with open_archive(sys.argv[1]) as arc:
        validate_archive(arc)
    print("accepted")
except PipescanError as exc:
    print(f"refused: {exc}")
"""


def test_an_e57_dtd_is_never_fetched(http_server, tmp_path) -> None:
    """The issue's exploit: an external DTD whose entities would read a local file and send it.
    libE57 fetched ``/d`` before this rule; now the file is refused before libE57 opens it."""
    url = f"http://127.0.0.1:{http_server.server_port}/d"
    given = in_cloud("cloud.e57", e57_doctype(url))(tmp_path, 1.0)
    done = subprocess.run(
        [sys.executable, "-c", _VALIDATE, given],
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.stdout.startswith("refused: "), done.stdout + done.stderr
    assert "DOCTYPE" in done.stdout and "cloud.e57" in done.stdout
    assert _Recorder.hits == []


def test_e57_scans_sharing_a_section_are_refused_naming_the_scan(tmp_path) -> None:
    given = in_cloud("cloud.e57", e57_shared_section(3))(tmp_path, 1.0)
    with pytest.raises(PointFileError) as info, open_archive(given) as arc:
        validate_archive(arc)
    assert info.value.file == "cloud.e57"
    assert info.value.field == "/data3D/vectorChild[1]/points"
    assert "shares its binary section with /data3D/vectorChild[0]/points" in str(info.value)


# --- ROS bags --------------------------------------------------------------------------------

_HOLD_SCRATCH = """
import sys, time
from pathlib import Path
from pipescan.storage.input.readers.bagguard import install
install()
from rosbags.rosbag2 import Reader
with Reader(Path(sys.argv[1])):
    print("open", flush=True)
    time.sleep(60)
"""


def test_a_file_compressed_bag_is_decompressed_into_marked_scratch_swept_after_a_kill(
    tmp_path,
) -> None:
    """A ROS 2 bag folder with ``compression_mode: file`` is decompressed into a run directory
    pipescan marks (not a bare ``$TMPDIR`` folder); killed with ``kill -9`` while it is open, the
    next bag read removes it."""
    from pipescan.storage.input.readers.bagguard import SCRATCH_MARKER, sweep_scratch
    from tests.hostile import ros2_bag

    root = ros2_bag(tmp_path, "sqlite3", "file", {"offsets": (0, 4, 8), "step": 12}, 10)
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    child = subprocess.Popen(
        [sys.executable, "-c", _HOLD_SCRATCH, str(root / "scan")],
        env=dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(tmpdir)),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "open"
        runs = list((tmpdir / "pipescan-bags").iterdir())
        assert len(runs) == 1 and (runs[0] / SCRATCH_MARKER).is_file()
        assert any(p.suffix == ".db3" or p.name.startswith("scan") for p in runs[0].iterdir())
        assert [p for p in tmpdir.iterdir() if p.name != "pipescan-bags"] == []
    finally:
        child.kill()
        child.wait()
    import tempfile

    old = tempfile.tempdir
    tempfile.tempdir = str(tmpdir)
    try:
        sweep_scratch()
    finally:
        tempfile.tempdir = old
    assert list((tmpdir / "pipescan-bags").iterdir()) == []


# --- credentials in every URL form fsspec accepts ----------------------------------------------


def _fsspec_forms() -> list[tuple[str, str, bool]]:
    """``(url, secret, refused)``: every protocol fsspec registers, with a key and secret or a
    user-only token in its authority, alone or as the inner link of a chain, over hosts
    ``urllib`` reads and one it cannot (an unbalanced ``[``). Each form is checked against
    fsspec's own split (``::`` links, :func:`fsspec.core.split_protocol`) to hold the secret in
    a link's authority, where its backend reads credentials."""
    from fsspec.core import split_protocol
    from fsspec.registry import known_implementations

    from pipescan.storage.input.urls import LOGIN_PROTOCOLS

    forms = []
    protocols = sorted(p for p in known_implementations if len(p) > 1 and "::" not in p)
    for protocol in protocols:
        for userinfo, secret in (
            ("AKIAKEY:S3cretValue@", "S3cretValue"),
            ("T0kenValue@", "T0kenValue"),
        ):
            for host in ("bucket", "host:8080", "[::1", "[host"):
                for chain in (
                    "",
                    "simplecache::",
                    "filecache::",
                    "zip://inner.zip::",
                    "blockcache::",
                ):
                    url = f"{chain}{protocol}://{userinfo}{host}/runs/x.zip"
                    links = [split_protocol(link) for link in url.split("::")]
                    assert any(rest.split("/", 1)[0].startswith(userinfo) for _, rest in links)
                    user_only = ":" not in userinfo
                    refused = not (user_only and protocol in LOGIN_PROTOCOLS)
                    forms.append((url, secret, refused))
    return forms


def test_credentials_are_refused_in_every_url_form_fsspec_accepts() -> None:
    from pipescan.core.errors import PipescanError
    from pipescan.flows.network import refuse_password_in_url

    forms = _fsspec_forms()
    assert len(forms) > 1000
    passed = []
    for url, secret, refused in forms:
        try:
            refuse_password_in_url(url, "archive")
        except PipescanError as exc:
            assert refused, f"a login name refused: {url}"
            assert secret not in str(exc), f"the refusal shows the secret: {exc}"
            assert "\n" not in str(exc)
        else:
            if refused:
                passed.append(url)
    assert passed == [], f"{len(passed)} forms passed, e.g. {passed[:5]}"


@pytest.mark.parametrize(
    "url",
    [
        "s3://bucket/runs/x.zip",
        "simplecache::s3://bucket/runs/x.zip",
        "zip://inner.zip::s3://bucket/x.zip",
        "https://host/x.zip?versionId=4",
        "https://host/user@example.org/x.zip",  # an @ in the path, not the authority
        "ftp://surveyor@host/x.zip",  # a login name, not a secret
        "/data/scans/site7.zip",
        "file:///data/scans/site7.zip",
    ],
)
def test_urls_without_a_secret_pass(url) -> None:
    from pipescan.flows.network import refuse_password_in_url

    refuse_password_in_url(url, "archive")


def test_a_secret_query_value_in_a_chain_is_refused() -> None:
    from pipescan.core.errors import PipescanError
    from pipescan.flows.network import refuse_password_in_url

    with pytest.raises(PipescanError, match="holds a secret") as info:
        refuse_password_in_url("simplecache::https://host/x.zip?X-Amz-Signature=abc123", "archive")
    assert "abc123" not in str(info.value)


# --- temporary output files: created exclusively, never a link followed -------------------------


def _plant(folder: Path, names: list[str], victim: Path) -> None:
    """Symlinks to ``victim`` at every name an export used to write through."""
    for name in names:
        (folder / name).symlink_to(victim)


def _victim(tmp_path: Path) -> tuple[Path, bytes]:
    victim = tmp_path / "victim.txt"
    victim.write_bytes(b"precious\n")
    return victim, victim.read_bytes()


def _left_parts(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".part" in p.name or ".tmp" in p.name)


def test_atomic_file_writes_through_no_planted_link_and_opens_no_fifo(tmp_path) -> None:
    from pipescan.storage.atomic import atomic_file

    victim, before = _victim(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    _plant(out, [".a.csv.part"], victim)
    os.mkfifo(out / ".b.csv.part")
    with time_limit(10):
        for name in ("a.csv", "b.csv"):
            with atomic_file(out / name, "w", encoding="utf-8") as fh:
                fh.write("x\n")
    assert victim.read_bytes() == before
    assert (out / "a.csv").read_text() == "x\n" and (out / "b.csv").read_text() == "x\n"
    assert oct((out / "a.csv").stat().st_mode & 0o777) == oct(0o666 & ~_umask())
    # A link at the output's own name is replaced, not written through.
    (out / "c.csv").symlink_to(victim)
    with atomic_file(out / "c.csv") as fh:
        fh.write(b"y")
    assert victim.read_bytes() == before and not (out / "c.csv").is_symlink()


def _umask() -> int:
    old = os.umask(0)
    os.umask(old)
    return old


def test_an_interrupted_atomic_write_leaves_nothing(tmp_path) -> None:
    from pipescan.storage.atomic import atomic_file, atomic_path

    for opener in (atomic_file, atomic_path):
        with pytest.raises(RuntimeError), opener(tmp_path / "x.bin"):
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_csv_export_does_not_write_through_a_planted_link(tmp_path) -> None:
    from pipescan.cli.export import _write_atomically

    victim, before = _victim(tmp_path)
    out = tmp_path / "share"
    out.mkdir()
    _plant(out, [".export.csv.part"], victim)
    os.mkfifo(out / ".export.jsonl.part")
    with time_limit(10):
        assert _write_atomically(out / "export.csv", lambda fh: fh.write("a,b\n")) == 4
        assert _write_atomically(out / "export.jsonl", lambda fh: fh.write("{}\n")) == 3
    assert victim.read_bytes() == before
    assert (out / "export.csv").read_text() == "a,b\n"


@pytest.fixture
def gis_db(tmp_path):
    """test_gis's database of two pipes on an imported GIS layer."""
    yield from test_gis.network.__wrapped__(tmp_path)


def test_gis_and_isybau_exports_do_not_write_through_planted_links(gis_db, tmp_path) -> None:
    from datetime import date

    from pipescan.exports.gis import export_gis
    from pipescan.exports.isybau import IsybauHeader, export_isybau

    engine, _ = gis_db
    victim, before = _victim(tmp_path)
    out = tmp_path / "share"
    (out / "gj").mkdir(parents=True)
    pid = os.getpid()
    _plant(out, [f".net.{pid}.tmp.gpkg", f".sw2.xml.{pid}.tmp"], victim)
    _plant(out / "gj", [f".pipes.{pid}.tmp.geojson", f".defects.{pid}.tmp.geojson"], victim)
    export_gis(engine, out / "net.gpkg")
    export_gis(engine, out / "gj", fmt="geojson")
    export_isybau(engine, out / "sw2.xml", IsybauHeader(date(2026, 12, 1)), asset_id="SW-2")
    assert victim.read_bytes() == before
    assert (out / "net.gpkg").stat().st_size > 0 and (out / "sw2.xml").stat().st_size > 0
    assert _left_parts(out) == [f".net.{pid}.tmp.gpkg", f".sw2.xml.{pid}.tmp"]  # the plants


# --- bounded parsing -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "body",
    [
        pytest.param(lambda: "[" + ".".join(["a"] * 200_000) + "]\n", id="header of 200,000 parts"),
        pytest.param(lambda: "x = " + "[" * 200_000 + "]" * 200_000, id="arrays 200,000 deep"),
        pytest.param(lambda: ".".join(["k"] * 200_000) + " = 1", id="dotted key of 200,000 parts"),
    ],
)
def test_a_deep_toml_is_refused_in_one_line_before_tomllib(body) -> None:
    """tomllib took minutes on the first and raised RecursionError on the second."""
    import time

    from pipescan.core.errors import MetadataError
    from pipescan.storage.input.metadata import parse_inspection_toml

    text = 'asset_id = "A"\ninspected_at = 2024-05-17\nnominal_diameter_m = 0.5\n' + body()
    started = time.perf_counter()
    with pytest.raises(MetadataError, match="more than 32 deep") as info:
        parse_inspection_toml(text, archive="run.zip")
    assert time.perf_counter() - started < 2.0
    assert info.value.field == "line 4" and "\n" not in str(info.value)


def test_toml_that_only_looks_deep_passes() -> None:
    """Dots and brackets inside strings and comments, floats, a genuine ``[[frames]]`` list."""
    from pipescan.storage.input.tomlguard import check_toml_depth

    text = (
        'x = "' + "[{." * 100 + '"\n'
        "y = '''" + "[[[" * 100 + "'''\n"
        "# " + "[." * 100 + "\n"
        "z = ["
        + "1.5, " * 100
        + "]\n"
        + "".join(f'[[frames]]\nfile = "frames/{i}.npy"\ntime_s = {i / 10}\n' for i in range(1000))
    )
    check_toml_depth(text)


# --- no Prefect server left after a kill -------------------------------------------------------

_START_SERVER = """
import os, time
import pipescan.flows  # guards the server
from prefect import flow

@flow
def one():
    return 1

one()
print("ran", flush=True)
time.sleep(120)
"""


def _prefect_env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(
        PYTHONPATH=str(ROOT),
        PREFECT_HOME=str(tmp_path / "prefect-home"),
        PREFECT_SERVER_ANALYTICS_ENABLED="false",
        PREFECT_LOGGING_LEVEL="ERROR",
        # The CLI's allowance (cli._app): Prefect's own 20 s is too short on a loaded machine
        # for a fresh home's migrations, and this test is about the server's end, not its start.
        PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="90",
    )
    return env


def test_a_killed_runs_prefect_server_stops_with_it(tmp_path) -> None:
    """kill -9 of a process on Prefect's ephemeral API, before any scratch marker recorded
    its server: the server gets SIGTERM from the kernel (PR_SET_PDEATHSIG) and ends."""
    import psutil

    from pipescan.flows.housekeeping import OWNER_ENV, PREFECT_SERVER_APP

    child = subprocess.Popen(
        [sys.executable, "-c", _START_SERVER],
        env=_prefect_env(tmp_path),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "ran"
        servers = [
            p for p in psutil.Process(child.pid).children() if PREFECT_SERVER_APP in p.cmdline()
        ]
        assert len(servers) == 1
        assert servers[0].environ()[OWNER_ENV].split()[0] == str(child.pid)
    finally:
        child.kill()
        child.wait()
    _, alive = psutil.wait_procs(servers, timeout=30)
    for proc in alive:
        proc.kill()
    assert alive == [], "the server outlived its killed parent"


def test_the_next_run_stops_a_tagged_server_whose_owner_is_gone(tmp_path) -> None:
    """The fallback when no parent-death signal was set (a server started from a thread):
    a process running Prefect's server app, tagged with an owner that has ended, is stopped;
    one whose owner runs, or without a tag, is left alone."""
    import psutil

    from pipescan.flows.housekeeping import (
        OWNER_ENV,
        PREFECT_SERVER_APP,
        stop_untracked_servers,
    )

    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended_ref = f"{ended.pid} {psutil.Process(ended.pid).create_time()!r}"
    ended.wait()
    me = f"{os.getpid()} {psutil.Process().create_time()!r}"
    fake = [sys.executable, "-c", "import time; time.sleep(60)", PREFECT_SERVER_APP]
    env = dict(os.environ)
    env.pop(OWNER_ENV, None)
    orphan = subprocess.Popen(fake, env={**env, OWNER_ENV: ended_ref})
    owned = subprocess.Popen(fake, env={**env, OWNER_ENV: me})
    untagged = subprocess.Popen(fake, env=env)
    try:
        time.sleep(0.5)  # the children's environment is readable once they exec
        assert stop_untracked_servers() >= 1
        assert orphan.wait(10) is not None
        assert owned.poll() is None and untagged.poll() is None
    finally:
        for proc in (orphan, owned, untagged):
            proc.kill()
            proc.wait()


# --- network import: caps on bytes, features and vertices; metres only -----------------------


def _layer(tmp_path: Path, name: str = "net.gpkg", **kwargs) -> Path:
    return test_gis.write_layer(
        tmp_path / name, test_gis.network_lines(), test_gis.network_fields(), **kwargs
    )


def _refused(path: Path, match: str, field: str, **limits):
    from pipescan.core.errors import LayerError
    from pipescan.storage.input.network_layer import LayerLimits, read_network_layer

    with pytest.raises(LayerError, match=match) as info:
        read_network_layer(path, id_field="FACILITYID", limits=LayerLimits(**limits))
    assert info.value.field == field and info.value.file == str(path)
    assert "\n" not in str(info.value)
    return info.value


def test_a_geopackage_view_or_generated_geometry_is_refused_before_gdal_reads_it(
    tmp_path,
) -> None:
    """An 86 KB GeoPackage whose layer is a view of zeroblobs took 3.9 GB."""
    import sqlite3

    view = _layer(tmp_path, "view.gpkg")
    with sqlite3.connect(view) as conn:
        conn.executescript(
            'ALTER TABLE "pipes" RENAME TO "pipe_rows";'
            'CREATE VIEW "pipes" AS SELECT fid, FACILITYID, zeroblob(400000000) AS geom '
            'FROM "pipe_rows";'
        )
    _refused(view, "is a view, not a table", "layer")
    generated = _layer(tmp_path, "generated.gpkg")
    with sqlite3.connect(generated) as conn:
        conn.executescript(
            'ALTER TABLE "pipes" ADD COLUMN pad BLOB GENERATED ALWAYS AS (zeroblob(400000000)) '
            "VIRTUAL;"
        )
    _refused(generated, "'pad' is generated", "pad")


def test_layer_caps_each_name_their_setting(tmp_path) -> None:
    import zipfile

    import shapely

    path = _layer(tmp_path)
    err = _refused(path, "layer_max_features", "features", layer_max_features=1)
    assert "PIPESCAN_LAYER_MAX_FEATURES" in str(err)
    err = _refused(path, "layer_max_bytes", "size", layer_max_bytes=1000)
    assert "PIPESCAN_LAYER_MAX_BYTES" in str(err)
    long = tmp_path / "long.gpkg"
    line = shapely.LineString([(test_gis.X0 + 0.01 * i, test_gis.Y0) for i in range(20_001)])
    test_gis.write_layer(long, [], {"FACILITYID": ["SW-1"]}, geometries=[line])
    err = _refused(long, "layer_max_vertices", "geometry")
    assert "PIPESCAN_LAYER_MAX_VERTICES" in str(err)
    # A zipped GeoPackage: its declared size, then what it unpacks to, against the cap.
    packed = tmp_path / "net.zip"
    with zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.write(long, "long.gpkg")
    _refused(packed, "the zip declares", "size", layer_max_bytes=long.stat().st_size - 1)
    _refused(packed, "layer_max_vertices", "geometry")  # unpacked, then read as the file


@pytest.mark.parametrize(
    ("crs", "units"),
    [("EPSG:4230", "geographic CRS"), ("EPSG:2227", "US survey foot"), ("EPSG:4326", "geographic")],
)
def test_a_layer_not_in_metres_is_refused(tmp_path, crs, units) -> None:
    _refused(_layer(tmp_path, crs=crs), units, "crs")


def test_a_layer_in_metres_passes(tmp_path) -> None:
    from pipescan.storage.input.network_layer import read_network_layer

    for crs in ("EPSG:25832", "EPSG:3857"):
        layer = read_network_layer(
            _layer(tmp_path, f"{crs[5:]}.gpkg", crs=crs), id_field="FACILITYID"
        )
        assert len(layer.pipes) == len(test_gis.network_lines())


@pytest.mark.slow
def test_a_layer_of_300000_pipes_imports(tmp_path) -> None:
    """Past SQLite's limit on variables (250,000 on Debian's builds): "too many SQL
    variables" before."""
    import numpy as np

    from pipescan.core.network import LayerPipe, NetworkLayer, PipeLine
    from pipescan.storage.database import db
    from pipescan.storage.database.network import import_network_layer

    pipes = tuple(
        LayerPipe(
            f"P{i}", f"A{i}", None, None, PipeLine(np.array([[10.0 * i, 0], [10.0 * i + 5, 0]]))
        )
        for i in range(300_000)
    )
    engine = db.connect(f"sqlite:///{tmp_path / 'net.db'}")
    try:
        result = import_network_layer(engine, NetworkLayer(pipes, "EPSG:25832", "test"))
    finally:
        engine.dispose()
    assert result.stored == 300_000


def test_the_cli_refuses_a_layer_over_a_cap_in_one_line(tmp_path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from pipescan.cli import app

    monkeypatch.setenv("PIPESCAN_LAYER_MAX_FEATURES", "1")
    path = _layer(tmp_path)
    url = f"sqlite:///{tmp_path / 'net.db'}"
    result = CliRunner().invoke(
        app, ["network", "import", str(path), "--id-field", "FACILITYID", "--db", url]
    )
    assert result.exit_code == 2, result.output
    [line] = result.output.strip().splitlines()
    assert (
        line.startswith("error:") and "net.gpkg" in line and "PIPESCAN_LAYER_MAX_FEATURES" in line
    )


# --- an in-memory database keeps nothing -------------------------------------------------------


@pytest.mark.parametrize(
    "url", ["sqlite://", "sqlite:///:memory:", "sqlite:///file:x?mode=memory&uri=true"]
)
def test_an_in_memory_database_is_refused_for_a_run(url) -> None:
    from pipescan.flows.database import refuse_memory_database
    from pipescan.storage.database.db import StorageError

    with pytest.raises(StorageError, match="in-memory SQLite database"):
        refuse_memory_database(url)


def test_inspect_refuses_an_in_memory_database_in_one_line(tmp_path) -> None:
    """``--db sqlite://`` reported "stored inspection 1" and kept nothing."""
    from typer.testing import CliRunner

    from pipescan.cli import app
    from tests.hostile import legit_dir

    root = legit_dir(tmp_path, 1.0)
    result = CliRunner().invoke(app, ["inspect", str(root), "--db", "sqlite://"])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "in-memory SQLite database" in errors[0], result.output
    for file_db in ("sqlite:///rel.db", f"sqlite:///{tmp_path / 'abs.db'}"):
        from pipescan.flows.database import refuse_memory_database

        refuse_memory_database(file_db)


# --- look-alike asset ids ------------------------------------------------------------------------


def _meta(asset_id: str):
    from pipescan.storage.input.metadata import parse_inspection_toml

    text = f'asset_id = "{asset_id}"\ninspected_at = 2024-05-17\nnominal_diameter_m = 0.5\n'
    return parse_inspection_toml(text, archive="run.zip")


def test_asset_ids_are_nfkc_folded() -> None:
    assert _meta("ＭＨ１-MH2").asset_id == "MH1-MH2"  # full-width: one asset with MH1-MH2
    assert _meta("MH1-MH2").asset_id == "MH1-MH2"


def test_a_lookalike_asset_id_is_kept_and_warned_of(caplog) -> None:
    """Cyrillic "МН" against Latin "MH": different letters, so another asset, said so."""
    import logging

    from pipescan.storage.lookalike import skeleton

    with caplog.at_level(logging.WARNING, logger="pipescan"):
        meta = _meta("МН7-MH8")
    assert meta.asset_id == "МН7-MH8"
    [record] = [r for r in caplog.records if "another script" in r.getMessage()]
    assert "Cyrillic Capital Letter Em" in record.getMessage() and "run.zip" in record.getMessage()
    assert skeleton("МН7-MH8") == skeleton("MH7-MH8") != skeleton("MH7-MH9")


def test_the_trend_plot_does_not_write_through_a_planted_link_or_open_a_fifo(tmp_path) -> None:
    from typer.testing import CliRunner

    from pipescan.cli import app
    from pipescan.storage.database.db import connect
    from tests.test_trends import T0, YEAR, save, sections_from, survey

    url = f"sqlite:///{tmp_path / 'trend.db'}"
    engine = connect(url)
    try:
        for year in range(3):
            save(engine, "P1", T0 + year * YEAR, sections_from(list(survey(year, 0.0))))
    finally:
        engine.dispose()
    victim, before = _victim(tmp_path)
    out = tmp_path / "share"
    out.mkdir()
    _plant(out, [".trend.png.part"], victim)
    os.mkfifo(out / ".trend.svg.part")
    with time_limit(60):
        for name in ("trend.png", "trend.svg"):
            result = CliRunner().invoke(
                app, ["trend", "P1", "--plot", str(out / name), "--db", url]
            )
            assert result.exit_code == 0, result.output
    assert victim.read_bytes() == before
    assert (out / "trend.png").read_bytes().startswith(b"\x89PNG")
    assert _left_parts(out) == [".trend.png.part", ".trend.svg.part"]  # only the plants


def test_a_new_asset_that_looks_like_a_stored_one_is_warned_of(tmp_path, caplog) -> None:
    import logging

    from pipescan.storage.database.db import connect
    from tests.test_trends import T0, YEAR, save, sections_from, survey

    engine = connect(f"sqlite:///{tmp_path / 'twins.db'}")
    sections = sections_from(list(survey(0, 0.0)))
    try:
        save(engine, "MH1-MH2", T0, sections)
        with caplog.at_level(logging.WARNING, logger="pipescan"):
            save(engine, "MH1-MH2", T0 + YEAR, sections)  # the same asset: no warning
            assert not [r for r in caplog.records if "looks like" in r.getMessage()]
            save(engine, "МН1-MH2", T0 + YEAR, sections)  # Cyrillic М and Н
    finally:
        engine.dispose()
    [record] = [r for r in caplog.records if "looks like" in r.getMessage()]
    assert "'МН1-MH2' looks like stored asset 'MH1-MH2'" in record.getMessage()


def test_genuine_compressed_bags_are_read_under_the_caps(tmp_path) -> None:
    """The bounds refuse bombs, not bags: a bz2 ROS 1 bag, a zstd MCAP and a file-compressed
    ROS 2 bag of a few real frames open and read, and the scratch is gone afterwards."""
    from pipescan.storage.input.readers.bagguard import scratch_root
    from tests.hostile import frame, ros1_bag, ros2_bag

    data = frame(5000).astype("<f4").tobytes()
    kwargs = {"offsets": (0, 4, 8), "step": 12, "data": data}
    builds = {
        "bz2": lambda w: ros1_bag(w, "bz2", kwargs, 5000),
        "mcap-zstd": lambda w: ros2_bag(w, "mcap", "storage", kwargs, 5000),
        "file-zstd": lambda w: ros2_bag(w, "sqlite3", "file", kwargs, 5000),
    }
    for name, build in builds.items():
        root = build(tmp_path / name)
        with open_archive(root) as arc:
            summary = validate_archive(arc)
        assert summary.point_count == 5000, name
    left = list(scratch_root().iterdir()) if scratch_root().is_dir() else []
    mine = [
        p
        for p in left
        if (p / ".pipescan-bag").is_file()
        and (p / ".pipescan-bag").read_text().split()[0] == str(os.getpid())
    ]
    assert mine == [], "the scratch of a closed bag was left"
