"""Condition grades from coded sections, and defects from coded features along the pipe.

Threshold tables are data: TOML files shipped in ``pipescan/core/tables/`` (or any TOML file
given by path), each recording its source. A table holds rules; each rule grades one measure
column of :class:`~pipescan.core.model.SectionMeasures` (a ratio) into condition classes
0 (worst) to 4 (best) for one EN 13508-2 code.

Grading rule (v2, docs/grading.md)
----------------------------------
Each section's displaced wall is first coded (:mod:`pipescan.core.coding`): settled deposits
(BBC), attached deposits (BBB), an obstacle (BBE), a deformation (BAA), or unclassified. A
feature is graded by its own family's rule on its own measure (BBC on
``deposit_height_ratio``, BAA on ``deformation_ratio`` with the pipe class's rule, BBE and BBB
on ``blockage_ratio``); an unclassified feature by the table's graded rules on the figure it
shows. A section's grade is the worst over its features, and class 4 when nothing is coded.
A section that is not ``ok`` is unmeasured: its grade is None, whatever figures it carries.
A measured section without a contour cannot be coded, and is graded as v1 did: the worst class
over the table's graded rules whose measure it has.

Everything here is pure: small dataclasses in, small dataclasses out.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from importlib import resources
from itertools import pairwise
from pathlib import Path
from typing import Any, Literal

from pipescan.core.coding import (
    BAA,
    UNCLASSIFIED,
    CodingParams,
    FeatureRun,
    SectionCoding,
    WallFeature,
    arcs_meet,
    clock_hours,
    code_sections,
    feature_runs,
)
from pipescan.core.contour.base import INVERT_ANGLE_RAD
from pipescan.core.errors import GradingError
from pipescan.core.flags import DEFAULT_TABLE, FlagRule
from pipescan.core.measures import DEPOSIT_TOP_HALF_WIDTH_RAD
from pipescan.core.model import Defect, SectionMeasures
from pipescan.core.summary import peak_blockage

__all__ = [
    "DEFAULT_TABLE",
    "GRADEABLE_MEASURES",
    "FlagRule",
    "GradeRule",
    "GradingChoice",
    "ThresholdTable",
    "available_tables",
    "choose_grading",
    "feature_value",
    "flag_section",
    "grade_feature",
    "grade_section",
    "grade_sections",
    "is_flagged",
    "load_table",
    "merge_defects",
    "pipe_class_for_material",
    "worst_defect",
]

PipeClass = Literal["rigid", "flexible"]

#: The SectionMeasures columns a rule may grade. All are ratios (fractions).
GRADEABLE_MEASURES = frozenset(
    {"deformation_ratio", "deposit_height_ratio", "blockage_ratio", "ovality_ratio"}
)
_PIPE_CLASSES = ("rigid", "flexible")
_N_BOUNDS = 4  # lower bounds of classes 0..3; class 4 is everything below the last
_RULE_KEYS = {"code", "pipe_class", "label", "measure", "lower_bounds_ratio", "graded"}
_TABLE_KEYS = {"name", "title", "source", "rules"}


@dataclass(frozen=True)
class GradeRule:
    """One code's thresholds on one measure column.

    Attributes
    ----------
    code
        EN 13508-2 observation code, e.g. ``"BAA"``.
    measure
        The :class:`SectionMeasures` column graded, e.g. ``"deformation_ratio"``.
    lower_bounds_ratio
        Lower bounds of classes 0, 1, 2, 3 (strictly decreasing fractions). A value at or
        above ``lower_bounds_ratio[k]`` and below ``lower_bounds_ratio[k - 1]`` is class k;
        below the last bound it is class 4.
    pipe_class
        ``"rigid"`` or ``"flexible"`` when the rule applies to one class of pipe only,
        None when it applies to all.
    label
        Human-readable description for reports.
    graded
        False for rules listed for reference only (not used by :func:`grade_section`).
    """

    code: str
    measure: str
    lower_bounds_ratio: tuple[float, float, float, float]
    pipe_class: PipeClass | None = None
    label: str = ""
    graded: bool = True

    def classify(self, value_ratio: float) -> int:
        """Condition class (0 worst ... 4 best) of one measured value (a fraction).

        >>> GradeRule("BAA", "deformation_ratio", (0.07, 0.04, 0.03, 0.01)).classify(0.0699)
        1
        """
        for condition_class, bound in enumerate(self.lower_bounds_ratio):
            if value_ratio >= bound:
                return condition_class
        return _N_BOUNDS

    def applies_to(self, pipe_class: PipeClass) -> bool:
        """Whether this rule grades sections of a pipe of ``pipe_class``."""
        return self.graded and (self.pipe_class is None or self.pipe_class == pipe_class)


@dataclass(frozen=True)
class ThresholdTable:
    """A validated threshold table.

    Attributes
    ----------
    name
        Short name, e.g. ``"vsa-2023"``; stored with each graded inspection.
    source
        Full citation of where the thresholds come from.
    rules
        The rules, in file order (which also breaks ties between codes of equal class).
    title
        Optional longer title.
    path
        The file it was read from.
    """

    name: str
    source: str
    rules: tuple[GradeRule, ...]
    title: str = ""
    path: str = ""

    def rules_for(self, pipe_class: PipeClass) -> tuple[GradeRule, ...]:
        """The graded rules applying to a pipe of ``pipe_class``, in table order."""
        return tuple(r for r in self.rules if r.applies_to(pipe_class))


def _tables_dir() -> Any:
    return resources.files("pipescan.core").joinpath("tables")


def available_tables() -> list[str]:
    """Names of the threshold tables shipped with pipescan, sorted.

    Files whose names start with ``_`` in the tables folder are other grading data (the
    material classes), not threshold tables.

    Returns
    -------
    list of str
        E.g. ``["vsa-2023"]``; each can be passed to :func:`load_table`.
    """
    return sorted(
        entry.name.removesuffix(".toml")
        for entry in _tables_dir().iterdir()
        if entry.name.endswith(".toml") and not entry.name.startswith("_")
    )


def load_table(name_or_path: str | Path = DEFAULT_TABLE) -> ThresholdTable:
    """Read and validate a threshold table.

    Parameters
    ----------
    name_or_path
        The name of a shipped table (see :func:`available_tables`) or the path of a TOML file.

    Returns
    -------
    ThresholdTable

    Raises
    ------
    GradingError
        The table is unknown, unreadable, not TOML, or a field is missing or invalid. The
        error names the file and the field.

    Examples
    --------
    >>> load_table("vsa-2023").rules_for("rigid")[0].lower_bounds_ratio
    (0.07, 0.04, 0.03, 0.01)
    """
    text, file_label = _read_table_text(name_or_path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise GradingError(
            f"not valid TOML: {exc}", file=file_label, hint="fix the TOML syntax"
        ) from exc
    return _parse_table(data, file_label)


def _read_table_text(name_or_path: str | Path) -> tuple[str, str]:
    text_name = str(name_or_path)
    looks_like_path = (
        isinstance(name_or_path, Path) or text_name.endswith(".toml") or "/" in text_name
    )
    if looks_like_path:
        path = Path(name_or_path)
        try:
            return path.read_text(encoding="utf-8"), str(path)
        except FileNotFoundError as exc:
            raise GradingError(
                "threshold table file not found",
                file=str(path),
                hint=f"give an existing TOML file or one of {available_tables()}",
            ) from exc
        except (OSError, UnicodeDecodeError) as exc:
            raise GradingError(f"cannot read threshold table: {exc}", file=str(path)) from exc
    entry = _tables_dir().joinpath(f"{text_name}.toml")
    if not entry.is_file():
        raise GradingError(
            f"unknown threshold table {text_name!r}",
            hint=f"use one of {available_tables()} or the path of a TOML file",
        )
    return entry.read_text(encoding="utf-8"), f"{text_name}.toml"


def _parse_table(data: dict[str, Any], file_label: str) -> ThresholdTable:
    def fail(field: str, message: str, hint: str | None = None) -> GradingError:
        return GradingError(message, file=file_label, field=field, hint=hint)

    unknown = set(data) - _TABLE_KEYS
    if unknown:
        raise fail(sorted(unknown)[0], "unknown key", hint=f"allowed keys: {sorted(_TABLE_KEYS)}")
    for key in ("name", "source"):
        value = data.get(key)
        if not isinstance(value, str) or not value.strip():
            raise fail(key, "missing or empty", hint="give a non-empty string")
    title = data.get("title", "")
    if not isinstance(title, str):
        raise fail("title", "must be a string")
    raw_rules = data.get("rules")
    if not isinstance(raw_rules, list) or not raw_rules:
        raise fail("rules", "missing or empty", hint="add at least one [[rules]] table")
    rules = tuple(_parse_rule(raw, f"rules[{i}]", fail) for i, raw in enumerate(raw_rules))
    for pipe_class in _PIPE_CLASSES:
        if not any(r.applies_to(pipe_class) for r in rules):  # type: ignore[arg-type]
            raise fail(
                "rules",
                f"no graded rule applies to {pipe_class} pipes",
                hint="set graded = true on at least one rule without a pipe_class",
            )
    return ThresholdTable(
        name=data["name"].strip(),
        source=data["source"].strip(),
        rules=rules,
        title=title.strip(),
        path=file_label,
    )


def _parse_rule(raw: Any, where: str, fail: Any) -> GradeRule:
    if not isinstance(raw, dict):
        raise fail(where, "must be a table", hint="write it as [[rules]]")
    unknown = set(raw) - _RULE_KEYS
    if unknown:
        raise fail(
            f"{where}.{sorted(unknown)[0]}", "unknown key", hint=f"allowed: {sorted(_RULE_KEYS)}"
        )
    code = raw.get("code")
    if not isinstance(code, str) or not code.strip():
        raise fail(f"{where}.code", "missing or empty", hint='e.g. code = "BAA"')
    measure = raw.get("measure")
    if measure not in GRADEABLE_MEASURES:
        raise fail(
            f"{where}.measure",
            f"{measure!r} is not a gradeable measure",
            hint=f"use one of {sorted(GRADEABLE_MEASURES)}",
        )
    pipe_class = raw.get("pipe_class")
    if pipe_class is not None and pipe_class not in _PIPE_CLASSES:
        raise fail(
            f"{where}.pipe_class",
            f"{pipe_class!r} is not a pipe class",
            hint='use "rigid" or "flexible", or leave it out',
        )
    bounds = raw.get("lower_bounds_ratio")
    if (
        not isinstance(bounds, list)
        or len(bounds) != _N_BOUNDS
        or not all(isinstance(b, int | float) and not isinstance(b, bool) for b in bounds)
        or not all(math.isfinite(b) for b in bounds)
    ):
        raise fail(
            f"{where}.lower_bounds_ratio",
            "must be a list of 4 finite numbers",
            hint="lower bounds of classes 0, 1, 2, 3 as fractions, e.g. [0.07, 0.04, 0.03, 0.01]",
        )
    if any(hi <= lo for hi, lo in pairwise(bounds)):
        raise fail(
            f"{where}.lower_bounds_ratio",
            f"{bounds} is not strictly decreasing",
            hint="class 0 (worst) has the highest lower bound",
        )
    if bounds[0] > 1.0:
        raise fail(
            f"{where}.lower_bounds_ratio",
            f"{bounds} looks like percentages",
            hint="bounds are fractions: write 0.07 for 7 %",
        )
    graded = raw.get("graded", True)
    if not isinstance(graded, bool):
        raise fail(f"{where}.graded", "must be true or false")
    label = raw.get("label", "")
    if not isinstance(label, str):
        raise fail(f"{where}.label", "must be a string")
    return GradeRule(
        code=code.strip(),
        measure=measure,
        lower_bounds_ratio=tuple(float(b) for b in bounds),  # type: ignore[arg-type]
        pipe_class=pipe_class,
        label=label,
        graded=graded,
    )


def _measure_value(s: SectionMeasures, measure: str) -> float | None:
    value = getattr(s, measure)
    if value is None or not math.isfinite(value):
        return None
    return float(value)


def feature_value(
    feature: WallFeature, s: SectionMeasures, coding: SectionCoding | None = None
) -> float | None:
    """The figure that quantifies a feature in its section: its measure's value there.

    For ``blockage_ratio`` it is the feature's own share: the section's blockage less the
    areas the other features coded in the section take (each between the wall and the
    contour over its own arc), so an obstacle over a deposit is not charged with the deposit.
    Alone in its section, a feature's blockage is the section's. None when the figure is
    missing, and for a deposit when another feature of the section stands over the invert
    where its height is read: that height is the other feature's top, not the deposit's.

    >>> from pipescan.core.model import SectionStatus
    >>> band = WallFeature("BBB", 4.2, 5.2, 0.004, 0.015, "a band")
    >>> fill = WallFeature("BBC", 3.9, 5.5, 0.018, 0.07, "a chord", measure="deposit_height_ratio")
    >>> s = SectionMeasures(0.0, 0.1, 0.2, SectionStatus.OK, 900, 1.0, blockage_ratio=0.11)
    >>> round(feature_value(band, s, SectionCoding((fill, band), 0.25, 0.001, 0.0075)), 3)
    0.02
    """
    if feature.measure == "deposit_height_ratio" and _over_the_invert(feature, coding):
        return None
    if feature.measure != "blockage_ratio":
        return _measure_value(s, feature.measure)
    return _own_blockage(feature, s, coding)


def _over_the_invert(feature: WallFeature, coding: SectionCoding | None) -> bool:
    """Whether another feature of the section (with an arc: not a deformation) covers the
    invert where a section's deposit height is read
    (``measures.DEPOSIT_TOP_HALF_WIDTH_RAD`` either side of straight down)."""
    if coding is None:
        return False
    invert, half = INVERT_ANGLE_RAD, DEPOSIT_TOP_HALF_WIDTH_RAD
    window = WallFeature("", invert - half, invert + half, 0.0, 0.0, "the invert")
    return any(
        g is not feature and g.arc_from_rad is not None and arcs_meet(g, window, 0.0)
        for g in coding.features
    )


def _own_blockage(
    feature: WallFeature, s: SectionMeasures, coding: SectionCoding | None
) -> float | None:
    """The section's blockage less the areas of the other features coded in it."""
    value = _measure_value(s, "blockage_ratio")
    if value is None or coding is None:
        return value
    others = sum(g.lost_area_m2 for g in coding.features if g is not feature)
    if not s.nominal_area_m2 > 0:
        return value
    return max(0.0, value - others / s.nominal_area_m2)


