"""Scratch space of one inspection run: the frames as read once, and registered points
bucketed by chainage window.

Registration reads (decodes) each frame once. As it streams a chunk of frames, it keeps what
the sections need, each frame's points within the section range as float32 in the sensor frame,
in one file per chunk (``frames/chunk_<first>.f32``, :class:`FrameStore`). Once the poses and
the axis are known, each chunk's stored frames are placed and written into one file per
chainage window (``win_<start_mm>/chunk_<first>.npy``). A window task then reads only its own
files, so peak memory is set by the window, not by the length of the pipe, and chunks never
append to a shared file (they can run in parallel, on other machines).

A frame in float32 keeps a sensor-frame coordinate to better than 1 µm within the 5 m section
range; it is half the bytes of float64 and, unlike a compressed archive, costs no decoding to
read again.

Bucketed points are stored in section coordinates, float32: millimetres along the axis from
the window's start (0.1 µm resolution over a 2 m window), then across and up in the section
plane. A point's chainage and plane position are computed once, when it is bucketed; a window
task reads them as they are.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import socket
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
import psutil

from pipescan.core.axis import PipeAxis
from pipescan.core.npyheader import read_npy_header
from pipescan.core.sections import ChainageWindow

RUN_MARKER = ".pipescan-run"
"""The file that marks a directory as a run's scratch space, created by pipescan."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ProcessRef:
    """One process, by id and start time (seconds since the epoch): together they tell it
    apart from a later process that was given the same id."""

    pid: int
    started: float

    @classmethod
    def of(cls, pid: int) -> ProcessRef:
        return cls(pid, psutil.Process(pid).create_time())

    def is_running(self) -> bool:
        """True while this very process runs (not a later one with the same id)."""
        try:
            proc = psutil.Process(self.pid)
            return (
                abs(proc.create_time() - self.started) < 1.0
                and proc.status() != psutil.STATUS_ZOMBIE
            )
        except psutil.Error:
            return False


@dataclass(frozen=True)
class RunOwner:
    """What a run directory's marker records: the process that owns the run, on which host,
    and helper processes it started for the run (a Prefect API server) that outlive it if
    it is killed."""

    owner: ProcessRef
    host: str
    helpers: tuple[ProcessRef, ...] = field(default=())

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> RunOwner | None:
        try:
            data = json.loads(text)
            return cls(
                owner=ProcessRef(int(data["owner"]["pid"]), float(data["owner"]["started"])),
                host=str(data["host"]),
                helpers=tuple(
                    ProcessRef(int(h["pid"]), float(h["started"])) for h in data["helpers"]
                ),
            )
        except (ValueError, KeyError, TypeError):
            return None


def create_run_dir(work_dir: Path, *, helpers: Sequence[ProcessRef] = ()) -> Path:
    """Create a new, empty scratch directory for one run under ``work_dir`` and mark it.

    Only a directory carrying the marker is ever deleted by :func:`remove_workspace` and
    :func:`sweep_stale_runs`, so a user's folder can never be removed by mistake, whatever it
    is called. The marker records this process and ``helpers`` (see :class:`RunOwner`).
    """
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    owner = RunOwner(ProcessRef.of(os.getpid()), socket.gethostname(), tuple(helpers))
    while True:
        run_dir = work_dir / f"run-{time.time_ns():x}-{os.getpid()}"
        try:
            run_dir.mkdir()
        except FileExistsError:
            continue
        (run_dir / RUN_MARKER).write_text(owner.to_json(), encoding="utf-8")
        return run_dir


@dataclass(frozen=True)
class Sweep:
    """What :func:`sweep_stale_runs` found: the run directories it removed, and the helper
    processes their dead owners had started (still to be stopped, if still running)."""

    removed: tuple[Path, ...]
    orphans: tuple[ProcessRef, ...]


