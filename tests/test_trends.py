"""Blockage over time: alignment, change per year and the network ranking, against known truth.

The database tests run on SQLite and on a real PostgreSQL (``engine``/``db_url`` fixtures of
tests/conftest.py). Synthetic pipes have deposits whose blockage grows at known rates, and
surveys whose chainages are off by known shifts.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.core import trends as core_trends
from pipescan.core.model import InspectionMeta, SectionMeasures, SectionStatus
from pipescan.storage.database import db, repository, trends
from tests.conftest import is_sqlite

STEP_M = 0.1
NOMINAL_AREA_M2 = math.pi * 0.3**2
YEAR = timedelta(days=365.25)  # the year of core.trends.SECONDS_PER_YEAR
T0 = datetime(2022, 5, 17, 9, 0, tzinfo=UTC)


# ---------------------------------------------------------------------------------------------
# Known data


def sections_from(
    values: Sequence[float | None],
    *,
    start_mm: int = 0,
    step_mm: int = 100,
    statuses: dict[int, SectionStatus] | None = None,
) -> list[SectionMeasures]:
    """One section per value; None is an unmeasured section (low coverage, no figures)."""
    out = []
    for k, value in enumerate(values):
        status = (statuses or {}).get(k, SectionStatus.OK if value is not None else None)
        status = status or SectionStatus.LOW_COVERAGE
        out.append(
            SectionMeasures(
                chainage_start_m=(start_mm + k * step_mm) / 1000,
                chainage_end_m=(start_mm + (k + 1) * step_mm) / 1000,
                nominal_area_m2=NOMINAL_AREA_M2,
                status=status,
                point_count=800 if value is not None else 5,
                coverage_ratio=0.95 if value is not None else 0.1,
                open_area_m2=None if value is None else NOMINAL_AREA_M2 * (1 - value),
                blockage_ratio=value,
            )
        )
    return out


def save(
    engine: sa.Engine,
    asset_id: str,
    when: datetime,
    sections: list[SectionMeasures],
    content_hash: str | None = None,
    params: dict[str, object] | None = None,
) -> int:
    return repository.save_inspection(
        engine,
        repository.InspectionToSave(
            meta=InspectionMeta(asset_id=asset_id, inspected_at=when, nominal_diameter_m=0.6),
            archive_uri=f"/scans/{asset_id}-{when.date()}.zip",
            content_hash=content_hash or f"sha256:{asset_id}-{when.isoformat()}",
            params=params or {"section_step_m": STEP_M},
            software_version="0.1.0",
            sections=sections,
            defects=[],
        ),
    )


def bump(x_m: np.ndarray, centre_m: float, sigma_m: float) -> np.ndarray:
    return np.exp(-((x_m - centre_m) ** 2) / (2 * sigma_m**2))


LENGTH_M = 20.0
SHAPES = ((5.0, 0.35), (12.0, 0.3))  # (centre, sigma) of two deposits


def true_blockage(x_m: np.ndarray, years: float) -> np.ndarray:
    """Blockage at true chainages x_m, ``years`` after T0: the deposit at 12 m grows 5 points a
    year, the one at 5 m 1 point a year, the rest of the pipe stays at 2 %."""
    (c5, s5), (c12, s12) = SHAPES
    return (
        0.02
        + bump(x_m, c5, s5) * (0.15 + 0.01 * years)
        + bump(x_m, c12, s12) * (0.25 + 0.05 * years)
    )


def true_change_per_year(x_m: np.ndarray) -> np.ndarray:
    (c5, s5), (c12, s12) = SHAPES
    return 0.01 * bump(x_m, c5, s5) + 0.05 * bump(x_m, c12, s12)


# Survey chainage errors, in metres: stored chainage = true chainage + error. The last
# (latest) survey is the reference, with no error.
ERRORS_M = (0.3, -0.4, 0.2, 0.0)


def survey(years: float, error_m: float) -> list[float]:
    """Blockage of the sections [k * 0.1, (k + 1) * 0.1) m of a survey, in its own chainage."""
    centres_stored = np.arange(round(LENGTH_M / STEP_M)) * STEP_M + STEP_M / 2
    return list(true_blockage(centres_stored - error_m, years))


@pytest.fixture
def pipe(engine: sa.Engine) -> list[int]:
    """Four yearly surveys of asset P1, with chainage errors ERRORS_M and some gaps."""
    ids = []
    for year, error_m in enumerate(ERRORS_M):
        values: list[float | None] = list(survey(year, error_m))
        statuses = {}
        if year == 1:
            values[100:110] = [None] * 10  # 10.0-11.0 m unmeasured
            # A section whose figures cannot be trusted: it must not count, even with a value.
            statuses[150] = SectionStatus.TOO_FEW_POINTS
            values[150] = 0.95
        ids.append(save(engine, "P1", T0 + year * YEAR, sections_from(values, statuses=statuses)))
    return ids


# ---------------------------------------------------------------------------------------------
# Numeric core


def test_robust_slopes_resist_an_outlier() -> None:
    times = np.arange(5.0)
    line = 0.1 + 0.03 * times
    wild = line.copy()
    wild[4] = 0.9  # one bad survey, the latest
    values = np.column_stack([line, wild, np.full(5, np.nan), [np.nan, 0.2, np.nan, np.nan, 0.5]])
    slopes = core_trends.robust_slopes(times, values)
    assert slopes[0] == pytest.approx(0.03, abs=1e-12)
    assert slopes[1] == pytest.approx(0.03, abs=1e-12)
    assert np.polyfit(times, wild, 1)[0] > 0.1  # where least squares follows the outlier
    assert math.isnan(slopes[2])  # never measured: no slope, not 0
    assert slopes[3] == pytest.approx(0.1)  # two samples: their slope


def test_robust_slopes_skip_simultaneous_pairs() -> None:
    times = np.array([0.0, 0.0, 2.0])
    values = np.array([[0.1], [0.3], [0.5]])
    # Pairs (0,2) and (1,2): slopes 0.2 and 0.1; the pair at the same time has none.
    assert core_trends.robust_slopes(times, values)[0] == pytest.approx(0.15)
    assert core_trends.robust_slope([1.0, 1.0], [0.1, 0.2]) is None
    assert core_trends.robust_slope([0.0, 2.0, 4.0], [0.1, None, 0.3]) == pytest.approx(0.05)
    with pytest.raises(ValueError, match=r"shape \(N, K\)"):
        core_trends.robust_slopes(np.arange(3.0), np.zeros((4, 2)))


@pytest.mark.parametrize("lag", [-7, -3, 0, 2, 5])
def test_estimate_offset_recovers_a_known_shift(lag: int) -> None:
    rng = np.random.default_rng(7 + lag)
    x = np.arange(300) * STEP_M
    reference = true_blockage(x, 3) + rng.normal(0, 0.005, x.size)
    # The same pipe a year earlier (deposits smaller), surveyed with its chainage off by
    # ``lag`` cells, with noise and a gap: profile[k] is the pipe at reference cell k + lag.
    profile = true_blockage(x + lag * STEP_M, 2) + rng.normal(0, 0.005, x.size)
    profile[140:160] = np.nan
    found, correlation = core_trends.estimate_offset(reference, profile, max_lag=10)
    assert found == lag
    assert correlation is not None and correlation > 0.9


def test_estimate_offset_keeps_featureless_profiles_in_place() -> None:
    rng = np.random.default_rng(3)
    flat = np.full(200, 0.02)
    assert core_trends.estimate_offset(flat, flat.copy(), max_lag=10) == (0, None)
    noise_a, noise_b = rng.normal(0, 0.01, 200), rng.normal(0, 0.01, 200)
    lag, correlation = core_trends.estimate_offset(noise_a, noise_b, max_lag=10)
    assert lag == 0
    assert correlation is None or correlation < core_trends.MIN_CORRELATION
    # Too little overlap: nothing to go on.
    assert core_trends.estimate_offset(np.arange(5.0), np.arange(5.0), max_lag=2) == (0, None)


def test_rasterise_puts_sections_on_the_grid() -> None:
    # Sections of 0.2 m with a gap, on a 0.1 m grid from -0.2 m.
    start = np.array([0, 200, 600])
    end = np.array([200, 400, 800])
    values = np.array([0.1, np.nan, 0.3])
    grid = core_trends.rasterise(start, end, values, first_cell=-2, cell_count=10, step_mm=100)
    expected = [np.nan, np.nan, 0.1, 0.1, np.nan, np.nan, np.nan, np.nan, 0.3, 0.3]
    np.testing.assert_array_equal(grid, expected)


# ---------------------------------------------------------------------------------------------
# One asset's trend (SQLite and PostgreSQL)


def test_trend_aligns_surveys_and_recovers_change_per_year(
    engine: sa.Engine, pipe: list[int]
) -> None:
    result = trends.asset_trend(engine, "P1")
    assert [s.inspection_id for s in result.surveys] == pipe
    assert [s.is_reference for s in result.surveys] == [False, False, False, True]
    # Each survey is shifted back by its chainage error.
    assert [s.offset_m for s in result.surveys] == pytest.approx([-e for e in ERRORS_M])
    assert all(s.correlation > 0.95 for s in result.surveys[:-1])  # type: ignore[operator]
    assert result.step_m == pytest.approx(STEP_M)

    # Aligned, every cell's series is the true linear growth: Theil-Sen returns it exactly.
    centres = result.chainage_start_m + STEP_M / 2
    every = result.measured_count == 4
    assert every.sum() > 150
    np.testing.assert_allclose(
        result.change_per_year[every], true_change_per_year(centres[every]), atol=1e-9
    )
    # The aligned values are the pipe's true blockage at each survey's date.
    for year, row in enumerate(result.blockage_ratio):
        measured = np.isfinite(row)
        np.testing.assert_allclose(row[measured], true_blockage(centres[measured], year))

    fastest_m, fastest_rate = result.fastest_growth()  # type: ignore[misc]
    assert 11.8 <= fastest_m <= 12.1
    assert fastest_rate == pytest.approx(0.05, abs=0.002)
    # The whole pipe: the peak (at the 12 m deposit) grows 5 points a year, sampled at the
    # section centre 0.05 m from the deposit's.
    assert result.peak_change_per_year == pytest.approx(0.05 * bump(np.array(0.05), 0, 0.3))
    assert result.mean_change_per_year == pytest.approx(
        core_trends.robust_slope(
            [i for i in range(4)], [s.mean_blockage_ratio for s in result.surveys]
        )
    )


def test_unmeasured_sections_are_gaps_not_zeros(engine: sa.Engine, pipe: list[int]) -> None:
    result = trends.asset_trend(engine, "P1")
    second = 1
    # The second survey's gap, 10.0-11.0 m in its own chainage, is 10.4-11.4 m aligned.
    gap = (result.chainage_start_m >= 10.4 - 1e-9) & (result.chainage_start_m < 11.4 - 1e-9)
    assert gap.sum() == 10
    assert np.isnan(result.blockage_ratio[second, gap]).all()
    assert set(result.section_status[second, gap]) == {"low_coverage"}
    assert (result.measured_count[gap] == 3).all()
    # The untrusted section (15.0 m, 0.95 "blockage", too_few_points) is not a measurement.
    untrusted = result.cell_at(15.0 + 0.4)
    assert np.isnan(result.blockage_ratio[second, untrusted])
    assert result.section_status[second, untrusted] == "too_few_points"
    record = repository.get_inspection(engine, pipe[second])
    assert record.measured_section_count == 200 - 11
    assert record.peak_blockage_ratio is not None and record.peak_blockage_ratio < 0.5
    # Where no survey has a section, there is nothing: no row, no slope.
    assert np.isfinite(result.change_per_year[result.measured_count >= 2]).all()
    assert np.isnan(result.change_per_year[result.measured_count < 2]).all()


def test_without_alignment_the_change_per_year_is_wrong(engine: sa.Engine, pipe: list[int]) -> None:
    # The check that alignment matters: the same data taken at face value.
    result = trends.asset_trend(engine, "P1", max_offset_m=0.0)
    assert {s.offset_m for s in result.surveys} == {0.0}
    centres = result.chainage_start_m + STEP_M / 2
    every = result.measured_count == 4
    error = np.abs(result.change_per_year[every] - true_change_per_year(centres[every]))
    assert error.max() > 0.02


def test_trend_at_a_chainage_matches_the_stored_sections(
    engine: sa.Engine, pipe: list[int]
) -> None:
    result = trends.asset_trend(engine, "P1")
    cell = result.cell_at(12.03)
    assert result.chainage_start_m[cell] == pytest.approx(12.0)
    # Survey 0 stored the pipe's 12.0-12.1 m at 12.3 m (error +0.3 m).
    stored = repository.list_section_trend(engine, "P1", 12.35)
    assert stored[0].section.blockage_ratio == pytest.approx(result.blockage_ratio[0, cell])
    with pytest.raises(db.StorageError, match="outside asset P1's inspected length"):
        result.cell_at(99.0)


def test_reprocessed_scans_count_once_and_since_filters(engine: sa.Engine) -> None:
    first = save(engine, "Q", T0, sections_from([0.1] * 30), content_hash="h0")
    later = save(engine, "Q", T0 + YEAR, sections_from([0.2] * 30), content_hash="h1")
    # The first scan processed again with other parameters and other figures: it stands for
    # that scan in trends (the latest save), it does not add a second point at its date.
    again = save(engine, "Q", T0, sections_from([0.15] * 30), content_hash="h0", params={"v": 2})
    assert len({first, later, again}) == 3
    result = trends.asset_trend(engine, "Q")
    assert [s.inspection_id for s in result.surveys] == [again, later]
    assert result.peak_change_per_year == pytest.approx(0.05)
    assert trends.worst_assets(engine)[0].peak_change_per_year == pytest.approx(0.05)
    assert trends.worst_assets(engine)[0].inspection_count == 2
    # Since: the later inspection alone, so no change per year.
    assert trends.asset_trend(engine, "Q", since=T0 + YEAR / 2).peak_change_per_year is None
    assert trends.worst_assets(engine, since=T0 + YEAR / 2) == []
    with pytest.raises(db.StorageError, match="no inspections since 2030-01-01"):
        trends.asset_trend(engine, "Q", since=datetime(2030, 1, 1))


def test_trend_errors(engine: sa.Engine) -> None:
    with pytest.raises(db.StorageError, match=r"no asset 'nope'.*pipescan assets"):
        trends.asset_trend(engine, "nope")
    with pytest.raises(db.StorageError, match="max_offset_m"):
        trends.asset_trend(engine, "nope", max_offset_m=-1)


# ---------------------------------------------------------------------------------------------
# The network's worst pipes (SQLite and PostgreSQL)


@pytest.fixture
def network(engine: sa.Engine) -> dict[str, float]:
    """Pipes whose peak blockage grows at known rates; returns the rates."""
    rates = {"A": 0.05, "B": 0.10, "E": -0.02}
    base = {"A": 0.30, "B": 0.10, "E": 0.40}
    for asset_id, rate in rates.items():
        for year in range(4):
            values = [0.02] * 40
            values[20] = base[asset_id] + rate * year
            if asset_id == "A" and year == 2:
                values[20] = 0.95  # one wild survey: Theil-Sen shrugs it off
            save(engine, asset_id, T0 + year * YEAR, sections_from(values))
    # One inspection only: it has a current blockage, but no growth.
    save(engine, "C", T0 + 3 * YEAR, sections_from([0.02] * 10 + [0.6] + [0.02] * 10))
    # Never measured: in neither list.
    save(engine, "D", T0, sections_from([None] * 10))
    return rates


def test_worst_by_growth(engine: sa.Engine, network: dict[str, float]) -> None:
    rows = trends.worst_assets(engine, by="growth")
    assert [r.asset_id for r in rows] == ["B", "A", "E"]
    assert [r.peak_change_per_year for r in rows] == pytest.approx([0.10, 0.05, -0.02])
    assert [r.mean_change_per_year for r in rows] == pytest.approx(
        [0.10 / 40, 0.05 / 40, -0.02 / 40]
    )
    b = rows[0]
    assert b.inspection_count == 4
    assert b.current_peak_blockage_ratio == pytest.approx(0.40)
    assert b.current_peak_chainage_m == pytest.approx(2.0)
    assert b.last_inspected_at == T0 + 3 * YEAR
    assert b.nominal_diameter_m == pytest.approx(0.6)
    assert [r.asset_id for r in trends.worst_assets(engine, by="growth", limit=1)] == ["B"]


def test_worst_by_current(engine: sa.Engine, network: dict[str, float]) -> None:
    rows = trends.worst_assets(engine, by="current")
    # A's latest peak is 0.45, E's 0.34, B's 0.40, C's 0.6; D was never measured.
    assert [r.asset_id for r in rows] == ["C", "A", "B", "E"]
    assert [r.current_peak_blockage_ratio for r in rows] == pytest.approx([0.6, 0.45, 0.4, 0.34])
    assert rows[0].peak_change_per_year is None
    with pytest.raises(db.StorageError, match="unknown ranking"):
        trends.worst_assets(engine, by="size")  # type: ignore[arg-type]
    with pytest.raises(db.StorageError, match="limit"):
        trends.worst_assets(engine, limit=0)


# ---------------------------------------------------------------------------------------------
# One growth figure for every output (SQLite and PostgreSQL)

GROWTH = {"G1": 0.10, "G2": 0.0, "G3": -0.05, "G4": 0.05}  # peak blockage, ratio per year


@pytest.fixture
def surveyed(engine: sa.Engine) -> list[str]:
    """Pipes surveyed as crawlers survey them: each survey's chainage off by a few sections,
    noise on every section (G2 is noisy and does not change), three surveys of G3, and G1's
    first scan processed twice. Returns the pipes in the order of their true growth."""
    rng = np.random.default_rng(21)
    peak = {"G1": 0.20, "G2": 0.25, "G3": 0.45, "G4": 0.15}
    noise = {"G1": 0.002, "G2": 0.02, "G3": 0.002, "G4": 0.002}
    lags = {"G1": (0, 1), "G2": (0, -1), "G3": (-3, 0, 3), "G4": (0, 0)}  # sections off
    for asset, rate in GROWTH.items():
        for year, lag in enumerate(lags[asset]):
            x = (np.arange(60) + lag) * STEP_M + STEP_M / 2  # where each section truly is
            height = peak[asset] + rate * year - 0.02
            values = 0.02 + height * bump(x, 3.0, 0.4) + rng.normal(0, noise[asset], x.size)
            when, content = T0 + year * YEAR, f"{asset}-{year}"
            save(engine, asset, when, sections_from(values.tolist()), content_hash=content)
            if asset == "G1" and year == 0:  # the same scan again, other parameters
                again = sections_from((values + 0.01).tolist())
                save(engine, asset, when, again, content_hash=content, params={"v": 2})
    return sorted(GROWTH, key=lambda a: -GROWTH[a])


def test_worst_by_growth_and_the_network_report_rank_pipes_the_same(
    engine: sa.Engine, db_url: str, surveyed: list[str], tmp_path: Path
) -> None:
    from pipescan.reports.network import build_network_context, summarise
    from pipescan.reports.render import render_network_pdf
    from pipescan.tasks.reporting import load_network_input
    from tests.test_report import pdf_text

    worst = json.loads(run("worst", "--by", "growth", "--json", "--db", db_url))
    inp = load_network_input(db_url)
    ranked = build_network_context(inp)["by_growth"]
    assert [r["asset_id"] for r in worst] == surveyed
    assert [r["asset_id"] for r in ranked] == surveyed
    growth = {p.asset_id: summarise(p).growth_per_year_ratio for p in inp.pipes}
    for r in worst:
        assert growth[r["asset_id"]] == pytest.approx(r["peak_change_per_year"], abs=1e-12)
        # and ``trend`` says the same of each pipe
        trend = trends.asset_trend(engine, r["asset_id"])
        assert trend.peak_change_per_year == pytest.approx(r["peak_change_per_year"], abs=1e-12)
    # Near the truth, chainage errors notwithstanding (G1's re-processed first scan, one point
    # higher, stands for that scan; G2's peak moves with its 2-point noise).
    expected = {**GROWTH, "G1": GROWTH["G1"] - 0.01}
    assert [r["peak_change_per_year"] for r in worst] == pytest.approx(
        [expected[a] for a in surveyed], abs=0.015
    )
    # The PDF's growth table, in its order.
    text = pdf_text(render_network_pdf(inp, tmp_path / "network.pdf"))
    section = text[text.index("Pipes ranked by growth") :]
    assert re.findall(r"^\d+ (G\d) ", section, flags=re.MULTILINE) == surveyed


# ---------------------------------------------------------------------------------------------
# CLI (SQLite and PostgreSQL)


def run(*args: str) -> str:
    result = CliRunner().invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.output


def test_cli_trend(
    engine: sa.Engine, db_url: str, pipe: list[int], tmp_path: pytest.TempPathFactory
) -> None:
    out = run("trend", "P1", "--db", db_url)
    assert "P1 (? -> ?, DN 600, circular): 4 inspections" in out
    assert f"chainages are those of inspection {pipe[-1]}" in out
    assert "peak blockage  +4.93 pt/yr (+14.8 pp over 3.0 years): growing" in out
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.lstrip().startswith("chainage m"))
    table = lines[header + 1 :]
    assert len(table) == 207  # 20 m, widened by the offsets applied (-0.3 ... +0.4 m)
    row = next(line for line in table if line.split()[0] == "12.00")
    assert row.split()[5] == f"{100 * true_change_per_year(np.array(12.05)):+.2f}"
    assert row.split()[6] == "growing"
    # Where nothing grows, the noise of the surveys is worded as such, never as a rate alone.
    assert "no significant change" in out
    assert "-0.0 " not in out and "-0.00 " not in out

    out = run("trend", "P1", "--chainage", "10.5", "--db", db_url)
    assert "at chainage 10.50-10.60 m:" in out
    assert "unmeasured (low_coverage)" in out
    assert "(3 measured inspections)" in out

    data = json.loads(run("trend", "P1", "--chainage", "12", "--json", "--db", db_url))
    assert [s["offset_m"] for s in data["inspections"]] == pytest.approx([-0.3, 0.4, -0.2, 0])
    (cell,) = data["chainages"]
    assert cell["chainage_start_m"] == 12.0
    assert cell["change_per_year"] == pytest.approx(true_change_per_year(np.array(12.05)))

    png = tmp_path / "trend.png"  # type: ignore[operator]
    run("trend", "P1", "--chainage", "12", "--plot", str(png), "--db", db_url)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 20_000
    # A name without a suffix is that file (matplotlib would add .png, and the command said
    # it wrote the name it was given); a folder, or a path under a file, is one line.
    bare = tmp_path / "trend-plot"  # type: ignore[operator]
    run("trend", "P1", "--plot", str(bare), "--db", db_url)
    assert bare.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not bare.with_suffix(".png").exists()
    for bad, reason in ((tmp_path, "it is a folder"), (png / "x.png", "is not a folder")):
        result = CliRunner().invoke(app, ["trend", "P1", "--plot", str(bad), "--db", db_url])
        assert result.exit_code == 2
        assert "cannot write the plot: " in result.output and reason in result.output

    result = CliRunner().invoke(app, ["trend", "nope", "--db", db_url])
    assert result.exit_code == 2
    assert "no asset 'nope'" in result.output


def test_cli_worst_assets_inspections(
    engine: sa.Engine, db_url: str, network: dict[str, float]
) -> None:
    out = run("worst", "--db", db_url)
    lines = out.splitlines()
    assert [line.split()[1] for line in lines[1:4]] == ["B", "A", "E"]
    assert "+10.00 pt/yr" in lines[1] and lines[1].endswith("growing")
    assert lines[4].startswith("(peak change: under 2 pp")
    data = json.loads(run("worst", "--by", "current", "--limit", "2", "--json", "--db", db_url))
    assert [r["asset_id"] for r in data] == ["C", "A"]
    assert data[0]["current_peak_blockage_ratio"] == pytest.approx(0.6)

    assets = run("assets", "--db", db_url).splitlines()
    assert assets[0].split()[0] == "asset"  # a header row
    assert [line.split()[0] for line in assets[1:]] == ["A", "B", "C", "D", "E"]
    assert "1 inspection," in assets[1] or "inspections," in assets[1]
    inspections = run("inspections", "--asset", "D", "--db", db_url).splitlines()
    assert inspections[0].split()[:4] == ["id", "asset", "inspected", "measured"]
    assert inspections[1].split()[3:5] == ["0/10", "-"]


def test_cli_db_upgrade_and_current(db_url: str) -> None:
    out = run("db", "current", "--db", db_url)
    assert "revision none (empty database)" in out
    assert "run `pipescan db upgrade`" in out
    out = run("db", "upgrade", "--db", db_url)
    assert f"database migrated from empty to revision {db.head_revision()}" in out
    assert "up to date" in run("db", "current", "--db", db_url)
    assert "already at revision" in run("db", "upgrade", "--db", db_url)
    if not is_sqlite(db_url):
        # PostgreSQL: the commands that read refuse an unmigrated database, with the fix.
        db.downgrade(db_url, "base")
        result = CliRunner().invoke(app, ["worst", "--db", db_url])
        assert result.exit_code == 2
        assert "pipescan db upgrade" in result.output


# ---------------------------------------------------------------------------------------------
# Trend plots that show change, not noise


def _two_identical_surveys() -> trends.AssetTrend:
    """Two surveys a year apart of an unchanged pipe: 23.49 % at 3.8 m, read 0.005 pp apart."""
    rng = np.random.default_rng(5)
    profile = np.where(np.abs(np.arange(40) - 38) < 3, 0.2349, 0.004)
    values = np.vstack([profile, profile + rng.normal(0, 0.00005, profile.size)])
    times = [T0, T0 + YEAR]
    surveys = tuple(
        trends.SurveyAlignment(
            inspection_id=i + 1,
            inspected_at=t,
            offset_m=0.0,
            correlation=None if i else 1.0,
            is_reference=bool(i),
            measured_section_count=values.shape[1],
            mean_blockage_ratio=float(values[i].mean()),
            peak_blockage_ratio=float(values[i].max()),
            peak_chainage_m=3.8,
        )
        for i, t in enumerate(times)
    )
    slopes = core_trends.robust_slopes(np.array([core_trends.years(t) for t in times]), values)
    return trends.AssetTrend(
        asset_id="SAME-1",
        upstream_node=None,
        downstream_node=None,
        nominal_diameter_m=0.5,
        pipe_shape="circular",
        material=None,
        step_m=STEP_M,
        surveys=surveys,
        chainage_start_m=np.arange(40) * STEP_M,
        blockage_ratio=values,
        section_status=np.full(values.shape, "ok", dtype=object),
        change_per_year=slopes,
        measured_count=np.full(40, 2),
        mean_change_per_year=None,
        peak_change_per_year=core_trends.growth_per_year(
            times, [s.peak_blockage_ratio for s in surveys]
        ),
    )


def test_the_trend_plot_of_an_unchanged_pipe_shows_no_change() -> None:
    import matplotlib.pyplot as plt

    from pipescan.cli.trends import _MIN_SPAN_PCT, _trend_figure

    result = _two_identical_surveys()
    figure = _trend_figure(result, result.cell_at(3.8))
    try:
        top, middle, bottom = figure.axes[:3]
        for axis in (top, middle, bottom):
            assert axis.yaxis.get_offset_text().get_text() == ""  # never "+2.349e1"
        for axis in (top, bottom):  # blockage: from 0, at least a few points tall
            low, high = axis.get_ylim()
            assert low <= 0 and high - low >= _MIN_SPAN_PCT and high > 23.49
        # The change per year: the band of no significant change (2 pp over 1 year) and
        # more, so a 0.01 pt/yr wobble is a sliver in grey, not a cliff in red.
        low, high = middle.get_ylim()
        band = 100 * core_trends.SIGNIFICANT_CHANGE_RATIO / 1.0
        assert -low == pytest.approx(high) and high >= 1.5 * band
        bars = [p for p in middle.containers[0] if p.get_height() != 0]
        assert bars and {p.get_facecolor()[:3] for p in bars} == {(0x9A / 255,) * 3}
        assert "no significant change" in bottom.get_title()
        # The earlier survey is drawn wider, beneath: visible although the two coincide.
        earlier, later = top.get_lines()[:2]
        assert earlier.get_linewidth() > later.get_linewidth() + 1
        assert earlier.get_zorder() < later.get_zorder()
    finally:
        plt.close(figure)


def test_trend_text_words_noise_as_no_significant_change(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from pipescan.cli import trends as cli_trends

    result = _two_identical_surveys()
    printed: list[str] = []
    monkeypatch.setattr(cli_trends.typer, "echo", lambda text="", **_: printed.append(text))
    cli_trends._print_trend(result, result.cell_at(3.8))
    text = "\n".join(printed)
    assert "peak blockage  " in text and "no significant change" in text
    assert "growing" not in text and "shrinking" not in text
    assert "-0.0" not in text