def _worst(
    s: SectionMeasures, rules: Iterable[GradeRule], value: float | None = None
) -> tuple[int | None, GradeRule | None]:
    """The worst class the rules give the section's figures (or ``value``, for every rule);
    on a tie, the first rule."""
    worst: tuple[int, GradeRule] | None = None
    given = value
    for rule in rules:
        value = _measure_value(s, rule.measure) if given is None else given
        if value is None:
            continue
        condition_class = rule.classify(value)
        # Strictly lower only: on a tie the earlier rule in the table governs.
        if worst is None or condition_class < worst[0]:
            worst = (condition_class, rule)
    if worst is None:
        return None, None
    return worst


def _grade_with_rule(
    s: SectionMeasures, table: ThresholdTable, pipe_class: PipeClass
) -> tuple[int | None, GradeRule | None]:
    """v1: the worst class over every graded rule (for sections that cannot be coded)."""
    if not s.is_ok:
        return None, None
    return _worst(s, table.rules_for(pipe_class))


def grade_feature(
    feature: WallFeature,
    s: SectionMeasures,
    table: ThresholdTable,
    *,
    pipe_class: PipeClass = "rigid",
    coding: SectionCoding | None = None,
) -> tuple[int | None, GradeRule | None]:
    """Grade one coded feature of a section: its family's rule on its own figure
    (:func:`feature_value`; ``coding`` is the section's, for a blockage's own share).

    A feature of a known family is graded by every rule of the table with its code (graded or
    not: ``graded = false`` only keeps a rule from grading what could not be coded) that
    applies to the pipe class and grades the feature's measure; an unclassified feature by
    the table's graded rules on the figure it shows (:attr:`WallFeature.measure`).

    Returns
    -------
    grade : int or None
        0 (worst) ... 4 (best); None when the section is not ``ok``, its figure is missing, or
        no rule of the table grades that code. A section with water in its invert whose
        figures are lower bounds (``SectionMeasures.is_lower_bound``) is graded on them: its
        feature is at least that bad.
    rule : GradeRule or None
        The rule that gave the grade.

    Examples
    --------
    An obstacle is graded on the blockage, whatever the deformation figure says:

    >>> from pipescan.core.model import SectionStatus
    >>> obstacle = WallFeature("BBE", 4.5, 5.0, 0.01, 0.1, "a body", measure="blockage_ratio")
    >>> s = SectionMeasures(0.0, 0.1, 0.5, SectionStatus.OK, 900, 1.0, blockage_ratio=0.035,
    ...                     deformation_ratio=0.043)
    >>> grade, rule = grade_feature(obstacle, s, load_table())
    >>> grade, rule.code
    (4, 'BBE')
    """
    if not (s.is_ok or s.is_lower_bound):
        return None, None
    if feature.code == UNCLASSIFIED:
        rules = [r for r in table.rules_for(pipe_class) if r.measure == feature.measure]
    else:
        rules = [
            r
            for r in table.rules
            if r.code == feature.code
            and r.measure == feature.measure
            and (r.pipe_class is None or r.pipe_class == pipe_class)
        ]
    value = feature_value(feature, s, coding)
    if value is None:
        return None, None
    return _worst(s, rules, value)