def sweep_stale_runs(work_dir: Path) -> Sweep:
    """Remove the run directories in ``work_dir`` whose owner is no longer running.

    A run killed with ``kill -9`` cannot clean up after itself; the next run does. Only
    directories carrying a run marker written on this host are considered, and only those
    whose owner process (by id and start time) is gone; a user's folder, a symlink, a run of
    another host (on a shared work directory) or a live run is never touched.
    """
    work_dir = Path(work_dir)
    if not work_dir.is_dir():
        return Sweep((), ())
    host = socket.gethostname()
    removed: list[Path] = []
    orphans: list[ProcessRef] = []
    for entry in sorted(work_dir.iterdir()):
        marker = entry / RUN_MARKER
        if entry.is_symlink() or not entry.is_dir() or marker.is_symlink():
            continue
        try:
            text = marker.read_text(encoding="utf-8")
        except OSError:  # no marker (not ours, or being created): leave it
            continue
        owner = RunOwner.from_json(text)
        if owner is None or owner.host != host or owner.owner.is_running():
            continue
        log.info("removing %s: its run (process %d) is gone", entry, owner.owner.pid)
        remove_workspace(entry)
        removed.append(entry)
        orphans += [h for h in owner.helpers if h.is_running()]
    return Sweep(tuple(removed), tuple(orphans))


_FRAME_INDEX = ".index"
_FRAME_TIME = ".time"


