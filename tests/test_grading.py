"""Grading against threshold tables, flagging, and merging flagged sections into defects."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipescan.core.errors import GradingError, PipescanError
from pipescan.core.grading import (
    available_tables,
    choose_grading,
    flag_section,
    grade_section,
    grade_sections,
    load_table,
    merge_defects,
    pipe_class_for_material,
)
from pipescan.core.model import SectionMeasures, SectionStatus

NOMINAL_AREA_M2 = math.pi * 0.5**2 / 4.0
STEP_M = 0.1


def section(
    index: int,
    *,
    status: SectionStatus = SectionStatus.OK,
    blockage: float | None = 0.0,
    deformation: float | None = 0.0,
    deposit: float | None = 0.0,
    grade: int | None = None,
) -> SectionMeasures:
    """Section ``index`` of a 0.1 m grid; figures None by default when not ok."""
    ok = status == SectionStatus.OK
    return SectionMeasures(
        chainage_start_m=round(index * STEP_M, 10),
        chainage_end_m=round((index + 1) * STEP_M, 10),
        nominal_area_m2=NOMINAL_AREA_M2,
        status=status,
        point_count=1200 if ok else 40,
        coverage_ratio=0.98 if ok else 0.3,
        open_area_m2=NOMINAL_AREA_M2 * (1 - blockage) if blockage is not None else None,
        blockage_ratio=blockage,
        ovality_ratio=0.01 if ok else None,
        deformation_ratio=deformation,
        deposit_height_ratio=deposit,
        grade=grade,
    )


@pytest.fixture(scope="module")
def table():
    return load_table("vsa-2023")


# --- the table ------------------------------------------------------------------------


def test_default_table_transcribes_design(table):
    assert "vsa-2023" in available_tables()
    assert table.name == "vsa-2023"
    assert "VSA" in table.source and "13508-2" in table.source
    by_key = {(r.code, r.pipe_class): r for r in table.rules}
    assert by_key[("BAA", "rigid")].lower_bounds_ratio == (0.07, 0.04, 0.03, 0.01)
    assert by_key[("BAA", "flexible")].lower_bounds_ratio == (0.15, 0.10, 0.06, 0.02)
    assert by_key[("BBC", None)].lower_bounds_ratio == (0.50, 0.40, 0.25, 0.10)
    assert by_key[("BBB", None)].lower_bounds_ratio == (0.30, 0.20, 0.10, 0.05)
    assert by_key[("BBE", None)].lower_bounds_ratio == (0.50, 0.35, 0.20, 0.05)
    assert by_key[("BAA", "rigid")].measure == "deformation_ratio"
    assert by_key[("BBC", None)].measure == "deposit_height_ratio"
    assert by_key[("BBE", None)].measure == "blockage_ratio"
    # v1 grades BAA, BBC and BBE only.
    assert [r.code for r in table.rules_for("rigid")] == ["BAA", "BBC", "BBE"]
    assert [r.pipe_class for r in table.rules_for("flexible")] == ["flexible", None, None]


def test_load_table_by_path(table, tmp_path):
    copy = tmp_path / "copy.toml"
    copy.write_text(
        (Path(__file__).parents[1] / "pipescan/core/tables/vsa-2023.toml").read_text("utf-8"),
        encoding="utf-8",
    )
    loaded = load_table(str(copy))
    assert loaded.rules == table.rules
    assert loaded.path == str(copy)


GOOD_RULE = """
[[rules]]
code = "BAA"
measure = "deformation_ratio"
lower_bounds_ratio = [0.07, 0.04, 0.03, 0.01]
"""


@pytest.mark.parametrize(
    ("text", "field", "words"),
    [
        ('source = "s"\n' + GOOD_RULE, "name", "missing"),
        ('name = "t"\n' + GOOD_RULE, "source", "missing"),
        ('name = "t"\nsource = "s"\n', "rules", "missing"),
        (
            'name = "t"\nsource = "s"\n' + GOOD_RULE.replace("deformation_ratio", "bogus_ratio"),
            "rules[0].measure",
            "not a gradeable measure",
        ),
        (
            'name = "t"\nsource = "s"\n' + GOOD_RULE.replace("0.04, 0.03", "0.03, 0.04"),
            "rules[0].lower_bounds_ratio",
            "not strictly decreasing",
        ),
        (
            'name = "t"\nsource = "s"\n'
            + GOOD_RULE.replace("[0.07, 0.04, 0.03, 0.01]", "[7, 4, 3, 1]"),
            "rules[0].lower_bounds_ratio",
            "percentages",
        ),
        (
            'name = "t"\nsource = "s"\n' + GOOD_RULE.replace(", 0.01]", "]"),
            "rules[0].lower_bounds_ratio",
            "4 finite numbers",
        ),
        (
            'name = "t"\nsource = "s"\n' + GOOD_RULE + 'pipe_class = "soft"\n',
            "rules[0].pipe_class",
            "not a pipe class",
        ),
        (
            'name = "t"\nsource = "s"\n' + GOOD_RULE + "treshold = 1\n",
            "rules[0].treshold",
            "unknown key",
        ),
        (
            'name = "t"\nsource = "s"\n' + GOOD_RULE + 'pipe_class = "rigid"\n',
            "rules",
            "no graded rule applies to flexible",
        ),
    ],
)
def test_table_errors_name_file_and_field(tmp_path, text, field, words):
    path = tmp_path / "bad.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(GradingError) as info:
        load_table(str(path))
    assert info.value.file == str(path)
    assert info.value.field == field
    assert words in str(info.value)
    assert str(path) in str(info.value)


def test_table_errors_unknown_name_missing_file_bad_toml(tmp_path):
    with pytest.raises(GradingError, match=r"unknown threshold table 'vsa-1999'.*vsa-2023"):
        load_table("vsa-1999")
    with pytest.raises(GradingError, match="not found"):
        load_table(str(tmp_path / "absent.toml"))
    broken = tmp_path / "broken.toml"
    broken.write_text("name = [unclosed\n", encoding="utf-8")
    with pytest.raises(PipescanError, match="not valid TOML") as info:
        load_table(broken)
    assert info.value.file == str(broken)


# --- grading one section ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("deformation", "expected"),
    [
        (0.0, 4),
        (0.0099, 4),
        (0.01, 3),
        (0.0299, 3),
        (0.03, 2),
        (0.0399, 2),
        (0.04, 1),
        (0.0699, 1),
        (0.07, 0),
        (0.5, 0),
    ],
)
def test_rigid_baa_boundaries(table, deformation, expected):
    assert grade_section(section(0, deformation=deformation), table) == (expected, "BAA")


@pytest.mark.parametrize(
    ("deformation", "expected"),
    [(0.0199, 4), (0.02, 3), (0.06, 2), (0.0999, 2), (0.10, 1), (0.1499, 1), (0.15, 0)],
)
def test_flexible_baa_boundaries(table, deformation, expected):
    s = section(0, deformation=deformation)
    assert grade_section(s, table, pipe_class="flexible") == (expected, "BAA")


@pytest.mark.parametrize(
    ("deposit", "expected"), [(0.0999, 4), (0.10, 3), (0.25, 2), (0.3999, 2), (0.40, 1), (0.5, 0)]
)
def test_bbc_boundaries(table, deposit, expected):
    s = section(0, deformation=None, blockage=None, deposit=deposit)
    assert grade_section(s, table) == (expected, "BBC")


@pytest.mark.parametrize(
    ("blockage", "expected"),
    [(-0.03, 4), (0.0499, 4), (0.05, 3), (0.1999, 3), (0.20, 2), (0.35, 1), (0.4999, 1), (0.5, 0)],
)
def test_bbe_boundaries(table, blockage, expected):
    s = section(0, deformation=None, deposit=None, blockage=blockage)
    assert grade_section(s, table) == (expected, "BBE")


def test_worst_measure_governs(table):
    # deformation 0.035 -> BAA 2; deposit 0.45 -> BBC 1; blockage 0.25 -> BBE 2.
    s = section(0, deformation=0.035, deposit=0.45, blockage=0.25)
    assert grade_section(s, table) == (1, "BBC")
    # On a tie the first rule in the table (BAA) governs.
    s = section(0, deformation=0.035, deposit=0.0, blockage=0.25)
    assert grade_section(s, table) == (2, "BAA")


def test_missing_measures_are_skipped_not_zero(table):
    s = section(0, deformation=None, deposit=None, blockage=0.30)
    assert grade_section(s, table) == (2, "BBE")
    s = section(0, deformation=math.nan, deposit=None, blockage=None)
    assert grade_section(s, table) == (None, None)


@pytest.mark.parametrize("status", [s for s in SectionStatus if s != SectionStatus.OK])
def test_not_ok_is_ungraded_even_with_figures(table, status):
    s = section(0, status=status, deformation=0.5, deposit=0.6, blockage=0.7)
    assert grade_section(s, table) == (None, None)


def test_grade_sections_sets_grade_only(table):
    sections = [
        section(0, deformation=0.05),
        section(1, status=SectionStatus.LOW_COVERAGE, blockage=None, deformation=None),
    ]
    graded = grade_sections(sections, table)
    assert [s.grade for s in graded] == [1, None]
    assert graded[0].deformation_ratio == 0.05
    assert sections[0].grade is None  # inputs untouched


ratio = st.floats(min_value=-0.2, max_value=1.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    deformation=ratio,
    deposit=ratio,
    blockage=ratio,
    growth=st.floats(min_value=0.0, max_value=0.8),
    which=st.sampled_from(["deformation", "deposit", "blockage"]),
    pipe_class=st.sampled_from(["rigid", "flexible"]),
)
def test_grade_never_improves_when_a_measure_grows(
    table, deformation, deposit, blockage, growth, which, pipe_class
):
    before = {"deformation": deformation, "deposit": deposit, "blockage": blockage}
    after = dict(before)
    after[which] += growth
    grade_before, _ = grade_section(section(0, **before), table, pipe_class=pipe_class)
    grade_after, _ = grade_section(section(0, **after), table, pipe_class=pipe_class)
    assert grade_after <= grade_before


# --- flagging and merging ---------------------------------------------------------------


def test_flag_section_thresholds():
    assert flag_section(section(0, blockage=0.10, grade=3))
    assert not flag_section(section(0, blockage=0.0999, grade=3))
    assert flag_section(section(0, blockage=0.0, grade=2))
    assert not flag_section(section(0, blockage=0.0, grade=3))
    assert flag_section(section(0, blockage=0.0, grade=3), flag_grade=3)
    assert not flag_section(section(0, blockage=0.12, grade=3), blockage_threshold_ratio=0.15)
    low = section(0, status=SectionStatus.LOW_COVERAGE, blockage=0.9, grade=0)
    assert not flag_section(low)


def test_two_spans_separated_by_an_unflagged_section_stay_two(table):
    sections = [
        section(0),
        section(1, blockage=0.12),  # BBE 3, flagged on blockage
        section(2, blockage=0.25),  # BBE 2
        section(3, blockage=0.03),  # ok, not flagged
        section(4, deformation=0.08),  # BAA 0
        section(5, deformation=0.05, blockage=0.11),  # BAA 1
        section(6),
    ]
    defects = merge_defects(list(reversed(sections)), table)  # order of input does not matter
    assert len(defects) == 2
    first, second = defects
    assert (first.chainage_start_m, first.chainage_end_m) == pytest.approx((0.1, 0.3))
    assert (first.code, first.measure, first.grade) == ("BBE", "blockage_ratio", 2)
    assert first.peak_chainage_m == pytest.approx(0.2)
    assert first.peak_value == pytest.approx(0.25)
    assert first.peak_blockage_ratio == pytest.approx(0.25)
    assert (second.chainage_start_m, second.chainage_end_m) == pytest.approx((0.4, 0.6))
    assert (second.code, second.measure, second.grade) == ("BAA", "deformation_ratio", 0)
    assert second.peak_chainage_m == pytest.approx(0.4)
    assert second.peak_value == pytest.approx(0.08)
    assert second.peak_blockage_ratio == pytest.approx(0.11)


def test_a_short_unmeasured_stretch_inside_one_feature_is_bridged(table):
    # One section lost (to a shadow, say) between two sections of the same feature: one
    # defect over all three (v1 split it in two).
    sections = [
        section(0, blockage=0.15),
        section(1, status=SectionStatus.LOW_COVERAGE, blockage=None, deformation=None),
        section(2, blockage=0.18),
    ]
    (defect,) = merge_defects(sections, table)
    assert (defect.chainage_start_m, defect.chainage_end_m) == pytest.approx((0.0, 0.3))
    # Flagged on blockage alone (BBE class 3 > flag grade 2): code is BBE.
    assert (defect.code, defect.grade, defect.peak_value) == ("BBE", 3, pytest.approx(0.18))


def test_a_long_unmeasured_stretch_splits_a_span(table):
    lost = [
        section(i, status=SectionStatus.LOW_COVERAGE, blockage=None, deformation=None)
        for i in (1, 2, 3)
    ]
    sections = [section(0, blockage=0.15), *lost, section(4, blockage=0.18)]
    defects = merge_defects(sections, table)
    ends = [m for d in defects for m in (d.chainage_start_m, d.chainage_end_m)]
    assert ends == pytest.approx([0.0, 0.1, 0.4, 0.5])


def test_a_chainage_gap_splits_a_span(table):
    sections = [section(0, blockage=0.15), section(2, blockage=0.15)]
    assert len(merge_defects(sections, table)) == 2


def test_merge_regrades_ignoring_stored_grade_and_respects_thresholds(table):
    sections = [section(0, blockage=0.12, grade=4), section(1, blockage=0.13, grade=4)]
    (defect,) = merge_defects(sections, table)
    assert defect.grade == 3 and defect.peak_chainage_m == pytest.approx(0.1)
    assert merge_defects(sections, table, blockage_threshold_ratio=0.2) == []
    assert len(merge_defects(sections, table, blockage_threshold_ratio=0.2, flag_grade=3)) == 1


def test_nothing_flagged_gives_no_defects(table):
    assert merge_defects([section(i, blockage=0.02) for i in range(5)], table) == []
    assert merge_defects([], table) == []


# --- choosing the table and the pipe class -----------------------------------------------


@pytest.mark.parametrize(
    ("material", "expected"),
    [
        ("concrete", "rigid"),
        ("Vitrified clay", "rigid"),
        ("vitrified_clay", "rigid"),
        ("Grey cast iron", "rigid"),
        ("PVC-U", "flexible"),
        ("PVC-U DN300 SN8", "flexible"),  # first word
        ("PE-HD", "flexible"),
        ("GRP", "flexible"),
        ("unobtainium", None),
        ("", None),
        (None, None),
    ],
)
def test_pipe_class_for_material(material, expected):
    assert pipe_class_for_material(material) == expected


def test_material_classes_are_not_a_threshold_table():
    assert "_pipe-classes" not in available_tables()


def test_choose_grading_by_material_run_and_class_table():
    auto = choose_grading("PVC")
    assert (auto.table, auto.pipe_class) == ("vsa-2023", "flexible")
    assert auto.reason == "from the material: PVC"
    assert choose_grading("PVC", pipe_class="rigid").pipe_class == "rigid"
    unknown = choose_grading("oak staves")
    assert unknown.pipe_class == "rigid" and "not classified" in unknown.reason
    assert choose_grading(None, fallback_pipe_class="flexible").reason == (
        "assumed: no material recorded"
    )
    per_class = {"flexible": "utility-flexible.toml"}
    assert choose_grading("HDPE", table_by_pipe_class=per_class).table == "utility-flexible.toml"
    assert choose_grading("concrete", table_by_pipe_class=per_class).table == "vsa-2023"
    with pytest.raises(GradingError, match="not a pipe class"):
        choose_grading("PVC", pipe_class="soft")  # type: ignore[arg-type]
    with pytest.raises(GradingError, match="not a pipe class"):
        choose_grading("PVC", table_by_pipe_class={"bendy": "x.toml"})


def test_material_selects_the_deformation_rule(table):
    # 8 % deformation: class 0 in a rigid pipe (>= 7 %), class 2 in a flexible one (6-10 %).
    s = section(0, deformation=0.08)
    for material, grade in (("concrete", 0), ("PVC", 2)):
        choice = choose_grading(material)
        assert grade_section(s, load_table(choice.table), pipe_class=choice.pipe_class) == (
            grade,
            "BAA",
        )
