"""A staged archive, registering a chunk of its frames, and measuring a window of placed
points: the work of the register-chunk and measure-window tasks, without Prefect, so that it
also runs in the engine pool's lean worker processes (:mod:`pipescan.tasks.enginepool`)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipescan.core.axis import PipeAxis
from pipescan.core.measures import MeasureParams
from pipescan.core.model import InspectionMeta, SectionMeasures
from pipescan.core.registration import (
    FramePoses,
    RegistrationEvidence,
    RegistrationParams,
    Trajectory,
    register_keyframes,
)
from pipescan.core.registration.deskew import deskew_points, odometer_travel
from pipescan.core.registration.preprocess import crop_range, range_mask
from pipescan.core.sections import ChainageWindow, measure_window
from pipescan.storage.input.archive import ScanArchive
from pipescan.storage.input.limits import DEFAULT_LIMITS, InputLimits
from pipescan.storage.input.readers.bags import BagIndex
from pipescan.storage.scratch import FrameStore, read_window_rows


@dataclass(frozen=True)
class StagedArchive:
    """An archive ready to process: its content as a local directory, its metadata, and the
    limits its point files are read under. ``name`` carries no credentials."""

    name: str
    root: Path
    meta: InspectionMeta
    content_hash: str
    frame_count: int
    cloud_member: str | None
    limits: InputLimits = DEFAULT_LIMITS
    bag: BagIndex | None = None
    """For an archive holding a ROS bag, what :func:`stage_archive` found in it."""

    def reopen(self) -> ScanArchive:
        """The staged archive, as staging validated it. Its layout is not inspected again:
        that parses ``inspection.toml`` and resolves every frame's path, which for 2,000
        frames cost each chunk task as much as registering 20 of its frames."""
        return ScanArchive(
            name=self.name,
            root=self.root,
            meta=self.meta,
            cloud_member=self.cloud_member,
            limits=self.limits,
            bag=self.bag,
        )


def odometer_at(meta: InspectionMeta, i: int) -> float | None:
    """Frame ``i``'s odometer reading, if the archive gives one."""
    return meta.frames[i].odometer_m if meta.frames else None


def crop(points_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """The points within ``max_range_m`` of the sensor (the sections' range)."""
    return crop_range(points_m, max_range_m)


def crop_timed(
    points_m: np.ndarray, time_s: np.ndarray | None, max_range_m: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`crop`, and the kept points' times (None without)."""
    if time_s is None:
        return crop(points_m, max_range_m), None
    keep = range_mask(points_m, max_range_m)
    return np.compress(keep, points_m, axis=0), np.compress(keep, time_s)


def deskewed_by_odometer(
    meta: InspectionMeta, i: int, points_m: np.ndarray, time_s: np.ndarray | None
) -> np.ndarray:
    """Frame ``i``'s points deskewed by the odometer's travel over its interval
    (:func:`~pipescan.core.registration.deskew.odometer_travel`), where its points carry
    times and ``[[frames]]`` gives times and odometer readings: for what is read before
    registration (the survey's instrument). As read otherwise."""
    if time_s is None or not meta.frames:
        return points_m
    times = [f.time_s for f in meta.frames]
    motion = odometer_travel(i, times, [f.odometer_m for f in meta.frames])
    return points_m if motion is None else deskew_points(points_m, time_s, *motion)


def frame_time_at(meta: InspectionMeta, i: int) -> float | None:
    """Frame ``i``'s time in ``[[frames]]``, if the archive gives one."""
    return meta.frames[i].time_s if meta.frames else None


def register_staged_frames(
    staged: StagedArchive,
    first: int,
    last: int,
    params: RegistrationParams,
    frame_store: FrameStore | None = None,
    keep_range_m: float = np.inf,
    stride: int = 1,
) -> Trajectory:
    """Register frames ``first..last`` (inclusive) relative to frame ``first``: with
    ``stride`` k, every k-th of them and the last, and every frame for a while after one
    whose ICP disagreed with the odometer; the frames between are tracked
    (:func:`~pipescan.core.registration.register_keyframes`).

    Every frame of the chunk is decoded once, in order. With ``frame_store``, each frame's
    points within ``keep_range_m`` are written there as they are read, registered or not, so
    that the sections place every frame and never decode the archive again. Only the local
    map and the frames since the last registered one (a share of their points) stay in
    memory. The IMU's gravity direction, when ``[[frames]]`` gives it, holds the roll about
    the axis. A frame whose points carry times (:meth:`ScanArchive.iter_timed_frames`) is
    deskewed before ICP, and its times are kept with its points for the sections.
    """
    meta = staged.meta
    with contextlib.ExitStack() as stack:
        arc = stack.enter_context(staged.reopen())
        keep = None if frame_store is None else stack.enter_context(frame_store.writer(first))

        def frames():
            for i, pts, time_s in arc.iter_timed_frames(range(first, last + 1)):
                if keep is not None:
                    keep.add(i, *crop_timed(pts, time_s, keep_range_m))
                gravity = meta.frames[i].gravity if meta.frames else None
                yield i, pts, odometer_at(meta, i), gravity, time_s, frame_time_at(meta, i)

        return register_keyframes(frames(), first, last, stride, params, along=frame_along(meta))


def frame_along(meta: InspectionMeta) -> list[float | None] | None:
    """What the archive's frames are placed along between registered frames
    (:meth:`~pipescan.core.registration.FramePoses.along_from`)."""
    if not meta.frames:
        return None
    return FramePoses.along_from(
        [f.time_s for f in meta.frames], [f.odometer_m for f in meta.frames]
    )


def measure_placed_window(
    bucket_root: Path,
    window: ChainageWindow,
    axis: PipeAxis,
    nominal_diameter_m: float,
    params: MeasureParams,
    evidence: RegistrationEvidence | None = None,
) -> tuple[list[SectionMeasures], int]:
    """Measure every section of one window from the points placed in its files (with what
    registration says of each); the sections, and the points read."""
    points = read_window_rows(bucket_root, window)
    sections = measure_window(
        points,
        axis,
        window,
        nominal_diameter_m=nominal_diameter_m,
        params=params,
        evidence=evidence,
        section_rows=points,
    )
    return sections, len(points)