class FrameStore:
    """The frames of one run as read once: per chunk, one file of float32 ``(x, y, z)`` rows
    (``chunk_<first>.f32``) and its index (``.f32.index``, int64: each frame's archive index,
    then each frame's first row). Where some frame of the chunk carries point times, a third
    file (``.f32.time``) holds one float32 per row: the point's time after its frame's
    earliest (s; NaN for a frame without times), what deskewing needs.

    Write a chunk with :meth:`writer`; read it back with :meth:`iter_frames`. A chunk's file
    appears under its final name only once all its frames are written.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"FrameStore({str(self.root)!r})"

    def chunk_path(self, first: int) -> Path:
        return self.root / f"chunk_{first:07d}.f32"

    def writer(self, first: int) -> FrameWriter:
        """A writer for the chunk that starts at frame ``first``."""
        self.root.mkdir(parents=True, exist_ok=True)
        return FrameWriter(self.chunk_path(first))

    def has_chunk(self, first: int) -> bool:
        path = self.chunk_path(first)
        return path.is_file() and path.with_name(path.name + _FRAME_INDEX).is_file()

    def iter_frames(
        self, first: int, indices: Sequence[int] | None = None
    ) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(frame_index, points)`` for the frames of the chunk that starts at ``first``
        (all, or those in ``indices``), in order; ``points`` is (N, 3) float32, sensor frame.
        Frames are read one at a time."""
        for i, pts, _ in self.iter_timed_frames(first, indices, with_time=False):
            yield i, pts

    def iter_timed_frames(
        self, first: int, indices: Sequence[int] | None = None, *, with_time: bool = True
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
        """As :meth:`iter_frames`, with each frame's point times: ``(frame_index, points,
        time_s)``, ``time_s`` (N,) float32 seconds after the frame's earliest point, or None
        for a frame stored without times."""
        path = self.chunk_path(first)
        table = np.fromfile(path.with_name(path.name + _FRAME_INDEX), dtype=np.int64)
        frames, starts = table.reshape(2, -1)
        wanted = None if indices is None else set(int(i) for i in indices)
        time_path = path.with_name(path.name + _FRAME_TIME)
        with contextlib.ExitStack() as stack:
            fh = stack.enter_context(path.open("rb"))
            th = (
                stack.enter_context(time_path.open("rb"))
                if with_time and time_path.is_file()
                else None
            )
            for k, i in enumerate(frames[:-1]):
                if wanted is not None and int(i) not in wanted:
                    continue
                rows = int(starts[k + 1] - starts[k])
                fh.seek(int(starts[k]) * 12)
                pts = np.fromfile(fh, dtype=np.float32, count=3 * rows).reshape(rows, 3)
                time_s = None
                if th is not None:
                    th.seek(int(starts[k]) * 4)
                    time_s = np.fromfile(th, dtype=np.float32, count=rows)
                    if rows == 0 or np.isnan(time_s[0]):
                        time_s = None
                yield int(i), pts, time_s

    # A registered cloud is kept as float64 rows (it may be georeferenced: float32
    # would lose millimetres there), and placed in slices of rows.
    def _cloud_path(self) -> Path:
        return self.root / "cloud.f64"

    def save_cloud(self, points_m: np.ndarray | Iterable[np.ndarray]) -> None:
        """Keep a registered cloud, (N, 3) metres (or its chunks, in order), for
        :meth:`read_cloud_rows`. The file gets its name once every chunk is written: an error
        from the chunks' source leaves no cloud behind."""
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = self.root / ".cloud.f64.tmp"
        chunks = [points_m] if isinstance(points_m, np.ndarray) else points_m
        try:
            with tmp.open("wb") as fh:
                for chunk in chunks:
                    np.ascontiguousarray(chunk, dtype=np.float64).reshape(-1, 3).tofile(fh)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        tmp.replace(self._cloud_path())

    def cloud_rows(self) -> int:
        """Points of the kept cloud (0 when there is none)."""
        path = self._cloud_path()
        return path.stat().st_size // 24 if path.is_file() else 0

    def read_cloud_rows(self, first: int, stop: int) -> np.ndarray:
        """Rows ``first`` to ``stop`` (exclusive) of the kept cloud, (K, 3) float64."""
        with self._cloud_path().open("rb") as fh:
            fh.seek(first * 24)
            data = np.fromfile(fh, dtype=np.float64, count=3 * max(0, stop - first))
        return data.reshape(-1, 3)


class FrameWriter:
    """Appends one chunk's frames to its file (see :class:`FrameStore`); a context manager.
    The file gets its final name on a clean exit only."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.tmp")
        self._fh = self._tmp.open("wb")
        self._time_tmp = self.path.with_name(f".{self.path.name}{_FRAME_TIME}.tmp")
        self._th: BinaryIO | None = None
        self._frames: list[int] = []
        self._starts: list[int] = [0]

    def add(self, frame_index: int, points_m: np.ndarray, time_s: np.ndarray | None = None) -> None:
        """Append one frame's (N, 3) points (stored as float32), and its points' times (N,)
        seconds when given (stored after the frame's earliest, float32)."""
        pts = np.ascontiguousarray(points_m, dtype=np.float32).reshape(-1, 3)
        if time_s is not None and self._th is None:
            # The chunk's first timed frame: the frames before it get NaN rows.
            self._th = self._time_tmp.open("wb")
            np.full(self._starts[-1], np.nan, dtype=np.float32).tofile(self._th)
        if self._th is not None:
            if time_s is None:
                rel = np.full(len(pts), np.nan, dtype=np.float32)
            else:
                t = np.asarray(time_s, dtype=np.float64)
                if t.shape != (len(pts),):
                    raise ValueError(f"time_s must have shape ({len(pts)},), got {t.shape}")
                rel = (t - t.min()).astype(np.float32) if len(t) else t.astype(np.float32)
            rel.tofile(self._th)
        pts.tofile(self._fh)
        self._frames.append(int(frame_index))
        self._starts.append(self._starts[-1] + len(pts))

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._fh.close()
        if self._th is not None:
            self._th.close()
        if exc_type is not None:
            self._tmp.unlink(missing_ok=True)
            self._time_tmp.unlink(missing_ok=True)
            return
        if self._th is not None:
            self._time_tmp.replace(self.path.with_name(self.path.name + _FRAME_TIME))
        # Row 0: archive frame indices (with a -1 after the last); row 1: each frame's first row.
        table = np.array([[*self._frames, -1], self._starts], dtype=np.int64)
        index_tmp = self.path.with_name(f".{self.path.name}{_FRAME_INDEX}.tmp")
        table.tofile(index_tmp)
        self._tmp.replace(self.path)
        index_tmp.replace(self.path.with_name(self.path.name + _FRAME_INDEX))


def window_dir(bucket_root: Path, window: ChainageWindow) -> Path:
    return Path(bucket_root) / f"win_{window.start_mm:09d}"


@dataclass(frozen=True)
class Bucketed:
    """What :func:`write_buckets` wrote: how many points, into which windows (their
    ``start_mm``)."""

    points: int = 0
    windows_mm: tuple[int, ...] = ()


PLACE_BLOCK_ROWS = 262_144
"""Points placed at a time. Placing along a bent axis holds about ten temporary arrays the size
of what is placed (float64, three columns): 60 MB for a block of this size, against 330 MB for
a whole chunk of 60 frames of 23,000 points, and 1 GB for a slice of a registered cloud."""


def write_buckets(
    points_world_m: np.ndarray | Iterable[np.ndarray],
    axis: PipeAxis,
    windows: Sequence[ChainageWindow],
    bucket_root: Path,
    tag: str,
) -> Bucketed:
    """Split registered points by chainage window and write them to the windows' files, in
    section coordinates (see :func:`read_window_rows`).

    Points are placed a block of :data:`PLACE_BLOCK_ROWS` at a time, so that what this holds
    is bounded by the block, not by the chunk or the cloud; each block writes one file per
    window it reaches, named so that a window's files sort in the order the points came.

    Parameters
    ----------
    points_world_m : (N, 3) float, or an iterable of them
        Registered points, world frame, metres: one array, or consecutive arrays (a chunk's
        frames, in order), placed without first joining them all.
    axis : PipeAxis
    windows : sequence of ChainageWindow
        Consecutive windows; points outside all of them are dropped.
    bucket_root : Path
        The run's bucket directory.
    tag : str
        Unique per writer (e.g. the chunk's first frame), so parallel writers never collide.

    Returns
    -------
    Bucketed
        Points written, and the windows they went to.
    """
    if not windows:
        return Bucketed()
    written, into = 0, set()
    for k, block in enumerate(_blocks(points_world_m, PLACE_BLOCK_ROWS)):
        n, reached = _write_block(block, axis, windows, bucket_root, f"{tag}-{k:05d}")
        written += n
        into.update(reached)
    return Bucketed(written, tuple(sorted(into)))


def _blocks(points: np.ndarray | Iterable[np.ndarray], rows: int) -> Iterator[np.ndarray]:
    """``points`` in consecutive blocks of about ``rows`` rows (an array: views of it)."""
    if isinstance(points, np.ndarray):
        for start in range(0, len(points), rows):
            yield points[start : start + rows]
        return
    pending: list[np.ndarray] = []
    count = 0
    for part in points:
        pending.append(part)
        count += len(part)
        if count >= rows:
            yield np.concatenate(pending)
            pending, count = [], 0
    if count:
        yield np.concatenate(pending)


def _write_block(
    points_world_m: np.ndarray,
    axis: PipeAxis,
    windows: Sequence[ChainageWindow],
    bucket_root: Path,
    tag: str,
) -> tuple[int, list[int]]:
    if len(points_world_m) == 0:
        return 0, []
    # The one place a point's chainage and section-plane position are computed (along a bent
    # axis, the costly part: a nearest-node search per point).
    chain_m, plane = axis.section_coordinates(points_world_m)
    chain_mm = chain_m * 1000.0
    edges = np.array([w.start_mm for w in windows] + [windows[-1].end_mm], dtype=np.float64)
    which = np.searchsorted(edges, chain_mm, side="right") - 1
    keep = (which >= 0) & (which < len(windows))
    written = 0
    into = []
    # The windows the block reaches, ascending (a count per window: no sort of the block).
    for w_index in np.flatnonzero(np.bincount(which[keep], minlength=len(windows))):
        sel = np.flatnonzero(which == w_index)
        window = windows[int(w_index)]
        rows = np.empty((len(sel), 3), dtype=np.float32)
        rows[:, 0] = chain_mm[sel] - window.start_mm
        # float32 rounding must not carry a point onto the next window's start.
        below_end = np.nextafter(np.float32(window.end_mm - window.start_mm), np.float32(0))
        np.minimum(rows[:, 0], below_end, out=rows[:, 0])
        rows[:, 1:] = plane[sel]
        out_dir = window_dir(bucket_root, window)
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = out_dir / f".{tag}.npy.tmp"
        with tmp.open("wb") as fh:
            np.save(fh, rows)
        tmp.replace(out_dir / f"{tag}.npy")
        written += len(sel)
        into.append(window.start_mm)
    return written, into


def read_window_rows(bucket_root: Path, window: ChainageWindow) -> np.ndarray:
    """All registered points of one window in section coordinates, (N, 3) float32: millimetres
    along the axis from the window's start, then across and up in the section plane (metres).
    Pass them on as ``section_rows``."""
    files = sorted(window_dir(bucket_root, window).glob("*.npy"))
    if not files:
        return np.empty((0, 3), dtype=np.float32)
    # Each file is read straight into its place in the window's array: joining them after
    # held every row twice (67 MB more for a window of 5.6 M rows) and copied them once more.
    layout = [_npy_layout(f) for f in files]
    if any(
        dtype != np.float32 or fortran or shape[1:] != (3,) for _, shape, fortran, dtype in layout
    ):
        return np.concatenate([_read_npy(f) for f in files])
    rows = np.empty((sum(shape[0] for _, shape, _, _ in layout), 3), dtype=np.float32)
    at = 0
    for f, (offset, shape, _, _) in zip(files, layout, strict=True):
        part = rows[at : at + shape[0]]
        if not len(part):
            continue
        with f.open("rb") as fh:
            fh.seek(offset)
            got = fh.readinto(part.data.cast("B"))
        if got != part.nbytes:
            raise ValueError(f"{f}: {got:,} bytes of rows where its header says {part.nbytes:,}")
        at += shape[0]
    return rows


def _npy_layout(path: Path) -> tuple[int, tuple[int, ...], bool, np.dtype]:
    """Where the rows of a scratch ``.npy`` file start, and its shape, order and dtype."""
    with path.open("rb") as fh:
        shape, fortran, dtype = read_npy_header(fh)
        return fh.tell(), shape, fortran, dtype


def _read_npy(path: Path) -> np.ndarray:
    """One scratch file pipescan wrote itself, read with the header parsed under
    :mod:`pipescan.core.npyheader`'s lock (windows are read from several threads)."""
    with path.open("rb") as fh:
        shape, fortran, dtype = read_npy_header(fh)
        data = np.fromfile(fh, dtype=dtype, count=int(np.prod(shape)))
    return data.reshape(shape, order="F" if fortran else "C")


def remove_workspace(path: Path) -> None:
    """Delete a run's scratch directory made by :func:`create_run_dir` (safe if it does not
    exist). A directory without the run marker, or a symlink, is left alone and logged: it
    was not made by pipescan."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    if path.is_symlink() or not (path / RUN_MARKER).is_file():
        log.warning("not deleting %s: it is not a pipescan run directory", path)
        return
    # The marker goes last, and only once nothing else is left: a task still writing (an
    # interrupted run's threads, an engine worker finishing its chunk) may create files while
    # this runs, and a directory that lost its marker could never be swept again.
    marker = (path / RUN_MARKER).read_text(encoding="utf-8")
    for entry in list(path.iterdir()):
        if entry.name == RUN_MARKER:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
    if any(entry.name != RUN_MARKER for entry in path.iterdir()):
        log.info("%s is still being written to: the next run removes it", path)
        return
    (path / RUN_MARKER).unlink(missing_ok=True)
    try:
        path.rmdir()
    except OSError:  # written to in the last instant: marked again, for the next run
        (path / RUN_MARKER).write_text(marker, encoding="utf-8")
        log.info("%s was written to as it was removed: the next run removes it", path)
