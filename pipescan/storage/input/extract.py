"""Getting an archive's content onto local disk, safely: copying a remote archive from its
store, and extracting a zip or tar in one streaming pass.

Nothing is trusted: every member's name is checked (no absolute paths, ``..``, names no file
system holds, clashes), every kind (no links, devices, sparse files), and every byte is
counted against the :class:`~pipescan.storage.input.limits.InputLimits` as it is written,
with the compression ratio so far. A refused archive raises an :class:`ArchiveError` naming
the member and the limit; the caller removes whatever was written (docs/security.md).
"""

from __future__ import annotations

import bz2
import errno
import gzip
import io
import lzma
import os
import re
import stat
import tarfile
import tempfile
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import IO, cast

from pipescan.core.errors import ArchiveError, FetchError, PipescanError, ScratchSpaceError
from pipescan.storage.input.limits import (
    RATIO_FLOOR_BYTES,
    InputLimits,
    archive_limit_error,
    format_bytes,
)
from pipescan.storage.input.urls import is_local, unopened_url_error, url_filesystem

COPY_CHUNK_BYTES = 1 << 20
UNSAFE_HINT = (
    "rebuild the archive with plain relative paths: no absolute paths, no '..', "
    "no symlinks, hardlinks or device files"
)


# --- locating and fetching --------------------------------------------------------------------


def local_path(uri: str | Path, name: str) -> Path | None:
    """The local path of ``uri``, or None when it is a remote fsspec URL."""
    if isinstance(uri, Path) or "://" not in uri:
        return Path(uri)
    try:
        fs, path = url_filesystem(uri, name)
    except ArchiveError:
        raise
    except Exception as exc:  # a backend that connects on creation (ftp://, sftp://)
        raise _fetch_error(exc, name) from exc
    return Path(path) if is_local(fs) else None


def make_tempdir(workdir: Path | None) -> Path:
    try:
        if workdir is not None:
            Path(workdir).mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix="pipescan-archive-", dir=workdir))
    except OSError as exc:
        raise ScratchSpaceError(
            f"cannot create the extraction directory: {exc}",
            file=str(workdir) if workdir else None,
            hint="check PIPESCAN_WORK_DIR: it must be writable and have free space",
        ) from exc


def _fetch_error(exc: BaseException, name: str) -> FetchError:
    return FetchError(
        f"cannot copy the archive: {type(exc).__name__}: {exc}",
        archive=name,
        hint="check the URL, the credentials (give them to the backend, not in the URL) and "
        "that the fsspec backend is installed",
    )


def fetch(uri: str, dest: Path, name: str, budget: Budget) -> Path:
    """Copy a remote archive (file or directory) to ``dest``, streamed; return the local copy.

    The copy counts against ``budget``: a remote folder's files as members, a remote file's
    bytes against the archive's total (an archive never packs to more than it expands to).
    """
    dest.mkdir(parents=True)
    try:
        fs, path = url_filesystem(uri, name)
        if not fs.exists(path):
            raise ArchiveError("the archive does not exist", archive=name, hint="check the URL")
        if fs.isdir(path):
            base = path.rstrip("/")
            for remote in fs.find(base):
                member = budget.add_member(remote[len(base) :].lstrip("/"), is_dir=False)
                target = dest / member
                _mkdirs(target.parent, budget)
                with fs.open(remote, "rb") as src:
                    budget.copy(src, target, member)
            return dest
        target = dest / "archive"
        with fs.open(path, "rb") as src:
            budget.copy(src, target, PurePosixPath(path).name or "archive", packed=True)
        return target
    except (ArchiveError, ScratchSpaceError):
        raise
    except (ValueError, ImportError) as exc:
        raise unopened_url_error(exc, name) from exc
    except Exception as exc:  # whatever the backend raises: typed, named, and its cause kept
        raise _fetch_error(exc, name) from exc


# --- safe extraction --------------------------------------------------------------------------

MAX_NAME_BYTES = 255
"""Longest name of one path component (what Linux, macOS and Windows file systems allow)."""
MAX_PATH_BYTES = 1024
"""Longest member path: far beyond any scan archive's, well within any file system's."""
MAX_PATH_DEPTH = 32
"""Deepest member path (``frames/000001.las`` is 2)."""
_MAX_TAR_READ_BYTES = 8 << 20
"""Largest single read tarfile may make of an archive: a tar header (a long name, a pax
record) that declares more is refused instead of being read into memory."""
# errno values of a write into the scratch space that are the work directory's condition
# (any other is put down to the member's name, which a pre-check missed): never retried.
_SCRATCH_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}