def _section_grade(
    s: SectionMeasures, coding: SectionCoding | None, table: ThresholdTable, pipe_class: PipeClass
) -> tuple[int | None, str | None]:
    if not s.is_ok:
        return None, None
    if coding is None:
        grade, rule = _grade_with_rule(s, table, pipe_class)
        return grade, (rule.code if rule is not None else None)
    worst: tuple[int, str] | None = None
    for feature in coding.features:
        grade, rule = grade_feature(feature, s, table, pipe_class=pipe_class, coding=coding)
        if grade is not None and (worst is None or grade < worst[0]):
            worst = (grade, feature.code)
    if worst is None:
        return _N_BOUNDS, None  # nothing coded (or nothing gradeable): no defect
    return worst


def grade_section(
    s: SectionMeasures,
    table: ThresholdTable,
    *,
    pipe_class: PipeClass = "rigid",
    coding: SectionCoding | None = None,
    params: CodingParams = CodingParams(),
) -> tuple[int | None, str | None]:
    """Grade one section: the worst class over its coded features, and the code of that one.

    Parameters
    ----------
    s
        The section. Only ``ok`` sections are graded.
    table
        The threshold table (see :func:`load_table`).
    pipe_class
        ``"rigid"`` or ``"flexible"``: selects the BAA deformation rule.
    coding
        The section's coding; by default it is coded from its contour
        (:func:`pipescan.core.coding.code_section`). A section without a contour cannot be
        coded and is graded as v1 did: the worst class over the table's graded rules.
    params
        The coder's parameters, when the section is coded here.

    Returns
    -------
    grade : int or None
        0 (worst) ... 4 (best): 4 when nothing is coded; None when the status is not ``ok``.
    code : str or None
        The code of the feature (or, uncoded, of the rule) that gives that grade; None when
        nothing does.

    Examples
    --------
    BAA on a rigid pipe, for a section without a contour (graded as v1): 7 % deformation or
    more is class 0, 4-7 % class 1.

    >>> from pipescan.core.model import SectionStatus
    >>> s = SectionMeasures(0.0, 0.1, 0.196, SectionStatus.OK, 900, 1.0,
    ...                     deformation_ratio=0.0699)
    >>> grade_section(s, load_table())
    (1, 'BAA')
    """
    if coding is None:
        coding = code_sections([s], params)[0]
    return _section_grade(s, coding, table, pipe_class)


