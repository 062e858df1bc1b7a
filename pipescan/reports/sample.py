"""Synthetic report inputs with known figures, for the docs build, benchmarks and tests.

A sample pipe is a straight circular pipe whose cross-sections are built geometrically
(shapely): an elliptical deformation, a flat deposit at the invert and an obstacle hanging
from the crown, each rising and falling smoothly over a chainage span. Every section carries
its contour, and its measures are computed from that contour, so figures, contours and grades
agree with each other as they would in a real inspection. Nothing here reads a scan.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta

import numpy as np
import shapely
from shapely.geometry import Point, box

from pipescan.core.grading import DEFAULT_TABLE, grade_sections, load_table, merge_defects
from pipescan.core.model import SectionMeasures, SectionStatus
from pipescan.reports.context import EarlierInspection, ReportInput, TableCitation

__all__ = ["Feature", "sample_input", "sample_sections"]


@dataclass(frozen=True)
class Feature:
    """A defect planted in a sample pipe.

    ``kind`` is ``"deposit"`` (height as a share of the diameter), ``"obstacle"`` (hanging
    from the crown, depth as a share of the diameter) or ``"deformation"`` (reduction of the
    vertical diameter, a share of it). ``peak_ratio`` is reached at the middle of
    ``[start_m, end_m)`` and falls off as a raised cosine to 0 at both ends.
    """

    kind: str
    start_m: float
    end_m: float
    peak_ratio: float

    def at(self, chainage_m: float) -> float:
        if not self.start_m <= chainage_m < self.end_m:
            return 0.0
        phase = (chainage_m - self.start_m) / (self.end_m - self.start_m)
        return self.peak_ratio * 0.5 * (1.0 - math.cos(2.0 * math.pi * phase))


def _section_geometry(
    diameter_m: float, deformation: float, deposit: float, obstacle: float
) -> shapely.Polygon:
    radius_m = diameter_m / 2.0
    # An ellipse of the same perimeter-ish size: vertical axis reduced, horizontal grown.
    shape = shapely.affinity.scale(
        Point(0.0, 0.0).buffer(radius_m, quad_segs=90), 1.0 + deformation / 2.0, 1.0 - deformation
    )
    if deposit > 0:
        shape = shape.intersection(
            box(-diameter_m, -radius_m + deposit * diameter_m, diameter_m, 1)
        )
    if obstacle > 0:
        half_width_m = 0.18 * diameter_m
        shape = shape.difference(
            box(-half_width_m, radius_m - obstacle * diameter_m, half_width_m, diameter_m)
        )
    return shape


_ANGLES_RAD = np.radians(np.arange(0.0, 360.0, 1.0))


def _contour(polygon: shapely.Polygon, rng: np.random.Generator, noise_m: float) -> np.ndarray:
    # One point per degree around the centre, as the polar contour method gives: the nearest
    # crossing of each ray from the centre with the section's boundary.
    far_m = 10.0
    ends = np.column_stack((far_m * np.cos(_ANGLES_RAD), far_m * np.sin(_ANGLES_RAD)))
    rays = shapely.linestrings(
        np.stack((np.zeros_like(ends), ends), axis=1)  # (360, 2, 2)
    )
    hits = shapely.intersection(rays, polygon.exterior)
    coords, index = shapely.get_coordinates(hits, return_index=True)
    distance = np.hypot(coords[:, 0], coords[:, 1])
    order = np.lexsort((distance, index))
    first = order[np.r_[True, np.diff(index[order]) != 0]]
    contour = coords[first]
    return contour + rng.normal(0.0, noise_m, contour.shape)


def _circle_contour(radius_m: float, rng: np.random.Generator, noise_m: float) -> np.ndarray:
    contour = radius_m * np.column_stack((np.cos(_ANGLES_RAD), np.sin(_ANGLES_RAD)))
    return contour + rng.normal(0.0, noise_m, contour.shape)


def sample_sections(
    length_m: float,
    *,
    diameter_m: float = 0.5,
    step_m: float = 0.1,
    features: Sequence[Feature] = (),
    unmeasured: Sequence[tuple[float, float, SectionStatus]] = (),
    seed: int = 0,
    noise_m: float = 0.002,
    contours: bool = True,
) -> list[SectionMeasures]:
    """Sections of a sample pipe with known defects.

    Parameters
    ----------
    length_m
        Length of pipe, from chainage 0.
    diameter_m
        Nominal inner diameter in metres.
    step_m
        Section length.
    features
        Defects to plant (see :class:`Feature`).
    unmeasured
        ``(start_m, end_m, status)`` spans reported as not measured.
    seed
        Seed of the contour noise.
    noise_m
        Standard deviation of the contour noise in metres.
    contours
        Keep each section's contour (needed for the cross-section figures).

    Returns
    -------
    list of SectionMeasures
        Ungraded; ``round(length_m / step_m)`` sections.
    """
    rng = np.random.default_rng(seed)
    nominal_area_m2 = math.pi * diameter_m**2 / 4.0
    out = []
    for i in range(round(length_m / step_m)):
        start_m, end_m = round(i * step_m, 6), round((i + 1) * step_m, 6)
        mid_m = 0.5 * (start_m + end_m)
        status = next((st for a, b, st in unmeasured if a <= mid_m < b), SectionStatus.OK)
        if status != SectionStatus.OK:
            out.append(
                SectionMeasures(
                    start_m, end_m, nominal_area_m2, status,
                    point_count=int(rng.integers(5, 80)),
                    coverage_ratio=float(rng.uniform(0.2, 0.7)),
                )
            )  # fmt: skip
            continue
        amount = {"deposit": 0.0, "obstacle": 0.0, "deformation": 0.0}
        for f in features:
            amount[f.kind] = max(amount[f.kind], f.at(mid_m))
        if any(amount.values()):
            polygon = _section_geometry(
                diameter_m, amount["deformation"], amount["deposit"], amount["obstacle"]
            )
            contour = _contour(polygon, rng, noise_m)
        else:
            contour = _circle_contour(diameter_m / 2.0, rng, noise_m)
        open_area_m2 = float(shapely.Polygon(contour).area)
        widths = np.ptp(contour, axis=0)
        d_mean = float(widths.mean())
        out.append(
            SectionMeasures(
                start_m,
                end_m,
                nominal_area_m2,
                SectionStatus.OK,
                point_count=int(rng.integers(6000, 9000)),
                coverage_ratio=float(min(1.0, rng.uniform(0.95, 1.02))),
                open_area_m2=open_area_m2,
                blockage_ratio=1.0 - open_area_m2 / nominal_area_m2,
                ovality_ratio=float(abs(widths[0] - widths[1]) / 2.0 / d_mean),
                deformation_ratio=max(0.0, amount["deformation"] + float(rng.normal(0, 0.002))),
                deposit_height_ratio=max(0.0, amount["deposit"] + float(rng.normal(0, 0.003))),
                contour_m=contour if contours else None,
            )
        )
    return out


_DEFAULT_FEATURES = (
    Feature("deformation", 8.0, 9.2, 0.075),
    Feature("obstacle", 21.0, 22.4, 0.30),
    Feature("deposit", 40.0, 43.0, 0.36),
)


def sample_input(
    length_m: float = 60.0,
    *,
    features: Sequence[Feature] = _DEFAULT_FEATURES,
    unmeasured: Sequence[tuple[float, float, SectionStatus]] = (
        (30.0, 31.2, SectionStatus.LOW_COVERAGE),
        (51.5, 51.8, SectionStatus.TOO_FEW_POINTS),
    ),
    earlier: int = 2,
    asset_id: str = "MH1042-MH1043",
    diameter_m: float = 0.5,
    seed: int = 0,
) -> ReportInput:
    """A complete sample inspection report, graded with vsa-2023, with earlier inspections.

    Earlier inspections (one every two years before this one) carry the same features at a
    smaller size (60 %, then 36 % ...), so the trend page shows them grow.

    Parameters
    ----------
    length_m
        Length of the pipe.
    features, unmeasured
        See :func:`sample_sections`; features must lie inside ``[0, length_m)``.
    earlier
        Number of earlier inspections to add (0 for none: no trend page).
    asset_id, diameter_m, seed
        The asset, its nominal diameter and the noise seed.
    """
    table = load_table(DEFAULT_TABLE)
    sections = grade_sections(
        sample_sections(
            length_m, diameter_m=diameter_m, features=features, unmeasured=unmeasured, seed=seed
        ),
        table,
    )
    defects = merge_defects(sections, table)
    inspected_at = datetime(2025, 3, 14, 9, 30, tzinfo=UTC)
    history = []
    for k in range(1, earlier + 1):
        scale = 0.6**k
        grown = [replace(f, peak_ratio=f.peak_ratio * scale) for f in features]
        earlier_sections = grade_sections(
            sample_sections(
                length_m,
                diameter_m=diameter_m,
                features=grown,
                unmeasured=[(a + 0.4 * k, b + 0.4 * k, st) for a, b, st in unmeasured],
                seed=seed + k,
                contours=False,
            ),
            table,
        )
        history.append(
            EarlierInspection(
                inspection_id=100 - k,
                inspected_at=inspected_at - timedelta(days=730 * k),
                sections=earlier_sections,
                defect_count=len(merge_defects(earlier_sections, table)),
            )
        )
    return ReportInput(
        asset_id=asset_id,
        upstream_node=asset_id.split("-")[0] if "-" in asset_id else None,
        downstream_node=asset_id.split("-")[-1] if "-" in asset_id else None,
        inspected_at=inspected_at,
        nominal_diameter_m=diameter_m,
        material="vitrified clay",
        pipe_shape="circular",
        inspection_id=100,
        archive_uri=f"s3://network-scans/2025/{asset_id}.tar.gz",
        software_version="sample",
        threshold_table=TableCitation(table.name, table.source),
        blockage_threshold_ratio=0.10,
        point_count=sum(s.point_count for s in sections),
        frame_count=round(length_m / 0.015),
        scanned_length_m=length_m,
        registration={
            "engine": "open3d point_to_plane",
            "mean_fitness": 0.993,
            "mean_rmse_m": 0.0041,
            "degenerate_frames": 12,
        },
        sections=sections,
        defects=defects,
        generated_at=datetime(2025, 3, 15, 8, 0, tzinfo=UTC),
        pipe_class_reason="from the material: vitrified clay",
        history=history,
    )
