"""The ``inspect-archive`` flow: one scan archive in, one stored, graded inspection out.

Work fans out twice inside one archive: over chunks of frames (registration and bucketing) and
over chainage windows (sections). Tasks exchange paths, ids and small dataclasses only.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from prefect import flow
from prefect.utilities.annotations import quote

import pipescan
from pipescan.core import defaults
from pipescan.core.errors import MetadataError
from pipescan.core.flags import DEFAULT_TABLE, FlagRule
from pipescan.core.grading import choose_grading, is_flagged
from pipescan.core.instrument import (
    Instrument,
    instrument_summary,
    instrumented,
    registration_trusted,
)
from pipescan.core.measures import MeasureParams, withhold_smeared_object_edges
from pipescan.core.model import SectionMeasures
from pipescan.core.registration import (
    FrameStride,
    PlacedShare,
    RegistrationEvidence,
    RegistrationParams,
    Trajectory,
    chain_trajectories,
    plan_chunks,
    registration_evidence,
    registration_summary,
    used_frame_indices,
)
from pipescan.core.sanitize import strip_credentials
from pipescan.core.sections import ChainageWindow, plan_windows, windows_reached
from pipescan.core.summary import (
    InnerDiameter,
    diameter_mismatch,
    measured_inner_diameter,
    peak_blockage,
)
from pipescan.core.water import confirm_surfaceless_water, explain_invert_shadows
from pipescan.flows.database import run_database_url
from pipescan.flows.housekeeping import start_run_dir
from pipescan.flows.runners import engine_processes, engine_threads, limit_library_threads
from pipescan.settings import get_settings
from pipescan.storage.database.repository import InspectionToSave, params_hash
from pipescan.storage.scratch import FrameStore, remove_workspace
from pipescan.tasks import enginepool
from pipescan.tasks.inspection import (
    AxisFit,
    bucket_points,
    fit_pipe_axis,
    grade,
    measure_sections,
    read_sensor_sight,
    register_chunk,
    survey_scan,
)
from pipescan.tasks.network import (
    find_stored_inspection,
    load_stored_inspection,
)
from pipescan.tasks.reporting import render_report
from pipescan.tasks.staged import StagedArchive
from pipescan.tasks.storing import save_results, stage_archive

log = logging.getLogger("pipescan")


@dataclass(frozen=True)
class InspectionParams:
    """Every parameter that changes an inspection's figures (their hash keys re-runs)."""

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    measure: MeasureParams = field(default_factory=MeasureParams)
    step_m: float = defaults.SECTION_STEP_M
    window_m: float = defaults.WINDOW_M
    chunk_frames: int = defaults.CHUNK_FRAMES
    max_section_range_m: float = 5.0
    frame_stride: int | None = None
    """Register every k-th frame (the others are tracked, and every frame is placed); None:
    chosen from the scan (the largest k the local map allows: ``choose_frame_stride``)."""
    placed_share: float | None = None
    """The share of each frame's points placed in the sections (1: every point); None: chosen
    from the scan (``choose_placed_share``: twice what an inner section keeps)."""
    threshold_table: str = DEFAULT_TABLE
    pipe_class: str = defaults.PIPE_CLASS
    blockage_threshold_ratio: float = FlagRule.blockage_threshold_ratio
    flag_grade: int = FlagRule.flag_grade

    def stride_bounds(self) -> dict:
        """What ``choose_stride`` weighs a scan's frames against, from these parameters: the
        sections' range, step and points kept, and the local map's keyframe distance."""
        return {
            "max_range_m": self.max_section_range_m,
            "step_m": self.step_m,
            "section_points": self.measure.max_points,
            "keyframe_distance_m": self.registration.keyframe_distance_m,
        }

    def figure_params(self) -> dict:
        """The parameters that change figures: stored with the inspection and hashed into its
        identity. Chunking and windowing change how the work is split, not the figures."""
        figures = asdict(self)
        for key in ("window_m", "chunk_frames"):
            figures.pop(key)
        return figures


