"""Open scan archives: a directory, a ``.zip``, a ``.tar`` or ``.tar.gz``, locally or at an
fsspec URL, laid out as the archive contract (docs/archive.md) says.

:func:`open_archive` copies a remote archive and extracts a file archive into a temporary
directory (:mod:`pipescan.storage.input.extract`: streaming, under the input limits, refusing
unsafe members), reads and validates ``inspection.toml``, and checks the layout: ``frames/``
or one registered cloud, never both, every listed frame present, and (for a directory used
in place) every file it reads inside the directory, not linked out of it. Point files are
read later, one at a time, by :meth:`ScanArchive.read_frame` / :meth:`ScanArchive.iter_frames`; call
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

import dataclasses
import hashlib
import re
import shutil
import stat
import weakref
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path, PurePosixPath

import numpy as np

from pipescan.core.errors import (
    ArchiveError,
    MetadataError,
)
from pipescan.core.model import FrameRef, InspectionMeta
from pipescan.storage.input.extract import (
    COPY_CHUNK_BYTES,
    Budget,
    extract,
    fetch,
    local_path,
    make_tempdir,
    unsafe,
)
from pipescan.storage.input.limits import (
    DEFAULT_LIMITS,
    InputLimits,
    archive_limit_error,
)
from pipescan.storage.input.metadata import INSPECTION_FILE, read_inspection_toml
from pipescan.storage.input.pointfiles import (
    POINT_SUFFIXES,
    TIMED_FRAME_SUFFIXES,
    PointChunk,
    check_points,
    frame_times_s,
    is_point_file,
    iter_point_chunks,
    point_suffix,
    read_point_time,
    read_points,
    read_timed_frame,
)
from pipescan.storage.input.readers import Where
from pipescan.storage.input.readers.bags import BagIndex, index_bag, is_bag, iter_bag_frames
from pipescan.storage.input.urls import without_secrets

FRAMES_DIR = "frames"
# Files that archiving tools add and that are never content (macOS resource forks, ...).
_JUNK_NAMES = {"__MACOSX", ".DS_Store", "Thumbs.db", "desktop.ini"}
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
    bag : BagIndex or None
        For an archive holding a ROS bag: the bag, its topics and frames (whose
        ``meta.frames`` files read ``"<bag>#<i>"``); None otherwise.
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
        bag: BagIndex | None = None,
    ) -> None:
        self.name = name
        self.root = root
        self.meta = meta
        self.cloud_member = cloud_member
        self.bag = bag
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
        if self.bag is not None:
            bag_path = self.root / self.bag.member
            files = sorted(bag_path.rglob("*")) if bag_path.is_dir() else [bag_path]
            members += [str(f.relative_to(self.root)) for f in files if f.is_file()]
        else:
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
                while chunk := fh.read(COPY_CHUNK_BYTES):
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
        self._check_index(i)
        if self.bag is not None:
            return next(self.iter_frames([i]))[1]
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
        wanted = range(self.frame_count) if indices is None else indices
        if self.bag is None:
            for i in wanted:
                yield i, self.read_frame(i)
            return
        for i, points, _ in self._iter_bag_frames(wanted, None):
            yield i, points

    def _iter_bag_frames(
        self, wanted: Iterable[int], interval_s: float | None
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
        """The bag's frames ``wanted``, checked; with ``interval_s``, each point's time (s)
        from the message's time field, decoded with its points."""
        self._check_open()
        wanted = list(wanted)
        for i in wanted:
            self._check_index(i)
        bag = self.bag
        assert bag is not None
        for i, points, raw, field in iter_bag_frames(
            self.root / bag.member,
            bag,
            wanted,
            archive=self.name,
            limits=self.limits,
            with_time=interval_s is not None,
        ):
            where = Where(self.name, f"{bag.member} ({bag.points_topic}, frame {i})", self.limits)
            check_points(points, archive=where.archive, member=where.member, limits=self.limits)
            time_s = None
            if raw is not None and field is not None and interval_s is not None:
                time_s = frame_times_s(raw, interval_s, where, field=field)
            yield i, points, time_s

    def iter_timed_frames(
        self, indices: Iterable[int] | None = None
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
        """Yield ``(i, points, time_s)`` for each frame (or each index in ``indices``), one at
        a time, each file or message decoded once: ``points`` as :meth:`read_frame`, ``time_s``
        (N,) each point's capture time (s, the file's own time base) where the frame carries
        times and ``[[frames]]`` (or the bag) gives frame times (what deskewing needs); None
        otherwise (formats without times, all points at one time).

        Times come from a LAS/LAZ frame's GPS time (seconds), a PCD field or PLY property
        ``time``, ``timestamp``, ``gps_time`` or ``t``, or a bag's PointCloud2 field ``t``,
        ``time``, ``timestamp`` or ``offset_time``; the unit of the last three kinds is told
        by the frame's span (:func:`~pipescan.core.registration.deskew.point_times_s`).

        Raises
        ------
        PointFileError
            As :meth:`read_frame`; and when a frame's point times span more than
            :data:`~pipescan.core.registration.deskew.FRAME_TIME_SPAN_RATIO` times the
            interval between frames in every unit its field may be in (not one frame's
            times), or its time field is not one number per point, naming the field.
        """
        interval_s = self._frame_interval_s
        if interval_s is None:
            for i, points in self.iter_frames(indices):
                yield i, points, None
            return
        wanted = range(self.frame_count) if indices is None else indices
        if self.bag is not None:
            yield from self._iter_bag_frames(wanted, interval_s)
            return
        self._check_open()
        for i in wanted:
            self._check_index(i)
            ref = self.meta.frames[i]
            if point_suffix(ref.file) not in TIMED_FRAME_SUFFIXES:
                yield i, self.read_frame(i), None
                continue
            points, time_s = read_timed_frame(
                self.root / ref.file,
                interval_s=interval_s,
                archive=self.name,
                member=ref.file,
                limits=self.limits,
            )
            yield i, points, time_s

    @cached_property
    def _frame_interval_s(self) -> float | None:
        """The median time between consecutive frames in ``[[frames]]`` (s), or None when
        some frame has no time or the times do not increase."""
        times = [f.time_s for f in self.meta.frames]
        if len(times) < 2 or any(t is None for t in times):
            return None
        steps = np.diff(np.asarray(times, dtype=np.float64))
        interval = float(np.median(steps))
        return interval if np.isfinite(interval) and interval > 0 else None

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
        return read_points(
            self._cloud_path(),
            archive=self.name,
            member=self.cloud_member,
            kind="cloud",
            limits=self.limits,
        )

    def read_cloud_time(self) -> np.ndarray | None:
        """Each point of the registered cloud's capture time, ``(N,)`` seconds, in the order
        of :meth:`read_cloud`; None when the file holds no time (or all points the same).

        Raises
        ------
        PointFileError
            The cloud's time is corrupt or not finite.
        """
        self._check_open()
        if self.cloud_member is None:
            return None
        time_s = read_point_time(
            self.root / self.cloud_member,
            archive=self.name,
            member=self.cloud_member,
            limits=self.limits,
        )
        if time_s is None or len(time_s) == 0 or float(np.ptp(time_s)) == 0.0:
            return None
        return time_s

    def iter_cloud(
        self, *, with_time: bool = False, chunk_points: int | None = None
    ) -> Iterator[PointChunk]:
        """The registered cloud a chunk at a time (see
        :func:`~pipescan.storage.input.pointfiles.iter_point_chunks`): LAS, LAZ, E57, binary PLY,
        ASCII and ``.npy`` stream, so a cloud of any size is read with one chunk in memory. The same
        points, in the same order, as :meth:`read_cloud`, with each point's time when ``with_time``
        and the file holds one. The cloud's checks raise at the chunk that fails them; the
        millimetre check after the last chunk.

        Raises
        ------
        PointFileError
            As :meth:`read_cloud` and :meth:`read_cloud_time`.
        ArchiveError
            The archive holds frames, not a cloud, or is closed.
        """
        yield from iter_point_chunks(
            self._cloud_path(),
            archive=self.name,
            member=self.cloud_member,
            kind="cloud",
            limits=self.limits,
            chunk_points=chunk_points,
            with_time=with_time,
        )

    def _cloud_path(self) -> Path:
        """The registered cloud's file (checked open, and a cloud archive)."""
        self._check_open()
        if self.cloud_member is None:
            raise ArchiveError(
                "the archive holds frames, not a registered cloud",
                archive=self.name,
                file=f"{FRAMES_DIR}/",
                hint="use read_frame() or iter_frames()",
            )
        return self.root / self.cloud_member

    def close(self) -> None:
        """Remove the temporary extraction, if any. Safe to call more than once."""
        self._closed = True
        if self._cleanup is not None:
            self._cleanup()

    def _check_open(self) -> None:
        if self._closed:
            raise ArchiveError("the archive is closed", archive=self.name)

    def _check_index(self, i: int) -> None:
        if not 0 <= i < self.frame_count:
            raise IndexError(f"frame {i} out of range: the archive has {self.frame_count}")


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
    name = without_secrets(name if name is not None else str(uri))
    tempdir: Path | None = None
    try:
        local = local_path(uri, name)
        if local is None:
            tempdir = make_tempdir(workdir)
            budget = Budget(limits, name, packed_bytes=None)  # a copy: nothing unpacks
            local = fetch(str(uri), tempdir / "download", name, budget)
        if not local.exists():
            raise ArchiveError(
                "the archive does not exist", archive=name, hint="check the path or URL"
            )
        if local.is_dir():
            content = local
        else:
            tempdir = tempdir or make_tempdir(workdir)
            content = tempdir / "content"
            content.mkdir()
            extract(local, content, name, limits)
            if local.is_relative_to(tempdir):
                local.unlink()  # a downloaded copy: once extracted, it only takes up disk
        root = _find_root(content)
        meta, cloud_member, bag = _inspect_layout(root, name, limits)
        return ScanArchive(
            name=name,
            root=root,
            meta=meta,
            cloud_member=cloud_member,
            tempdir=tempdir,
            limits=limits,
            bag=bag,
        )
    except BaseException:
        if tempdir is not None:
            shutil.rmtree(tempdir, ignore_errors=True)
        raise


def validate_archive(arc: ScanArchive, *, check_points: bool = True) -> ArchiveSummary:
    """Check a whole archive before anything is processed or written.

    With ``check_points``, every point file is read once, one at a time, and checked as
    :func:`~pipescan.storage.input.pointfiles.read_points` does, with its points' times where
    it carries them (:meth:`ScanArchive.iter_timed_frames`); the first problem is raised.

    Returns
    -------
    ArchiveSummary
        Frame count, and the total point count (None without ``check_points``).

    Raises
    ------
    PointFileError
        The first corrupt, empty, non-finite or millimetre point file, or one whose points'
        times are not one frame's.
    ArchiveError
        A point file vanished since the archive was opened.
    """
    for ref in [] if arc.bag is not None else arc.meta.frames:
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
        total = sum(len(points) for _, points, _ in arc.iter_timed_frames())
    else:
        total = sum(len(chunk.points) for chunk in arc.iter_cloud())
    return ArchiveSummary(frame_count=arc.frame_count, point_count=total)


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
        raise unsafe(member, archive, f"cannot be resolved ({exc})") from exc
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
        raise unsafe(member, archive, "is not a regular file (a device, FIFO or socket)")


def _inspect_layout(
    root: Path, name: str, limits: InputLimits
) -> tuple[InspectionMeta, str | None, BagIndex | None]:
    """Validate the metadata and the layout; return the metadata with frames filled in and
    the registered cloud's member path (None for a frames archive).

    Every file the run will read is checked to lie inside ``root``: extracted archives were
    checked member by member, but a directory archive is used in place and may hold links.
    """
    _check_inside(root, INSPECTION_FILE, name)
    meta = read_inspection_toml(
        root / INSPECTION_FILE, archive=name, max_bytes=limits.metadata_max_bytes
    )
    bag = _bag_layout(root, name, meta, limits)
    if bag is not None:
        return bag
    meta, cloud = _layout(root, name, meta, limits)
    for member in [f.file for f in meta.frames] if cloud is None else [cloud]:
        _check_inside(root, member, name)
    return meta, cloud, None


def _bag_layout(
    root: Path, name: str, meta: InspectionMeta, limits: InputLimits
) -> tuple[InspectionMeta, None, BagIndex] | None:
    """An archive holding one ROS bag at its root (a ``.bag``, ``.db3`` or ``.mcap`` file,
    or a ROS 2 bag folder): its frames, odometry and IMU from the bag. None without a bag."""
    entries = [e for e in root.iterdir() if not _is_junk(e.name) and e.name != FRAMES_DIR]
    bags = sorted((e.name for e in entries if is_bag(e)), key=natural_key)
    if not bags:
        return None
    if len(bags) > 1:
        raise _layout_error(
            f"holds {len(bags)} ROS bags ({', '.join(bags)})",
            name,
            bags[1],
            hint="keep one bag per archive (one inspection of one pipe run)",
        )
    member = bags[0]
    others = [e.name for e in entries if is_point_file(e.name)]
    if meta.frames or (root / FRAMES_DIR).is_dir() or others:
        raise _layout_error(
            f"holds both the ROS bag {member} and frames or a cloud; keep one",
            name,
            member,
            hint="an archive holds the raw frames, one registered cloud or one bag",
        )
    bag_path = root / member
    for path in sorted(bag_path.rglob("*")) if bag_path.is_dir() else [bag_path]:
        _check_inside(root, str(path.relative_to(root)), name)
    index, frames = index_bag(bag_path, member, archive=name, topics=meta.ros, limits=limits)
    if len(frames) > limits.archive_max_members:
        raise archive_limit_error(
            "archive_max_members",
            limits,
            f"the bag has {len(frames):,} frames",
            archive=name,
            file=member,
        )
    return dataclasses.replace(meta, frames=frames), None, index


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