def grade_sections(
    sections: Iterable[SectionMeasures],
    table: ThresholdTable,
    *,
    pipe_class: PipeClass = "rigid",
    codings: Sequence[SectionCoding | None] | None = None,
    params: CodingParams = CodingParams(),
) -> list[SectionMeasures]:
    """Copies of ``sections`` with ``grade`` set by :func:`grade_section` (None if unmeasured).

    ``codings`` (one per section, see :func:`pipescan.core.coding.code_sections`) saves coding
    the sections again when the caller has them.
    """
    sections = list(sections)
    if codings is None:
        codings = code_sections(sections, params)
    if len(codings) != len(sections):
        raise ValueError(f"{len(codings)} codings for {len(sections)} sections")
    return [
        replace(s, grade=_section_grade(s, c, table, pipe_class)[0])
        for s, c in zip(sections, codings, strict=True)
    ]


def flag_section(
    s: SectionMeasures,
    *,
    blockage_threshold_ratio: float = FlagRule.blockage_threshold_ratio,
    flag_grade: int = FlagRule.flag_grade,
) -> bool:
    """Whether a section is over the report's threshold.

    A section is flagged when its status is ``ok`` and its blockage is at or above
    ``blockage_threshold_ratio``, or its (already computed) ``grade`` is ``flag_grade`` or
    worse. Unmeasured sections are never flagged: they are reported as unmeasured instead.

    Parameters
    ----------
    s
        The section, graded (see :func:`grade_sections`).
    blockage_threshold_ratio
        Blockage (a fraction) at or above which a section is flagged; 0.10 is 10 %.
    flag_grade
        Condition class at or below which (i.e. as bad or worse) a section is flagged.
    """
    if not s.is_ok:
        return False
    blockage = _measure_value(s, "blockage_ratio")
    if blockage is not None and blockage >= blockage_threshold_ratio:
        return True
    return s.grade is not None and s.grade <= flag_grade


