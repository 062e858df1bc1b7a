"""The per-inspection report: context, HTML (escaping) and the rendered PDF's text."""

from __future__ import annotations

import base64
import dataclasses
import math
import os
import re
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from pipescan.core.grading import grade_sections, load_table, merge_defects
from pipescan.core.model import SectionMeasures, SectionStatus
from pipescan.reports import (
    EarlierInspection,
    ReportInput,
    TableCitation,
    build_context,
    render_html,
    render_network_pdf,
    render_pdf,
)
from pipescan.reports.charts import blockage_chart_svg, cross_section_svg
from pipescan.reports.context import APPENDIX_ALL_MAX_SECTIONS, fmt_pct
from pipescan.reports.network import (
    EarlierScan,
    FailedArchive,
    NetworkInput,
    PipeInspection,
    summarise,
)
from pipescan.reports.sample import Feature, sample_input, sample_sections
from pipescan.tasks.reporting import network_message

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
def rendered(report_input, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("report") / "nested" / "report.pdf"
    render_pdf(report_input, out)
    return out, pdf_text(out)


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
    assert rows[10]["reason"] == "not measured" and "blockage" not in rows[10]
    assert rows[10]["status"] == "low coverage"
    assert rows[22]["blockage"] == "31.0" and rows[22]["flagged"]


def test_water_depth_is_reported_with_its_plus_minus():
    sections = _sections()
    sections[10] = dataclasses.replace(
        sections[10],
        status=SectionStatus.INVERT_UNDER_WATER,
        water_depth_ratio=0.059,
        water_depth_uncertainty_ratio=0.0081,
    )
    sections[11] = dataclasses.replace(
        sections[11], status=SectionStatus.INVERT_UNDER_WATER, water_depth_ratio=0.06
    )
    rows = build_context(make_input(sections=sections), chart=False)["sections"]
    assert plain(rows[10]["reason"]) == "not measured (water 5.9 ± 0.8 % of the diameter deep)"
    # Stored before the ± was recorded: the depth alone, as before.
    assert plain(rows[11]["reason"]) == "not measured (water 6 % of the diameter deep)"


def test_fmt_pct_never_prints_none_or_nan():
    assert fmt_pct(None) == "not measured"
    assert fmt_pct(math.nan) == "not measured"
    assert plain(fmt_pct(0.1234)) == "12.3 %"
    assert plain(fmt_pct(-0.00001)) == "0.0 %"
    assert fmt_pct(-0.021, unit=False) == "-2.1"


def test_pdf_holds_the_figures(rendered):
    path, text = rendered
    assert path.exists() and path.read_bytes().startswith(b"%PDF")
    assert not list(path.parent.glob("*.part")), "temporary file left behind"
    assert "MH1042-MH1043" in text
    # Defect table: chainages and peaks of both planted spans.
    flat = re.sub(r"\s+", " ", text)
    assert re.search(r"BBE .*?2\.00 2\.50 0\.50 2\.20 blockage 31\.0 31\.0 2", flat), flat[:3000]
    # Peak blockage over 5.00-5.20 m: max(0.0165, 0.0172) of the background pattern.
    assert re.search(r"BBC .*?5\.00 5\.20 0\.20 5\.00 deposit height 30\.0 1\.7 2", flat)
    # Unmeasured sections are named, with their reason and where they are.
    assert "not measured" in text and "low coverage" in text
    assert "too few points" in text
    assert "1.00–1.40 m" in text
    # Cover facts.
    assert "DN 500" in text and "1 234 567" in text
    assert "vsa-2023" in text and "VSA" in text
    assert re.search(r"page 1 of \d", text)
    for bad in ("None", "nan", "NaN"):
        assert not re.search(rf"\b{bad}\b", text), bad


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
    assert "Defects" in text


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
    assert html.count('<td class="status">low coverage</td>') == 5


def test_a_crash_while_writing_leaves_no_pdf(tmp_path, monkeypatch, report_input):
    import weasyprint

    def half_written(self, target, *args, **kwargs):
        target.write(b"%PDF-1.7 truncated")
        raise RuntimeError("renderer crashed")

    # The laid-out document writes the PDF (render.py lays it out first, for the tables' tails).
    monkeypatch.setattr(weasyprint.document.Document, "write_pdf", half_written)
    out = tmp_path / "report.pdf"
    out.write_bytes(b"%PDF previous report")
    with pytest.raises(RuntimeError, match="renderer crashed"):
        render_pdf(report_input, out)
    assert out.read_bytes() == b"%PDF previous report"  # the old report is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.pdf"]


# --- cross-sections, trend, compact appendix ----------------------------------------------


def _deposit_contour(radius_m: float, deposit_m: float, n: int = 720) -> np.ndarray:
    """A circle of ``radius_m`` cut flat ``deposit_m`` above the invert, centre at origin."""
    theta = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    pts = radius_m * np.column_stack((np.cos(theta), np.sin(theta)))
    pts[:, 1] = np.maximum(pts[:, 1], -radius_m + deposit_m)
    return pts


def test_cross_section_figure_gives_true_dimensions():
    # DN 500 with 100 mm of deposit: clear height 400 mm, clear width 500 mm (at the centre).
    svg = cross_section_svg(
        _deposit_contour(0.25, 0.10), nominal_diameter_m=0.5, blockage_ratio=0.142, title="1 BBC"
    )
    text = plain(re.sub(r"<[^>]+>", " ", svg))
    assert "clear height" in text and re.search(r"\b400 mm", text), text[:2000]
    assert re.search(r"clear width\s+500 mm", text)
    assert "nominal ⌀ 500 mm" in text
    assert re.search(r"\b100 mm", text)  # the loss at the invert
    assert "blockage 14.2 %" in text
    # Without a nominal diameter: the contour alone, no lost area.
    bare = cross_section_svg(_deposit_contour(0.25, 0.10), nominal_diameter_m=None)
    assert "lost area" not in bare and "nominal" not in bare
    with pytest.raises(ValueError, match=r"shape \(M, 2\)"):
        cross_section_svg(np.zeros((2, 2)), nominal_diameter_m=0.5)
    with pytest.raises(ValueError, match="non-finite"):
        cross_section_svg(np.full((5, 2), np.nan), nominal_diameter_m=0.5)


def test_one_cross_section_per_defect_at_its_peak():
    inp = sample_input(45.0, earlier=0)
    ctx = build_context(inp)
    assert [f["at"] for f in ctx["figures"]] == [
        fmt.replace(" ", "\u00a0") for fmt in ("8.60 m", "21.60 m", "41.40 m")
    ]
    peak = next(s for s in inp.sections if abs(s.chainage_start_m - 21.6) < 1e-6)
    first_svg = base64.b64decode(ctx["figures"][1]["uri"].split(",")[1]).decode()
    assert f"blockage {peak.blockage_ratio * 100:.1f} %" in first_svg
    # A section without a stored contour says so instead of drawing nothing.
    no_contours = dataclasses.replace(
        inp, sections=[dataclasses.replace(s, contour_m=None) for s in inp.sections]
    )
    figures = build_context(no_contours)["figures"]
    assert all(f["uri"] is None and "not stored" in f["missing"] for f in figures)


def test_trend_compares_each_defect_with_earlier_inspections():
    inp = make_input()
    older = dataclasses.replace(
        inp,
        sections=[
            dataclasses.replace(s, blockage_ratio=s.blockage_ratio / 2) if s.is_ok else s
            for s in inp.sections
        ],
    )
    with_history = dataclasses.replace(
        inp,
        history=[
            EarlierInspection(
                "A1", datetime(2022, 5, 13, 9, 30, tzinfo=UTC), older.sections, defect_count=1
            ),
            # Taken after this inspection: not "earlier", never shown.
            EarlierInspection("Z9", datetime(2030, 1, 1, tzinfo=UTC), older.sections, 0),
        ],
    )
    assert build_context(inp, chart=False)["trend"] is None
    trend = build_context(with_history, chart=False)["trend"]
    assert [i["inspection_id"] for i in trend["inspections"]] == ["7f3c2a", "A1"]
    obstacle = trend["changes"][0]
    # Peak blockage over 2.00-2.50 m: 31.0 % now, 15.5 % two years before.
    assert (obstacle["now"], obstacle["earlier"], obstacle["change"]) == ("31.0", ["15.5"], "+15.5")
    # points per year over 2.0 years (15.5 / 2.0 = 7.75): a change, not noise
    assert obstacle["rate"] == {"value": "+7.7", "note": ""}
    text = pdf_text(render_pdf(with_history, Path(tempfile.mkdtemp()) / "trend.pdf"))
    assert "Trend: this inspection against earlier ones" in text
    assert "2022-05-13" in text and "+15.5" in text


def test_compact_appendix_for_a_long_scan():
    sections = grade_sections(
        sample_sections(
            100.0,
            features=[Feature("obstacle", 40.0, 41.0, 0.35)],
            unmeasured=[(70.0, 71.5, SectionStatus.LOW_COVERAGE)],
            contours=False,
        ),
        load_table(),
    )
    assert len(sections) == 1000 > APPENDIX_ALL_MAX_SECTIONS
    inp = make_input(sections=sections)
    ctx = build_context(inp, chart=False)
    rows = ctx["sections"]
    (defect,) = inp.defects
    assert 40.0 < defect.chainage_start_m < defect.chainage_end_m < 41.0

    def in_defect(start_m: float) -> bool:
        return defect.chainage_start_m - 1e-6 <= start_m < defect.chainage_end_m - 1e-6

    flagged = [r["start"] for r in rows if r["flagged"]]
    assert flagged == [
        f"{s.chainage_start_m:.2f}" for s in sections if in_defect(s.chainage_start_m)
    ]
    unmeasured = [r for r in rows if not r["ok"]]
    assert len(unmeasured) == 1 and "(15 sections)" in unmeasured[0]["reason"]
    assert (unmeasured[0]["start"], unmeasured[0]["end"]) == ("70.00", "71.50")
    # One measured row per whole metre outside flagged and unmeasured stretches.
    metre_rows = {r["start"] for r in rows if r["ok"] and not r["flagged"]}
    assert metre_rows == {f"{m:.2f}" for m in range(100) if m not in (70, 71)}
    assert not ctx["appendix"]["complete"]
    assert "pipescan export sections --inspection 7f3c2a" in ctx["appendix"]["export_command"]
    # A short scan keeps every section.
    assert build_context(make_input(), chart=False)["appendix"]["complete"]


@pytest.mark.slow
def test_a_100_m_scan_renders_with_a_compact_listing(tmp_path):
    """1,000 sections: the listing is compacted and points to the export. How long it takes
    is measured by ``benchmarks/bench_report.py``, not here."""
    inp = sample_input(100.0)
    out = render_pdf(inp, tmp_path / "long.pdf")
    text = pdf_text(out)
    assert "compact listing" in text and "pipescan export sections" in text


# --- network summary ---------------------------------------------------------------------


def _pipe(
    asset_id: str, blockage_now: float, blockage_before: float | None, **kw
) -> PipeInspection:
    def sections(peak: float) -> list[SectionMeasures]:
        out = []
        for i in range(20):
            b = peak if i == 7 else 0.01
            out.append(
                SectionMeasures(i * 0.1, (i + 1) * 0.1, NOMINAL_AREA_M2, SectionStatus.OK, 900,
                                1.0, open_area_m2=NOMINAL_AREA_M2 * (1 - b), blockage_ratio=b)
            )  # fmt: skip
        return grade_sections(out, load_table())

    return PipeInspection(
        asset_id=asset_id,
        upstream_node=asset_id.split("-")[0],
        downstream_node=asset_id.split("-")[1],
        nominal_diameter_m=DIAMETER_M,
        material="concrete",
        inspection_id=kw.get("inspection_id", 1),
        inspected_at=datetime(2025, 6, 1, tzinfo=UTC),
        sections=sections(blockage_now),
        defect_count=int(blockage_now >= 0.10),
        earlier=(
            [EarlierScan(0, datetime(2023, 6, 1, tzinfo=UTC), blockage_before)]
            if blockage_before is not None
            else []
        ),
    )


def test_network_summary_ranks_by_grade_and_by_growth(tmp_path):
    pipes = [
        _pipe("A1-A2", 0.25, 0.24),  # BBE class 2, grew 1 point
        _pipe("B1-B2", 0.12, 0.02),  # class 3, grew 10 points
        _pipe("C1-C2", 0.55, None),  # class 0, first inspection
        _pipe("D1-D2", 0.03, 0.03),  # class 4, no growth
    ]
    b = summarise(pipes[1])
    assert b.change_ratio == pytest.approx(0.10) and b.max_blockage_at_m == pytest.approx(0.7)
    assert b.growth_per_year_ratio == pytest.approx(0.10 / (731 / 365.25))  # 2024 is a leap year
    inp = NetworkInput(
        pipes=pipes,
        generated_at=datetime(2025, 6, 2, tzinfo=UTC),
        software_version="0.1.0",
        threshold_tables=[TableCitation("vsa-2023", "VSA")],
    )
    from pipescan.reports.network import build_network_context

    ctx = build_network_context(inp)
    assert [r["asset_id"] for r in ctx["by_grade"]] == ["C1-C2", "A1-A2", "B1-B2", "D1-D2"]
    assert [r["asset_id"] for r in ctx["by_growth"]] == ["B1-B2", "A1-A2", "D1-D2"]
    assert ctx["first_inspections"] == ["C1-C2"]
    assert [g["count"] for g in ctx["grade_counts"]] == [1, 0, 1, 1, 1]
    text = re.sub(r"\s+", " ", pdf_text(render_network_pdf(inp, tmp_path / "net.pdf")))
    assert re.search(r"1 C1-C2 .*? 0 55\.0 0\.70", text), text[:3000]
    # growth per year, inspections, change, largest blockage now and before, worst class
    assert re.search(r"1 B1-B2 .*?\+5\.0 2 \+10\.0 12\.0 2\.0 3", text), text[:4000]
    assert "Inspected for the first time (no growth figure): C1-C2" in text
    # A1-A2 grew 1 point in 2 years, D1-D2 not at all: within what two surveys of an
    # unchanged pipe differ by, and worded so.
    assert re.search(r"2 A1-A2 .*?\+0\.5 ?no significant change ?2 \+1\.0", text), text
    assert re.search(r"3 D1-D2 .*?0\.0 ?no significant change ?2 0\.0", text), text


def test_network_summary_lists_the_archives_that_failed(tmp_path):
    reason = (
        "archive site9.zip, file inspection.toml, field 'nominal_diameter_m': 500 looks like "
        "millimetres: write 0.5"
    )
    inp = NetworkInput(
        pipes=[_pipe("A1-A2", 0.25, 0.24)],
        generated_at=datetime(2025, 6, 2, tzinfo=UTC),
        software_version="0.1.0",
        failed=[FailedArchive("site9", reason), FailedArchive("site12", "archive site12: x")],
    )
    text = re.sub(r"\s+", " ", pdf_text(render_network_pdf(inp, tmp_path / "net.pdf")))
    assert "1 pipe inspected 2025-06-01; 2 archives failed" in text
    section = text[text.index("Archives that failed") : text.index("Pipes ranked by condition")]
    assert "site9 " + reason in section and "site12 archive site12: x" in section
    subject, body = network_message(inp)
    assert subject.startswith("Network condition summary: 1 pipe,")
    assert "2 archives failed (nothing stored):\n  site9: " + reason in body
    assert "1 pipe inspected" in body and "1 pipes" not in body


# --- from the database -------------------------------------------------------------------


PARAMS = {
    "threshold_table": "vsa-2023",
    "pipe_class": "rigid",
    "blockage_threshold_ratio": 0.10,
    "flag_grade": 2,
}


def save_sample(database_url: str, inp: ReportInput, *, content_hash: str) -> int:
    """Store a report input as an inspection (its sections, defects and parameters)."""
    from pipescan.core.model import InspectionMeta
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import InspectionToSave, save_inspection

    engine = connect(database_url)
    try:
        return save_inspection(
            engine,
            InspectionToSave(
                meta=InspectionMeta(
                    asset_id=inp.asset_id,
                    inspected_at=inp.inspected_at,
                    nominal_diameter_m=inp.nominal_diameter_m,
                    upstream_node=inp.upstream_node,
                    downstream_node=inp.downstream_node,
                    material=inp.material,
                ),
                archive_uri=inp.archive_uri,
                content_hash=content_hash,
                params=PARAMS,
                software_version="0.1.0",
                sections=inp.sections,
                defects=inp.defects,
                threshold_table="vsa-2023",
                point_count=inp.point_count,
                frame_count=inp.frame_count,
                scanned_length_m=inp.scanned_length_m,
            ),
        )
    finally:
        engine.dispose()


@pytest.fixture(scope="module")
def report_db(tmp_path_factory) -> tuple[str, dict[str, int]]:
    """Two inspections of one pipe (the obstacle grew), one of another, without defects."""
    url = f"sqlite:///{tmp_path_factory.mktemp('db') / 'pipescan.db'}"
    now = sample_input(30.0, earlier=0, features=[Feature("obstacle", 20.0, 21.4, 0.35)],
                       unmeasured=[(5.0, 5.5, SectionStatus.LOW_COVERAGE)])  # fmt: skip
    before = sample_input(30.0, earlier=0, features=[Feature("obstacle", 20.0, 21.4, 0.2)],
                          unmeasured=(), seed=5)  # fmt: skip
    before = dataclasses.replace(before, inspected_at=datetime(2023, 3, 14, 9, 30, tzinfo=UTC))
    quiet = sample_input(12.0, earlier=0, features=(), unmeasured=(), asset_id="MH7-MH8")
    ids = {
        "before": save_sample(url, before, content_hash="sha256:before"),
        "now": save_sample(url, now, content_hash="sha256:now"),
        "quiet": save_sample(url, quiet, content_hash="sha256:quiet"),
    }
    return url, ids


def test_report_from_the_database_holds_its_figures(report_db, tmp_path):
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import list_defects, list_sections
    from pipescan.tasks.reporting import load_report_input

    url, ids = report_db
    inp = load_report_input(url, ids["now"])
    assert [h.inspection_id for h in inp.history] == [ids["before"]]
    text = pdf_text(render_pdf(inp, tmp_path / "now.pdf"))
    flat = re.sub(r"\s+", " ", text)
    engine = connect(url)
    defects, sections = list_defects(engine, ids["now"]), list_sections(engine, ids["now"])
    engine.dispose()
    assert len(defects) == 1
    (d,) = defects
    peak = max((s for s in sections if s.is_ok), key=lambda s: s.blockage_ratio)
    assert "MH1042-MH1043" in text
    # The flagged span and its peak, as stored, in the defects table.
    assert f"{d.chainage_start_m:.2f} {d.chainage_end_m:.2f}" in flat
    assert f"{d.peak_chainage_m:.2f} blockage {d.peak_value * 100:.1f}" in flat
    assert (
        f"Largest blockage: {peak.blockage_ratio * 100:.1f} % at {peak.chainage_start_m:.2f} m"
        in flat
    )
    assert f"Defect 1, {d.code}" in flat  # its cross-section figure
    assert "Trend: this inspection against earlier ones" in text and "2023-03-14" in text
    assert "5.00–5.50 m" in text  # the unmeasured stretch, by chainage
    # The quiet pipe: no defects, no trend page.
    quiet = pdf_text(render_pdf(load_report_input(url, ids["quiet"]), tmp_path / "quiet.pdf"))
    assert "No defects" in quiet and "Trend:" not in quiet and "MH7-MH8" in quiet


def test_network_report_from_the_database(report_db, tmp_path):
    from pipescan.storage.database.db import StorageError
    from pipescan.tasks.reporting import render_network_report

    url, ids = report_db
    out = render_network_report(url, tmp_path / "net.pdf")
    flat = re.sub(r"\s+", " ", pdf_text(out))
    # One line per pipe, the latest inspection of each; worst first.
    assert re.search(r"1 MH1042-MH1043 .*? 2 MH7-MH8", flat), flat[:2000]
    assert "Inspected for the first time (no growth figure): MH7-MH8" in flat
    assert re.search(r"1 MH1042-MH1043 MH1042 → MH1043 2025-03-14 2023-03-14 \+\d", flat)
    # Filters: since a date after the first pipe's inspections; an explicit id list.
    only = pdf_text(
        render_network_report(url, tmp_path / "one.pdf", inspection_ids=[ids["before"]])
    )
    assert "MH7-MH8" not in only and "1 pipe inspected 2023-03-14" in plain(only)
    later = pdf_text(
        render_network_report(url, tmp_path / "later.pdf", since=datetime(2025, 3, 15, tzinfo=UTC))
    )
    assert "MH1042-MH1043" not in later and "MH7-MH8" not in later  # both from 2025-03-14
    with pytest.raises(StorageError, match="no inspection with id 999"):
        render_network_report(url, tmp_path / "bad.pdf", inspection_ids=[999])


def test_the_registration_block_says_the_odometer_slipped_and_that_the_chainage_allows_for_it():
    from pipescan.reports.context import _registration_only_rows

    inp = make_input()
    reg = inp.registration | {
        "chainage_uncertainty_m": 0.62,
        "odometer_slips_caught_m": [0.21, 0.44],
    }
    rows = dict(_registration_only_rows(dataclasses.replace(inp, registration=reg)))
    assert plain(rows["chainage uncertainty"]).startswith("up to ±0.62 m at the end")
    assert "possible slips" in rows["chainage uncertainty"]
    assert plain(rows["odometer slips caught"]) == (
        "2 with features in view, up to 0.44 m; allowed for where it was alone"
    )  # a summary stored before the allowance was kept
    kept = dict(
        _registration_only_rows(
            dataclasses.replace(inp, registration=reg | {"unseen_slips_allowed_m": 0.5})
        )
    )
    assert plain(kept["odometer slips caught"]) == (
        "2 with features in view, up to 0.44 m; the ± allows 0.50 m for unseen ones where it "
        "was alone"
    )
    short = dict(
        _registration_only_rows(
            dataclasses.replace(inp, registration=reg | {"unseen_slips_allowed_m": 0.0})
        )
    )
    assert "possible slips" not in short["chainage uncertainty"]
    assert "unseen odometer slips" not in short
    assert plain(short["odometer slips caught"]).endswith(
        "no stretch rested on the odometer long enough to hide one"
    )
    # Where frames rested on the odometer, the ± allows for slips as large as the largest
    # caught, and the block says that a larger one is not allowed for (at any stride).
    held_some = reg | {"degenerate_frames": 40}
    for extra in ({}, {"frame_stride": 4, "frame_stride_reason": "views"}):
        rows = dict(
            _registration_only_rows(dataclasses.replace(inp, registration=held_some | extra))
        )
        assert plain(rows["unseen odometer slips"]).startswith(
            "The ± allows for slips where the odometer was alone as large as the largest "
            "caught (0.44 m); a larger one there is not allowed for"
        )
    # An odometer never caught slipping: no such row; the ± claims no slips, and where frames
    # rested on the odometer the block says what it cannot allow for.
    held = inp.registration | {
        "chainage_uncertainty_m": 0.09,
        "odometer_slips_caught_m": [],
        "degenerate_frames": 120,
        "along_axis_prior": "odometer",
        "odometer_uncertainty_ratio": 0.05,
        "unconstrained_spans": [{"start_travel_m": 0.5, "end_travel_m": 2.0}],
    }
    rows = dict(_registration_only_rows(dataclasses.replace(inp, registration=held)))
    assert "odometer slips caught" not in rows
    assert plain(rows["chainage uncertainty"]) == (
        "up to ±0.09 m at the end (the odometer's error over the travel it placed)"
    )
    assert plain(rows["unseen odometer slips"]).startswith(
        "1.5 m of travel rested on the odometer alone: the ± there is the odometer's 5 % and "
        "allows for no slip"
    )
    # The operator stated the crawler's largest slip: the ± holds one, and both rows say so.
    stated = held | {"odometer_slip_stated_m": 0.2, "unseen_slips_allowed_m": 0.2}
    rows = dict(_registration_only_rows(dataclasses.replace(inp, registration=stated)))
    assert plain(rows["chainage uncertainty"]) == (
        "up to ±0.09 m at the end (the odometer's error over the travel it placed, and its "
        "possible slips)"
    )
    assert "one unseen slip of the stated 0.20 m" in plain(rows["unseen odometer slips"])
    # Every frame placed against features: the ± is registration's own, whatever was caught.
    anchored = reg | {"degenerate_frames": 0}
    rows = dict(_registration_only_rows(dataclasses.replace(inp, registration=anchored)))
    assert plain(rows["chainage uncertainty"]) == (
        "up to ±0.62 m at the end (registration's own error: no frame rested on the odometer)"
    )


def test_a_report_path_that_cannot_be_written_is_one_error_and_leaves_nothing(tmp_path):
    """A folder, a path under a file, or a folder without write permission: an OutputError
    naming the path (the CLI prints it in one line, exit 2), found before any work by
    ``check_report_path``, and nothing left behind by ``render_pdf``. They used to end in
    tracebacks from ``os.replace`` and ``mkdir``."""
    from pipescan.core.errors import OutputError
    from pipescan.reports.render import check_report_path

    folder = tmp_path / "reports"
    folder.mkdir()
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    bad = {
        folder: "it is a folder",
        a_file / "r.pdf": "is not a folder",
        a_file / "sub" / "r.pdf": "is not a folder",
    }
    if os.geteuid() != 0:  # root may write anywhere
        bad[locked / "sub" / "r.pdf"] = "no permission"
    inp = sample_input(10.0, earlier=0)
    for path, reason in bad.items():
        with pytest.raises(OutputError, match=reason) as caught:
            check_report_path(path)
        assert str(path) in str(caught.value)
        with pytest.raises(OutputError, match="cannot write the report"):
            render_pdf(inp, path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["locked", "notes.txt", "reports"]
    assert list(folder.iterdir()) == []
    check_report_path(tmp_path / "new" / "deeper" / "r.pdf")  # folders to be made: fine
    assert not (tmp_path / "new").exists()
