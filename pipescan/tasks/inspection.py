"""Prefect tasks of one archive's inspection: thin wrappers over core and storage.

Each task reads its input, calls core or storage, and returns a small value (paths, ids, small
dataclasses). Only I/O is retried; geometry errors are deterministic and fail at once.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from pipescan.core.axis import PipeAxis, axis_direction, fit_axis
from pipescan.core.coding import code_sections
from pipescan.core.grading import choose_grading, grade_sections, load_table, merge_defects
from pipescan.core.instrument import (
    Instrument,
    consecutive_frame_indices,
    estimate_instrument,
    partial_view_stride,
)
from pipescan.core.measures import MeasureParams
from pipescan.core.model import Defect, SectionMeasures
from pipescan.core.registration import (
    FrameStride,
    PlacedShare,
    RegistrationEvidence,
    RegistrationParams,
    Trajectory,
    choose_frame_stride,
    choose_placed_share,
    iter_registered_points,
    sample_frame_indices,
)
from pipescan.core.sections import ChainageWindow
from pipescan.core.start import cloud_start, sensor_ahead_m
from pipescan.core.water import SensorSight, sensor_sight
from pipescan.storage.input.pointfiles import StridedSample
from pipescan.storage.scratch import (
    Bucketed,
    FrameStore,
    write_buckets,
)
from pipescan.tasks import enginepool
from pipescan.tasks.memory import releases_memory
from pipescan.tasks.retries import IO_RETRY_OPTIONS
from pipescan.tasks.staged import (
    StagedArchive,
    crop_timed,
    deskewed_by_odometer,
    frame_along,
    measure_placed_window,
    register_staged_frames,
)

log = logging.getLogger("pipescan")


@dataclass(frozen=True)
class AxisFit:
    """The fitted axis, the chainage range the scan covers, and where its start came from
    (a key of ``pipescan.core.start.START_SOURCES``)."""

    axis: PipeAxis
    chainage_min_m: float
    chainage_max_m: float
    start_source: str = "first_frame"
    start_uncertainty_m: float = 0.0


@task(name="register-chunk", cache_policy=NO_CACHE)
def register_chunk(
    staged: StagedArchive,
    first: int,
    last: int,
    params: RegistrationParams,
    frame_store: FrameStore | None = None,
    keep_range_m: float = np.inf,
    engine_processes: int = 0,
    stride: int = 1,
) -> Trajectory:
    """Register frames ``first..last`` (inclusive; every ``stride``-th and the last) relative
    to frame ``first`` (:func:`pipescan.tasks.staged.register_staged_frames`), in this process
    or, with ``engine_processes`` > 0, in one of the engine pool's worker processes."""
    args = (staged, first, last, params, frame_store, keep_range_m, stride)
    if engine_processes:
        trajectory = enginepool.run(engine_processes, register_staged_frames, *args)
    else:
        trajectory = register_staged_frames(*args)
    held = sum(q.degenerate for q in trajectory.quality)
    log.info("registered frames %d-%d of %d (%s)", first, last, staged.frame_count, params.label)
    untracked = trajectory.frames_not_tracked
    if untracked:
        log.warning(
            "frames %d-%d: %d frame(s) between registered ones could not be tracked on the "
            "local map; they are not placed",
            first, last, untracked,
        )  # fmt: skip
    if held and trajectory.along_axis_prior != "odometer":
        log.warning(
            "frames %d-%d: %d frame(s) without odometer and without geometry along the axis; "
            "their chainage is extrapolated, not measured",
            first, last, held,
        )  # fmt: skip
    return trajectory


@dataclass(frozen=True)
class ScanSurvey:
    """What a first look at a scan's frames decides: its instrument and the frames to read."""

    instrument: Instrument
    stride: FrameStride
    placed: PlacedShare


