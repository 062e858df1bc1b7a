"""The per-inspection report: context, HTML (escaping) and the rendered PDF's text."""

from __future__ import annotations

import dataclasses
import math
import re
import time
from datetime import UTC, datetime
from pathlib import Path

import pytest

from pipescan.core.grading import grade_sections, load_table, merge_defects
from pipescan.core.model import SectionMeasures, SectionStatus
from pipescan.reports import ReportInput, TableCitation, build_context, render_html, render_pdf
from pipescan.reports.charts import blockage_chart_svg
from pipescan.reports.context import fmt_pct

pypdf = pytest.importorskip("pypdf")

DIAMETER_M = 0.5
NOMINAL_AREA_M2 = math.pi * DIAMETER_M**2 / 4.0
STEP_M = 0.1
N_SECTIONS = 60
# Ground truth of the synthetic inspection.
LOW_COVERAGE = range(10, 14)  # 1.00-1.40 m
TOO_FEW_POINTS = (40,)  # 4.00-4.10 m
OBSTACLE = {20: 0.12, 21: 0.24, 22: 0.31, 23: 0.18, 24: 0.11}  # blockage, 2.00-2.50 m
DEPOSIT = {50: 0.30, 51: 0.27}  # deposit height ratio (BBC class 2), 5.00-5.20 m


def _sections() -> list[SectionMeasures]:
    out = []
    for i in range(N_SECTIONS):
        start_m, end_m = round(i * STEP_M, 10), round((i + 1) * STEP_M, 10)
        if i in LOW_COVERAGE or i in TOO_FEW_POINTS:
            status = (
                SectionStatus.LOW_COVERAGE if i in LOW_COVERAGE else SectionStatus.TOO_FEW_POINTS
            )
            out.append(
                SectionMeasures(
                    start_m, end_m, NOMINAL_AREA_M2, status,
                    point_count=35 if i in LOW_COVERAGE else 4,
                    coverage_ratio=0.42 if i in LOW_COVERAGE else 0.05,
                )
            )  # fmt: skip
            continue
        # Small, distinct background blockage: 0.0130, 0.0137, ... (never on a boundary).
        blockage = OBSTACLE.get(i, 0.013 + 0.0007 * (i % 9))
        deposit = DEPOSIT.get(i, 0.02)
        out.append(
            SectionMeasures(
                start_m,
                end_m,
                NOMINAL_AREA_M2,
                SectionStatus.OK,
                point_count=1500 + 7 * i,
                coverage_ratio=0.97,
                open_area_m2=NOMINAL_AREA_M2 * (1.0 - blockage),
                blockage_ratio=blockage,
                ovality_ratio=0.012,
                deformation_ratio=0.008,
                deposit_height_ratio=deposit,
            )
        )
    return out


def make_input(
    *, asset_id: str = "MH1042-MH1043", sections: list[SectionMeasures] | None = None
) -> ReportInput:
    table = load_table("vsa-2023")
    graded = grade_sections(sections if sections is not None else _sections(), table)
    return ReportInput(
        asset_id=asset_id,
        upstream_node="MH1042",
        downstream_node="MH1043",
        inspected_at=datetime(2024, 5, 13, 9, 30, tzinfo=UTC),
        nominal_diameter_m=DIAMETER_M,
        material="vitrified clay",
        pipe_shape="circular",
        inspection_id="7f3c2a",
        archive_uri="s3://network-scans/2024/MH1042-MH1043.tar.gz",
        software_version="0.1.0",
        threshold_table=TableCitation(table.name, table.source),
        blockage_threshold_ratio=0.10,
        point_count=1_234_567,
        frame_count=120,
        scanned_length_m=6.0,
        registration={
            "engine": "open3d point-to-plane ICP",
            "mean_fitness": 0.934,
            "mean_rmse_m": 0.0042,
            "degenerate_frames": 3,
        },
        sections=graded,
        defects=merge_defects(graded, table),
        generated_at=datetime(2024, 5, 14, 8, 0, tzinfo=UTC),
    )


def plain(text: str) -> str:
    """Text with no-break and thin spaces (used between figures and units) as plain spaces."""
    return text.replace("\u00a0", " ").replace("\u202f", " ")


def pdf_text(path: Path) -> str:
    reader = pypdf.PdfReader(str(path))
    return plain("\n".join(page.extract_text() for page in reader.pages))


@pytest.fixture(scope="module")
def report_input() -> ReportInput:
    return make_input()


@pytest.fixture(scope="module")
def rendered(report_input, tmp_path_factory) -> tuple[Path, str, float]:
    out = tmp_path_factory.mktemp("report") / "nested" / "report.pdf"
    t0 = time.perf_counter()
    render_pdf(report_input, out)
    elapsed_s = time.perf_counter() - t0
    return out, pdf_text(out), elapsed_s


def test_defects_are_the_ground_truth(report_input):
    # The fixture itself: the two planted spans and nothing else.
    spans = [(d.code, d.chainage_start_m, d.chainage_end_m, d.grade) for d in report_input.defects]
    assert spans == [("BBE", 2.0, 2.5, 2), ("BBC", 5.0, 5.2, 2)]