def is_flagged(
    defect: Defect,
    *,
    blockage_threshold_ratio: float = FlagRule.blockage_threshold_ratio,
    flag_grade: int = FlagRule.flag_grade,
) -> bool:
    """Whether a defect is over the report's threshold: its class is ``flag_grade`` or worse,
    or its peak blockage is at or above ``blockage_threshold_ratio``. A defect graded on its
    blockage counts its own share too: under water (a lower bound) the sections give no
    measured blockage, and the feature alone takes at least that much.

    >>> from pipescan.core.model import Defect
    >>> under = Defect("BBE", "blockage_ratio", 2.6, 2.9, 2.8, 0.171, None, 3, lower_bound=True)
    >>> is_flagged(under), is_flagged(replace(under, peak_value=0.05))
    (True, False)
    """
    if defect.grade is not None and defect.grade <= flag_grade:
        return True
    peaks = [defect.peak_blockage_ratio]
    if defect.measure == "blockage_ratio":
        peaks.append(defect.peak_value)
    return any(p is not None and math.isfinite(p) and p >= blockage_threshold_ratio for p in peaks)


def _coder_estimate(feature: WallFeature, s: SectionMeasures) -> float:
    """The coder's own estimate of a feature's figure, as a ratio: its height (a deposit) or
    its diameter loss (a deformation) over the nominal diameter, else its lost area over the
    nominal area."""
    if feature.measure == "blockage_ratio" or not s.nominal_area_m2 > 0:
        return feature.lost_area_m2 / s.nominal_area_m2 if s.nominal_area_m2 > 0 else 0.0
    return feature.height_m / s.nominal_diameter_m


