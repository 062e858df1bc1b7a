"""The defaults of grading that the settings, the flows and the reports share: the threshold
table a run grades against, and the rule that flags a section or defect in a report.

Kept apart from :mod:`pipescan.core.grading` (which re-exports them) so that reading the
settings does not import NumPy and SciPy.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["DEFAULT_TABLE", "FlagRule"]

DEFAULT_TABLE = "vsa-2023"


@dataclass(frozen=True)
class FlagRule:
    """The report's threshold: a section or defect is flagged at ``blockage_threshold_ratio``
    blockage or more, or at condition class ``flag_grade`` or worse
    (:func:`pipescan.core.grading.flag_section`, :func:`pipescan.core.grading.is_flagged`).
    The one place its defaults are written.

    >>> FlagRule.from_params({"flag_grade": 1}).kwargs()
    {'blockage_threshold_ratio': 0.1, 'flag_grade': 1}
    """

    blockage_threshold_ratio: float = 0.10
    flag_grade: int = 2

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> FlagRule:
        """The rule an inspection was stored with (its parameters), the defaults where a
        parameter is missing."""
        return cls(
            blockage_threshold_ratio=params.get(
                "blockage_threshold_ratio", cls.blockage_threshold_ratio
            ),
            flag_grade=params.get("flag_grade", cls.flag_grade),
        )

    def kwargs(self) -> dict[str, Any]:
        """As the keyword arguments of :func:`flag_section` and :func:`is_flagged`."""
        return {
            "blockage_threshold_ratio": self.blockage_threshold_ratio,
            "flag_grade": self.flag_grade,
        }
