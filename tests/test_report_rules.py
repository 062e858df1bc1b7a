"""The condition report follows its own rules: one flag rule applied to every row, statuses
named for their reason, figures rounded to what they are worth, the limits stated where the
reader meets them, registration's details in an appendix, and tables that neither break inside
a header nor leave a page holding a few rows of their tail."""

from __future__ import annotations

import dataclasses
import re

import pypdf
import pytest

from pipescan.core.grading import flag_section
from pipescan.core.model import SectionStatus
from pipescan.reports import render_html, render_pdf
from pipescan.reports.context import build_context
from pipescan.reports.render import MIN_TAIL_ROWS
from pipescan.reports.sample import sample_input
from tests.test_report import make_input, pdf_text, plain

FLAGS = {"blockage_threshold_ratio": 0.10, "flag_grade": 2}


def _pages(path) -> list[str]:
    return [plain(page.extract_text()) for page in pypdf.PdfReader(str(path)).pages]


@pytest.fixture(scope="module")
def sample():
    return sample_input()


@pytest.fixture(scope="module")
def sample_pdf(sample, tmp_path_factory):
    return render_pdf(sample, tmp_path_factory.mktemp("rules") / "sample.pdf")


def test_no_row_is_flagged_against_the_stated_rule(sample):
    ctx = build_context(sample, chart=False)
    assert ctx["summary"]["flag_rule"] == (
        "blockage of 10.0\u00a0% or more, or condition class 2 or worse"
    )
    by_start = {f"{s.chainage_start_m:.2f}": s for s in sample.sections if s.is_ok}
    rows = [r for r in ctx["sections"] + ctx["worst"] if r["ok"]]
    assert rows
    for row in rows:
        section = by_start[row["start"]]
        assert row["flagged"] == flag_section(section, **FLAGS), row
    # The defects' spans hold sections under the rule (their tails): those are not flagged.
    flagged_spans = [d for d in sample.defects if d.grade is not None and d.grade <= 2]
    inside = [
        s
        for s in sample.sections
        if s.is_ok
        and any(d.chainage_start_m <= s.chainage_start_m < d.chainage_end_m for d in flagged_spans)
    ]
    assert any(not flag_section(s, **FLAGS) for s in inside)
    unflagged_inside = {f"{s.chainage_start_m:.2f}" for s in inside if not flag_section(s, **FLAGS)}
    assert not any(r["flagged"] for r in ctx["sections"] if r["start"] in unflagged_inside)


def test_the_rule_is_stated_once_and_referred_to(sample):
    html = plain(render_html(sample))
    assert html.count("or condition class 2 or worse") == 1


def test_statuses_say_their_reason_in_a_word():
    base = make_input().sections
    changed = []
    for s in base:
        if s.status == SectionStatus.TOO_FEW_POINTS:
            changed += [
                s,
                dataclasses.replace(
                    s,
                    point_count=27_043,
                    chainage_start_m=4.1,
                    chainage_end_m=4.2,
                    coverage_ratio=0.99,
                ),
            ]
        elif s.status == SectionStatus.LOW_COVERAGE and s.chainage_start_m > 1.25:
            changed.append(dataclasses.replace(s, coverage_ratio=0.93, point_count=40_000))
        elif not (4.1 <= s.chainage_start_m < 4.15):
            changed.append(s)
    ctx = build_context(make_input(sections=changed), chart=False)
    status = {r["start"]: r["status"] for r in ctx["sections"]}
    assert status["4.00"] == "too few points"  # 4 points
    assert status["4.10"] == "uncertain: wall scatter"  # 27,043 points
    assert status["1.00"] == "low coverage"  # 42 % seen
    assert status["1.30"] == "low coverage: unseen arc"  # 93 % seen
    reasons = {u["reason"]: plain(u["explanation"]) for u in ctx["unmeasured"]}
    assert reasons["low coverage"].startswith("less than 90 % of the wall, by angle, was seen")
    assert "an unseen arc over 20°" in reasons["low coverage: unseen arc"]
    assert "within ±2.5 points" in reasons["uncertain: wall scatter"]
    assert "fewer than 100 points" in reasons["too few points"]


def test_figures_are_rounded_to_what_they_are_worth(tmp_path):
    sections = [
        dataclasses.replace(s, blockage_uncertainty_ratio=0.0002) if s.is_ok else s
        for s in make_input().sections
    ]
    inp = make_input(sections=sections)
    ctx = build_context(inp, chart=False)
    assert all(plain(r["blockage"]).endswith("± <0.05") for r in ctx["worst"])
    text = pdf_text(render_pdf(inp, tmp_path / "r.pdf"))
    assert "± <0.05" in text
    assert not re.search(r"±\s*0\.0(?!\d)", text)