def worst_defect(defects: Iterable[Defect]) -> Defect | None:
    """The defect that sets a pipe's condition: the worst class (an ungraded one last), then
    the largest peak blockage, then the upstream one. None when there is none.

    >>> a = Defect("BBE", "blockage_ratio", 1.0, 1.2, 1.1, 0.035, 0.035, 4)
    >>> b = Defect("BBC", "deposit_height_ratio", 3.4, 4.0, 3.8, 0.285, 0.235, 2)
    >>> worst_defect([a, b]).code
    'BBC'
    """

    def key(d: Defect) -> tuple[int, float, float]:
        peak = d.peak_blockage_ratio
        return (
            d.grade if d.grade is not None else _N_BOUNDS + 1,
            -(peak if peak is not None and math.isfinite(peak) else -math.inf),
            d.chainage_start_m,
        )

    return min(defects, key=key, default=None)


def _uncoded(s: SectionMeasures, table: ThresholdTable, pipe_class: PipeClass, **flags: Any):
    """A measured section without a contour, as v1 saw it: one feature of the governing
    rule's code when the section is flagged, none otherwise."""
    grade, rule = _grade_with_rule(s, table, pipe_class)
    if not flag_section(replace(s, grade=grade), **flags):
        return SectionCoding((), float("nan"), float("nan"), float("nan"))
    blockage_rule = next(
        (r for r in table.rules_for(pipe_class) if r.measure == "blockage_ratio"), None
    )
    if rule is None or (grade is not None and grade > flags["flag_grade"] and blockage_rule):
        rule = blockage_rule  # flagged on blockage alone
    code, measure = (rule.code, rule.measure) if rule is not None else ("", "blockage_ratio")
    feature = WallFeature(code, None, None, 0.0, 0.0, "not coded: no contour", measure=measure)
    return SectionCoding((feature,), float("nan"), float("nan"), float("nan"))


