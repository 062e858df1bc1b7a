"""The true feature list of a simulated scene: what an engineer should code, and where.

One :class:`TrueFeature` per deformation, deposit, obstacle and band of a
:class:`~pipescan.simulator.scan.Scenario`, with its EN 13508-2 code, its chainage span, its
clock arc (12 at the crown, 3 on the right looking downstream, the survey's direction), and
its own figures, computed on the scene with that feature alone. ``pipescan simulate`` writes
them to ``ground_truth/features.csv`` beside the true sections; the coding benchmark and tests
score the coder against them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely

from pipescan.core.coding import BAA, BBB, BBC, BBE, clock_hours
from pipescan.core.grading import ThresholdTable
from pipescan.core.model import Defect, SectionMeasures
from pipescan.simulator.scan import (
    BoxObstacle,
    DepositFill,
    EllipticalDeformation,
    Scenario,
    WallBand,
    free_area_m2,
)

__all__ = [
    "TRUE_FEATURE_COLUMNS",
    "FeatureOutcome",
    "TrueFeature",
    "score_defects",
    "true_features",
]

_SAMPLES = 41  # positions along a feature at which its own figures are computed


@dataclass(frozen=True)
class TrueFeature:
    """One feature of a simulated scene, as it should be coded.

    Attributes
    ----------
    code
        ``BBC`` (a deposit), ``BBB`` (a band), ``BBE`` (a box obstacle) or ``BAA`` (a
        deformation).
    chainage_start_m, chainage_end_m
        Its span along the pipe (a deposit's ramps included), chainage from the upstream node.
    clock_from_h, clock_to_h
        The arc of wall it displaces, clockwise, in hours: for a deposit, where its top meets
        the wall at its peak height; for an obstacle, the arc it hides from the axis; for a
        band, its own. None for a deformation (the whole ring).
    measure, peak_value
        The figure EN 13508-2 quantifies it by (``deposit_height_ratio``,
        ``deformation_ratio`` or ``blockage_ratio``) and its largest value, with the feature
        alone in the pipe.
    peak_blockage_ratio
        The largest share of the nominal cross-section it takes on its own.
    """

    code: str
    chainage_start_m: float
    chainage_end_m: float
    clock_from_h: float | None
    clock_to_h: float | None
    measure: str
    peak_value: float
    peak_blockage_ratio: float


TRUE_FEATURE_COLUMNS = tuple(f.name for f in dataclasses.fields(TrueFeature))
"""Columns of ``ground_truth/features.csv``, in order."""


def _alone(scenario: Scenario, feature: object) -> Scenario:
    """The scene with only ``feature`` in it."""
    kinds = {
        EllipticalDeformation: "deformations",
        DepositFill: "deposits",
        BoxObstacle: "obstacles",
        WallBand: "bands",
    }
    fields: dict[str, tuple[object, ...]] = {name: () for name in kinds.values()}
    fields[kinds[type(feature)]] = (feature,)
    return dataclasses.replace(scenario, **fields)  # type: ignore[arg-type]


def _peak_blockage(scenario: Scenario, start_m: float, end_m: float) -> float:
    xs = np.linspace(start_m, end_m, _SAMPLES + 2)[1:-1]
    free = min(free_area_m2(scenario, float(x)) for x in xs)
    return 1.0 - free / scenario.nominal_area_m2


def _box_arc_h(box: BoxObstacle, radius_m: float) -> tuple[float, float]:
    """The clock arc a box hides from the axis: its section inside the wall, seen from the
    centre (pipe frame: y left, z up, so the angle ``atan2(z, y)`` is the section plane's)."""
    inside = shapely.box(box.y_min_m, box.z_min_m, box.y_max_m, box.z_max_m).intersection(
        shapely.Point(0.0, 0.0).buffer(radius_m, quad_segs=256)
    )
    yz = np.asarray(inside.exterior.coords)
    angles = np.sort(np.mod(np.arctan2(yz[:, 1], yz[:, 0]), 2.0 * math.pi))
    gaps = np.diff(np.append(angles, angles[0] + 2.0 * math.pi))
    k = int(np.argmax(gaps))  # the arc is everything but the largest gap between corners
    return clock_hours(float(angles[(k + 1) % len(angles)])), clock_hours(float(angles[k]))


def true_features(scenario: Scenario) -> list[TrueFeature]:
    """Every feature of ``scenario``, in chainage order (see :class:`TrueFeature`).

    Examples
    --------
    >>> from pipescan.simulator.scan import get_scenario
    >>> [(f.code, f.clock_from_h and round(f.clock_from_h, 1)) for f in
    ...  true_features(get_scenario("paper"))]
    [('BAA', None), ('BBE', 10.3), ('BBC', 3.8)]
    """
    offset = scenario.chainage_offset_m
    r = scenario.radius_m
    out = []
    for d in scenario.deformations:
        alone = _alone(scenario, d)
        out.append(
            TrueFeature(
                BAA,
                offset + d.start_m,
                offset + d.end_m,
                None,
                None,
                "deformation_ratio",
                max(d.vertical_reduction_ratio, -d.horizontal_increase_ratio),
                _peak_blockage(alone, d.start_m, d.end_m),
            )
        )
    for f in scenario.deposits:
        half_h = math.degrees(math.acos(max(-1.0, 1.0 - 2.0 * f.peak_height_ratio))) / 30.0
        out.append(
            TrueFeature(
                BBC,
                offset + f.start_m,
                offset + f.end_m,
                6.0 - half_h,
                6.0 + half_h,
                "deposit_height_ratio",
                f.peak_height_ratio,
                _peak_blockage(_alone(scenario, f), f.start_m, f.end_m),
            )
        )
    for b in scenario.obstacles:
        blockage = _peak_blockage(_alone(scenario, b), b.start_m, b.end_m)
        arc = _box_arc_h(b, r)
        out.append(
            TrueFeature(
                BBE,
                offset + b.start_m,
                offset + b.end_m,
                *arc,
                "blockage_ratio",
                blockage,
                blockage,
            )
        )
    for band in scenario.bands:
        blockage = _peak_blockage(_alone(scenario, band), band.start_m, band.end_m)
        out.append(
            TrueFeature(
                BBB,
                offset + band.start_m,
                offset + band.end_m,
                band.clock_from_h % 12.0 or 12.0,
                band.clock_to_h % 12.0 or 12.0,
                "blockage_ratio",
                blockage,
                blockage,
            )
        )
    return sorted(out, key=lambda f: (f.chainage_start_m, f.code))


# --------------------------------------------------------------------------- scoring


@dataclass(frozen=True)
class FeatureOutcome:
    """How the coder did on one true feature.

    ``outcome`` is ``found`` (one defect of its code), ``split`` (two or more defects),
    ``mis-coded`` (found, but under another code), ``merged`` (no defect of its own: it lies
    inside a defect given to another feature), ``missed`` (no defect there at all) or, when
    the sections are given, ``not measured`` (no defect, and no section over it was measured:
    nothing to code).
    ``clock_error_h`` is the larger of the errors at the arc's two ends, in hours, for a
    feature found with its code and an arc; ``over_threshold`` whether its own figures are over
    the report's threshold (class ``flag_grade`` or worse, or blockage over the threshold).
    """

    feature: TrueFeature
    outcome: str
    defects: tuple[Defect, ...]
    clock_error_h: float | None
    over_threshold: bool


def _clock_gap_h(a: float, b: float) -> float:
    d = abs(a - b) % 12.0
    return min(d, 12.0 - d)


def _arc_hours(start_h: float, end_h: float) -> tuple[float, float]:
    length = (end_h - start_h) % 12.0
    return start_h, length if length > 0 else 12.0


def _arcs_overlap_h(f: TrueFeature, d: Defect, slack_h: float) -> bool:
    if None in (f.clock_from_h, f.clock_to_h, d.clock_from_h, d.clock_to_h):
        return True
    a0, a_len = _arc_hours(f.clock_from_h, f.clock_to_h)  # type: ignore[arg-type]
    b0, b_len = _arc_hours(d.clock_from_h, d.clock_to_h)  # type: ignore[arg-type]
    return (b0 - a0 + slack_h) % 12.0 <= a_len + 2 * slack_h or (
        a0 - b0 + slack_h
    ) % 12.0 <= b_len + 2 * slack_h


def _overlap_m(f: TrueFeature, d: Defect, tol_m: float) -> float:
    lo = max(f.chainage_start_m - tol_m, d.chainage_start_m)
    hi = min(f.chainage_end_m + tol_m, d.chainage_end_m)
    return hi - lo


def score_defects(
    defects: Sequence[Defect],
    truths: Sequence[TrueFeature],
    table: ThresholdTable,
    *,
    pipe_class: str = "rigid",
    blockage_threshold_ratio: float = 0.10,
    flag_grade: int = 2,
    tol_m: float = 0.1,
    slack_h: float = 1.0,
    sections: Sequence[SectionMeasures] | None = None,
) -> tuple[list[FeatureOutcome], list[Defect]]:
    """Match an inspection's defects to the true features, and say how each feature fared.

    A defect can belong to a true feature when their spans overlap (the feature's widened by
    ``tol_m``, a section, each way) and so do their clock arcs (within ``slack_h``). Each
    defect goes to the feature of its own code it overlaps most, else to the one it overlaps
    most. See :class:`FeatureOutcome` for the outcomes.

    Returns
    -------
    outcomes
        One per true feature, in order.
    spurious
        The defects that overlap no true feature.
    """
    owner: dict[int, list[Defect]] = {i: [] for i in range(len(truths))}
    overlapping: dict[int, list[int]] = {i: [] for i in range(len(truths))}
    spurious = []
    for d in defects:
        options = [
            i
            for i, f in enumerate(truths)
            if _overlap_m(f, d, tol_m) > 1e-9 and _arcs_overlap_h(f, d, slack_h)
        ]
        for i in options:
            overlapping[i].append(id(d))
        if not options:
            spurious.append(d)
            continue
        best = max(
            options, key=lambda i: (truths[i].code == d.code, _overlap_m(truths[i], d, tol_m))
        )
        owner[best].append(d)
    outcomes = []
    for i, f in enumerate(truths):
        mine = owner[i]
        right = [d for d in mine if d.code == f.code]
        if len(mine) >= 2:
            outcome = "split"
        elif right:
            outcome = "found"
        elif mine:
            outcome = "mis-coded"
        elif overlapping[i]:
            outcome = "merged"
        elif sections is not None and not any(
            s.is_ok
            and s.chainage_start_m < f.chainage_end_m
            and s.chainage_end_m > f.chainage_start_m
            for s in sections
        ):
            outcome = "not measured"
        else:
            outcome = "missed"
        error = None
        if right and f.clock_from_h is not None and f.clock_to_h is not None:
            error = (
                min(
                    max(
                        _clock_gap_h(f.clock_from_h, d.clock_from_h),
                        _clock_gap_h(f.clock_to_h, d.clock_to_h),
                    )
                    for d in right
                    if d.clock_from_h is not None and d.clock_to_h is not None
                )
                if any(d.clock_from_h is not None for d in right)
                else None
            )
        outcomes.append(
            FeatureOutcome(
                f,
                outcome,
                tuple(mine),
                error,
                _over_threshold(f, table, pipe_class, blockage_threshold_ratio, flag_grade),
            )
        )
    return outcomes, spurious


def _over_threshold(
    f: TrueFeature,
    table: ThresholdTable,
    pipe_class: str,
    blockage_threshold_ratio: float,
    flag_grade: int,
) -> bool:
    if f.peak_blockage_ratio >= blockage_threshold_ratio:
        return True
    grades = [
        r.classify(f.peak_value)
        for r in table.rules
        if r.code == f.code and r.measure == f.measure and r.pipe_class in (None, pipe_class)
    ]
    return bool(grades) and min(grades) <= flag_grade
