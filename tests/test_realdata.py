"""The real S3DSS scan (800 mm concrete pipe, FARO Focus S): what the measures must show."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipescan.core.axis import fit_axis
from pipescan.core.model import SectionStatus
from pipescan.core.sections import measure_window, plan_windows
from pipescan.storage.input.pointfiles import read_points

# The shared data sit beside the repository (CI); PIPESCAN_REALDATA_DIR points elsewhere (a
# worktree whose parent has no shared/).
REALDATA = Path(
    os.environ.get("PIPESCAN_REALDATA_DIR")
    or Path(__file__).resolve().parents[2] / "shared" / "realdata"
)
REAL = REALDATA / "s3dss-real459-16k"


@pytest.fixture(scope="module")
def sections():
    path = REAL / "real_459_full.txt"
    if not path.exists():
        pytest.skip(f"the real scan is not at {path}")
    points = read_points(path, kind="cloud")  # x y z label: the label column is ignored
    axis = fit_axis(points)
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
