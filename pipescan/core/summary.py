"""Figures of an inspection's sections taken together: which sections touch, and the blockage
summary (measured sections, mean and peak).

Each figure has this one definition; the database, the reports, the flows and the CLI call it.

- **Measured** means status ``ok`` with a finite blockage ratio. An unmeasured section is never
  a blockage of 0: it is left out.
- **Peak blockage** is the largest measured blockage ratio, at the start chainage of its
  section; on a tie, the upstream section (the smaller chainage).
- **A pipe's condition class** (its worst grade) is the worst (smallest) class of its measured
  sections; None when none was graded. See :func:`worst_grade`.
- **Touching** sections: one starts where the other ends, within :data:`ADJACENT_TOL_M`.
  Chainages are sums of 0.1 m steps, so exact float equality would split runs on rounding
  noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from pipescan.core.model import SectionMeasures

__all__ = [
    "ADJACENT_TOL_M",
    "DIAMETER_TOLERANCE_RATIO",
    "BlockagePeak",
    "BlockageSummary",
    "InnerDiameter",
    "adjacent_runs",
    "blockage_summary",
    "diameter_mismatch",
    "measured_blockage",
    "measured_inner_diameter",
    "peak_blockage",
    "touches",
    "worst_grade",
]

ADJACENT_TOL_M = 1e-6
"""Sections whose chainage intervals meet within this distance (metres) touch."""


class _Interval(Protocol):
    @property
    def chainage_start_m(self) -> float: ...

    @property
    def chainage_end_m(self) -> float: ...


_S = TypeVar("_S", bound=_Interval)


def touches(end_m: float, start_m: float, *, gap_m: float = 0.0) -> bool:
    """Whether an interval starting at ``start_m`` continues one ending at ``end_m``.

    ``gap_m`` lets up to that much chainage lie between them (the defect coder bridges a
    section lost to a shadow inside one feature); the default is the touching definition.

    >>> touches(0.30000000000000004, 0.3), touches(0.3, 0.4), touches(0.3, 0.4, gap_m=0.1)
    (True, False, True)
    """
    return -ADJACENT_TOL_M <= start_m - end_m <= gap_m + ADJACENT_TOL_M


def adjacent_runs(
    sections: Sequence[_S],
    keep: Sequence[bool] | None = None,
    *,
    same: Callable[[_S], Any] | None = None,
) -> list[range]:
    """Runs of touching sections: the one way sections are merged into spans.

    Parameters
    ----------
    sections
        In chainage order (anything with ``chainage_start_m`` and ``chainage_end_m``).
    keep
        One flag per section: only sections flagged True join runs, and any other section
        ends a run. Default: every section.
    same
        Optionally, a key that must be equal along a run (e.g. the status).

    Returns
    -------
    list of range
        The index ranges of the runs, in order: ``sections[run.start : run.stop]``.

    Examples
    --------
    >>> from types import SimpleNamespace as S
    >>> spans = [S(chainage_start_m=a, chainage_end_m=a + 0.1) for a in (0.0, 0.1, 0.2, 0.5)]
    >>> adjacent_runs(spans), adjacent_runs(spans, [True, False, True, True])
    ([range(0, 3), range(3, 4)], [range(0, 1), range(2, 3), range(3, 4)])
    """
    flags = [True] * len(sections) if keep is None else list(keep)
    if len(flags) != len(sections):
        raise ValueError(f"keep has {len(flags)} flags for {len(sections)} sections")
    runs: list[range] = []
    start: int | None = None
    for i, s in enumerate(sections):
        joins = (
            start is not None
            and flags[i]
            and touches(sections[i - 1].chainage_end_m, s.chainage_start_m)
            and (same is None or same(s) == same(sections[i - 1]))
        )
        if joins:
            continue
        if start is not None:
            runs.append(range(start, i))
        start = i if flags[i] else None
    if start is not None:
        runs.append(range(start, len(sections)))
    return runs


def measured_blockage(section: SectionMeasures) -> float | None:
    """The section's blockage ratio if it was measured (status ``ok``, finite); else None."""
    value = section.blockage_ratio
    if not section.is_ok or value is None or not math.isfinite(value):
        return None
    return float(value)


@dataclass(frozen=True)
class BlockagePeak:
    """The largest measured blockage of a set of sections, and the start chainage of its
    section (metres)."""

    blockage_ratio: float
    chainage_start_m: float


def peak_blockage(sections: Sequence[SectionMeasures]) -> BlockagePeak | None:
    """The peak blockage of sections (see the module's definition); None if none is measured.

    >>> from pipescan.core.model import SectionStatus
    >>> def section(start_m, blockage, status=SectionStatus.OK):
    ...     return SectionMeasures(start_m, start_m + 0.1, 0.2, status, 900, 1.0,
    ...                            blockage_ratio=blockage)
    >>> peak_blockage([section(0.3, 0.2), section(0.1, 0.2), section(0.2, 0.9, "low_coverage")])
    BlockagePeak(blockage_ratio=0.2, chainage_start_m=0.1)
    """
    best: BlockagePeak | None = None
    for s in sections:
        value = measured_blockage(s)
        if value is None:
            continue
        if (
            best is None
            or value > best.blockage_ratio
            or (value == best.blockage_ratio and s.chainage_start_m < best.chainage_start_m)
        ):
            best = BlockagePeak(value, s.chainage_start_m)
    return best