def unsafe(member: str, archive: str, why: str) -> ArchiveError:
    return ArchiveError(
        f"unsafe path: member {member!r} {why}; the archive was rejected",
        archive=archive,
        file=member,
        field="path",
        hint=UNSAFE_HINT,
    )


def _bad_name(member: str, archive: str, why: str, hint: str) -> ArchiveError:
    return ArchiveError(
        f"member {member!r} {why}; the archive was rejected",
        archive=archive,
        file=member,
        field="path",
        hint=hint,
    )


def _check_member_path(member: str, archive: str) -> list[str]:
    """Reject absolute paths, ``..`` components (with either slash) and names no file system
    holds; return the path's components (without ``.`` and empty ones)."""
    normal = member.replace("\\", "/")
    if "\0" in normal:
        raise unsafe(member, archive, "holds a NUL character")
    if normal.startswith("/") or re.match(r"^[A-Za-z]:", normal):
        raise unsafe(member, archive, "is an absolute path")
    parts = normal.split("/")
    if ".." in parts:
        raise unsafe(member, archive, "has a '..' component")
    parts = [p for p in parts if p not in ("", ".")]
    hint = "rename it: shorter names, fewer folder levels"
    for part in parts:
        size = len(part.encode("utf-8", "surrogateescape"))
        if size > MAX_NAME_BYTES:
            raise _bad_name(
                member,
                archive,
                f"has a name of {size} bytes; file systems allow {MAX_NAME_BYTES}",
                hint,
            )
    if len(parts) > MAX_PATH_DEPTH:
        raise _bad_name(
            member[:200] + "...",
            archive,
            f"is {len(parts)} folders deep; pipescan allows {MAX_PATH_DEPTH}",
            hint,
        )
    if len(normal.encode("utf-8", "surrogateescape")) > MAX_PATH_BYTES:
        raise _bad_name(
            member[:200] + "...", archive, f"is longer than {MAX_PATH_BYTES} bytes", hint
        )
    return parts


def _scratch_error(exc: OSError, member: str, archive: str) -> PipescanError:
    """What a failed write into the scratch space is: never a retryable OSError."""
    if exc.errno in _SCRATCH_ERRNOS:
        return ScratchSpaceError(
            f"cannot write the extracted member {member!r}: {exc.strerror}",
            archive=archive,
            hint="free space in PIPESCAN_WORK_DIR (or point it elsewhere), then run again",
        )
    return _bad_name(
        member, archive, f"cannot be written: {exc.strerror}", "rename it in the archive"
    )


def _mkdirs(path: Path, budget: Budget) -> None:
    try:
        # os.makedirs, not Path.mkdir(parents=True): that one recurses once per level.
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise _scratch_error(exc, str(path), budget.archive) from exc