@dataclass(frozen=True)
class InspectionSummary:
    """What ``pipescan inspect`` prints (and ``--json`` emits)."""

    inspection_id: int
    asset_id: str
    inspected_at: str
    archive: str
    frame_count: int
    point_count: int
    scanned_length_m: float
    section_count: int
    sections_ok: int
    defect_count: int
    max_blockage_ratio: float | None
    max_blockage_chainage_m: float | None
    unmeasured_by_status: dict[str, int]
    registration: dict
    start_source: str | None
    report_path: str | None
    wall_time_s: float
    reused: bool = False
    """True when the archive was already inspected under the same parameters and the stored
    inspection was summarised instead of processing it again (``reuse_stored``)."""
    flagged_defect_count: int = 0
    """How many of the defects are over the flagging threshold (``is_flagged``)."""
    measured_inner_diameter_m: float | None = None
    """The wall's inner diameter as measured (``core.summary.measured_inner_diameter``)."""


def stored_params(params: InspectionParams, pipe_class: str, pipe_class_reason: str) -> dict:
    """The parameters stored with an inspection and hashed into its identity: the figure
    parameters, with the pipe class that graded the figures (``"auto"`` resolved)."""
    return params.figure_params() | {
        "pipe_class": pipe_class,
        "pipe_class_reason": pipe_class_reason,
    }


@flow(name="inspect-archive")
def inspect_archive(
    archive: str,
    report_path: str | None = None,
    params: InspectionParams | None = None,
    work_dir: str | None = None,
    reuse_stored: bool = False,
) -> InspectionSummary:
    """Register, section, measure, grade and store one scan archive; optionally render its PDF.

    The database is the one of the settings where the flow runs (``PIPESCAN_DATABASE_URL``, or
    :func:`pipescan.settings.use_settings`), never a parameter: Prefect keeps a run's
    parameters where anyone with access to its UI sees them. ``work_dir`` None: the
    ``PIPESCAN_WORK_DIR`` setting.

    Nothing is written to the database unless every stage succeeded; the sections, defects and
    registration quality are then written in one transaction.

    With ``reuse_stored``, an archive whose content (hash) was already inspected under the same
    figure parameters (hash) is not processed again: its stored inspection is summarised
    (``reused=True``). This is what lets a network run resume after a crash.

    The stages: stage the archive, reuse a stored inspection, register, fit the axis, place
    and measure, check the diameter, grade and store, report.
    """
    started = time.perf_counter()
    settings = get_settings()
    limit_library_threads(settings.library_threads)
    database_url = run_database_url(settings)
    run_dir = start_run_dir(Path(work_dir or settings.work_dir))
    pooled = engine_processes(settings.engine_processes)
    try:
        staged = _stage(archive, run_dir, pooled)
        # The crawler's own odometer uncertainty, where inspection.toml states it, is what
        # registration uses and what is stored with the inspection.
        meta = staged.meta
        params = params or InspectionParams()
        params = replace(
            params,
            registration=params.registration.for_odometer(
                meta.odometer_uncertainty_ratio, meta.odometer_slip_m
            ),
        )
        if reuse_stored and (
            done := _reuse(database_url, staged, params, archive, report_path, started)
        ):
            return done
        scan = _register(staged, params, run_dir, pooled)
        fit, windows, evidence = _fit_axis(staged, params, scan)
        sections, point_count = _place_and_measure(
            staged, params, scan, fit, windows, evidence, run_dir
        )
        inner = _check_diameter(sections, staged)
        stored = _grade_and_store(
            database_url, staged, params, scan, fit, windows, sections, point_count, inner
        )
        written = None
        if report_path:
            written = str(render_report(database_url, stored.inspection_id, Path(report_path)))
            log.info(f"report written to {written}")
        return _summarise(
            inspection_id=stored.inspection_id,
            meta=meta,
            archive=archive,
            frame_count=staged.frame_count,
            point_count=point_count,
            scanned_length_m=stored.scanned_length_m,
            graded=stored.graded,
            defects=stored.defects,
            registration=stored.registration,
            report_path=written,
            started=started,
            start_source=fit.start_source,
            flags=_flags(params),
        )
    finally:
        remove_workspace(run_dir)


