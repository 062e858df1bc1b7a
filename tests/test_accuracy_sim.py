"""Section figures against the simulator's ground truth: with true poses (issue 4's targets, on
a short scene that keeps the default test run quick; ``benchmarks/bench_sections.py accuracy``
runs the whole paper scenario), and with estimated poses on randomly drawn sensor and crawler
effects (issue 12)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import binom

from pipescan.core.axis import fit_axis
from pipescan.core.measures import MeasureParams
from pipescan.core.model import FrameQuality, SectionStatus
from pipescan.core.registration import Trajectory
from pipescan.core.sections import measure_window, plan_windows
from pipescan.simulator.scan import get_scenario, simulate_scan
from pipescan.simulator.sweep import (
    TrueBlockage,
    along_axis_travel,
    chainage_bound_misses,
    defect_scene,
    layout_draws,
    measure_scan,
    random_effects,
    score_sections,
    slip_draws,
    stretches_worse_than_odometer,
    true_shifts,
)

MAX_RANGE_M = 5.0


@pytest.fixture(scope="module")
def obstacle_sections():
    """The paper scenario's obstacle (16.8 % blockage, hanging from the crown at 2.6-2.9 m)
    scanned from 3 m of travel, measured with the true poses, paired with the truth."""
    scan = simulate_scan(get_scenario("paper", travel_m=3.0, deformations=(), deposits=()), seed=3)
    points = scan.points_true_poses(max_range_m=MAX_RANGE_M)
    start = scan.T_pipe_sensor(0)[:3, 3]
    axis = fit_axis(
        points, start_m=start, travel_m=scan.T_pipe_sensor(len(scan) - 1)[:3, 3] - start
    )
    chain = axis.chainage(points)
    sections = []
    for w in plan_windows(max(0.0, chain.min()), chain.max(), step_m=0.1, window_m=2.0):
        inside = (chain >= w.start_m) & (chain < w.end_m)
        sections += measure_window(
            points[inside], axis, w, nominal_diameter_m=0.5, params=MeasureParams()
        )
    truth = {round(t.chainage_start_m, 1): t for t in scan.true_sections()}
    return [
        (s, truth[round(s.chainage_start_m, 1)])
        for s in sections
        if round(s.chainage_start_m, 1) in truth
    ]


def test_sections_over_an_overhanging_obstacle_within_one_point(obstacle_sections):
    over = [(s, t) for s, t in obstacle_sections if t.blockage_ratio > 0.05]
    assert [round(s.chainage_start_m, 1) for s, _ in over] == [2.6, 2.7, 2.8]
    for s, t in over:
        assert s.is_ok, s
        error_pp = 100.0 * (s.blockage_ratio - t.blockage_ratio)
        # The free space beside the box that the sensor never saw counts as blocked, so the
        # error is one-sided; the space it did see counts as free, so it stays under a point.
        assert -0.3 <= error_pp <= 1.0, (s.chainage_start_m, error_pp)


def test_ok_sections_mean_error_and_shadow_behind_the_obstacle(obstacle_sections):
    ok = [(s, t) for s, t in obstacle_sections if s.is_ok]
    errors = np.array([100.0 * abs(s.blockage_ratio - t.blockage_ratio) for s, t in ok])
    assert len(ok) >= 20
    assert errors.mean() <= 0.3 and errors.max() <= 1.0
    shadows = [s for s, t in obstacle_sections if t.in_shadow and t.coverage_ratio < 0.95]
    assert shadows and not any(s.is_ok for s in shadows)


# ------------------------------------------------------------------ randomised realism

# The effects are drawn from issue 12's ranges (pipescan.simulator.sweep.random_effects), the
# scene is a pipe of 0.3-0.6 m with the paper's defects and the end wall out of registration's
# range, so that nothing flatters the along-axis position. The benchmark's sweep
# (benchmarks/bench_registration.py sweep) runs the full set through the flow.
RANDOM_DRAWS = [
    pytest.param(0, 0.3, id="draw0-0.3m"),
    pytest.param(1, 0.6, id="draw1-0.6m", marks=pytest.mark.slow),
    pytest.param(2, 0.5, id="draw2-0.5m", marks=pytest.mark.slow),
    pytest.param(3, 0.3, id="draw3-0.3m", marks=pytest.mark.slow),
]


@pytest.mark.parametrize(("draw", "diameter_m"), RANDOM_DRAWS)
def test_estimated_poses_hold_on_random_effects(draw, diameter_m):
    rng = np.random.default_rng(1000 + draw)
    effects = random_effects(rng)
    scene = defect_scene(diameter_m, 3.0, effects=effects, name=f"draw{draw}")
    scan = simulate_scan(dataclasses.replace(scene, points_per_s=200_000), seed=draw)
    trajectory, sections = measure_scan(scan)
    # Registered travel within the odometer's own error (plus 0.5 % for ICP's).
    true_m = scan.true_travel_m[-1]
    travel_error_m = abs(along_axis_travel(trajectory, scan)[1][-1] - true_m)
    odometer_error_m = abs(scan.odometer_m[-1] - true_m)
    assert travel_error_m <= odometer_error_m + 0.005 * true_m, effects
    # And over every half metre: never further off than the odometer there.
    worse, stretches = stretches_worse_than_odometer(trajectory, scan)
    assert stretches >= 5 and worse == 0, (worse, stretches, effects)
    # The chainage uncertainty bounds the error where no slip fooled the odometer unseen.
    if not len(scan.slip_frames):
        assert travel_error_m <= trajectory.quality[-1].chainage_uncertainty_m + 0.005
    score = score_sections(sections, TrueBlockage(scan), true_shifts(scan, trajectory))
    assert score.ok >= 10
    # Each ok section's points really were within its chainage uncertainty of it.
    assert score.beyond_u == 0, score
    # Issue 12's targets, on ok sections away from every defect's edge by more than their
    # chainage uncertainty; and no ok section off by more than 2 pp anywhere.
    assert score.mean_pp <= 0.3 and score.max_pp <= 1.0, score
    assert score.dishonest == 0, score
    # A section in a shadow may be ok only where what was seen of it bounds its figure (a
    # far section just under the shadow's coverage, sampled whole, can be).
    assert score.shadows_ok_wrong == 0, score
    # Each ok section's stated blockage ± is a 95 % bound: no more of them miss the truth (by
    # more than the report's 0.1 pp) than one in twenty would, but for chance (a binomial
    # count's 1-in-1000 tail). On these four draws 1 of 50, 1 of 23, 2 of 33 and 1 of 48
    # missed: 5 of 154, 3.2 %.
    assert score.beyond_stated <= binom.ppf(0.999, score.ok, 0.05), score


@pytest.mark.slow
def test_an_object_ghosted_by_an_unseen_slide_is_not_an_ok_figure():
    """A random layout (``layout_draws``, seed 2026 + 2) whose crawler slid 0.27 m while the
    count stood, with nothing registration could see in view: a box hanging from the crown
    ahead is placed about 0.3 m short by the frames after the slide, and where it is by those
    before. The sections through that ghost, where one set of frames saw the box and the
    other the bare crown, read several per cent where the pipe is clear; they must not be ok,
    nor must the sections across the ghost's edges, which hold the box in only some of their
    sub-slices (docs/measures.md). No ok section is left more than 2 points off the truth
    everywhere within its chainage ±."""
    draw = layout_draws(3)[2]
    scan = simulate_scan(draw.scenario, draw.seed)
    trajectory, sections = measure_scan(scan)
    assert not trajectory.odometer_slips_m  # the slide went unseen: the chainage ± is short
    truth = TrueBlockage(scan)
    ghost = [
        s
        for s in sections
        if s.blockage_ratio is not None
        and s.blockage_ratio > 0.015
        and truth.section(np.array([s.chainage_start_m]))[0] < 0.005
    ]
    assert len(ghost) >= 2, "the slide left no ghost: the scene no longer tests this"
    assert not any(s.is_ok for s in ghost), ghost
    assert all(s.status == SectionStatus.SMEARED_WALL for s in ghost), ghost
    assert score_sections(sections, truth).dishonest == 0


def test_true_shifts_say_where_a_drifted_section_really_was():
    """A section's true place follows the registered poses' error along the axis."""
    scene = defect_scene(0.5, 1.5, name="shifts")
    scan = simulate_scan(dataclasses.replace(scene, points_per_s=40_000), seed=5)
    frames = len(scan)
    exact = Trajectory(scan.T_world_sensor.copy(), (), tuple(range(frames)))
    assert set(true_shifts(scan, exact).values()) == {0.0}
    # From the middle frame on, every frame registered 0.2 m too far along the pipe: what
    # those frames alone saw lies 0.2 m before where its sections say.
    drifted = scan.T_world_sensor.copy()
    axis_world = scan.T_world_pipe[:3, 0]
    drifted[frames // 2 :, :3, 3] += 0.2 * axis_world
    shifts = true_shifts(scan, Trajectory(drifted, (), tuple(range(frames))))
    far = [v for k, v in shifts.items() if k >= scene.chainage_offset_m + 5.9]
    near = [v for k, v in shifts.items() if k < scene.chainage_offset_m + 0.5]
    assert far and all(v == pytest.approx(-0.2) for v in far)
    assert near and all(v == 0.0 for v in near)


def test_chainage_bound_misses_count_frames_off_beyond_their_uncertainty():
    scan = simulate_scan(
        dataclasses.replace(defect_scene(0.5, 1.0, name="bound"), points_per_s=20_000), seed=2
    )
    frames = len(scan)
    # Registration's world is the first frame's sensor frame.
    poses = np.linalg.inv(scan.T_world_sensor[0]) @ scan.T_world_sensor
    # The last ten frames 4 cm too far along the pipe; their stated ± is 3 cm, the rest 1 cm.
    poses[-10:, :3, 3] += 0.04 * (scan.T_world_sensor[0, :3, :3].T @ scan.T_world_pipe[:3, 0])
    quality = tuple(
        FrameQuality(
            i, 1.0, 0.0, False, 1.0, chainage_uncertainty_m=0.03 if i >= frames - 10 else 0.01
        )
        for i in range(frames)
    )
    trajectory = Trajectory(poses, quality, tuple(range(frames)))
    beyond, most = chainage_bound_misses(trajectory, scan)
    assert beyond == 10 and most == pytest.approx(0.01, abs=1e-6)
    # Within the tolerance (5 mm), a frame is not counted.
    quality = tuple(dataclasses.replace(q, chainage_uncertainty_m=0.036) for q in quality)
    assert chainage_bound_misses(Trajectory(poses, quality, tuple(range(frames))), scan)[0] == 0


def test_slip_draws_slip_often_and_do_not_change_with_their_count():
    draws = slip_draws(4)
    assert [d.name for d in draws] == [d.name for d in slip_draws(6)[:4]]
    assert all(0.15 <= d.scenario.effects.slip_per_m <= 0.5 for d in draws)
    assert len({d.seed for d in draws}) == 4


def test_layout_draws_are_varied_and_do_not_change_with_their_count():
    draws = layout_draws(12)
    assert [d.name for d in draws[:5]] == [d.name for d in layout_draws(5)]
    scenes = [d.scenario for d in draws]
    # Every kind of defect, in more than the sweep's three pipe sizes, never the fixed layout.
    assert all(any(getattr(s, kind) for s in scenes) for kind in (
        "deformations", "deposits", "obstacles", "bands"))  # fmt: skip
    assert len({s.nominal_diameter_m for s in scenes}) >= 4
    fixed = defect_scene(0.6, 8.0)
    assert not any(s.obstacles and s.obstacles[0] == fixed.obstacles[0] for s in scenes)
    # Each defect lies where the crawler passes, and the sensor clears every deposit.
    for s in scenes:
        parts = (*s.deformations, *s.deposits, *s.obstacles, *s.bands)
        assert 2 <= len(parts) <= 4
        assert all(0.8 <= p.start_m <= s.travel_m - 0.3 for p in parts)
