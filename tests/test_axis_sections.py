"""Pipe axis fitting and sectioning on synthetic pipes at arbitrary orientation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipescan.core.axis import NodeLocator, fit_axis, fit_circle_robust, nearest_node
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
    on_deposit = [s for c, s in prof.items() if 1.6 <= c < 2.4]
    clear = [s for c, s in prof.items() if 0.2 <= c < 1.4 or 2.6 <= c < 3.8]
    assert len(on_deposit) == 8 and len(clear) == 24, sorted(prof)
    for s in on_deposit:
        assert s.status.value == "ok"
        assert s.blockage_ratio == pytest.approx(expected, abs=0.005)
    for s in clear:
        assert s.blockage_ratio == pytest.approx(0.0, abs=0.005)


@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_blockage_invariant_under_rigid_motion_and_shuffle(seed):
    rng = np.random.default_rng(seed)
    cloud = pipe_cloud(length_m=4.0, points_per_m=20_000, deposit=(1.5, 2.5, 0.1), rng=rng)
    base = _blockage_profile(cloud, np.eye(4), np.array([0, 0, 1.0]))
    T = random_rigid(rng)
    moved = _blockage_profile(cloud[rng.permutation(len(cloud))], T, T[:3, 2])
    compared = [c for c in base if 0.3 <= c < 3.7 and base[c].is_ok]
    assert len(compared) >= 20, compared  # of the 34 sections in range, most are ok
    for c in compared:
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


def _ring_points(nodes, rng, n, radius_m):
    """Points on a ring of ``radius_m`` around random nodes, spread along the node step."""
    at = rng.integers(0, len(nodes), n)
    angle = rng.uniform(0, 2 * np.pi, n)
    ring = np.column_stack((rng.uniform(-0.03, 0.03, n), np.cos(angle), np.sin(angle)))
    return nodes[at] + ring * [1.0, radius_m, radius_m] + rng.normal(0, 0.005, (n, 3))


@pytest.mark.parametrize(
    "case",
    [
        "drifting",
        "bend 12 m",
        "tight sine",
        "kink",
        "step far off",
        "beyond the ends",
        "u-bend",
        "three nodes",
    ],
)
def test_node_locator_finds_the_k_d_trees_node(case):
    """The search along the chord gives every point the k-d tree's node, on centrelines it
    can prove (a registered straight pipe drifting by a centimetre) and on ones it cannot
    (a bend, a U-turn, points far beyond the ends), for float32 and float64 points."""
    rng = np.random.default_rng(7)
    if case == "drifting":
        s = np.arange(-1.5, 31.3, 0.05)
        nodes = np.column_stack((s, 0.01 * np.sin(s / 7), 0.015 * np.cos(s / 9)))
        points = _ring_points(nodes, rng, 40_000, 0.3)
    elif case == "bend 12 m":
        th = np.arange(0.0, 1.2, 0.05 / 12)
        nodes = np.column_stack((12 * np.sin(th), 12 * (1 - np.cos(th)), 0.03 * np.sin(5 * th)))
        points = _ring_points(nodes, rng, 40_000, 0.3)
    elif case == "tight sine":
        s = np.linspace(-0.5, 12.0, 250)
        nodes = np.column_stack((s, 0.3 * np.sin(s / 2), 0.1 * np.cos(s / 3)))
        points = nodes[rng.integers(0, len(s), 20_000)] + rng.normal(0.0, 0.3, (20_000, 3))
    elif case == "beyond the ends":
        s = np.arange(0.0, 5.0, 0.05)
        nodes = np.column_stack((s, 0.002 * s, np.zeros_like(s)))
        points = rng.uniform(-3.0, 8.0, (20_000, 3))
    elif case == "kink":
        # A node 5 cm off the line and two steps on can be nearer than the local minimum.
        s = np.arange(0.0, 5.0, 0.05)
        nodes = np.column_stack((s, np.where((s > 1.97) & (s < 2.23), 0.25, 0.0), 0 * s))
        points = rng.uniform([0.0, -0.5, -0.5], [5.0, 0.6, 0.5], (20_000, 3))
    elif case == "step far off":
        # Nodes beyond the reach along the chord, yet nearer than the local minimum.
        s = np.arange(0.0, 10.0, 0.05)
        nodes = np.column_stack((s, np.where((s > 7.18) & (s < 8.5), 2.5, 0.0), 0 * s))
        near = _ring_points(nodes[:120], rng, 16_000, 0.3)
        points = np.vstack((near, rng.uniform([4.0, 2.0, -0.5], [6.5, 3.0, 0.5], (4_000, 3))))
    elif case == "u-bend":
        th = np.linspace(0, np.pi, 200)
        nodes = np.column_stack((np.sin(th), 1 - np.cos(th), np.zeros_like(th)))
        points = rng.normal(0, 0.5, (20_000, 3)) + np.array([0.5, 1.0, 0.0])
    else:
        nodes = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.1, 0.001, 0]])
        points = rng.normal(0, 0.2, (2_000, 3))
    locator = NodeLocator(nodes)
    for pts in (points, points.astype(np.float32)):
        assert np.array_equal(locator.nearest(pts), nearest_node(nodes, pts))
    if case == "drifting":
        # The fast path carries it: nearly every point is proven without the k-d tree.
        _, proven = locator._along_chord(points)
        assert proven.mean() > 0.95
    assert locator.nearest(np.empty((0, 3))).shape == (0,)


def test_a_curved_axis_places_points_as_its_nodes_say():
    """``section_coordinates`` along a fitted curved centreline uses the locator's nodes:
    the same chainage as placing by the k-d tree's nearest node."""
    rng = np.random.default_rng(12)
    cloud, _ = curved_pipe_cloud(rng=rng)
    axis = fit_axis(cloud, start_m=np.zeros(3), travel_m=np.array([1.0, 0.0, 0.0]))
    assert axis.is_curved
    chainage, plane = axis.section_coordinates(cloud)
    nodes = axis.nodes_m - axis.origin_m
    i = nearest_node(nodes, cloud - axis.origin_m)
    d = cloud - axis.origin_m - nodes[i]
    assert np.allclose(chainage, axis.chainage_offset_m + axis.chainage_sign * (
        axis.arc_m[i] + np.einsum("ij,ij->i", d, axis.tangents[i])))  # fmt: skip
    assert np.allclose(plane[:, 1], np.einsum("ij,ij->i", d, axis.ups[i]))


def test_the_axis_is_the_same_on_two_threads():
    """Fitting the slices' circles on two threads changes nothing: each fit has its seed."""
    rng = np.random.default_rng(12)
    cloud, _ = curved_pipe_cloud(rng=rng)
    kwargs = {"start_m": np.zeros(3), "travel_m": np.array([1.0, 0.0, 0.0])}
    one, two = fit_axis(cloud, **kwargs), fit_axis(cloud, workers=2, **kwargs)
    assert two.is_curved
    assert np.array_equal(one.nodes_m, two.nodes_m) and np.array_equal(one.ups, two.ups)
    assert np.array_equal(one.origin_m, two.origin_m) and one.radius_m == two.radius_m
