"""Bounds on what ``rosbags`` may decompress or read for a bag, installed into its readers.

``rosbags`` trusts a bag's sizes: it decompresses a ROS 1 chunk (bz2, lz4) or an MCAP chunk
(zstd, lz4) whole, whatever it expands to, reads an MCAP record of any declared length, reads a
``.db3``'s ``data`` column whatever it is (a ``GENERATED ... zeroblob(N)`` column makes N bytes
per row from nothing), and decompresses a file-compressed ROS 2 bag whole into ``$TMPDIR``. So
pipescan replaces, in ``rosbags``' modules, the few functions that do so with bounded ones:

- a chunk's declared decompressed size (MCAP) is checked against the cap before decompressing,
  and every chunk is decompressed with a running bound (``max_length``), never past the cap;
- the cap is the archive's: ``compression_max_ratio`` times the compressed bytes (once
  :data:`~pipescan.storage.input.limits.RATIO_FLOOR_BYTES` came out), and at most
  ``member_max_bytes``;
- a record or field longer than what is left of the file is refused before it is read;
- a ``.db3``'s ``messages`` table must be a plain table whose columns are all stored;
- a file-compressed ROS 2 bag is decompressed under the same caps, into a folder that pipescan
  made and marked (:data:`SCRATCH_MARKER`) under :func:`scratch_root`, removed when the bag is
  closed, or by the next process that reads a bag after a kill (:func:`sweep_scratch`).

The limits in force are set by :func:`bag_limits` around each read (a context variable, so
threads reading bags with other limits do not mix).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from contextvars import ContextVar
from pathlib import Path

from pipescan.storage.input.limits import DEFAULT_LIMITS, RATIO_FLOOR_BYTES, InputLimits

_LIMITS: ContextVar[InputLimits] = ContextVar("pipescan_bag_limits", default=DEFAULT_LIMITS)
_SMALL_READ = 1 << 20  # reads below this are not worth a seek to check what is left
_INSTALLED = False
_INSTALL_LOCK = threading.Lock()


class BagOverCap(Exception):
    """A bag asked for more than a cap allows; ``cap`` names the limit."""

    def __init__(self, cap: str, what: str) -> None:
        super().__init__(what)
        self.cap, self.what = cap, what


@contextmanager
def bag_limits(limits: InputLimits) -> Iterator[None]:
    """Read bags under ``limits`` within this block (and install the bounds, once)."""
    install()
    token = _LIMITS.set(limits)
    try:
        yield
    finally:
        with suppress(ValueError):  # a generator closed in another context than it began in
            _LIMITS.reset(token)


def expansion_cap(compressed_bytes: int) -> tuple[int, str]:
    """The most ``compressed_bytes`` may expand to, and the cap that sets it."""
    limits = _LIMITS.get()
    by_ratio = max(RATIO_FLOOR_BYTES, int(limits.compression_max_ratio * compressed_bytes))
    if by_ratio < limits.member_max_bytes:
        return by_ratio, "compression_max_ratio"
    return limits.member_max_bytes, "member_max_bytes"


def _decompressor(kind: str):
    if kind == "bz2":
        import bz2

        return bz2.BZ2Decompressor()
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor()
    if kind == "zstd":
        try:
            from compression import zstd  # type: ignore[import-not-found]
        except ImportError:
            from backports import zstd  # type: ignore[no-redef]
        return zstd.ZstdDecompressor()
    raise ValueError(f"unknown compression {kind!r}")


def bounded_decompress(kind: str, data: bytes, declared: int | None = None) -> bytes:
    """``data`` decompressed, refused (:class:`BagOverCap`) as soon as it would pass the cap
    for its size or its ``declared`` size; a stream followed by another (bz2, lz4 frames) is
    decompressed on under the same bound."""
    cap, name = expansion_cap(len(data))
    if declared is not None and declared > cap:
        raise BagOverCap(name, f"a {kind} chunk of {len(data):,} bytes declares {declared:,} "
                               "bytes decompressed")  # fmt: skip
    out = bytearray()
    rest = bytes(data)
    while rest:
        d = _decompressor(kind)
        out += d.decompress(rest, max_length=cap + 1 - len(out))
        if len(out) > cap:
            raise BagOverCap(name, f"a {kind} chunk of {len(data):,} bytes expands past "
                                   f"{cap:,} bytes")  # fmt: skip
        if not d.eof:
            break  # truncated: the reader finds the size mismatch
        rest = d.unused_data
    return bytes(out)


def _left(bio) -> int:
    pos = bio.tell()
    end = bio.seek(0, os.SEEK_END)
    bio.seek(pos)
    return end - pos


def _checked_read(original: Callable, error: type[Exception]) -> Callable:
    def read(bio, size: int, *args):
        if size > _SMALL_READ and size > (left := _left(bio)):
            raise error(f"a record declares {size:,} bytes, but {left:,} are left in the file")
        return original(bio, size, *args)

    return read


class _BoundedReader:
    """A decompressing reader (``zstd.open``) that refuses to give more than the cap for the
    compressed file's size."""

    def __init__(self, raw, compressed_bytes: int) -> None:
        self._raw = raw
        self._cap, self._name = expansion_cap(compressed_bytes)
        self._compressed = compressed_bytes
        self._given = 0

    def read(self, size: int = -1) -> bytes:
        ask = self._cap + 1 - self._given if size is None or size < 0 else size
        data = self._raw.read(min(ask, self._cap + 1 - self._given))
        self._given += len(data)
        if self._given > self._cap:
            raise BagOverCap(self._name, f"a zstd-compressed bag file of {self._compressed:,} "
                                         f"bytes expands past {self._cap:,} bytes")  # fmt: skip
        return data

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._raw.close()