def merge_defects(
    sections: Sequence[SectionMeasures],
    table: ThresholdTable,
    *,
    blockage_threshold_ratio: float = FlagRule.blockage_threshold_ratio,
    flag_grade: int = FlagRule.flag_grade,
    pipe_class: PipeClass = "rigid",
    codings: Sequence[SectionCoding | None] | None = None,
    params: CodingParams = CodingParams(),
) -> list[Defect]:
    """The inspection's defects: one per physical feature, coded, located and graded.

    Sections are coded (or ``codings`` given, one per section in the order given), taken in
    chainage order, and their features followed along the chainage into runs
    (:func:`pipescan.core.coding.feature_runs`: same code, overlapping arcs, touching sections
    or a short stretch of unmeasured ones; a deposit's ramp and an obstacle's shadowed rear
    join their feature). Each run is one defect:

    - ``code``: the family; ``grade``: the worst :func:`grade_feature` over its sections;
    - ``measure``, ``peak_value``, ``peak_chainage_m``: the family's measure, its largest value
      in the run (:func:`feature_value`: a blockage is the feature's own share), and the start
      of that section (the upstream one on a tie);
    - ``peak_blockage_ratio``: the largest measured blockage over the run's span (all that is
      lost there, whatever takes it);
    - ``clock_from_h``, ``clock_to_h``: the union of its sections' displaced arcs;
    - ``characterisation``: a deformation's, at its peak;
    - ``lower_bound``: a section of the run had water in its invert, which returned nothing:
      its figure, and so the peak and the class, are at least what they say.

    A defect of a known family is listed whatever its class (it is an observation; see
    :func:`is_flagged` for the report's threshold). An unclassified one is listed only when it
    is flagged or its class reaches the table's classes (0-3): a small thing whose family is not
    known is not worth a look. Sections without a contour cannot be coded: each flagged one
    counts as a feature of its governing rule's code (as v1 did). A run whose figure is missing
    in every section is listed ungraded, with the coder's own estimate of it as its peak.

    Parameters
    ----------
    sections
        The sections of one inspection, in any order.
    table
        Threshold table.
    blockage_threshold_ratio, flag_grade
        The report's threshold, see :func:`is_flagged`.
    pipe_class
        ``"rigid"`` or ``"flexible"``.
    codings, params
        The sections' codings (one per section, in the order of ``sections``), or the coder's
        parameters to code them here.

    Returns
    -------
    list of Defect
        In chainage order; empty when nothing is coded.
    """
    if codings is None:
        codings = code_sections(sections, params)
    if len(codings) != len(sections):
        raise ValueError(f"{len(codings)} codings for {len(sections)} sections")
    order = sorted(range(len(sections)), key=lambda i: sections[i].chainage_start_m)
    ordered = [sections[i] for i in order]
    flags = FlagRule(blockage_threshold_ratio, flag_grade).kwargs()
    coded: list[SectionCoding | None] = []
    for i in order:
        s, c = sections[i], codings[i]
        if s.is_lower_bound:
            coded.append(c)  # what the water leaves to code (coding.lower_bound_coding)
        elif not s.is_ok:
            coded.append(None)
        elif c is None:
            coded.append(_uncoded(s, table, pipe_class, **flags))
        else:
            coded.append(c)

    defects = [
        _run_defect(run, ordered, coded, table, pipe_class) for run in feature_runs(ordered, coded)
    ]
    return [
        d
        for d in defects
        if d.code != UNCLASSIFIED
        or is_flagged(d, **flags)
        or (d.grade is not None and d.grade < _N_BOUNDS)
    ]


def _run_defect(
    run: FeatureRun,
    ordered: Sequence[SectionMeasures],
    coded: Sequence[SectionCoding | None],
    table: ThresholdTable,
    pipe_class: PipeClass,
) -> Defect:
    """One run of a feature along the chainage as a defect (see :func:`merge_defects`)."""
    graded = [
        grade_feature(f, ordered[k], table, pipe_class=pipe_class, coding=coded[k])[0]
        for k, f in zip(run.sections, run.features, strict=True)
    ]
    grades = [g for g in graded if g is not None]
    # The run's figure is its code's measure: a section that joined it with another code
    # (a deposit's unclassified ramp, graded on its blockage) is graded, but its figure,
    # in other units, does not compete for the peak.
    measure = next(f.measure for f in run.features if f.code == run.code)
    own = [(k, f) for k, f in zip(run.sections, run.features, strict=True) if f.measure == measure]
    candidates = [
        (value, k, f)
        for k, f in own
        if (value := feature_value(f, ordered[k], coded[k])) is not None
    ]
    if not candidates:
        # The figure is missing in every section of the run (the bins it is read from were
        # not seen): the feature is still listed, ungraded, with the coder's own estimate.
        candidates = [(_coder_estimate(f, ordered[k]), k, f) for k, f in own]
    # max() keeps the first of equal values, so ties go to the upstream section.
    peak_value, peak_index, peak_feature = max(candidates, key=lambda c: c[0])
    first, last = run.sections[0], run.sections[-1]
    span_peak = peak_blockage(ordered[first : last + 1])
    arc_from, arc_to = run.arc()
    return Defect(
        code=run.code,
        measure=measure,
        chainage_start_m=ordered[first].chainage_start_m,
        chainage_end_m=ordered[last].chainage_end_m,
        peak_chainage_m=ordered[peak_index].chainage_start_m,
        peak_value=peak_value,
        peak_blockage_ratio=None if span_peak is None else span_peak.blockage_ratio,
        grade=min(grades) if grades else None,
        clock_from_h=None if arc_from is None else clock_hours(arc_from),
        clock_to_h=None if arc_to is None else clock_hours(arc_to),
        characterisation=peak_feature.characterisation if run.code == BAA else None,
        lower_bound=any(ordered[k].is_lower_bound for k in run.sections),
    )


# --- choosing the table and the pipe class ---------------------------------------------------

