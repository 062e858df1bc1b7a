"""Crafted, hostile inputs: each is refused with a typed error naming what is wrong, nothing is
left written, the input is unchanged, and no error about the input is ever retried.

The corpus is ``tests/hostile.py`` (the bombs built small here; ``benchmarks/bench_hostile.py``
builds them full size and measures peak memory). A Hypothesis fuzz over archive members and
point-file headers checks that whatever the bytes, only pipescan's own errors come out.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import signal
import struct
import tarfile
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipescan.core.errors import FetchError, PipescanError
from pipescan.storage.input.archive import open_archive, validate_archive
from pipescan.storage.input.limits import InputLimits
from pipescan.storage.input.pointfiles import POINT_SUFFIXES, read_points
from pipescan.tasks.retries import is_transient_io_error
from tests.hostile import CASES, TOML, Case, fingerprint, frame

SCALE = 0.01
"""The bombs at 1 % of their size: still far past every ratio and line cap."""

FUZZ_EXAMPLES = int(os.environ.get("PIPESCAN_FUZZ_EXAMPLES", "1"))
"""Multiplies the fuzz tests' examples (a deeper run: ``PIPESCAN_FUZZ_EXAMPLES=20``)."""


@contextlib.contextmanager
def time_limit(seconds: int):
    """Fail an example that does not return (a reader looping on a lying header) instead of
    hanging the suite."""

    def expired(signum, frame):
        raise TimeoutError(f"no answer within {seconds} s: a reader does not terminate")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def test_the_corpus_covers_every_class() -> None:
    classes = {case.cls for case in CASES}
    assert len(CASES) >= 40
    assert classes == {
        "expansion", "lying header", "link", "name", "remote", "text", "fetch", "parse", "value",
    }  # fmt: skip


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_a_hostile_input_is_refused_cleanly(case: Case, tmp_path: Path) -> None:
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    given_ = case.build(inputs, SCALE)
    before = fingerprint(inputs)
    work = tmp_path / "work"
    limits = InputLimits(**case.limits)
    with (
        pytest.raises(PipescanError) as info,
        open_archive(given_, workdir=work, limits=limits) as a,
    ):
        validate_archive(a)
    err = info.value
    assert type(err) is case.error, f"{type(err).__name__}: {err}"
    assert re.search(case.match, str(err)), str(err)
    # One line, no control characters, no credentials: what a user sees.
    assert "\n" not in str(err) and "\x1b" not in str(err)
    # About the input: never retried. Only a remote store that cannot be reached may be.
    assert is_transient_io_error(err) is (case.error is FetchError)
    assert not work.exists() or list(work.iterdir()) == [], "the extraction was left behind"
    assert fingerprint(inputs) == before, "the input was changed"


def test_every_cap_names_its_setting(tmp_path: Path) -> None:
    """Each cap's error names the cap and the variable that raises it."""
    for case in CASES:
        if case.limits:
            cap = case.match
            inputs = tmp_path / cap
            inputs.mkdir()
            given_ = case.build(inputs, SCALE)
            limits = InputLimits(**case.limits)
            with (
                pytest.raises(PipescanError, match=f"PIPESCAN_{cap.upper()}"),
                open_archive(given_, limits=limits) as arc,
            ):
                validate_archive(arc)


def test_a_genuine_archive_passes_under_the_default_caps(tmp_path: Path) -> None:
    """The caps are not in the way of a real archive (here a small one with every format)."""
    root = tmp_path / "scan"
    toml = TOML
    for i, suffix in enumerate(POINT_SUFFIXES):
        from pipescan.storage.input.pointfiles import write_points

        write_points(root / "frames" / f"{i:03d}{suffix}", frame(2000, seed=i))
        toml += f'[[frames]]\nfile = "frames/{i:03d}{suffix}"\n'.encode()
    (root / "inspection.toml").write_bytes(toml)
    with zipfile.ZipFile(tmp_path / "run.zip", "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(root.rglob("*")):
            zf.write(p, p.relative_to(root).as_posix())
    for given_ in (root, tmp_path / "run.zip"):
        with open_archive(given_, workdir=tmp_path / "work") as arc:
            summary = validate_archive(arc)
        assert summary.frame_count == len(POINT_SUFFIXES)
        assert summary.point_count == 2000 * len(POINT_SUFFIXES)


# --- through the CLI: exit 2, one line, nothing stored -------------------------------------------

CLI_CASES = [
    c
    for c in CASES
    if c.name
    in (
        "zip bomb, one member ~1000:1",
        "PLY: 100 M vertices after an empty list element",
        "frame symlinked to a file outside",
        "asset_id with an ESC sequence",
        "zip member name of 300 bytes",
        "E57 XML with an external DTD (http)",
        "ROS 1 bag, bz2 chunk of 50 M points",
        "MCAP record length 2^40",
        "inspection.toml: arrays nested 200,000 deep",
        "inspected_at of year 9999 with an offset",
    )
]


@pytest.fixture(scope="module")
def prefect():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=60):
        yield