class Budget:
    """What an archive may still expand to, counted as it streams (see InputLimits), and the
    member paths seen so far (a second member at the same path, or a file where a folder
    is, is a name clash)."""

    def __init__(
        self, limits: InputLimits, archive: str, *, packed_bytes: Callable[[], int] | None
    ):
        self.limits = limits
        self.archive = archive
        self.members = 0
        self.total_bytes = 0
        self.packed_bytes = packed_bytes
        self.kinds: dict[str, str] = {}

    def over(self, cap: str, what: str, member: str | None = None) -> ArchiveError:
        return archive_limit_error(cap, self.limits, what, archive=self.archive, file=member)

    def add_member(self, name: str, *, is_dir: bool) -> str:
        """Count and check one member; return its normalised relative path ('' for the
        root itself)."""
        self.members += 1
        if self.members > self.limits.archive_max_members:
            raise self.over(
                "archive_max_members", f"the archive has more than {self.members - 1:,} members"
            )
        parts = _check_member_path(name, self.archive)
        key = "/".join(parts)
        for i in range(1, len(parts)):
            if self.kinds.setdefault("/".join(parts[:i]), "dir") == "file":
                raise self._clash(name, f"is inside {'/'.join(parts[:i])!r}, which is a file")
        before = self.kinds.get(key)
        if key and (before == "file" or (before == "dir" and not is_dir)):
            raise self._clash(name, f"is a second member at the path of a {before}")
        if key:
            self.kinds[key] = "dir" if is_dir else "file"
        return key

    def _clash(self, name: str, why: str) -> ArchiveError:
        return _bad_name(name, self.archive, f"{why} (a name clash)", "keep one member per path")

    def declare(self, member: str, size: int, packed: int | None = None) -> None:
        """Check a member's declared size (and its packed size) before writing it."""
        if size > self.limits.member_max_bytes:
            raise self.over("member_max_bytes", f"the member declares {format_bytes(size)}", member)
        if packed is not None and size > RATIO_FLOOR_BYTES:
            ratio = size / max(packed, 1)
            if ratio > self.limits.compression_max_ratio:
                raise self.over(
                    "compression_max_ratio",
                    f"the member expands {ratio:,.0f}:1 ({format_bytes(packed)} to "
                    f"{format_bytes(size)})",
                    member,
                )

    def copy(self, src: IO[bytes], target: Path, member: str, *, packed: bool = False) -> None:
        """Stream ``src`` to a new file ``target``, counting every byte against the caps."""
        written = 0
        try:
            with target.open("xb") as dst:
                while chunk := src.read(COPY_CHUNK_BYTES):
                    written += len(chunk)
                    self.total_bytes += len(chunk)
                    self._check_stream(member, written, packed=packed)
                    dst.write(chunk)
        except FileExistsError as exc:
            raise self._clash(member, "is a second member at the same path") from exc
        except OSError as exc:
            if exc.errno is None:  # a decompressor's complaint (bz2): the data is corrupt
                raise
            raise _scratch_error(exc, member, self.archive) from exc

    def _check_stream(self, member: str, written: int, *, packed: bool) -> None:
        limits = self.limits
        if packed:  # a packed archive copied from a store: bounded by the total only
            if written > limits.archive_max_bytes:
                raise self.over(
                    "archive_max_bytes", "the packed archive is larger than that", member
                )
            return
        if written > limits.member_max_bytes:
            raise self.over(
                "member_max_bytes", f"the member expands past {format_bytes(written)}", member
            )
        if self.total_bytes > limits.archive_max_bytes:
            raise self.over(
                "archive_max_bytes", f"the archive expands past {format_bytes(self.total_bytes)}"
            )
        if self.packed_bytes is not None and self.total_bytes > RATIO_FLOOR_BYTES:
            ratio = self.total_bytes / max(self.packed_bytes(), 1)
            if ratio > limits.compression_max_ratio:
                raise self.over(
                    "compression_max_ratio",
                    f"the archive expands {ratio:,.0f}:1 so far "
                    f"({format_bytes(self.total_bytes)} out)",
                    member,
                )


_GZIP_MAGIC = b"\x1f\x8b"
_BZIP2_MAGIC = b"BZh"
_XZ_MAGIC = b"\xfd7zXZ\x00"


def extract(path: Path, dest: Path, archive: str, limits: InputLimits) -> None:
    with path.open("rb") as fh:
        magic = fh.read(6)
    if zipfile.is_zipfile(path):
        _extract_zip(path, dest, archive, limits)
    elif magic.startswith((_GZIP_MAGIC, _BZIP2_MAGIC, _XZ_MAGIC)) or _looks_like_tar(path):
        _extract_tar(path, dest, archive, limits)
    else:
        raise ArchiveError(
            "not a directory, .zip, .tar or .tar.gz archive",
            archive=archive,
            hint="give a directory, or pack it with zip or tar",
        )


def _looks_like_tar(path: Path) -> bool:
    """True when the file starts with a valid tar header block (checksum and all)."""
    with path.open("rb") as fh:
        block = fh.read(tarfile.BLOCKSIZE)
    try:
        tarfile.TarInfo.frombuf(block, tarfile.ENCODING, "surrogateescape")
    except (tarfile.HeaderError, ValueError):
        return False
    return True


def _zip_member_count(fh: IO[bytes]) -> int | None:
    """The member count the zip's end record declares, read before the central directory."""
    end = zipfile._EndRecData(fh)  # type: ignore[attr-defined]  # stable since Python 2
    return int(end[zipfile._ECD_ENTRIES_TOTAL]) if end else None  # type: ignore[attr-defined]