_MATERIALS_FILE = "_pipe-classes.toml"


@dataclass(frozen=True)
class GradingChoice:
    """Which threshold table and which pipe class grade one inspection, and why.

    Attributes
    ----------
    table
        Name (or path) of the threshold table, for :func:`load_table`.
    pipe_class
        ``"rigid"`` or ``"flexible"``: selects the table's BAA deformation rule.
    reason
        Why that pipe class, in words for the report, e.g.
        ``"from the material: PVC-U"``.
    """

    table: str
    pipe_class: PipeClass
    reason: str


def _normalise_material(material: str) -> str:
    return " ".join(material.lower().replace("_", " ").replace("-", " ").split())


def _material_classes() -> dict[str, PipeClass]:
    text = _tables_dir().joinpath(_MATERIALS_FILE).read_text(encoding="utf-8")
    data = tomllib.loads(text)
    classes: dict[str, PipeClass] = {}
    for pipe_class in _PIPE_CLASSES:
        for material in data.get(pipe_class, {}).get("materials", []):
            classes[_normalise_material(material)] = pipe_class  # type: ignore[assignment]
    return classes


def pipe_class_for_material(material: str | None) -> PipeClass | None:
    """The pipe class (rigid or flexible) of a pipe material, or None when it is not known.

    The classes are data (``tables/_pipe-classes.toml``). Matching ignores case, hyphens and
    underscores, and tries the whole name first, then its first word (``"PVC-U"`` matches
    ``"pvc u"``, then ``"pvc"``).

    Parameters
    ----------
    material
        As recorded in ``inspection.toml`` (``material = "vitrified clay"``), or None.

    Examples
    --------
    >>> pipe_class_for_material("Vitrified clay"), pipe_class_for_material("PE-HD")
    ('rigid', 'flexible')
    >>> pipe_class_for_material("unobtainium") is None
    True
    """
    if material is None or not material.strip():
        return None
    classes = _material_classes()
    name = _normalise_material(material)
    if name in classes:
        return classes[name]
    return classes.get(name.split(" ")[0])


def choose_grading(
    material: str | None,
    *,
    pipe_class: Literal["rigid", "flexible", "auto"] = "auto",
    table: str = DEFAULT_TABLE,
    table_by_pipe_class: dict[str, str] | None = None,
    fallback_pipe_class: PipeClass = "rigid",
) -> GradingChoice:
    """Choose the threshold table and pipe class for one inspection.

    Parameters
    ----------
    material
        The pipe's material, as recorded (may be None).
    pipe_class
        ``"rigid"`` or ``"flexible"`` to set it for the run; ``"auto"`` to take it from the
        material (:func:`pipe_class_for_material`), falling back to ``fallback_pipe_class``
        when the material is missing or unknown.
    table
        The table for the run (a shipped name or a TOML path).
    table_by_pipe_class
        Optional per-class tables, e.g. ``{"flexible": "my-utility-flexible.toml"}``; a class
        listed here overrides ``table``.
    fallback_pipe_class
        The class assumed for an unknown material under ``"auto"``.

    Returns
    -------
    GradingChoice

    Raises
    ------
    GradingError
        If ``pipe_class`` or a key of ``table_by_pipe_class`` is not a pipe class.

    Examples
    --------
    >>> choose_grading("PVC").pipe_class
    'flexible'
    >>> choose_grading("PVC", pipe_class="rigid").reason
    'set for the run'
    """
    if pipe_class not in (*_PIPE_CLASSES, "auto"):
        raise GradingError(
            f"{pipe_class!r} is not a pipe class",
            field="pipe_class",
            hint='use "rigid", "flexible" or "auto" (from the material)',
        )
    for key in table_by_pipe_class or {}:
        if key not in _PIPE_CLASSES:
            raise GradingError(
                f"{key!r} is not a pipe class",
                field="table_by_pipe_class",
                hint='map "rigid" and/or "flexible" to table names',
            )
    chosen: PipeClass
    if pipe_class != "auto":
        chosen, reason = pipe_class, "set for the run"  # type: ignore[assignment]
    else:
        from_material = pipe_class_for_material(material)
        if from_material is not None:
            chosen, reason = from_material, f"from the material: {material}"
        elif material is None or not material.strip():
            chosen, reason = fallback_pipe_class, "assumed: no material recorded"
        else:
            chosen, reason = fallback_pipe_class, f"assumed: material {material!r} not classified"
    table_name = (table_by_pipe_class or {}).get(chosen, table)
    return GradingChoice(table=table_name, pipe_class=chosen, reason=reason)
