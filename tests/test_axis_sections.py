"""Pipe axis fitting and sectioning on synthetic pipes at arbitrary orientation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipescan.core.axis import fit_axis, fit_circle_robust, nearest_node
from pipescan.core.errors import GeometryError
from pipescan.core.sections import measure_window, plan_windows
from tests.synthetic import (
    curved_pipe_cloud,
    pipe_cloud,
    random_rigid,
    segment_area_ratio,
    transform,
)

R = 0.25


def test_robust_circle_ignores_deposit():
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, 3000)
    wall = np.column_stack((0.1 + R * np.cos(t), -0.2 + R * np.sin(t)))
    debris = np.column_stack((rng.uniform(0.0, 0.2, 1500), rng.uniform(-0.4, -0.33, 1500)))
    centre, radius, inliers = fit_circle_robust(np.vstack((wall, debris)))
    assert np.allclose(centre, [0.1, -0.2], atol=0.002)
    assert radius == pytest.approx(R, abs=0.002)
    assert inliers[len(wall) :].mean() < 0.05


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_axis_recovered_at_any_orientation_despite_deposits(seed):
    rng = np.random.default_rng(seed)
    cloud = pipe_cloud(length_m=4.0, deposit=(1.0, 3.0, 0.12), rng=rng)
    T = random_rigid(rng)
    start = transform(T, np.zeros((1, 3)))[0]
    travel = T[:3, :3] @ np.array([1.0, 0, 0])
    axis = fit_axis(transform(T, cloud), start_m=start, travel_m=travel, up_hint=T[:3, 2])
    true_dir = T[:3, :3] @ np.array([1.0, 0, 0])
    angle_deg = np.degrees(np.arccos(min(1.0, abs(axis.direction @ true_dir))))
    assert angle_deg < 0.2
    assert axis.direction @ true_dir > 0
    # The axis passes through the pipe centre, not the deposit-biased centroid.
    assert np.linalg.norm(axis.origin_m - start) < 0.003
    assert axis.radius_m == pytest.approx(R, abs=0.002)
    # Chainage starts at the scan start.
    assert axis.chainage(start[None])[0] == pytest.approx(0.0, abs=1e-9)


def test_upstream_survey_counts_chainage_down_from_offset():
    rng = np.random.default_rng(4)
    cloud = pipe_cloud(length_m=3.0, rng=rng)
    axis = fit_axis(
        cloud,
        start_m=np.zeros(3),
        travel_m=np.array([1.0, 0, 0]),
        chainage_offset_m=50.0,
        direction="upstream",
    )
    assert axis.chainage(np.array([[2.0, 0, 0]]))[0] == pytest.approx(48.0, abs=0.01)


def test_fit_axis_rejects_a_blob():
    rng = np.random.default_rng(5)
    with pytest.raises(GeometryError, match="elongated"):
        fit_axis(rng.normal(size=(5000, 3)))


def test_plan_windows_cover_whole_sections():
    windows = plan_windows(0.03, 4.96, step_m=0.1, window_m=2.0)
    assert windows[0].start_mm == 0 and windows[-1].end_mm == 5000
    assert all(a.end_mm == b.start_mm for a, b in itertools.pairwise(windows))
    assert sum(len(w.section_starts_mm()) for w in windows) == 50


def _blockage_profile(cloud, T, up):
    axis = fit_axis(transform(T, cloud), start_m=T[:3, 3], travel_m=T[:3, 0], up_hint=up)
    sections = []
    for w in plan_windows(0.0, 4.0, step_m=0.1, window_m=1.0):
        sections += measure_window(transform(T, cloud), axis, w, nominal_diameter_m=0.5)
    return {round(s.chainage_start_m, 3): s for s in sections}


def test_sections_measure_deposit_span_at_the_right_chainage():
    rng = np.random.default_rng(6)
    cloud = pipe_cloud(length_m=4.0, deposit=(1.5, 2.5, 0.1), rng=rng)
    prof = _blockage_profile(cloud, np.eye(4), np.array([0, 0, 1.0]))
    expected = segment_area_ratio(0.1, R)
    for c, s in prof.items():
        if 1.6 <= c < 2.4:
            assert s.status.value == "ok"
            assert s.blockage_ratio == pytest.approx(expected, abs=0.005)
        elif 0.2 <= c < 1.4 or 2.6 <= c < 3.8:
            assert s.blockage_ratio == pytest.approx(0.0, abs=0.005)


@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_blockage_invariant_under_rigid_motion_and_shuffle(seed):
    rng = np.random.default_rng(seed)
    cloud = pipe_cloud(length_m=4.0, points_per_m=20_000, deposit=(1.5, 2.5, 0.1), rng=rng)
    base = _blockage_profile(cloud, np.eye(4), np.array([0, 0, 1.0]))
    T = random_rigid(rng)
    moved = _blockage_profile(cloud[rng.permutation(len(cloud))], T, T[:3, 2])
    for c in base:
        if 0.3 <= c < 3.7 and base[c].is_ok:
            assert moved[c].blockage_ratio == pytest.approx(base[c].blockage_ratio, abs=0.004)


def _profile(cloud, axis):
    sections = []
    for w in plan_windows(0.3, 5.7, step_m=0.1, window_m=2.0):
        sections += measure_window(cloud, axis, w, nominal_diameter_m=0.5)
    return sections


def test_centreline_follows_a_bend_and_a_sag():
    rng = np.random.default_rng(12)
    cloud, true_arc = curved_pipe_cloud(rng=rng)
    axis = fit_axis(cloud, start_m=np.zeros(3), travel_m=np.array([1.0, 0.0, 0.0]))
    assert axis.is_curved
    # Chainage is the distance along the bent centreline, not along a chord.
    assert np.abs(axis.chainage(cloud) - true_arc).max() < 0.01
    sections = _profile(cloud, axis)
    ok = [s for s in sections if s.is_ok]
    assert len(ok) >= 50
    assert max(abs(s.blockage_ratio) for s in ok) < 0.005
    # A straight axis through the same bend smears every section: the test can tell.
    straight = fit_axis(
        cloud, start_m=np.zeros(3), travel_m=np.array([1.0, 0.0, 0.0]), curve_tolerance_m=1.0
    )
    assert not straight.is_curved
    smeared = [s for s in _profile(cloud, straight) if s.blockage_ratio is not None]
    assert max(abs(s.blockage_ratio) for s in smeared) > 0.02


def test_straight_pipe_stays_a_line():
    rng = np.random.default_rng(13)
    axis = fit_axis(pipe_cloud(length_m=4.0, rng=rng), start_m=np.zeros(3))
    assert not axis.is_curved


def test_each_point_is_placed_at_its_nearest_node_of_a_bent_centreline():
    rng = np.random.default_rng(3)
    s = np.linspace(-0.5, 12.0, 250)
    nodes = np.column_stack((s, 0.3 * np.sin(s / 2), 0.1 * np.cos(s / 3)))
    points = nodes[rng.integers(0, len(s), 5000)] + rng.normal(0.0, 0.3, (5000, 3))
    brute = np.argmin(((points[:, None, :] - nodes[None, :, :]) ** 2).sum(axis=2), axis=1)
    assert np.array_equal(nearest_node(nodes, points), brute)
    assert np.array_equal(nearest_node(nodes, points.astype(np.float32)), brute)
    assert nearest_node(nodes, np.empty((0, 3))).shape == (0,)
