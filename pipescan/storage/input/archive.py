"""Open scan archives: a directory, a ``.zip``, a ``.tar`` or ``.tar.gz``, locally or at an
fsspec URL, laid out as the archive contract in DESIGN.md says.

:func:`open_archive` extracts a file archive safely into a temporary directory (rejecting
absolute paths, ``..`` components, links and device files before anything is written),
reads and validates ``inspection.toml``, and checks the layout: ``frames/`` or one
registered cloud, never both, and every listed frame present. Point files are read later,
one at a time, by :meth:`ScanArchive.read_frame` / :meth:`ScanArchive.iter_frames`; call
:func:`validate_archive` to read them all once, before writing anything anywhere, so that a
bad frame halfway through never leaves half-written results.

Example
-------
>>> with open_archive("runs/MH1042-MH1043.zip") as arc:  # doctest: +SKIP
...     validate_archive(arc)
...     for i, points in arc.iter_frames():
...         ...
"""

from __future__ import annotations

import bz2
import dataclasses
import errno
import gzip
import hashlib
import io
import lzma
import os
import re
import shutil
import stat
import tarfile
import tempfile
import weakref
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path, PurePosixPath
from typing import IO, cast

import numpy as np

from pipescan.core.errors import (
    ArchiveError,
    FetchError,
    MetadataError,
    PipescanError,
    ScratchSpaceError,
)
from pipescan.core.model import FrameRef, InspectionMeta
from pipescan.core.sanitize import strip_credentials
from pipescan.storage.input.limits import (
    DEFAULT_LIMITS,
    RATIO_FLOOR_BYTES,
    InputLimits,
    archive_limit_error,
    format_bytes,
)
from pipescan.storage.input.metadata import INSPECTION_FILE, read_inspection_toml
from pipescan.storage.input.pointfiles import (
    POINT_SUFFIXES,
    is_point_file,
    point_suffix,
    read_points,
)

FRAMES_DIR = "frames"
_COPY_CHUNK_BYTES = 1 << 20
# Files that archiving tools add and that are never content (macOS resource forks, ...).
_JUNK_NAMES = {"__MACOSX", ".DS_Store", "Thumbs.db", "desktop.ini"}
_UNSAFE_HINT = (
    "rebuild the archive with plain relative paths: no absolute paths, no '..', "
    "no symlinks, hardlinks or device files"
)
_OUTSIDE_HINT = (
    "copy the file into the archive folder instead of linking to it; a link may point "
    "only to a file inside the archive"
)


@dataclass(frozen=True)
class ArchiveSummary:
    """What :func:`validate_archive` checked: frames read (0 for a cloud archive) and
    points read (None when point files were not read)."""

    frame_count: int
    point_count: int | None