def test_context_figures(report_input):
    ctx = build_context(report_input, chart=False)
    summary = {k: plain(v) if isinstance(v, str) else v for k, v in ctx["summary"].items()}
    assert summary["section_count"] == N_SECTIONS
    assert summary["measured_count"] == N_SECTIONS - len(LOW_COVERAGE) - len(TOO_FEW_POINTS)
    assert summary["unmeasured_length"] == "0.5 m"
    assert summary["max_blockage"] == "31.0 %" and summary["max_blockage_at"] == "2.20 m"
    assert summary["defect_count"] == 2 and summary["flagged_length"] == "0.7 m"
    by_reason = {u["reason"]: u for u in ctx["unmeasured"]}
    assert plain(by_reason["low coverage"]["length"]) == "0.4 m"
    assert plain(by_reason["low coverage"]["spans"]) == "1.00–1.40 m"
    assert plain(by_reason["too few points"]["spans"]) == "4.00–4.10 m"
    # Counts by grade cover measured sections only and add up.
    counts = {g["grade"]: g["count"] for g in ctx["grades"]}
    assert sum(counts.values()) == summary["measured_count"]
    assert counts["2"] == 4  # blockage 0.24, 0.31 (BBE 2); deposit 0.30, 0.27 (BBC 2)
    # The worst sections, by blockage, measured only.
    assert [w["blockage"] for w in ctx["worst"][:5]] == ["31.0", "24.0", "18.0", "12.0", "11.0"]
    assert len(ctx["worst"]) == 10
    rows = ctx["sections"]
    assert rows[10]["reason"] == "not measured: low coverage" and "blockage" not in rows[10]
    assert rows[22]["blockage"] == "31.0" and rows[22]["flagged"]


def test_fmt_pct_never_prints_none_or_nan():
    assert fmt_pct(None) == "not measured"
    assert fmt_pct(math.nan) == "not measured"
    assert plain(fmt_pct(0.1234)) == "12.3 %"
    assert plain(fmt_pct(-0.00001)) == "0.0 %"
    assert fmt_pct(-0.021, unit=False) == "-2.1"


def test_pdf_holds_the_figures(rendered):
    path, text, _ = rendered
    assert path.exists() and path.read_bytes().startswith(b"%PDF")
    assert not list(path.parent.glob("*.part")), "temporary file left behind"
    assert "MH1042-MH1043" in text
    # Defect table: chainages and peaks of both planted spans.
    flat = re.sub(r"\s+", " ", text)
    assert re.search(r"BBE .*?2\.00 2\.50 0\.50 2\.20 blockage 31\.0 31\.0 2", flat), flat[:3000]
    # Peak blockage over 5.00-5.20 m: max(0.0165, 0.0172) of the background pattern.
    assert re.search(r"BBC .*?5\.00 5\.20 0\.20 5\.00 deposit height 30\.0 1\.7 2", flat)
    # Unmeasured sections are named, with their reason and where they are.
    assert "not measured: low coverage" in text
    assert "not measured: too few points" in text
    assert "1.00–1.40 m" in text
    # Cover facts.
    assert "DN 500" in text and "1 234 567" in text
    assert "vsa-2023" in text and "VSA" in text
    assert re.search(r"page 1 of \d", text)
    for bad in ("None", "nan", "NaN"):
        assert not re.search(rf"\b{bad}\b", text), bad


def test_pdf_renders_fast(rendered):
    *_, elapsed_s = rendered
    assert elapsed_s < 8.0  # ~60 sections; typically 1-2 s on one core


def test_unmeasured_never_drawn_as_zero():
    sections = _sections()
    svg = blockage_chart_svg(sections, [], blockage_threshold_ratio=0.10)
    assert svg.lstrip().startswith("<?xml") and "</svg>" in svg
    assert "not measured" in svg
    # One bar per measured section only (bars are <path> elements in a patch group).
    with_unmeasured_dropped = blockage_chart_svg(
        [s for s in sections if s.is_ok], [], blockage_threshold_ratio=0.10
    )
    assert svg.count('id="patch_') - with_unmeasured_dropped.count('id="patch_') == 2 * 2 + 1
    # Same input, same SVG (stable ids, no date).
    assert svg == blockage_chart_svg(sections, [], blockage_threshold_ratio=0.10)


def test_html_is_autoescaped():
    html = render_html(make_input(asset_id='<script>alert("x")</script>&MH1'))
    assert "<script>" not in html
    assert "&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt;&amp;MH1" in html


def test_report_without_defects_says_so(tmp_path):
    quiet = [
        dataclasses.replace(s, blockage_ratio=0.02, deposit_height_ratio=0.02) if s.is_ok else s
        for s in _sections()
    ]
    inp = make_input(sections=quiet)
    assert inp.defects == []
    html = render_html(inp)
    assert "No defects" in html
    text = pdf_text(render_pdf(inp, tmp_path / "quiet.pdf"))
    assert "No defects" in text
    assert "Flagged sections" in text


def test_all_unmeasured_report(tmp_path):
    blind = [
        SectionMeasures(i * 0.1, (i + 1) * 0.1, NOMINAL_AREA_M2, SectionStatus.LOW_COVERAGE, 3, 0.1)
        for i in range(5)
    ]
    inp = make_input(sections=blind)
    ctx = build_context(inp, chart=False)
    assert ctx["summary"]["max_blockage"] == "not measured"
    assert ctx["summary"]["worst_grade"] == "not graded"
    html = render_html(inp)
    assert "Nothing measured" in html and "No defects: no measured section" not in html
    assert not re.search(r"\b(None|nan|NaN)\b", html)
    assert html.count("not measured: low coverage") == 5


def test_a_crash_while_writing_leaves_no_pdf(tmp_path, monkeypatch, report_input):
    import weasyprint

    def half_written(self, target, *args, **kwargs):
        target.write(b"%PDF-1.7 truncated")
        raise RuntimeError("renderer crashed")

    monkeypatch.setattr(weasyprint.HTML, "write_pdf", half_written)
    out = tmp_path / "report.pdf"
    out.write_bytes(b"%PDF previous report")
    with pytest.raises(RuntimeError, match="renderer crashed"):
        render_pdf(report_input, out)
    assert out.read_bytes() == b"%PDF previous report"  # the old report is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.pdf"]