def _extract_zip(path: Path, dest: Path, archive: str, limits: InputLimits) -> None:
    packed_total = path.stat().st_size
    budget = Budget(limits, archive, packed_bytes=lambda: packed_total)
    try:
        with path.open("rb") as fh:
            declared = _zip_member_count(fh)
        if declared is not None and declared > limits.archive_max_members:
            raise budget.over("archive_max_members", f"the archive declares {declared:,} members")
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            # Check every member before writing any: names, kinds, declared sizes and ratios
            # (zipfile then never reads past a member's declared sizes).
            declared_total = 0
            keys = []
            for info in infos:
                mode = info.external_attr >> 16  # Unix mode, when a Unix tool wrote the zip
                if stat.S_ISLNK(mode):
                    raise unsafe(info.filename, archive, "is a symlink")
                if stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                    raise unsafe(info.filename, archive, "is a device or special file")
                keys.append(budget.add_member(info.filename, is_dir=info.is_dir()))
                budget.declare(info.filename, info.file_size, info.compress_size)
                declared_total += info.file_size
                if declared_total > limits.archive_max_bytes:
                    raise budget.over(
                        "archive_max_bytes",
                        f"the members declare {format_bytes(declared_total)} in all",
                    )
            for info, key in zip(infos, keys, strict=True):
                target = dest / key
                if info.is_dir() or not key:
                    _mkdirs(target, budget)
                    continue
                _mkdirs(target.parent, budget)
                with zf.open(info) as src:
                    budget.copy(src, target, info.filename)
    except (
        zipfile.BadZipFile,
        zlib.error,
        EOFError,
        NotImplementedError,
        RuntimeError,
        ValueError,
        OSError,
    ) as exc:
        if isinstance(exc, OSError) and exc.errno is not None:
            raise _read_error(exc, archive) from exc
        raise ArchiveError(
            f"cannot extract the zip archive: {exc}",
            archive=archive,
            hint="the archive is corrupt, truncated or encrypted: pack it again",
        ) from exc


def _read_error(exc: OSError, archive: str) -> FetchError:
    """Reading the archive file itself failed (an I/O error of the disk or network share)."""
    return FetchError(f"cannot read the archive: {exc}", archive=archive)


class _TarSource(io.RawIOBase):
    """The decompressed tar stream, as tarfile reads it: refuses a single read larger than
    :data:`_MAX_TAR_READ_BYTES` (a header that declares a huge long name or pax record)."""

    def __init__(self, stream: IO[bytes], archive: str) -> None:
        self._stream = stream
        self._archive = archive

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def read(self, size: int | None = -1) -> bytes:
        if size is None or size < 0 or size > _MAX_TAR_READ_BYTES:
            raise ArchiveError(
                f"a tar header declares {size:,} bytes of metadata (a long name or pax "
                "record), more than any archive needs",
                archive=self._archive,
                field="header",
                hint="the archive is corrupt or crafted: pack it again with tar",
            )
        return self._stream.read(size)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._stream.seek(offset, whence)

    def tell(self) -> int:
        return self._stream.tell()


def _open_decompressed(raw: IO[bytes]) -> IO[bytes]:
    magic = raw.read(6)
    raw.seek(0)
    stream: io.BufferedIOBase | IO[bytes] = raw
    # Returned open: the caller's ``with`` closes it.
    if magic.startswith(_GZIP_MAGIC):
        stream = gzip.GzipFile(fileobj=raw, mode="rb")
    elif magic.startswith(_BZIP2_MAGIC):
        stream = bz2.BZ2File(raw, mode="rb")
    elif magic.startswith(_XZ_MAGIC):
        stream = lzma.LZMAFile(raw, mode="rb")  # noqa: SIM115
    return cast(IO[bytes], stream)


def _extract_tar(path: Path, dest: Path, archive: str, limits: InputLimits) -> None:
    try:
        with path.open("rb") as raw, _open_decompressed(raw) as stream:
            # The raw file's position is how much of the packed archive was read so far.
            budget = Budget(limits, archive, packed_bytes=raw.tell)
            with tarfile.open(fileobj=_TarSource(stream, archive), mode="r:") as tf:
                # One pass, streaming: each member is checked, then written, then the next
                # header is read; a refused member stops the extraction (the caller removes
                # what was written).
                for member in tf:
                    if member.issym():
                        raise unsafe(member.name, archive, f"is a symlink to {member.linkname!r}")
                    if member.islnk():
                        raise unsafe(member.name, archive, f"is a hardlink to {member.linkname!r}")
                    if member.issparse():
                        raise unsafe(member.name, archive, "is a sparse file")
                    if not (member.isfile() or member.isdir()):
                        raise unsafe(member.name, archive, "is a device or special file")
                    key = budget.add_member(member.name, is_dir=member.isdir())
                    target = dest / key
                    if member.isdir() or not key:
                        _mkdirs(target, budget)
                        continue
                    budget.declare(member.name, member.size)
                    _mkdirs(target.parent, budget)
                    src = tf.extractfile(member)
                    assert src is not None  # a regular file
                    with src:
                        budget.copy(src, target, member.name)
    except (tarfile.TarError, EOFError, zlib.error, lzma.LZMAError, ValueError, OSError) as exc:
        if isinstance(exc, OSError) and exc.errno is not None:
            raise _read_error(exc, archive) from exc
        raise ArchiveError(
            f"cannot extract the tar archive: {exc}",
            archive=archive,
            hint="the archive is corrupt or truncated: pack it again",
        ) from exc