@task(name="survey-scan", cache_policy=NO_CACHE)
def survey_scan(
    staged: StagedArchive,
    *,
    max_range_m: float,
    step_m: float,
    section_points: int,
    keyframe_distance_m: float,
    frame_stride: int | None = None,
    placed_share: float | None = None,
) -> ScanSurvey:
    """The scan's instrument (:func:`~pipescan.core.instrument.estimate_instrument`:
    ``inspection.toml``'s ``[sensor]`` where it says, the frames otherwise) and which frames
    the run reads and registers (``frame_stride`` when set; every frame when one frame covers
    part of the view; else :func:`~pipescan.core.registration.choose_frame_stride`), from a
    few frames spread over the run and a run of consecutive ones from its middle, each
    decoded once."""
    meta, n = staged.meta, staged.frame_count
    sample_at, run_at = sample_frame_indices(n), consecutive_frame_indices(n)
    with staged.reopen() as arc:
        # Deskewed where the points carry times: a frame's motion reads as range noise.
        read = {
            i: deskewed_by_odometer(meta, i, pts, time_s)
            for i, pts, time_s in arc.iter_timed_frames(sorted(set(sample_at) | set(run_at)))
        }
    sample = [read[i] for i in sample_at]
    instrument = estimate_instrument(
        sample, [read[i] for i in run_at], max_range_m=max_range_m, profile=meta.sensor
    )
    log.info(instrument.describe())
    odometer = [f.odometer_m for f in meta.frames] if meta.frames else None
    if frame_stride:
        stride = FrameStride(frame_stride, "set for the run")
    else:
        stride = partial_view_stride(instrument) or choose_frame_stride(
            sample,
            odometer,
            max_range_m=max_range_m,
            step_m=step_m,
            section_points=section_points,
            keyframe_distance_m=keyframe_distance_m,
        )
    log.info(stride.describe(n))
    placed = (
        PlacedShare(placed_share)
        if placed_share
        else choose_placed_share(
            sample,
            odometer,
            max_range_m=max_range_m,
            step_m=step_m,
            section_points=section_points,
        )
    )
    log.info(placed.describe())
    return ScanSurvey(instrument, stride, placed)


def _frame_points_world(
    arc,
    trajectory: Trajectory,
    indices,
    max_range_m: float,
    along=None,
    placed_share=1.0,
    early_return_ratio=0.0,
):
    def cropped():
        for i, pts, time_s in arc.iter_timed_frames(indices):
            yield i, *crop_timed(pts, time_s, max_range_m)

    times = [f.time_s for f in arc.meta.frames]
    yield from iter_registered_points(
        cropped(),
        trajectory,
        along,
        times,
        placed_share=placed_share,
        early_return_ratio=early_return_ratio,
    )


def _stored_frames(
    frame_store: FrameStore, chunks: Sequence[tuple[int, int]], indices: Sequence[int]
) -> Iterator[tuple[int, np.ndarray]]:
    """Frames ``indices`` (ascending) as the registration pass stored them (cropped)."""
    wanted = sorted(set(indices))
    for first, last in chunks:
        mine = [i for i in wanted if first <= i <= last]
        wanted = [i for i in wanted if i > last]
        if mine:
            yield from frame_store.iter_frames(first, mine)


CLOUD_SAMPLE_POINTS = 2_000_000
"""A registered cloud's axis, start and chainage range come from a uniform stride through it
of at most this many points (48 MB), read in the one pass that keeps the cloud for the
sections: memory does not grow with the cloud. The axis fit itself takes 200,000 of them. On
the 49 M-point 30 m cloud (1 point in 32) every point's chainage moved by 0.08 mm against the
whole cloud, the start and the range's ends by up to 1 mm (docs/throughput.md, *A registered
cloud in one pass*)."""


CLOUD_PROGRESS_POINTS = 20_000_000
"""A progress line each time this many more of a cloud's points are read."""