class ScanArchive:
    """An opened, validated scan archive. Use as a context manager (``with``).

    Attributes
    ----------
    name : str
        The archive as given to :func:`open_archive` (path or URL) without credentials,
        used in messages and records.
    root : pathlib.Path
        The directory holding the (extracted) content: ``inspection.toml``, ``frames/``...
    meta : InspectionMeta
        The metadata, with ``meta.frames`` filled from ``[[frames]]`` or, without it, from
        the point files in ``frames/`` in natural file-name order (``2`` before ``10``).
        Empty for a cloud archive.
    cloud_member : str or None
        The registered cloud's path relative to ``root`` (e.g. ``"cloud.las"``), or None
        for a frames archive.
    limits : InputLimits
        The caps its point files are read under.
    """

    def __init__(
        self,
        *,
        name: str,
        root: Path,
        meta: InspectionMeta,
        cloud_member: str | None,
        tempdir: Path | None = None,
        limits: InputLimits = DEFAULT_LIMITS,
    ) -> None:
        self.name = name
        self.root = root
        self.meta = meta
        self.cloud_member = cloud_member
        self.limits = limits
        self._closed = False
        self._tempdir = tempdir
        # Remove the extraction even if the caller forgets close(): at GC or interpreter exit.
        self._cleanup = (
            weakref.finalize(self, shutil.rmtree, tempdir, ignore_errors=True)
            if tempdir is not None
            else None
        )

    def __enter__(self) -> ScanArchive:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        content = f"{len(self.meta.frames)} frames" if self.has_frames else self.cloud_member
        return f"ScanArchive({self.name!r}, asset_id={self.meta.asset_id!r}, {content})"

    @property
    def is_extracted(self) -> bool:
        """True when ``root`` lies in a temporary directory this object created (a file
        archive unpacked, or a remote one copied); False when ``root`` is the user's own
        directory, used in place."""
        return self._tempdir is not None and self.root.is_relative_to(self._tempdir)

    def detach_extraction(self, dest: Path) -> Path:
        """Move an extracted ``root`` to ``dest`` (so that it outlives :meth:`close`) and
        return where the content now is.

        The user's own directory is never moved: for an archive used in place this returns
        ``root`` unchanged. Only what pipescan itself extracted is ever moved or deleted.
        """
        self._check_open()
        if not self.is_extracted:
            return self.root
        shutil.move(str(self.root), dest)
        self.root = Path(dest)
        return self.root

    @property
    def has_frames(self) -> bool:
        """True for a frames archive, False for a registered-cloud archive."""
        return self.cloud_member is None

    @property
    def frame_count(self) -> int:
        """Number of frames (0 for a cloud archive)."""
        return len(self.meta.frames)

    @cached_property
    def content_hash(self) -> str:
        """SHA-256 (hex) over the sorted member paths and bytes of ``inspection.toml`` and
        the point files in use. The same bytes give the same hash, whatever the container."""
        self._check_open()
        members = [INSPECTION_FILE]
        members += [f.file for f in self.meta.frames]
        if self.cloud_member is not None:
            members.append(self.cloud_member)
        digest = hashlib.sha256()
        for member in sorted(members):
            path = self.root / member
            # Path and size delimit each member, so that bytes cannot shift between members.
            digest.update(member.encode("utf-8") + b"\0")
            digest.update(path.stat().st_size.to_bytes(8, "little"))
            with path.open("rb") as fh:
                while chunk := fh.read(_COPY_CHUNK_BYTES):
                    digest.update(chunk)
        return digest.hexdigest()

    def read_frame(self, i: int) -> np.ndarray:
        """Read frame ``i`` (in ``meta.frames`` order).

        Returns
        -------
        numpy.ndarray
            Shape ``(N, 3)``, float64, metres, in the sensor frame of that frame.

        Raises
        ------
        PointFileError
            The frame file is corrupt, empty, holds NaN/inf or millimetres.
        ArchiveError
            The archive holds a cloud, not frames, or is closed.
        IndexError
            ``i`` is out of range.
        """
        self._check_open()
        if not self.has_frames:
            raise ArchiveError(
                "the archive holds a registered cloud, not frames",
                archive=self.name,
                file=self.cloud_member,
                hint="use read_cloud()",
            )
        if not 0 <= i < len(self.meta.frames):
            raise IndexError(f"frame {i} out of range: the archive has {self.frame_count}")
        ref = self.meta.frames[i]
        return read_points(
            self.root / ref.file,
            archive=self.name,
            member=ref.file,
            kind="frame",
            limits=self.limits,
        )

    def iter_frames(self, indices: Iterable[int] | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(i, points)`` for each frame (or each index in ``indices``), one at a time.

        ``points`` is as :meth:`read_frame` returns; only one frame is in memory at once.
        """
        for i in range(self.frame_count) if indices is None else indices:
            yield i, self.read_frame(i)

    def read_cloud(self) -> np.ndarray:
        """Read the registered cloud.

        Returns
        -------
        numpy.ndarray
            Shape ``(N, 3)``, float64, metres, in the cloud's common frame.

        Raises
        ------
        PointFileError
            The cloud file is corrupt, empty, holds NaN/inf or millimetres.
        ArchiveError
            The archive holds frames, not a cloud, or is closed.
        """
        self._check_open()
        if self.cloud_member is None:
            raise ArchiveError(
                "the archive holds frames, not a registered cloud",
                archive=self.name,
                file=f"{FRAMES_DIR}/",
                hint="use read_frame() or iter_frames()",
            )
        return read_points(
            self.root / self.cloud_member,
            archive=self.name,
            member=self.cloud_member,
            kind="cloud",
            limits=self.limits,
        )

    def close(self) -> None:
        """Remove the temporary extraction, if any. Safe to call more than once."""
        self._closed = True
        if self._cleanup is not None:
            self._cleanup()

    def _check_open(self) -> None:
        if self._closed:
            raise ArchiveError("the archive is closed", archive=self.name)


def open_archive(
    uri: str | Path,
    *,
    workdir: Path | None = None,
    limits: InputLimits = DEFAULT_LIMITS,
    name: str | None = None,
) -> ScanArchive:
    """Open and validate a scan archive.

    Parameters
    ----------
    uri
        A directory, a ``.zip``, ``.tar`` or ``.tar.gz``/``.tgz`` file (recognised by
        content), or an fsspec URL of one (``file://``, ``s3://``, ``memory://`` ...). A
        remote archive is first copied, streamed, to the temporary directory. A single
        top-level folder holding ``inspection.toml`` is looked into.
    workdir
        Where to create the temporary extraction directory (default: the system's).
    limits
        Caps on what the archive may expand to and on its point files (docs/security.md).
    name
        What to call the archive in messages (default: ``uri`` without credentials); a task
        that reopens a staged extraction passes the archive's own name.

    Returns
    -------
    ScanArchive
        Validated: ``inspection.toml`` parsed, the layout checked, every listed frame
        present. Point file *contents* are checked as they are read.

    Raises
    ------
    ArchiveError
        Missing or unreadable archive, an unsafe member ("unsafe path"), a link out of a
        directory archive, a name clash or a name no file system holds, an archive over a
        limit (the error names it), a bad layout (both or neither of ``frames/`` and a
        cloud). Never worth a retry.
    MetadataError
        ``inspection.toml`` missing or invalid, or a ``[[frames]]`` file missing or not a
        point file.
    FetchError
        A remote archive could not be copied (network, credentials, backend).
    ScratchSpaceError
        The work directory could not hold the extraction (full, read-only).
    """
    name = strip_credentials(name if name is not None else str(uri))
    tempdir: Path | None = None
    try:
        local = _local_path(uri, name)
        if local is None:
            tempdir = _make_tempdir(workdir)
            budget = _Budget(limits, name, packed_bytes=None)  # a copy: nothing unpacks
            local = _fetch(str(uri), tempdir / "download", name, budget)
        if not local.exists():
            raise ArchiveError(
                "the archive does not exist", archive=name, hint="check the path or URL"
            )
        if local.is_dir():
            content = local
        else:
            tempdir = tempdir or _make_tempdir(workdir)
            content = tempdir / "content"
            content.mkdir()
            _extract(local, content, name, limits)
            if local.is_relative_to(tempdir):
                local.unlink()  # a downloaded copy: once extracted, it only takes up disk
        root = _find_root(content)
        meta, cloud_member = _inspect_layout(root, name, limits)
        return ScanArchive(
            name=name,
            root=root,
            meta=meta,
            cloud_member=cloud_member,
            tempdir=tempdir,
            limits=limits,
        )
    except BaseException:
        if tempdir is not None:
            shutil.rmtree(tempdir, ignore_errors=True)
        raise


def validate_archive(arc: ScanArchive, *, check_points: bool = True) -> ArchiveSummary:
    """Check a whole archive before anything is processed or written.

    With ``check_points``, every point file is read once, one at a time, and checked as
    :func:`~pipescan.storage.input.pointfiles.read_points` does; the first problem is raised.

    Returns
    -------
    ArchiveSummary
        Frame count, and the total point count (None without ``check_points``).

    Raises
    ------
    PointFileError
        The first corrupt, empty, non-finite or millimetre point file.
    ArchiveError
        A point file vanished since the archive was opened.
    """
    for ref in arc.meta.frames:
        if not (arc.root / ref.file).is_file():
            raise ArchiveError(
                "the frame file is missing (removed since the archive was opened?)",
                archive=arc.name,
                file=ref.file,
                field="points",
            )
    if not check_points:
        return ArchiveSummary(frame_count=arc.frame_count, point_count=None)
    if arc.has_frames:
        total = sum(len(points) for _, points in arc.iter_frames())
    else:
        total = len(arc.read_cloud())
    return ArchiveSummary(frame_count=arc.frame_count, point_count=total)


# --- locating and fetching --------------------------------------------------------------------


def _local_path(uri: str | Path, name: str) -> Path | None:
    """The local path of ``uri``, or None when it is a remote fsspec URL."""
    if isinstance(uri, Path) or "://" not in uri:
        return Path(uri)
    import fsspec
    from fsspec.implementations.local import LocalFileSystem

    try:
        fs, path = fsspec.core.url_to_fs(uri)
    except (ValueError, ImportError) as exc:
        raise ArchiveError(
            f"cannot open the URL: {exc}",
            archive=name,
            hint="check the protocol, and install its fsspec backend (e.g. s3fs for s3://)",
        ) from exc
    except Exception as exc:  # a backend that connects on creation (ftp://, sftp://)
        raise _fetch_error(exc, name) from exc
    return Path(path) if isinstance(fs, LocalFileSystem) else None


def _make_tempdir(workdir: Path | None) -> Path:
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


def _fetch(uri: str, dest: Path, name: str, budget: _Budget) -> Path:
    """Copy a remote archive (file or directory) to ``dest``, streamed; return the local copy.

    The copy counts against ``budget``: a remote folder's files as members, a remote file's
    bytes against the archive's total (an archive never packs to more than it expands to).
    """
    import fsspec

    dest.mkdir(parents=True)
    try:
        fs, path = fsspec.core.url_to_fs(uri)
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
        raise ArchiveError(
            f"cannot open the URL: {exc}",
            archive=name,
            hint="check the protocol, and install its fsspec backend (e.g. s3fs for s3://)",
        ) from exc
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
# errno values of a write into the scratch space that are the work directory's condition,
# and of one that is the member's name (a pre-check missed it): neither is retried.
_SCRATCH_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}
_NAME_ERRNOS = {errno.ENAMETOOLONG, errno.EEXIST, errno.ENOTDIR, errno.EISDIR, errno.EILSEQ}


def _unsafe(member: str, archive: str, why: str) -> ArchiveError:
    return ArchiveError(
        f"unsafe path: member {member!r} {why}; the archive was rejected",
        archive=archive,
        file=member,
        field="path",
        hint=_UNSAFE_HINT,
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
        raise _unsafe(member, archive, "holds a NUL character")
    if normal.startswith("/") or re.match(r"^[A-Za-z]:", normal):
        raise _unsafe(member, archive, "is an absolute path")
    parts = normal.split("/")
    if ".." in parts:
        raise _unsafe(member, archive, "has a '..' component")
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


def _mkdirs(path: Path, budget: _Budget) -> None:
    try:
        # os.makedirs, not Path.mkdir(parents=True): that one recurses once per level.
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise _scratch_error(exc, str(path), budget.archive) from exc


class _Budget:
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
                while chunk := src.read(_COPY_CHUNK_BYTES):
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


def _extract(path: Path, dest: Path, archive: str, limits: InputLimits) -> None:
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
    budget = _Budget(limits, archive, packed_bytes=lambda: packed_total)
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
                    raise _unsafe(info.filename, archive, "is a symlink")
                if stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                    raise _unsafe(info.filename, archive, "is a device or special file")
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
            budget = _Budget(limits, archive, packed_bytes=raw.tell)
            with tarfile.open(fileobj=_TarSource(stream, archive), mode="r:") as tf:
                # One pass, streaming: each member is checked, then written, then the next
                # header is read; a refused member stops the extraction (the caller removes
                # what was written).
                for member in tf:
                    if member.issym():
                        raise _unsafe(member.name, archive, f"is a symlink to {member.linkname!r}")
                    if member.islnk():
                        raise _unsafe(member.name, archive, f"is a hardlink to {member.linkname!r}")
                    if member.issparse():
                        raise _unsafe(member.name, archive, "is a sparse file")
                    if not (member.isfile() or member.isdir()):
                        raise _unsafe(member.name, archive, "is a device or special file")
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


def _find_root(content: Path) -> Path:
    """``content``, or its single top-level folder when that holds ``inspection.toml``."""
    if (content / INSPECTION_FILE).is_file():
        return content
    entries = [e for e in content.iterdir() if not _is_junk(e.name)]
    if len(entries) == 1 and entries[0].is_dir() and (entries[0] / INSPECTION_FILE).is_file():
        return entries[0]
    return content


def _is_junk(name: str) -> bool:
    return name in _JUNK_NAMES or name.startswith(".")


# --- layout -----------------------------------------------------------------------------------


def natural_key(name: str) -> list[int | str]:
    """Sort key that orders digit runs by value: ``f2.las`` before ``f10.las``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _point_files(folder: Path) -> list[str]:
    # Everything but folders: a link, a FIFO or a device named like a point file is listed,
    # so that it is refused by name rather than silently skipped.
    return sorted(
        (p.name for p in folder.iterdir() if not p.is_dir() and not _is_junk(p.name)),
        key=natural_key,
    )


def _layout_error(reason: str, archive: str, member: str, hint: str) -> ArchiveError:
    return ArchiveError(reason, archive=archive, file=member, field="layout", hint=hint)


def _check_inside(root: Path, member: str, archive: str) -> None:
    """Refuse a member of a directory archive that resolves outside the archive's root (a
    symlink, or a folder on its path that is one) or that is not a regular file (a FIFO
    would block the run, a device never ends)."""
    path = root / member
    if not path.exists() and not path.is_symlink():
        return  # missing: reported where it is needed, with its field
    try:
        real = path.resolve(strict=True)
        inside = real.is_relative_to(root.resolve(strict=True))
        regular = stat.S_ISREG(real.stat().st_mode)
    except (OSError, RuntimeError) as exc:  # a dangling link, or a loop of links
        raise _unsafe(member, archive, f"cannot be resolved ({exc})") from exc
    if not inside:
        raise ArchiveError(
            f"unsafe path: member {member!r} links to {str(real)!r}, outside the archive; "
            "the archive was rejected",
            archive=archive,
            file=member,
            field="path",
            hint=_OUTSIDE_HINT,
        )
    if not regular:
        raise _unsafe(member, archive, "is not a regular file (a device, FIFO or socket)")


def _inspect_layout(
    root: Path, name: str, limits: InputLimits
) -> tuple[InspectionMeta, str | None]:
    """Validate the metadata and the layout; return the metadata with frames filled in and
    the registered cloud's member path (None for a frames archive).

    Every file the run will read is checked to lie inside ``root``: extracted archives were
    checked member by member, but a directory archive is used in place and may hold links.
    """
    _check_inside(root, INSPECTION_FILE, name)
    meta = read_inspection_toml(
        root / INSPECTION_FILE, archive=name, max_bytes=limits.metadata_max_bytes
    )
    meta, cloud = _layout(root, name, meta, limits)
    for member in [f.file for f in meta.frames] if cloud is None else [cloud]:
        _check_inside(root, member, name)
    return meta, cloud


def _layout(
    root: Path, name: str, meta: InspectionMeta, limits: InputLimits
) -> tuple[InspectionMeta, str | None]:
    frames_dir = root / FRAMES_DIR
    frame_files = (
        [f for f in _point_files(frames_dir) if is_point_file(f)] if frames_dir.is_dir() else []
    )
    frame_count = max(len(frame_files), len(meta.frames))
    if frame_count > limits.archive_max_members:
        raise archive_limit_error(
            "archive_max_members",
            limits,
            f"the archive has {frame_count:,} frames",
            archive=name,
            file=f"{FRAMES_DIR}/",
        )
    root_points = [f for f in _point_files(root) if is_point_file(f)]
    clouds = [f for f in root_points if PurePosixPath(f).stem.lower() == "cloud"]
    has_frames = bool(meta.frames) or bool(frame_files)

    if len(clouds) > 1:
        raise _layout_error(
            f"holds {len(clouds)} registered clouds ({', '.join(clouds)})",
            name,
            clouds[1],
            hint="keep one cloud.<suffix>",
        )
    if has_frames and clouds:
        raise _layout_error(
            f"holds both {FRAMES_DIR}/ and a registered cloud ({clouds[0]}); keep one",
            name,
            clouds[0],
            hint="an archive holds either the raw frames or one registered cloud",
        )
    if not has_frames:
        if not clouds and len(root_points) > 1:
            raise _layout_error(
                f"has no {FRAMES_DIR}/ and {len(root_points)} point files at its root "
                f"({', '.join(root_points[:5])})",
                name,
                root_points[1],
                hint=f"put frames in {FRAMES_DIR}/, or keep one registered cloud named "
                "cloud.<suffix>",
            )
        cloud = clouds[0] if clouds else (root_points[0] if root_points else None)
        if cloud is None:
            what = (
                f"{FRAMES_DIR}/ holds no point files"
                if frames_dir.is_dir()
                else f"holds neither {FRAMES_DIR}/ nor a registered cloud"
            )
            raise _layout_error(
                what,
                name,
                f"{FRAMES_DIR}/",
                hint=f"add the frames as {FRAMES_DIR}/<name>.<suffix> or one cloud.<suffix>, "
                f"with a suffix among {', '.join(POINT_SUFFIXES)}",
            )
        return meta, cloud

    if meta.frames:
        return dataclasses.replace(meta, frames=_resolve_listed(meta.frames, root, name)), None
    listed = tuple(FrameRef(file=f"{FRAMES_DIR}/{f}") for f in frame_files)
    return dataclasses.replace(meta, frames=listed), None


def _resolve_listed(frames: tuple[FrameRef, ...], root: Path, name: str) -> tuple[FrameRef, ...]:
    """Check every ``[[frames]]`` file is a point file present in the archive."""
    resolved = []
    for i, ref in enumerate(frames):
        field = f"frames[{i}].file"
        if not is_point_file(ref.file):
            raise MetadataError(
                f"{ref.file!r} has the unsupported suffix {point_suffix(ref.file) or '(none)'!r}",
                archive=name,
                file=INSPECTION_FILE,
                field=field,
                hint=f"frames must be point files: {', '.join(POINT_SUFFIXES)}",
            )
        _check_inside(root, ref.file, name)  # a link out, a FIFO: refused, not "missing"
        if not (root / ref.file).is_file():
            # Tolerate a path given relative to frames/ rather than to the root.
            in_frames = f"{FRAMES_DIR}/{ref.file}"
            if (root / in_frames).is_file():
                ref = dataclasses.replace(ref, file=in_frames)
            else:
                raise MetadataError(
                    f"lists {ref.file!r}, which is not in the archive",
                    archive=name,
                    file=INSPECTION_FILE,
                    field=field,
                    hint="add the file, or fix the path (relative to the archive root, "
                    f"e.g. {FRAMES_DIR}/000001.npy)",
                )
        resolved.append(ref)
    return tuple(resolved)