@pytest.mark.e2e
@pytest.mark.slow  # ~30 s: a Prefect API for ten runs through the CLI
def test_the_cli_refuses_hostile_inputs_in_one_line(prefect, tmp_path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from pipescan.cli import app
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import list_inspections

    assert len(CLI_CASES) == 10
    monkeypatch.setenv("PIPESCAN_WORK_DIR", str(tmp_path / "work"))
    db = f"sqlite:///{tmp_path / 'pipescan.db'}"
    runner = CliRunner()
    for case in CLI_CASES:
        inputs = tmp_path / f"in-{CLI_CASES.index(case)}"
        inputs.mkdir()
        given_ = case.build(inputs, SCALE)
        before = fingerprint(inputs)
        result = runner.invoke(app, ["inspect", given_, "--db", db])
        assert result.exit_code == 2, (case.name, result.output)
        # Progress lines may come first; the error is one line, the last, and the only one.
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        errors = [line for line in lines if "error" in line.lower()]
        assert errors == [lines[-1]] and lines[-1].startswith("error: archive "), result.stderr
        assert "Traceback" not in result.output
        assert fingerprint(inputs) == before
        assert list((tmp_path / "work").iterdir()) == []
    engine = connect(db)
    try:
        assert list_inspections(engine) == []
    finally:
        engine.dispose()


# --- fuzz: whatever the bytes, only pipescan's errors ---------------------------------------------

_names = st.one_of(
    st.sampled_from(
        [
            "inspection.toml",
            "frames/1.npy",
            "frames/",
            "frames",
            "../x",
            "/abs",
            "a/../../b",
            "frames/1.npy/x",
            "C:/x",
            "frames\\2.xyz",
            "./frames/3.xyz",
            "",
            "frames//4.xyz",
        ]
    ),
    st.text(st.characters(codec="utf-8"), min_size=1, max_size=300),
    st.lists(st.sampled_from(["a", "b", ".", ".."]), min_size=1, max_size=60).map("/".join),
)
_data = st.one_of(
    st.binary(max_size=256),
    st.just(TOML),
    st.sampled_from([b"1 2 3\n4 5 6\n", b"\x93NUMPY", b"ply\n", b"PK\x03\x04"]),
)


@settings(max_examples=150 * FUZZ_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    members=st.lists(st.tuples(_names, _data), min_size=1, max_size=6),
    kind=st.sampled_from(["zip", "tar", "tar.gz"]),
)
def test_fuzz_archive_members(tmp_path_factory, members, kind) -> None:
    where = tmp_path_factory.mktemp("fuzz")
    path = where / f"run.{kind}"
    try:
        if kind == "zip":
            with zipfile.ZipFile(path, "w") as zf, warnings.catch_warnings():
                warnings.simplefilter("ignore")  # duplicate names are welcome here
                for name, data in members:
                    zf.writestr(name or "x", data)
        else:
            with tarfile.open(path, "w:gz" if kind == "tar.gz" else "w") as tf:
                for name, data in members:
                    info = tarfile.TarInfo(name or "x")
                    info.size = len(data)
                    tf.addfile(info, io.BytesIO(data))
    except (ValueError, UnicodeError, OSError, IndexError):
        return  # the writer itself refused these names
    work = where / "work"
    try:
        with time_limit(30), open_archive(path, workdir=work) as arc:
            validate_archive(arc)
    except PipescanError as exc:
        assert not is_transient_io_error(exc), exc
    assert not work.exists() or list(work.iterdir()) == []


def _ply(count: str, fmt: str, elements: str, body: bytes) -> bytes:
    head = f"ply\nformat {fmt} 1.0\n{elements}element vertex {count}\n"
    head += "property float x\nproperty float y\nproperty float z\nend_header\n"
    return head.encode() + body


_counts = st.one_of(
    st.integers(-5, 50).map(str),
    st.sampled_from(["100000000", str(2**63), str(2**64 + 1), "1e9", "", "0x10"]),
)
_headers = st.one_of(
    st.builds(
        lambda c, f, e, b: ("ply", _ply(c, f, e, b)),
        _counts,
        st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "bogus"]),
        st.sampled_from(
            [
                "",
                "element face 0\nproperty list uchar int v\n",
                "element face 2\nproperty list uchar int v\n",
                "element junk 3\nproperty int a\n",
            ]
        ),
        st.binary(max_size=200),
    ),
    st.builds(
        lambda c, d, b: (
            "pcd",
            (
                f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {c}\n"
                f"HEIGHT 1\nPOINTS {c}\nDATA {d}\n"
            ).encode()
            + b,
        ),
        _counts,
        st.sampled_from(["ascii", "binary", "binary_compressed", "bogus"]),
        st.binary(max_size=200),
    ),
    st.builds(
        lambda shape, descr, b: ("npy", _npy(shape, descr) + b),
        st.tuples(st.integers(-1, 10**13), st.integers(-1, 4)),
        st.sampled_from(["<f8", ">f4", "<i4", "|O", "<f8'"]),
        st.binary(max_size=200),
    ),
    st.builds(
        lambda offset, value, suffix: (suffix, _patched_las(suffix, offset, value)),
        st.integers(0, 374),
        st.integers(0, 2**64 - 1),
        st.sampled_from(["las", "laz"]),
    ),
)