def _stage(archive: str, run_dir: Path, pooled: int) -> StagedArchive:
    """The archive staged (validated, local), with its first log line. With frames, the engine
    pool's workers start as the archive opens; a registered cloud releases them."""
    staged = stage_archive(archive, run_dir, get_settings().input_limits(), pooled)
    if not staged.frame_count:
        enginepool.release_unused()  # a registered cloud: nothing registers
    content = (
        f"{staged.frame_count} frames"
        if staged.cloud_member is None
        else f"a registered cloud ({staged.cloud_member})"
    )
    log.info(f"archive {staged.name}: asset {staged.meta.asset_id}, {content}")
    return staged


def _reuse(
    database_url: str,
    staged: StagedArchive,
    params: InspectionParams,
    archive: str,
    report_path: str | None,
    started: float,
) -> InspectionSummary | None:
    """The stored inspection of this content under these figure parameters, summarised (its
    report rendered when asked), or None when there is none."""
    meta = staged.meta
    # The same choice as the grade task's, so the same parameters and hash as a save.
    choice = choose_grading(
        meta.material, pipe_class=params.pipe_class, table=params.threshold_table
    )
    stored_id = find_stored_inspection(
        database_url,
        meta.asset_id,
        staged.content_hash,
        params_hash(stored_params(params, choice.pipe_class, choice.reason)),
    )
    if stored_id is None:
        return None
    log.info(f"archive {staged.name} already stored as inspection {stored_id}")
    stored = load_stored_inspection(database_url, stored_id)
    rec = stored.record
    written = None
    if report_path:
        written = str(render_report(database_url, stored_id, Path(report_path)))
    return _summarise(
        inspection_id=stored_id,
        meta=meta,
        archive=archive,
        frame_count=rec.frame_count,
        point_count=rec.point_count,
        scanned_length_m=rec.scanned_length_m,
        graded=stored.sections,
        defects=stored.defects,
        registration=rec.registration,
        report_path=written,
        started=started,
        reused=True,
        start_source=rec.start_source,
        flags=_flags(params),
    )


@dataclass(frozen=True)
class _Registered:
    """What registration leaves for the later stages: the scan's instrument and the parameters
    it sets, the stride, the chunks, the frames kept and the trajectory (None for a cloud)."""

    instrument: Instrument | None
    stride: FrameStride
    placed: PlacedShare
    registration: RegistrationParams
    measure: MeasureParams
    chunks: list[tuple[int, int]]
    frame_store: FrameStore
    trajectory: Trajectory | None
    closer: int
    """Frames registered besides the stride's (where ICP disagreed with the odometer)."""


def _register(
    staged: StagedArchive, params: InspectionParams, run_dir: Path, pooled: int
) -> _Registered:
    """The scan's instrument and stride (``survey_scan``), then its chunks registered in
    parallel and chained; every frame kept in the frame store for the sections."""
    # The sensor's blind zone, noise and pattern, from inspection.toml's [sensor] or the
    # scan: figures of the run, not of the stored parameters (the same archive and parameters
    # give the same instrument, so the stored hash still keys re-runs).
    survey = (
        survey_scan(
            quote(staged),
            frame_stride=params.frame_stride,
            placed_share=params.placed_share,
            **params.stride_bounds(),
        )
        if staged.frame_count
        else None
    )
    instrument = survey.instrument if survey else None
    stride = survey.stride if survey else FrameStride(1, "a registered cloud")
    placed = survey.placed if survey else PlacedShare(1.0)
    reg_params, measure_params = instrumented(params.registration, params.measure, instrument)
    # As many chunks as registering at once keeps every core busy to the end: the engine
    # pool's processes, or the task runner's workers.
    workers = pooled or get_settings().workers
    chunks = plan_chunks(staged.frame_count, params.chunk_frames, stride.stride, workers)
    # Each frame is decoded once: registration keeps what the sections need here.
    frame_store = FrameStore(run_dir / "frames")
    trajectory, closer = None, 0
    if chunks:
        used = len(used_frame_indices(staged.frame_count, stride.stride))
        log.info(
            f"registering {used} of {staged.frame_count} frames in {len(chunks)} chunks, "
            "tracking the others: every frame is placed"
        )
        # How the work is split, not the figures: kept out of the stored parameters. In the
        # engine pool's processes, one engine thread each: both cores are busy.
        registering = replace(reg_params, num_threads=1 if pooled else engine_threads())
        # Large arguments without futures in them (the staged archive's frame list, here and
        # below the trajectory, the axis, the windows, the evidence) are quoted: Prefect
        # would otherwise walk every element of them for every task, under the GIL
        # (docs/throughput.md).
        futures = [
            register_chunk.submit(
                quote(staged),
                a,
                b,
                registering,
                frame_store,
                params.max_section_range_m,
                engine_processes=pooled,
                stride=stride.stride,
            )
            for a, b in chunks
        ]
        trajectory = chain_trajectories([f.result() for f in futures])
        closer = len(trajectory.frame_indices) - used
        tracked = len(trajectory.tracked_indices)
        log.info(
            f"registered {len(trajectory.frame_indices)} of {staged.frame_count} frames"
            + (f" ({closer} more where ICP disagreed with the odometer)" if closer else "")
            + (f", tracked {tracked}" if tracked else "")
        )
    return _Registered(
        instrument,
        stride,
        placed,
        reg_params,
        measure_params,
        chunks,
        frame_store,
        trajectory,
        closer,
    )