def test_coverage_limits_are_stated_where_the_reader_sees_coverage(sample_pdf):
    text = re.sub(r"\s+", " ", "\n".join(_pages(sample_pdf)))
    # The chart's caption, the not-measured table, the appendix's lead.
    assert "a section is measured from 90 % (the dotted line)" in text
    assert "less than 90 % of the wall, by angle, was seen" in text
    assert "A section is measured when at least 90 % of its wall was seen" in text


def test_the_cover_says_how_far_to_trust_and_the_appendix_says_why(tmp_path):
    inp = make_input()
    reg = {
        **inp.registration,
        "frames": 40,
        "frame_stride": 3,
        "frame_stride_reason": "each section seen from about 59 positions; bound by the points",
        "chainage_uncertainty_m": 0.09,
        "degenerate_frames": 12,
        "along_axis_prior": "odometer",
        "odometer_uncertainty_ratio": 0.05,
        "odometer_slips_caught_m": [],
        "unconstrained_spans": [{"start_travel_m": 0.5, "end_travel_m": 2.0}],
    }
    pages = _pages(render_pdf(dataclasses.replace(inp, registration=reg), tmp_path / "r.pdf"))
    cover = re.sub(r"\s+", " ", pages[0])
    assert "chainage within ±0.09 m at the end of the scan" in cover
    assert "figures each measured blockage within ±2.5 points (95 %)" in cover
    for developer_words in ("bound by", "ICP", "rested on the odometer", "fitness"):
        assert developer_words not in cover, developer_words
    appendix = re.sub(r"\s+", " ", next(p for p in pages if "Appendix A: registration" in p))
    used = "frames used 40 of 120: every 3rd (each section seen from about 59 positions)"
    assert used in appendix  # stored before every frame was placed
    placed = dataclasses.replace(inp, registration=reg | {"frames_tracked": 78})
    pages = _pages(render_pdf(placed, tmp_path / "placed.pdf"))
    placed_appendix = re.sub(r"\s+", " ", next(p for p in pages if "Appendix A: registration" in p))
    assert "frames registered 40 of 120: every 3rd" in placed_appendix
    assert "frames placed all 120: the 78 between registered ones aligned to the map" in (
        placed_appendix
    )
    assert "rested on the odometer alone" in appendix  # the caveat, in full, for the engineer
    assert "bound by" not in appendix
    assert "sensor" not in appendix  # stored before the instrument was read


def test_the_appendix_names_the_sensor_the_limits_came_from(tmp_path):
    inp = make_input()
    described = (
        "sensor unknown; minimum range 0.50 m (estimated); range noise 6.3 mm (estimated); "
        "one frame sees 97 % of the view (estimated)"
    )
    reg = {**inp.registration, "instrument": described}
    pages = _pages(render_pdf(dataclasses.replace(inp, registration=reg), tmp_path / "s.pdf"))
    appendix = re.sub(r"\s+", " ", next(p for p in pages if "Appendix A: registration" in p))
    assert "sensor minimum range 0.50 m (estimated); range noise 6.3 mm (estimated)" in appendix
    assert "sensor unknown" not in appendix


def test_tables_break_neither_inside_a_header_nor_before_a_short_tail(sample_pdf):
    pages = _pages(sample_pdf)
    trend = next(p for p in pages if "Trend: this inspection" in p)
    assert re.search(r"# code span \(m\) now", trend), trend
    row = re.compile(r"^\d+\.\d\d–\d+\.\d\d ", re.MULTILINE)
    assert "Appendix B" not in pages[-1] and len(row.findall(pages[-1])) >= MIN_TAIL_ROWS
    # The short tables are whole on one page.
    grades = next(p for p in pages if "Measured sections by condition class" in p)
    assert "0 (worst)" in grades and "4 (best)" in grades
    inspections = next(p for p in pages if "Inspections of MH1042-MH1043" in p)
    assert "2021-03-15 09:30 UTC" in inspections.split("Inspections of MH1042-MH1043")[1]


def test_a_lower_bound_defect_reads_at_least_its_figure(sample):
    first = dataclasses.replace(sample.defects[0], lower_bound=True, grade=3)
    inp = dataclasses.replace(sample, defects=[first, *sample.defects[1:]])
    ctx = build_context(inp, chart=False)
    row = ctx["defects"][0]
    assert row["peak_value"].startswith("\u2265\u00a0") and row["grade"] == "3 or worse"
    assert not any(r["peak_value"].startswith("\u2265") for r in ctx["defects"][1:])
    html = render_html(inp)
    assert "the part under the water was not seen" in html
    assert "the part under the water was not seen" not in render_html(sample)