def _npy(shape: tuple[int, int], descr: str) -> bytes:
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}".ljust(117)
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header) + 1) + header.encode() + b"\n"


_LAS: dict[str, bytes] = {}


def _patched_las(suffix: str, offset: int, value: int) -> bytes:
    """A valid 10-point LAS/LAZ with 8 bytes of its header overwritten."""
    if suffix not in _LAS:
        from pipescan.storage.input.pointfiles import write_points

        path = Path(os.environ.get("TMPDIR", "/tmp")) / f"pipescan-fuzz-{os.getpid()}.{suffix}"
        write_points(path, frame(10))
        _LAS[suffix] = path.read_bytes()
        path.unlink()
    data = bytearray(_LAS[suffix])
    struct.pack_into("<Q", data, offset, value)
    return bytes(data)


@settings(max_examples=400 * FUZZ_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(header=_headers)
def test_fuzz_point_file_headers(tmp_path_factory, header) -> None:
    """A header of any counts, types and lengths: points that match it, or a PointFileError;
    never another exception, never an allocation the file does not back (a lying count of
    10^13 points would take minutes and terabytes)."""
    suffix, data = header
    path = tmp_path_factory.mktemp("hdr") / f"frame.{suffix}"
    path.write_bytes(data)
    try:
        with time_limit(30):
            points = read_points(path, archive="fuzz.zip", kind="cloud")
    except PipescanError as exc:
        assert not is_transient_io_error(exc)
        return
    assert points.ndim == 2 and points.shape[1] == 3 and np.isfinite(points).all()
    assert points.nbytes <= 24 * max(len(data), 1)


def test_a_full_work_directory_is_typed_and_not_retried(tmp_path, monkeypatch) -> None:
    """ENOSPC while extracting is the work directory's condition: a ScratchSpaceError that
    says so, never retried (a retry 2, 4 and 8 s later finds the disk as full)."""
    import errno

    from pipescan.core.errors import ScratchSpaceError

    zip_path = tmp_path / "run.zip"
    with zipfile.ZipFile(zip_path, "w") as zf:
        zf.writestr("inspection.toml", TOML)
        zf.writestr("frames/1.xyz", b"1 2 3\n" * 1000)

    class FullDisk(io.BytesIO):
        def write(self, data) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

    real_open = Path.open

    def open_on_a_full_disk(self, mode="r", *args, **kwargs):
        return FullDisk() if mode == "xb" else real_open(self, mode, *args, **kwargs)

    monkeypatch.setattr(Path, "open", open_on_a_full_disk)
    with pytest.raises(ScratchSpaceError, match="PIPESCAN_WORK_DIR") as info:
        open_archive(zip_path, workdir=tmp_path / "work")
    assert not is_transient_io_error(info.value)
    assert list((tmp_path / "work").iterdir()) == []


def test_a_remote_folder_is_copied_under_the_caps_but_without_a_ratio(tmp_path) -> None:
    """A folder in a store is copied, not unpacked: large frames pass, too many files do not."""
    import fsspec

    fs = fsspec.filesystem("memory")
    base = "memory://pipescan-remote-folder"
    try:
        fs.pipe(f"{base}/inspection.toml", TOML)
        for i in range(3):
            buf = io.BytesIO()
            np.save(buf, frame(300_000, seed=i))  # 7 MB each, past the 4 MiB ratio floor
            fs.pipe(f"{base}/frames/{i}.npy", buf.getvalue())
        with open_archive(base, workdir=tmp_path / "work") as arc:
            assert validate_archive(arc).point_count == 900_000
        with pytest.raises(PipescanError, match="archive_max_members"):
            open_archive(base, workdir=tmp_path / "work", limits=InputLimits(archive_max_members=3))
        assert list((tmp_path / "work").iterdir()) == []
    finally:
        fs.rm(base, recursive=True)


@pytest.mark.parametrize("engine_processes", [0, 2], ids=["here", "engine-worker"])
def test_a_bad_frame_found_mid_run_names_the_archive_given(tmp_path, engine_processes) -> None:
    """Tasks reopen the staged extraction; an error there still names the user's archive,
    not the scratch directory, also when raised in an engine worker process."""
    from pipescan.core.errors import PointFileError
    from pipescan.core.registration import RegistrationParams
    from pipescan.storage.scratch import create_run_dir
    from pipescan.tasks.inspection import register_chunk
    from pipescan.tasks.storing import stage_archive
    from tests.hostile import ply_list_then_vertices

    zip_path = tmp_path / "site7.zip"
    with zipfile.ZipFile(zip_path, "w") as zf:
        zf.writestr("inspection.toml", TOML)
        zf.writestr("frames/000000.ply", ply_list_then_vertices(tmp_path))
    staged = stage_archive.fn(str(zip_path), create_run_dir(tmp_path / "work"))
    with pytest.raises(PointFileError) as info:
        register_chunk.fn(staged, 0, 0, RegistrationParams(), engine_processes=engine_processes)
    assert info.value.archive == str(zip_path) and info.value.file == "frames/000000.ply"


_timed_headers = st.one_of(
    st.builds(
        lambda c, t, d, b: (
            "pcd",
            (
                f"VERSION 0.7\nFIELDS x y z t\nSIZE 4 4 4 {t[1]}\nTYPE F F F {t[0]}\n"
                f"COUNT 1 1 1 {t[2]}\nWIDTH {c}\nHEIGHT 1\nPOINTS {c}\nDATA {d}\n"
            ).encode()
            + b,
        ),
        _counts,
        st.tuples(st.sampled_from("FIUX"), st.sampled_from([1, 2, 3, 4, 8]), st.integers(0, 3)),
        st.sampled_from(["ascii", "binary", "binary_compressed"]),
        st.binary(max_size=200),
    ),
    st.builds(
        lambda c, t, f, b: ("ply", _ply(c, f, "", b).replace(b"end_header", t + b"end_header")),
        _counts,
        st.sampled_from([b"property uint t\n", b"property double time\n", b"property char t\n"]),
        st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]),
        st.binary(max_size=200),
    ),
)


@settings(max_examples=100 * FUZZ_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(header=_timed_headers)
def test_fuzz_timed_frame_headers(tmp_path_factory, header) -> None:
    """A PCD or PLY frame with a time field of any type, size and count, and any body: points
    and times that match it, or a PointFileError; never another exception or a crash in the
    reader it is handed to."""
    from pipescan.storage.input.pointfiles import read_timed_frame

    suffix, data = header
    path = tmp_path_factory.mktemp("timed") / f"frame.{suffix}"
    path.write_bytes(data)
    try:
        with time_limit(30):
            points, time_s = read_timed_frame(path, interval_s=0.1, archive="fuzz.zip")
    except PipescanError as exc:
        assert not is_transient_io_error(exc)
        return
    assert points.ndim == 2 and points.shape[1] == 3 and np.isfinite(points).all()
    assert time_s is None or time_s.shape == (len(points),)