def _fit_axis(
    staged: StagedArchive, params: InspectionParams, scan: _Registered
) -> tuple[AxisFit, list[ChainageWindow], RegistrationEvidence]:
    """The axis, the chainage windows it spans, and each section's registration evidence."""
    meta = staged.meta
    fit = fit_pipe_axis(
        quote(staged),
        quote(scan.trajectory),
        max_range_m=params.max_section_range_m,
        frame_store=scan.frame_store,
        chunks=scan.chunks,
        workers=engine_threads(),  # nothing else runs while the axis is fitted
    )
    windows = plan_windows(
        max(fit.chainage_min_m, meta.chainage_offset_m)
        if meta.direction == "downstream"
        else fit.chainage_min_m,
        fit.chainage_max_m,
        step_m=params.step_m,
        window_m=params.window_m,
    )
    log.info(
        f"axis fitted; chainage {fit.chainage_min_m:.2f}-{fit.chainage_max_m:.2f} m "
        f"in {len(windows)} windows"
    )
    # Each section's chainage uncertainty, and whether a frame that saw it slid.
    trajectory = scan.trajectory
    evidence = (
        registration_evidence(
            trajectory,
            fit.axis.chainage(trajectory.positions_m()),
            seen_from_m=params.max_section_range_m,
        )
        if trajectory is not None
        else RegistrationEvidence.uniform(fit.start_uncertainty_m)
    )
    if not registration_trusted(scan.instrument):
        log.warning(
            "one frame covers only part of the view: registration of such a scan is not yet "
            "trusted for figures, and every section is weak_registration (docs/instrument.md)"
        )
        evidence = replace(evidence, untrusted=True)
    return fit, windows, evidence


def _place_and_measure(
    staged: StagedArchive,
    params: InspectionParams,
    scan: _Registered,
    fit: AxisFit,
    windows: list[ChainageWindow],
    evidence: RegistrationEvidence,
    run_dir: Path,
) -> tuple[list[SectionMeasures], int]:
    """Every frame's points (or the cloud's) placed into window files, each window measured as
    soon as the chunks that reach it are placed (:func:`_schedule_windows`), then the rules
    that take sections on both sides of a window's edge. Returns the sections and the points
    placed."""
    bucket_root = run_dir / "buckets"
    trajectory = scan.trajectory
    # Frames are placed by chunk; a registered cloud by slices of its rows.
    rows = scan.frame_store.cloud_rows() if trajectory is None else 0
    spans = scan.chunks or [
        (i, min(i + CLOUD_SLICE_POINTS, rows)) for i in range(0, rows, CLOUD_SLICE_POINTS)
    ]

    # Windows are measured in the engine pool's processes where registration ran there: on
    # the flow's threads two windows would share one core (measure_sections). (Placing there
    # too gained nothing measurable: 7.9 against 7.7 s for the sections of slow30-laz.)
    engines = enginepool.pool_size()

    def place(a: int, b: int):
        return bucket_points.submit(
            quote(staged),
            quote(trajectory),
            a,
            b,
            quote(fit.axis),
            quote(windows),
            bucket_root,
            params.max_section_range_m,
            scan.frame_store,
            scan.placed.share,
            scan.registration.early_return_ratio,
        )

    def measure(w: int, after: list):
        return measure_sections.submit(
            bucket_root,
            windows[w],
            quote(fit.axis),
            staged.meta.nominal_diameter_m,
            scan.measure,
            quote(evidence),
            engines,
            wait_for=after,
        )

    reached = windows_reached(
        _chunk_chainages(trajectory, fit.axis, spans),
        windows,
        reach_m=params.max_section_range_m + BENT_AXIS_MARGIN_M,
    )
    # Where the sensor looked from, and how steeply: how far a shadow reaches.
    sight = (
        read_sensor_sight.submit(
            scan.frame_store,
            scan.chunks,
            quote(trajectory),
            quote(fit.axis),
            params.max_section_range_m,
        )
        if trajectory is not None
        else None
    )
    placed, measured = _schedule_windows(spans, reached, windows, place, measure)
    # Water read where a deposit's or obstacle's shadow explains the unseen invert is taken
    # back, and an object's edge is withheld where the object was seen where other frames saw
    # bare wall (both take sections on both sides of a window's edge).
    sections = withhold_smeared_object_edges(
        explain_invert_shadows(
            confirm_surfaceless_water(measured), sight.result() if sight is not None else None
        ),
        scan.measure,
    )
    return sections, sum(p.points for p in placed)


