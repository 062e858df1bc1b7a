"""The real S3DSS scan (800 mm concrete pipe, FARO Focus S): what the measures must show.

The scan is looked for in ``$PIPESCAN_REALDATA_DIR`` when that is set, else in
``shared/realdata/s3dss-real459-16k`` beside the repository (as CI has it).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from pipescan.core.axis import fit_axis
from pipescan.core.coding import BAA, BBE, clock_hours, code_sections
from pipescan.core.grading import grade_sections, load_table, merge_defects
from pipescan.core.model import SectionStatus
from pipescan.core.sections import measure_window, plan_windows
from pipescan.storage.input.pointfiles import read_points
from tests.conftest import _in_ci

# The shared data sit beside the repository (CI); PIPESCAN_REALDATA_DIR points elsewhere (a
# worktree whose parent has no shared/).
REALDATA = Path(
    os.environ.get("PIPESCAN_REALDATA_DIR")
    or Path(__file__).resolve().parents[2] / "shared" / "realdata"
)
REAL = REALDATA / "s3dss-real459-16k"
LABEL_BLOCKAGE = 2  # the file's fourth column: a segmentation model's label (PROVENANCE.md)


@pytest.fixture(scope="module")
def scan():
    path = REAL / "real_459_full.txt"
    if not path.exists():
        message = f"the real scan is not at {path} (set PIPESCAN_REALDATA_DIR)"
        if _in_ci():
            pytest.fail(f"{message} (CI is set: CI has ../shared/realdata)", pytrace=False)
        pytest.skip(message)
    points = read_points(path, kind="cloud")  # x y z label: the label column is ignored
    return points, fit_axis(points), np.loadtxt(path)[:, 3]


@pytest.fixture(scope="module")
def sections(scan):
    points, axis, _ = scan
    chain = axis.chainage(points)
    out = []
    for w in plan_windows(chain.min(), chain.max(), step_m=0.1, window_m=1.0):
        for s in measure_window(points, axis, w, nominal_diameter_m=0.8):
            x_m = float(axis.point_at(s.chainage_start_m + 0.05, 0.0, 0.0)[0])
            out.append((x_m, s))
    return out


def test_clean_sections_measure_800_mm(sections):
    clean = [s for x, s in sections if s.is_ok and not 0.4 <= x <= 0.7]
    assert len(clean) >= 8
    for s in clean:
        diameter = 2.0 * np.sqrt(s.open_area_m2 / np.pi)
        assert diameter == pytest.approx(0.800, abs=0.005), s


def test_intrusion_is_the_largest_blockage(sections):
    ok = [(x, s) for x, s in sections if s.is_ok]
    x_worst, worst = max(ok, key=lambda xs: xs[1].blockage_ratio)
    # The blockage-labelled points of the file lie at x = +0.45 ... +0.65.
    assert 0.4 <= x_worst <= 0.7
    assert worst.blockage_ratio > 0.02


def test_data_gap_is_low_coverage_not_pipe(sections):
    in_gap = [s for x, s in sections if -0.2 <= x <= 0.1]
    assert in_gap
    assert all(s.status == SectionStatus.LOW_COVERAGE for s in in_gap)
    assert all(s.coverage_ratio < 0.95 for s in in_gap)


def test_the_object_is_coded_an_obstacle_where_its_points_are(scan, sections):
    # The object at x = +0.45 ... +0.65 m stands off the wall at the invert (its points are
    # labelled Blockage in the file): one BBE defect there, at the clock positions of those
    # points, not a deformation; concrete, so the rigid pipe's rules.
    points, axis, labels = scan
    table = load_table()
    measured = [s for _, s in sections]
    codings = code_sections(measured)
    graded = grade_sections(measured, table, pipe_class="rigid", codings=codings)
    defects = merge_defects(graded, table, pipe_class="rigid", codings=codings)
    assert BAA not in [d.code for d in defects]
    (obstacle,) = [d for d in defects if d.code == BBE]
    x_from = float(axis.point_at(obstacle.chainage_start_m, 0.0, 0.0)[0])
    x_to = float(axis.point_at(obstacle.chainage_end_m, 0.0, 0.0)[0])
    assert 0.35 <= x_from < x_to <= 0.75
    # The labelled points' clock positions, looking in the survey's direction.
    _, plane = axis.local_coordinates(points[labels == LABEL_BLOCKAGE])
    hours = np.array([clock_hours(math.atan2(y, x)) for x, y in plane])
    lo, hi = np.percentile(hours, [5, 95])
    assert 4.0 < lo < hi < 6.5  # right of the invert: the file's -y side, z down
    assert abs(obstacle.clock_from_h - lo) <= 1.0 and abs(obstacle.clock_to_h - hi) <= 1.0
    # About 3 % of the cross-section: class 4 under vsa-2023, so no section is worse.
    assert obstacle.grade == 4
    assert min(s.grade for s in graded if s.grade is not None) == 4