def worst_grade(sections: Sequence[SectionMeasures]) -> int | None:
    """The worst condition class (0 worst ... 4 best) of the ``ok`` sections; None if none
    was graded.

    >>> from pipescan.core.model import SectionStatus
    >>> def section(grade, status=SectionStatus.OK):
    ...     return SectionMeasures(0.0, 0.1, 0.2, status, 900, 1.0, grade=grade)
    >>> worst_grade([section(3), section(1), section(0, "low_coverage"), section(None)])
    1
    """
    grades = [s.grade for s in sections if s.is_ok and s.grade is not None]
    return min(grades) if grades else None


@dataclass(frozen=True)
class BlockageSummary:
    """An inspection's blockage summary, over its measured sections only.

    ``mean_blockage_ratio``, ``peak_blockage_ratio`` and ``peak_chainage_m`` are None when no
    section was measured.
    """

    measured_section_count: int
    mean_blockage_ratio: float | None
    peak_blockage_ratio: float | None
    peak_chainage_m: float | None


def blockage_summary(sections: Sequence[SectionMeasures]) -> BlockageSummary:
    """How many sections were measured, their mean blockage and the peak (see
    :func:`peak_blockage`)."""
    values = [v for s in sections if (v := measured_blockage(s)) is not None]
    peak = peak_blockage(sections)
    return BlockageSummary(
        measured_section_count=len(values),
        mean_blockage_ratio=math.fsum(values) / len(values) if values else None,
        peak_blockage_ratio=None if peak is None else peak.blockage_ratio,
        peak_chainage_m=None if peak is None else peak.chainage_start_m,
    )


DIAMETER_TOLERANCE_RATIO = 0.10
"""How far the wall's measured inner diameter may be from the stated nominal one before the run
stops. Real pipes differ from their nominal diameter by a few per cent (a DN 300 PVC sewer pipe
is 285 mm inside, a concrete one 300 mm within ±1.5 %), and a deformed pipe's median
diameter moves less than its ovality; a tenth is beyond both. Past it, blockage, which is
the open area's share of the nominal area, would read the wrong pipe (a clean 0.80 m pipe
stated as 1.00 m read 38 % blocked)."""

_MIN_DIAMETER_COVERAGE = 0.9
_MIN_DIAMETER_SECTIONS = 3


@dataclass(frozen=True)
class InnerDiameter:
    """The wall's measured inner diameter: the median over sections of twice the median
    radius of each section's contour, and how many sections it rests on."""

    diameter_m: float
    sections: int


def measured_inner_diameter(sections: Sequence[SectionMeasures]) -> InnerDiameter | None:
    """The pipe's inner diameter as its wall measures, or None with too few sections.

    Each section whose contour is known and whose perimeter was seen (90 % of it) gives twice
    its contour's median radius about the axis: a deposit or an obstacle takes a minority of
    the perimeter and moves the median little, an oval keeps its mean radius. The median over
    the sections is the figure. It does not depend on the nominal diameter.

    Examples
    --------
    >>> from pipescan.core.model import SectionStatus
    >>> t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    >>> ring = 0.4 * np.column_stack((np.cos(t), np.sin(t)))
    >>> s = [SectionMeasures(i / 10, i / 10 + 0.1, 0.5, SectionStatus.OK, 1000, 1.0, contour_m=ring)
    ...      for i in range(5)]
    >>> measured_inner_diameter(s)
    InnerDiameter(diameter_m=0.8, sections=5)
    """
    diameters = []
    for s in sections:
        contour = s.contour_m
        if contour is None or len(contour) < 8 or s.coverage_ratio < _MIN_DIAMETER_COVERAGE:
            continue
        radii = np.hypot(contour[:, 0], contour[:, 1])
        diameters.append(2.0 * float(np.median(radii)))
    if len(diameters) < _MIN_DIAMETER_SECTIONS:
        return None
    return InnerDiameter(round(float(np.median(diameters)), 4), len(diameters))


def diameter_mismatch(
    measured: InnerDiameter | None,
    nominal_diameter_m: float,
    tolerance_ratio: float = DIAMETER_TOLERANCE_RATIO,
) -> str | None:
    """Why the stated nominal diameter cannot be right, in one sentence, or None when the
    wall agrees with it (within ``tolerance_ratio``) or was not measured.

    >>> diameter_mismatch(InnerDiameter(0.8, 40), 1.0)
    'the wall measures 0.800 m across (median of 40 sections), 20 % below the stated 1.000 m'
    >>> diameter_mismatch(InnerDiameter(0.8, 40), 0.82) is None
    True
    """
    if measured is None or not math.isfinite(nominal_diameter_m) or nominal_diameter_m <= 0:
        return None
    off = measured.diameter_m / nominal_diameter_m - 1.0
    if abs(off) <= tolerance_ratio:
        return None
    return (
        f"the wall measures {measured.diameter_m:.3f} m across (median of "
        f"{measured.sections} sections), {100 * abs(off):.0f} % {'below' if off < 0 else 'above'} "
        f"the stated {nominal_diameter_m:.3f} m"
    )