def _schedule_windows(spans, reached, windows, place, measure):
    """Place every span and measure every window, overlapping the two on the pool's workers:
    spans are submitted in order along the pipe, each followed by the windows it completes
    (``reached[w]``: the spans whose points can reach window ``w``). A bent axis can carry a
    span's points further than planned: a window such a span wrote into after it was measured
    is measured again. Returns the placements and the sections, in window order."""
    last_needed = [max(r, default=-1) for r in reached]
    placing: list = []
    measuring: list = [None] * len(windows)
    for k, (a, b) in enumerate(spans):
        placing.append(place(a, b))
        for w in range(len(windows)):
            if measuring[w] is None and last_needed[w] <= k:
                measuring[w] = measure(w, [placing[j] for j in reached[w]])
    for w in range(len(windows)):  # reached by no span (nothing to place)
        if measuring[w] is None:
            measuring[w] = measure(w, placing)
    placed = [f.result() for f in placing]
    for k, p in enumerate(placed):
        for w, window in enumerate(windows):
            if window.start_mm in p.windows_mm and k not in reached[w]:
                log.info(f"window at {window.start_m:.1f} m measured again: a chunk reached it")
                reached[w].append(k)
                measuring[w] = measure(w, placing)
    return placed, [s for f in measuring for s in f.result()]


def _check_diameter(sections: list[SectionMeasures], staged: StagedArchive) -> InnerDiameter | None:
    """The wall's measured inner diameter; a nominal diameter it contradicts stops the run
    (blockage is a share of the nominal area: it would grade the wrong pipe) before anything
    is stored."""
    inner = measured_inner_diameter(sections)
    mismatch = diameter_mismatch(inner, staged.meta.nominal_diameter_m)
    if mismatch is not None:
        raise MetadataError(
            mismatch,
            archive=staged.name,
            file="inspection.toml",
            field="nominal_diameter_m",
            hint="state the pipe's inner diameter in metres; nothing was stored",
        )
    return inner


@dataclass(frozen=True)
class _Stored:
    inspection_id: int
    graded: list
    defects: list
    registration: dict
    scanned_length_m: float