def _cloud_sample(arc, frame_store: FrameStore | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the registered cloud once, in chunks: keep it in ``frame_store`` for the sections
    (when given) and return a strided sample of its points and their times (None when the
    file holds none, or every point has the same)."""
    sample = StridedSample(CLOUD_SAMPLE_POINTS)

    def chunks() -> Iterator[np.ndarray]:
        read = 0
        for chunk in arc.iter_cloud(with_time=True):
            sample.add(chunk.first, chunk.points, chunk.time_s)
            yield chunk.points
            read += len(chunk.points)
            if read // CLOUD_PROGRESS_POINTS > (read - len(chunk.points)) // CLOUD_PROGRESS_POINTS:
                log.info("read %s points of the cloud", f"{read:,}")
        share = "every point" if sample.stride == 1 else f"1 point in {sample.stride}"
        log.info("read the cloud: %s points; its axis comes from %s", f"{read:,}", share)

    if frame_store is not None:  # decoded once: the sections read it from here
        frame_store.save_cloud(chunks())
    else:
        for _ in chunks():
            pass
    points, time_s = sample.columns()
    assert points is not None
    if time_s is not None and float(np.ptp(time_s)) == 0.0:
        time_s = None
    return points, time_s


@task(name="fit-axis", cache_policy=NO_CACHE)
def fit_pipe_axis(
    staged: StagedArchive,
    trajectory: Trajectory | None,
    *,
    max_range_m: float,
    sample_frames: int = 40,
    frame_store: FrameStore | None = None,
    chunks: Sequence[tuple[int, int]] = (),
    workers: int = 1,
) -> AxisFit:
    """Fit the pipe axis on a sample of the registered points, and the chainage they span.

    A registered cloud's start is chosen by ``pipescan.core.start.cloud_start``; up is the
    cloud's +z. For frames, up is against the IMU's gravity at the first frame, where given,
    else the first frame's +z. With ``frame_store`` (written by :func:`register_chunk` for
    ``chunks``, cropped to ``max_range_m``), the sample frames are read from it. ``workers``
    threads fit the axis's slices (``pipescan.core.axis.fit_axis``).
    """
    meta = staged.meta
    diameter = meta.nominal_diameter_m
    up = np.array([0.0, 0.0, 1.0])
    with staged.reopen() as arc:
        if trajectory is None:
            points, time_s = _cloud_sample(arc, frame_store)
            choice = cloud_start(
                points,
                axis_direction(points, diameter),
                time_s=time_s,
                start_xyz=None if meta.start_xyz is None else np.array(meta.start_xyz),
                sensor_ahead_m=sensor_ahead_m(meta.sensor, diameter),
            )
            start, travel, source = choice.start_m, choice.travel_m, choice.source
            start_uncertainty = choice.uncertainty_m
        else:
            stride = max(1, len(trajectory.frame_indices) // sample_frames)
            indices = trajectory.frame_indices[::stride]
            rng = np.random.default_rng(0)
            parts = []
            sample = (
                iter_registered_points(_stored_frames(frame_store, chunks, indices), trajectory)
                if frame_store is not None
                else _frame_points_world(arc, trajectory, indices, max_range_m)
            )
            for pts in sample:
                take = min(len(pts), 5000)
                parts.append(pts[rng.choice(len(pts), take, replace=False)])
            points = np.concatenate(parts)
            positions = trajectory.positions_m()
            start, travel, source = positions[0], positions[-1] - positions[0], "first_frame"
            start_uncertainty = 0.0
            first = meta.frames[trajectory.frame_indices[0]] if meta.frames else None
            if first is not None and first.gravity is not None:
                up = -np.asarray(first.gravity, dtype=np.float64)
    axis = fit_axis(
        points,
        start_m=start,
        travel_m=travel,
        up_hint=up,
        chainage_offset_m=meta.chainage_offset_m,
        direction=meta.direction,
        nominal_diameter_m=diameter if np.isfinite(diameter) else None,
        workers=workers,
    )
    chain = axis.chainage(points)
    lo, hi = np.percentile(chain, [0.05, 99.95])
    return AxisFit(
        axis=axis,
        chainage_min_m=float(lo),
        chainage_max_m=float(hi),
        start_source=source,
        start_uncertainty_m=start_uncertainty,
    )


@task(name="bucket-points", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
@releases_memory
def bucket_points(
    staged: StagedArchive,
    trajectory: Trajectory | None,
    first: int,
    last: int,
    axis: PipeAxis,
    windows: list[ChainageWindow],
    bucket_root: Path,
    max_range_m: float,
    frame_store: FrameStore | None = None,
    placed_share: float = 1.0,
    early_return_ratio: float = 0.0,
) -> Bucketed:
    """Write the points of every frame ``first..last`` (or the cloud) into window files:
    registered frames by their poses, the frames between them by interpolated ones
    (:class:`~pipescan.core.registration.FramePoses`), so that a section's coverage does not
    depend on which frames were registered. A chunk's last frame is the next chunk's first:
    it is placed there (the run's last frame here).

    With ``frame_store``, the frames are those :func:`register_chunk` stored for the chunk
    that starts at ``first`` (already cropped to ``max_range_m``): the archive is not read.
    A registered cloud that :func:`fit_pipe_axis` kept there is placed by rows: ``first`` to
    ``last`` (exclusive). ``placed_share``: the share of each frame's points placed
    (:func:`~pipescan.core.registration.stride.choose_placed_share`); a cloud's every row.
    ``early_return_ratio``: the frames' early returns are left out (``iter_registered_points``).
    """
    if trajectory is None and frame_store is not None and frame_store.cloud_rows():
        rows = frame_store.read_cloud_rows(first, last)
        return write_buckets(rows, axis, windows, bucket_root, f"cloud_{first:011d}")
    tag = f"chunk_{first:07d}"
    along = frame_along(staged.meta)
    if trajectory is not None and frame_store is not None:
        # Every frame the chunk decoded; its last is the next chunk's first, placed there.
        # Frames that slid along the axis are not placed (iter_registered_points).
        final = last == staged.frame_count - 1
        frames = (f for f in frame_store.iter_timed_frames(first) if f[0] < last or final)
        times = [f.time_s for f in staged.meta.frames]
        placed = iter_registered_points(
            frames,
            trajectory,
            along,
            times,
            placed_share=placed_share,
            early_return_ratio=early_return_ratio,
        )
        return write_buckets(placed, axis, windows, bucket_root, tag)
    with staged.reopen() as arc:
        if trajectory is None:
            chunks = (chunk.points for chunk in arc.iter_cloud())
            return write_buckets(chunks, axis, windows, bucket_root, "cloud")
        stop = last + 1 if last == staged.frame_count - 1 else last
        placed = _frame_points_world(
            arc,
            trajectory,
            range(first, stop),
            max_range_m,
            along,
            placed_share,
            early_return_ratio,
        )
        return write_buckets(placed, axis, windows, bucket_root, tag)


@task(name="sensor-sight", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def read_sensor_sight(
    frame_store: FrameStore,
    chunks: Sequence[tuple[int, int]],
    trajectory: Trajectory,
    axis: PipeAxis,
    max_range_m: float,
) -> SensorSight | None:
    """The sensor's positions along the axis and how steeply it looked down
    (:func:`~pipescan.core.water.sensor_sight`), from every registered frame as
    :func:`register_chunk` stored it, one at a time."""
    rows = {i: r for r, i in enumerate(trajectory.frame_indices)}
    stored = _stored_frames(frame_store, chunks, trajectory.frame_indices)
    frames = ((rows[i], points) for i, points in stored)
    return sensor_sight(axis, trajectory.T_world_frame, frames, max_range_m=max_range_m)


@task(name="measure-window", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
@releases_memory
def measure_sections(
    bucket_root: Path,
    window: ChainageWindow,
    axis: PipeAxis,
    nominal_diameter_m: float,
    params: MeasureParams,
    evidence: RegistrationEvidence | None = None,
    engine_processes: int = 0,
) -> list[SectionMeasures]:
    """Measure every section of one chainage window (with what registration says of it), in
    this process or, with ``engine_processes`` > 0, in one of the engine pool's worker
    processes: measuring is NumPy work in many small steps, which holds the GIL between them,
    so on the flow's threads two windows share one core."""
    args = (bucket_root, window, axis, nominal_diameter_m, params, evidence)
    if engine_processes:
        sections, points = enginepool.run(engine_processes, measure_placed_window, *args)
    else:
        sections, points = measure_placed_window(*args)
    log.info("measured %.1f-%.1f m (%d points)", window.start_m, window.end_m, points)
    return sections


@dataclass(frozen=True)
class GradeResult:
    """Graded sections, their defects, and which table and pipe class graded them, and why."""

    sections: list[SectionMeasures]
    defects: list[Defect]
    table: str
    pipe_class: str
    pipe_class_reason: str


@task(name="grade", cache_policy=NO_CACHE)
def grade(
    sections: list[SectionMeasures],
    table_name: str,
    *,
    material: str | None,
    pipe_class: str,
    blockage_threshold_ratio: float,
    flag_grade: int,
) -> GradeResult:
    """Code and grade sections, and follow their features into defects (docs/coding.md).
    ``pipe_class="auto"`` takes the pipe class (rigid or flexible: the BAA deformation rule)
    from the archive's material."""
    choice = choose_grading(material, pipe_class=pipe_class, table=table_name)
    table = load_table(choice.table)
    codings = code_sections(sections)
    graded = grade_sections(sections, table, pipe_class=choice.pipe_class, codings=codings)
    defects = merge_defects(
        graded,
        table,
        blockage_threshold_ratio=blockage_threshold_ratio,
        flag_grade=flag_grade,
        pipe_class=choice.pipe_class,
        codings=codings,
    )
    return GradeResult(graded, defects, choice.table, choice.pipe_class, choice.reason)
