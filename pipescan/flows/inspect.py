"""The ``inspect-archive`` flow: one scan archive in, one stored, graded inspection out.

Work fans out twice inside one archive: over chunks of frames (registration and bucketing) and
over chainage windows (sections). Tasks exchange paths, ids and small dataclasses only.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from prefect import flow

import pipescan
from pipescan.core.measures import MeasureParams
from pipescan.core.registration import (
    RegistrationParams,
    chain_trajectories,
    plan_chunks,
    registration_summary,
)
from pipescan.core.sections import plan_windows
from pipescan.storage.workspace import remove_workspace
from pipescan.tasks.inspection import (
    bucket_points,
    fit_pipe_axis,
    grade,
    measure_sections,
    register_chunk,
)
from pipescan.tasks.reporting import render_report
from pipescan.tasks.storing import save_results, stage_archive

log = logging.getLogger("pipescan")


@dataclass(frozen=True)
class InspectionParams:
    """Every parameter that changes an inspection's figures (their hash keys re-runs)."""

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    measure: MeasureParams = field(default_factory=MeasureParams)
    step_m: float = 0.1
    window_m: float = 2.0
    chunk_frames: int = 60
    max_section_range_m: float = 5.0
    threshold_table: str = "vsa-2023"
    pipe_class: str = "auto"
    blockage_threshold_ratio: float = 0.10
    flag_grade: int = 2

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
    report_path: str | None
    wall_time_s: float


@flow(name="inspect-archive")
def inspect_archive(
    archive: str,
    database_url: str = "sqlite:///pipescan.db",
    report_path: str | None = None,
    params: InspectionParams | None = None,
    work_dir: str = ".pipescan-work",
) -> InspectionSummary:
    """Register, section, measure, grade and store one scan archive; optionally render its PDF.

    Nothing is written to the database unless every stage succeeded; the sections, defects and
    registration quality are then written in one transaction.
    """
    started = time.perf_counter()
    params = params or InspectionParams()
    run_dir = Path(work_dir) / f"run-{time.time_ns():x}"
    try:
        staged = stage_archive(archive, run_dir)
        meta = staged.meta
        log.info(f"archive {staged.name}: asset {meta.asset_id}, {staged.frame_count} frames")

        trajectory = None
        chunks = plan_chunks(staged.frame_count, params.chunk_frames)
        if chunks:
            log.info(f"registering {staged.frame_count} frames in {len(chunks)} chunks")
            futures = [register_chunk.submit(staged, a, b, params.registration) for a, b in chunks]
            trajectory = chain_trajectories([f.result() for f in futures])

        fit = fit_pipe_axis(staged, trajectory, max_range_m=params.max_section_range_m)
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
        bucket_root = run_dir / "buckets"
        spans = chunks or [(0, 0)]
        counts = [
            bucket_points.submit(
                staged,
                trajectory,
                a,
                b,
                fit.axis,
                windows,
                bucket_root,
                params.max_section_range_m,
            )
            for a, b in spans
        ]
        point_count = sum(c.result() for c in counts)

        window_futures = [
            measure_sections.submit(
                bucket_root, w, fit.axis, meta.nominal_diameter_m, params.measure
            )
            for w in windows
        ]
        sections = [s for f in window_futures for s in f.result()]
        grading = grade(
            sections,
            params.threshold_table,
            material=meta.material,
            pipe_class=params.pipe_class,
            blockage_threshold_ratio=params.blockage_threshold_ratio,
            flag_grade=params.flag_grade,
        )
        graded, defects = grading.sections, grading.defects
        registration = (
            registration_summary(trajectory, params.registration)
            if trajectory is not None
            else {"engine": "none (registered cloud)", "frames": 0}
        )
        ok = [s for s in graded if s.is_ok]
        scanned = (windows[-1].end_m - windows[0].start_m) if windows else 0.0
        inspection_id = save_results(
            database_url,
            meta=meta,
            archive_uri=str(archive),
            content_hash=staged.content_hash,
            # The resolved pipe class, not "auto", is what graded these figures.
            params=params.figure_params()
            | {"pipe_class": grading.pipe_class, "pipe_class_reason": grading.pipe_class_reason},
            software_version=pipescan.__version__,
            sections=graded,
            defects=defects,
            frame_quality=list(trajectory.quality) if trajectory else [],
            registration=registration,
            threshold_table=params.threshold_table,
            point_count=point_count,
            frame_count=staged.frame_count,
            scanned_length_m=scanned,
        )
        log.info(
            f"stored inspection {inspection_id}: {len(graded)} sections, {len(defects)} defects"
        )
        written = None
        if report_path:
            written = str(render_report(database_url, inspection_id, Path(report_path)))
            log.info(f"report written to {written}")
        worst = max(ok, key=lambda s: s.blockage_ratio or 0.0, default=None)
        unmeasured: dict[str, int] = {}
        for s in graded:
            if not s.is_ok:
                unmeasured[s.status.value] = unmeasured.get(s.status.value, 0) + 1
        return InspectionSummary(
            inspection_id=inspection_id,
            asset_id=meta.asset_id,
            inspected_at=meta.inspected_at.isoformat(),
            archive=str(archive),
            frame_count=staged.frame_count,
            point_count=point_count,
            scanned_length_m=scanned,
            section_count=len(graded),
            sections_ok=len(ok),
            defect_count=len(defects),
            max_blockage_ratio=worst.blockage_ratio if worst else None,
            max_blockage_chainage_m=worst.chainage_start_m if worst else None,
            unmeasured_by_status=unmeasured,
            registration=registration,
            report_path=written,
            wall_time_s=time.perf_counter() - started,
        )
    finally:
        remove_workspace(run_dir)