class _Zstd:
    """What ``rosbags.rosbag2.reader`` uses of ``zstd``, bounded."""

    def __init__(self, zstd) -> None:
        self._zstd = zstd

    def decompress(self, data: bytes) -> bytes:
        return bounded_decompress("zstd", data)

    def open(self, bio, mode: str = "rb"):
        size = os.fstat(bio.fileno()).st_size
        return _BoundedReader(self._zstd.open(bio, mode), size)


def scratch_root() -> Path:
    """Where file-compressed bags are decompressed: pipescan's own folder in ``$TMPDIR``."""
    return Path(tempfile.gettempdir()) / "pipescan-bags"


SCRATCH_MARKER = ".pipescan-bag"
"""The marker of a scratch folder of a bag read: the owning process's id and start time."""


def _owner_alive(text: str) -> bool:
    import psutil

    try:
        pid, started = text.split()
        return abs(psutil.Process(int(pid)).create_time() - float(started)) < 1e-3
    except (ValueError, psutil.Error):
        return False


def sweep_scratch() -> None:
    """Remove the scratch folders of bag reads whose process is gone (killed while it read a
    file-compressed bag). Only folders carrying the marker are removed, never a link."""
    root = scratch_root()
    if root.is_symlink() or not root.is_dir():
        return
    for entry in root.iterdir():
        marker = entry / SCRATCH_MARKER
        if entry.is_symlink() or not entry.is_dir() or marker.is_symlink():
            continue
        try:
            text = marker.read_text(encoding="ascii")
        except OSError:  # no marker: not ours, or being created
            continue
        if not _owner_alive(text):
            shutil.rmtree(entry, ignore_errors=True)


class _MarkedScratch:
    """``TemporaryDirectory``'s part that ``rosbags`` uses, as a folder of pipescan's own
    under :func:`scratch_root`, marked with this process (so that the next read removes it
    after a kill); dead readers' folders are swept first."""

    def __init__(self) -> None:
        import psutil

        root = scratch_root()
        root.mkdir(mode=0o700, exist_ok=True)
        if root.is_symlink() or not root.is_dir() or root.stat().st_uid != os.getuid():
            raise OSError(f"{root} is not a folder of this user's")
        sweep_scratch()
        folder = Path(tempfile.mkdtemp(prefix="bag-", dir=root))
        started = psutil.Process().create_time()
        (folder / SCRATCH_MARKER).write_text(f"{os.getpid()} {started!r}", encoding="ascii")
        self.name = str(folder)

    def cleanup(self) -> None:
        shutil.rmtree(self.name, ignore_errors=True)

    def __enter__(self) -> str:
        return self.name

    def __exit__(self, *exc) -> None:
        self.cleanup()


def _checked_sqlite(base: type) -> type:
    class CheckedSqlite3Reader(base):  # type: ignore[misc, valid-type]
        """rosbags' sqlite reader, opening only a ``messages`` table of stored columns."""

        def open(self) -> None:
            check_sqlite_bag(Path(str(self.path)))
            super().open()

    return CheckedSqlite3Reader


def check_sqlite_bag(path: Path) -> None:
    """Refuse a ``.db3`` whose ``messages`` is a view, a virtual table or has a generated or
    hidden column (which makes its bytes from nothing), raising rosbags' ``ReaderError``."""
    import apsw
    from rosbags.rosbag2 import ReaderError

    conn = apsw.Connection(
        f"file:{path}?immutable=1", flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI
    )
    try:
        rows = list(conn.execute("SELECT type, sql FROM sqlite_master WHERE name = 'messages'"))
        if [r[0] for r in rows] != ["table"] or str(rows[0][1]).upper().startswith(
            "CREATE VIRTUAL"
        ):
            raise ReaderError("the messages table is not a plain table")
        for column in conn.execute("PRAGMA table_xinfo(messages)"):
            name, hidden = column[1], column[6]
            if hidden:
                raise ReaderError(
                    f"the messages table's column {name!r} is generated or hidden, not stored"
                )
    finally:
        conn.close()


def install() -> None:
    """Put the bounded functions into ``rosbags``' reader modules (once per process)."""
    global _INSTALLED
    with _INSTALL_LOCK:
        if _INSTALLED:
            return
        import rosbags.rosbag1.reader as r1
        import rosbags.rosbag2.reader as r2
        import rosbags.rosbag2.storage_mcap as mcap

        r1.decompressors[r1.Compression.BZ2.value] = lambda x: bounded_decompress("bz2", x)
        r1.decompressors[r1.Compression.LZ4.value] = lambda x: bounded_decompress("lz4", x)
        r1.read_bytes = _checked_read(r1.read_bytes, r1.ReaderError)
        mcap.DECOMPRESSORS["lz4"] = lambda x, size: bounded_decompress("lz4", x, size)
        mcap.DECOMPRESSORS["zstd"] = lambda x, size: bounded_decompress("zstd", x, size)
        mcap.read_exact = _checked_read(mcap.read_exact, mcap.ReaderError)
        r2.zstd = _Zstd(r2.zstd)
        r2.TemporaryDirectory = _MarkedScratch
        sweep_scratch()
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        checked = _checked_sqlite(Sqlite3Reader)
        for cls in (getattr(r2, n) for n in dir(r2)):
            if isinstance(cls, type) and isinstance(getattr(cls, "STORAGE_PLUGINS", None), dict):
                cls.STORAGE_PLUGINS = {
                    k: checked if v is Sqlite3Reader else v for k, v in cls.STORAGE_PLUGINS.items()
                }
        _INSTALLED = True