def _grade_and_store(
    database_url, staged, params, scan: _Registered, fit, windows, sections, point_count, inner
) -> _Stored:
    """Code and grade the sections, and store them with the registration's summary, in one
    transaction."""
    meta = staged.meta
    grading = grade(
        sections,
        params.threshold_table,
        material=meta.material,
        pipe_class=params.pipe_class,
        blockage_threshold_ratio=params.blockage_threshold_ratio,
        flag_grade=params.flag_grade,
    )
    trajectory = scan.trajectory
    registration = (
        registration_summary(
            trajectory,
            params.registration,
            odometer_m=(meta.frames[0].odometer_m, meta.frames[-1].odometer_m)
            if meta.frames
            else None,
        )
        | {
            "frame_stride": scan.stride.stride,
            "frame_stride_reason": scan.stride.reason,
            "placed_share": scan.placed.share,
            "points_per_section": scan.placed.points_per_section,
            "section_points": scan.placed.section_points,
            "frames_looked_closer": scan.closer,
        }
        | instrument_summary(scan.instrument)
        if trajectory is not None
        else {
            "engine": "none (registered cloud)",
            "frames": 0,
            "chainage_uncertainty_m": fit.start_uncertainty_m,
        }
    ) | {"measured_inner_diameter_m": inner.diameter_m if inner else None}
    scanned = (windows[-1].end_m - windows[0].start_m) if windows else 0.0
    inspection = InspectionToSave(
        meta=meta,
        archive_uri=staged.name,  # without credentials
        content_hash=staged.content_hash,
        params=stored_params(params, grading.pipe_class, grading.pipe_class_reason),
        software_version=pipescan.__version__,
        sections=grading.sections,
        defects=grading.defects,
        frame_quality=list(trajectory.quality) if trajectory else [],
        registration=registration,
        status="ok" if any(s.is_ok for s in grading.sections) else "unmeasured",
        threshold_table=params.threshold_table,
        point_count=point_count,
        frame_count=staged.frame_count,
        scanned_length_m=scanned,
        start_source=fit.start_source,
    )
    inspection_id = save_results(database_url, inspection)
    log.info(
        f"stored inspection {inspection_id}: {len(grading.sections)} sections, "
        f"{len(grading.defects)} defects"
    )
    return _Stored(inspection_id, grading.sections, grading.defects, registration, scanned)


def _flags(params: InspectionParams) -> dict:
    return {
        "blockage_threshold_ratio": params.blockage_threshold_ratio,
        "flag_grade": params.flag_grade,
    }


CLOUD_SLICE_POINTS = 4_000_000
"""Rows of a registered cloud placed by one task (about 100 MB as float64)."""

BENT_AXIS_MARGIN_M = 0.5
"""Added to the section range when planning which chunks a window waits for: along a bent axis
a point's chainage can differ from its sensor's by a little more than its range."""


def _chunk_chainages(trajectory, axis, spans) -> list[tuple[float, float]]:
    """The chainage range the sensor covered in each chunk (every chunk: a cloud's only one)."""
    if trajectory is None:
        return [(-np.inf, np.inf)] * len(spans)
    chain = axis.chainage(trajectory.positions_m())
    row = {i: k for k, i in enumerate(trajectory.frame_indices)}
    return [
        (float(chain[row[a] : row[b] + 1].min()), float(chain[row[a] : row[b] + 1].max()))
        for a, b in spans
    ]


def _summarise(
    *,
    inspection_id: int,
    meta,
    archive: str,
    frame_count: int,
    point_count: int,
    scanned_length_m: float,
    graded,
    defects,
    registration: dict,
    report_path: str | None,
    started: float,
    reused: bool = False,
    start_source: str | None = None,
    flags: dict | None = None,
) -> InspectionSummary:
    ok = [s for s in graded if s.is_ok]
    worst = peak_blockage(graded)
    unmeasured: dict[str, int] = {}
    for s in graded:
        if not s.is_ok:
            unmeasured[s.status.value] = unmeasured.get(s.status.value, 0) + 1
    return InspectionSummary(
        inspection_id=inspection_id,
        asset_id=meta.asset_id,
        inspected_at=meta.inspected_at.isoformat(),
        archive=strip_credentials(str(archive)),
        frame_count=frame_count,
        point_count=point_count,
        scanned_length_m=scanned_length_m,
        section_count=len(graded),
        sections_ok=len(ok),
        defect_count=len(defects),
        flagged_defect_count=sum(is_flagged(d, **(flags or {})) for d in defects),
        max_blockage_ratio=worst.blockage_ratio if worst else None,
        max_blockage_chainage_m=worst.chainage_start_m if worst else None,
        unmeasured_by_status=unmeasured,
        registration=registration,
        start_source=start_source,
        report_path=report_path,
        measured_inner_diameter_m=registration.get("measured_inner_diameter_m"),
        wall_time_s=time.perf_counter() - started,
        reused=reused,
    )
