"""Tests of the scan simulator and its archive writer, against analytic ground truth."""

from __future__ import annotations

import math
import tomllib
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import shapely
from scipy.spatial.transform import Rotation

from pipescan.core.errors import ArchiveError
from pipescan.simulator.archive import (
    read_ground_truth,
    read_simulated_scene,
    write_simulated_archive,
)
from pipescan.simulator.scan import (
    SCENARIO_NAMES,
    SURFACE_END_WALL,
    SURFACE_WALL,
    BoxObstacle,
    DepositFill,
    Effects,
    Scenario,
    cast_rays,
    ellipse_axes_m,
    free_area_m2,
    get_scenario,
    ray_directions_sensor,
    simulate_scan,
    surface_normals,
    surface_residual_m,
)

FAST = {"points_per_s": 100_000}


@pytest.fixture(scope="module")
def paper_scan():
    return simulate_scan(get_scenario("paper", **FAST), seed=7)


@pytest.fixture(scope="module")
def paper_sections(paper_scan):
    return paper_scan.true_sections(0.1)


def _to_pipe(scan, i, points_sensor):
    T = scan.T_pipe_sensor(i)
    return points_sensor.astype(np.float64) @ T[:3, :3].T + T[:3, 3]


def _section_at(sections, chainage_m):
    return next(s for s in sections if s.chainage_start_m <= chainage_m < s.chainage_end_m)


# ------------------------------------------------------------------ scenarios and pattern


def test_named_scenarios_and_overrides():
    for name in SCENARIO_NAMES:
        assert get_scenario(name).name == name
    s = get_scenario("paper", travel_m=1.0, points_per_s=100_000)
    assert (s.travel_m, s.rays_per_frame) == (1.0, 10_000)
    assert get_scenario("paper").nominal_area_m2 == pytest.approx(0.1963, abs=1e-4)
    with pytest.raises(ValueError, match="Unknown scenario"):
        get_scenario("nope")
    with pytest.raises(ValueError, match="travel_mm"):
        get_scenario("paper", travel_mm=1.0)


def test_scenario_refuses_a_sensor_path_through_a_deposit():
    with pytest.raises(ValueError, match="pass through deposit"):
        Scenario(travel_m=2.0, deposits=(DepositFill(1.0, 1.5, 0.1, 0.45),))
    with pytest.raises(ValueError, match="pass through obstacle"):
        Scenario(travel_m=2.0, obstacles=(BoxObstacle(1.0, 1.2, -0.1, 0.1, -0.1, 0.3),))


def test_pattern_spans_the_field_of_view_denser_at_the_centre():
    s = get_scenario("clean")
    d = np.concatenate([ray_directions_sensor(s, i) for i in range(3)])
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    el = np.degrees(np.arcsin(d[:, 2]))
    assert 59.5 < az.max() <= 60.0 and -60.0 <= az.min() < -59.5
    assert 12.3 < el.max() <= 12.5 and -12.5 <= el.min() < -12.3
    # Spacing 0.2° at the centre and 0.3° at the edges: 1.5x the density per degree.
    centre = np.mean(np.abs(az) < 3.0) / 6.0
    edge = np.mean(np.abs(az) > 57.0) / 6.0
    assert centre / edge == pytest.approx(1.5, rel=0.05)


def test_pattern_does_not_repeat_across_frames():
    s = get_scenario("clean", **FAST)
    d0, d1, d50 = (ray_directions_sensor(s, i) for i in (0, 1, 50))
    for other in (d1, d50):
        # Not one ray of frame 0 comes back: the nearest direction is always elsewhere.
        assert not np.any(np.all(np.isclose(d0[:2000, None], other[None, :2000]), axis=2))

    # Two frames together fill the field of view more evenly than one: the largest empty
    # 0.5° cell count drops.
    def empty_cells(d):
        az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
        el = np.degrees(np.arcsin(d[:, 2]))
        h, _, _ = np.histogram2d(az, el, bins=(240, 50), range=((-60, 60), (-12.5, 12.5)))
        return int((h == 0).sum())

    assert empty_cells(np.concatenate([d0, d1])) < empty_cells(d0)


# ------------------------------------------------------------------ frames


def test_same_seed_same_points_different_seed_different():
    s = get_scenario("clean", travel_m=0.6, **FAST)
    a, b, c = simulate_scan(s, 3), simulate_scan(s, 3), simulate_scan(s, 4)
    fa, fb, fc = a.frame(2), b.frame(2), c.frame(2)
    assert fa.points_sensor.dtype == np.float32 and fa.points_sensor.shape[1] == 3
    np.testing.assert_array_equal(fa.points_sensor, fb.points_sensor)
    np.testing.assert_array_equal(a.T_world_sensor, b.T_world_sensor)
    assert fa.points_sensor.shape != fc.points_sensor.shape or not np.array_equal(
        fa.points_sensor, fc.points_sensor
    )
    m = min(len(a), len(c))
    assert not np.allclose(a.odometer_m[1:m], c.odometer_m[1:m])
    # A frame does not depend on which frames were generated before it.
    np.testing.assert_array_equal(simulate_scan(s, 3).frame(2).points_sensor, fa.points_sensor)


def test_no_point_inside_the_blind_zone(paper_scan):
    for i in (0, 40, 120, 200):
        rng = np.linalg.norm(paper_scan.frame(i).points_sensor, axis=1)
        assert rng.size > 1000
        assert rng.min() >= paper_scan.scenario.blind_zone_m


def test_noise_free_points_lie_on_the_analytic_surfaces(paper_scan):
    s = paper_scan.scenario
    r = s.radius_m
    for i in (10, 110, 170, 230, len(paper_scan) - 1):
        p = _to_pipe(paper_scan, i, paper_scan.frame(i, noise_free=True).points_sensor)
        assert surface_residual_m(s, p).max() < 2e-6
        x, y, z = p.T
        # Independent of surface_residual_m: clean stretches lie on the circle r, points in
        # the deformation's plateau on its ellipse, and the rest on the end wall.
        clean = (x > 4.35) & (x < s.end_wall_m - 1e-3) | (x > 0.5) & (x < 1.5)
        assert np.abs(np.hypot(y, z) - r)[clean].max() < 2e-6
        plateau = (x > 1.71) & (x < 1.99)
        a, b = r * 1.03, r * 0.93
        ell = np.sqrt((y / a) ** 2 + (z / b) ** 2)[plateau]
        assert ell.size == 0 or np.abs(ell - 1.0).max() < 1e-5
        far = x >= s.end_wall_m - 1e-3
        assert np.abs(x[far] - s.end_wall_m).max(initial=0.0) < 2e-6


def _range_errors(scan, frames, **frame_kwargs):
    """Reported minus exact range of every return of some frames, with the noise model's σ."""
    s = scan.scenario
    errors, sigmas, exacts = [], [], []
    for i in frames:
        pts = scan.frame(i, **frame_kwargs).points_sensor.astype(np.float64)
        rng = np.linalg.norm(pts, axis=1)
        T = scan.T_pipe_sensor(i)
        d = (pts / rng[:, None]) @ T[:3, :3].T
        exact, surface = cast_rays(s, T[:3, 3], d)
        cos_incidence = np.abs(
            np.einsum("ij,ij->i", surface_normals(s, T[:3, 3] + d * exact[:, None], surface), d)
        )
        errors.append(rng - exact)
        sigmas.append(s.effects.range_sigma_m(exact, cos_incidence))
        exacts.append(exact)
    return np.concatenate(errors), np.concatenate(sigmas), np.concatenate(exacts)


def test_range_noise_grows_with_range_and_incidence_and_spurious_returns_come_early():
    # Mixed pixels (at the corner of wall and end wall) are tested on their own below.
    s = get_scenario("clean", travel_m=1.0, mixed_pixel_ratio=0.0)
    err, sigma, exact = _range_errors(simulate_scan(s, seed=11), (0, 3, 6, 9))
    spurious = err < -6 * sigma
    # Early returns land anywhere between the blind zone and the surface: those within 6σ of
    # the surface pass for noise.
    beyond = np.clip(1.0 - 6 * sigma / (exact - s.blind_zone_m), 0.0, 1.0)
    expected = s.effects.spurious_return_ratio * beyond.mean()
    assert spurious.mean() == pytest.approx(expected, rel=0.15)
    z = err[~spurious] / sigma[~spurious]
    assert np.std(z) == pytest.approx(1.0, rel=0.03) and abs(np.mean(z)) < 0.02
    # The model's σ spans what a sewer gives: a few mm close and facing, ~1 cm grazing at range.
    assert sigma.min() < 0.005 and np.percentile(sigma, 99) > 0.008
    # No return lands behind the surface by more than the noise.
    assert (err < 6 * sigma).all()


def test_ideal_effects_give_exact_ranges_and_each_effect_draws_on_its_own():
    ideal = simulate_scan(get_scenario("paper", travel_m=1.0, effects=Effects.ideal()), seed=2)
    np.testing.assert_array_equal(
        ideal.frame(5).points_sensor, ideal.frame(5, noise_free=True).points_sensor
    )
    assert ideal.odometer_m[-1] == ideal.true_travel_m[-1]
    # Spurious returns switched on leave every other return where it was.
    some = simulate_scan(
        get_scenario("paper", travel_m=1.0, effects=Effects.ideal(spurious_return_ratio=0.01)),
        seed=2,
    )
    a, b = ideal.frame(5).points_sensor, some.frame(5).points_sensor
    assert a.shape == b.shape
    moved = np.any(a != b, axis=1)
    assert 0.005 < moved.mean() < 0.015
    np.testing.assert_array_equal(ideal.T_world_sensor, some.T_world_sensor)


def test_mixed_pixels_sit_between_the_surfaces_of_a_depth_edge():
    # Frames looking at the obstacle hanging from the crown (2.6-2.9 m): its lower edge is a
    # depth edge against the wall behind it.
    base = dict(travel_m=2.4, deformations=(), deposits=())
    frames = (0, 40, 80, 120)
    for ratio in (0.0, 1.0):
        effects = Effects.ideal(mixed_pixel_ratio=ratio, beam_footprint_deg=0.15)
        scan = simulate_scan(get_scenario("paper", effects=effects, **base), seed=1)
        off = []
        for i in frames:
            p = _to_pipe(scan, i, scan.frame(i).points_sensor)
            off.append(surface_residual_m(scan.scenario, p))
        off = np.concatenate(off)
        mixed = off > 0.01
        if ratio == 0.0:
            assert not mixed.any()
        else:
            assert 20 < mixed.sum() < 0.01 * off.size


def test_deformed_wall_hits_match_a_brute_force_search():
    s = get_scenario("paper")
    scan = simulate_scan(s, seed=0)
    rng = np.random.default_rng(0)
    for i in (5, 100, 125):  # looking into, standing in, leaving the deformation
        T = scan.T_pipe_sensor(i)
        d = ray_directions_sensor(s, i)[rng.choice(s.rays_per_frame, 60, replace=False)]
        d = d @ T[:3, :3].T
        t, surface = cast_rays(s, T[:3, 3], d)
        for j in np.flatnonzero(surface == SURFACE_WALL):
            ts = np.linspace(0.0, t[j] + 0.5, 20001)
            p = T[:3, 3] + ts[:, None] * d[j]
            a, b = ellipse_axes_m(s, p[:, 0])
            outside = (p[:, 1] / a) ** 2 + (p[:, 2] / b) ** 2 >= 1.0
            first = ts[np.argmax(outside)]
            assert first - (ts[1] - ts[0]) <= t[j] <= first + 1e-12


def test_memory_stays_bounded_over_many_frames():
    scan = simulate_scan(get_scenario("clean", travel_m=3.0, **FAST), seed=0)
    tracemalloc.start()
    try:
        scan.frame(0)
        _, one = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        n_points = sum(f.points_sensor.shape[0] for f in scan.frames())
        _, many = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(scan) > 190
    assert many < 2 * one  # the peak of one frame, whatever the number of frames
    assert many < n_points * 12 / 5  # far below holding every frame's points


# ------------------------------------------------------------------ motion and odometer


def test_odometer_scale_error_and_frame_zero():
    s = get_scenario(
        "paper", travel_m=3.0, effects=Effects(odometer_scale_error_ratio=0.035, slip_per_m=0)
    )
    scan = simulate_scan(s, seed=2)
    assert scan.odometer_m[0] == 0.0 and scan.true_travel_m[0] == 0.0
    assert scan.T_pipe_sensor(0)[0, 3] == 0.0
    np.testing.assert_allclose(np.diff(scan.times_s), 0.1)
    slope = np.polyfit(scan.true_travel_m, scan.odometer_m, 1)[0]
    assert slope == pytest.approx(1.035, abs=5e-4)
    residual = scan.odometer_m - 1.035 * scan.true_travel_m
    assert np.std(residual) == pytest.approx(s.effects.odometer_noise_m, rel=0.3)
    assert 3.0 - 0.03 < scan.true_travel_m[-1] <= 3.0
    # The speed varies around 0.15 m/s rather than staying constant.
    speed = np.diff(scan.true_travel_m) / 0.1
    assert (
        speed.min() < 0.145 and speed.max() > 0.155 and speed.mean() == pytest.approx(0.15, rel=0.1)
    )


def test_poses_follow_a_pipe_not_aligned_with_world_axes(paper_scan):
    Twp = paper_scan.T_world_pipe
    axis = Twp[:3, 0]
    assert np.abs(axis).max() < 0.9
    assert axis[2] == pytest.approx(-0.01, abs=1e-4)  # 1 % downhill
    pos = paper_scan.T_world_sensor[:, :3, 3]
    along = (pos - pos[0]) @ axis
    np.testing.assert_allclose(along, paper_scan.true_travel_m, atol=1e-12)
    for T in paper_scan.T_world_sensor[::25]:
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
    # Rocking about 1°, plus a vibration that changes every frame.
    fwd = paper_scan.T_world_sensor[:, :3, 0]
    tilt = np.degrees(np.arccos(np.clip(fwd @ axis, -1, 1)))
    assert 0.5 < tilt.max() < 3.0 + 2.0
    step = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1, 1)))
    # The forward axis turns by pitch and yaw: each changes by √2 σ between frames.
    vibration = paper_scan.scenario.effects.vibration_deg
    assert np.sqrt(np.mean(step**2)) == pytest.approx(2.0 * vibration, rel=0.15)


def test_vibration_and_mount_jitter_are_new_every_frame():
    e = Effects.ideal(vibration_deg=1.0, mount_jitter_m=0.01)
    scan = simulate_scan(get_scenario("clean", travel_m=3.0, effects=e, **FAST), seed=3)
    roll = np.array(
        [
            Rotation.from_matrix(scan.T_pipe_sensor(i)[:3, :3]).as_euler("xyz")[0]
            for i in range(len(scan))
        ]
    )
    assert np.degrees(np.std(roll)) == pytest.approx(1.0, rel=0.15)
    assert abs(np.corrcoef(roll[1:], roll[:-1])[0, 1]) < 0.2  # not smooth
    lateral = np.array([scan.T_pipe_sensor(i)[1:3, 3] for i in range(len(scan))])
    s = scan.scenario
    np.testing.assert_allclose(
        lateral.mean(axis=0), [s.mount_offset_y_m, s.mount_offset_z_m], atol=0.003
    )
    np.testing.assert_allclose(lateral.std(axis=0), 0.01, rtol=0.15)


def test_slip_stuck_counts_on_while_the_crawler_stands_sliding_the_reverse():
    e = Effects.ideal(slip_per_m=2.0, slip_duration_s=(1.0, 1.0))
    scan = simulate_scan(get_scenario("clean", travel_m=3.0, effects=e, **FAST), seed=5)
    assert len(scan.slip_frames) > 20
    moved = np.diff(scan.true_travel_m) > 0
    counted = np.diff(scan.odometer_m) > 0
    assert (moved & ~counted).sum() > 5  # sliding
    assert (~moved & counted).sum() > 5  # stuck
    assert np.all(moved | counted)  # one or the other always advances
    assert not np.allclose(scan.odometer_m, scan.true_travel_m)
    # Without slip the count is the distance.
    plain = simulate_scan(get_scenario("clean", travel_m=3.0, effects=Effects.ideal(), **FAST), 5)
    np.testing.assert_allclose(plain.odometer_m, plain.true_travel_m)


def test_imu_noise_and_dropouts():
    e = Effects.ideal(imu_noise_deg=0.3, imu_dropout_ratio=0.2)
    scan = simulate_scan(get_scenario("clean", travel_m=3.0, effects=e, **FAST), seed=6)
    missing = [i for i in range(len(scan)) if scan.gravity(i) is None]
    assert 0.12 < len(missing) / len(scan) < 0.28
    assert scan.meta.frames[missing[0]].gravity is None
    kept = [i for i in range(len(scan)) if scan.gravity(i) is not None]
    true_down = -scan.T_world_sensor[kept, 2, :3]
    angle = np.degrees(np.arccos(np.clip(np.sum(scan.gravity_sensor[kept] * true_down, 1), -1, 1)))
    # The angle between two directions off by N(0, σ) per axis: RMS √2 σ.
    assert np.sqrt(np.mean(angle**2)) == pytest.approx(0.3 * np.sqrt(2), rel=0.15)
    assert simulate_scan(get_scenario("clean", travel_m=0.5, imu=False), 0).gravity(0) is None


# ------------------------------------------------------------------ ground truth


def test_free_area_matches_closed_forms_and_shapely():
    s = get_scenario("paper")
    r = s.radius_m
    nominal = math.pi * r * r
    assert free_area_m2(s, 1.0) == pytest.approx(nominal, rel=1e-12)
    assert free_area_m2(s, 1.85) == pytest.approx(math.pi * r * 1.03 * r * 0.93, rel=1e-12)
    k = 0.2851 * 2 * r  # deposit plateau height
    segment = r * r * math.acos((r - k) / r) - (r - k) * math.sqrt(2 * r * k - k * k)
    assert free_area_m2(s, 3.8) == pytest.approx(nominal - segment, rel=1e-9)
    circle = shapely.Point(0, 0).buffer(r, quad_segs=4096)
    box = shapely.box(-0.14, 0.1184, 0.14, 0.35)
    assert free_area_m2(s, 2.75) == pytest.approx(circle.difference(box).area, rel=2e-6)


def test_paper_blockage_spans_table_1(paper_sections):
    blockage = np.array([s.blockage_ratio for s in paper_sections])
    defective = blockage[blockage > 1e-6]
    assert defective.min() <= 0.025 and defective.max() >= 0.23
    assert np.any((blockage > 0.02) & (blockage < 0.03))
    assert _section_at(paper_sections, 1.85).blockage_ratio == pytest.approx(0.0421, abs=1e-4)
    assert _section_at(paper_sections, 1.85).deformation_ratio == pytest.approx(0.07, abs=1e-9)
    assert _section_at(paper_sections, 2.75).blockage_ratio == pytest.approx(0.168, abs=5e-4)
    assert _section_at(paper_sections, 3.85).blockage_ratio == pytest.approx(0.235, abs=5e-4)
    assert _section_at(paper_sections, 3.85).deposit_height_ratio == pytest.approx(0.2851)
    chainages = [s.chainage_start_m for s in paper_sections]
    np.testing.assert_allclose(np.diff(chainages), 0.1, atol=1e-9)
    assert chainages[0] == 0.0 and paper_sections[-1].chainage_end_m == pytest.approx(6.5)


def test_no_defect_in_the_first_metres(paper_sections):
    first = [s for s in paper_sections if s.chainage_end_m <= 1.3]
    assert len(first) == 13
    for s in first:
        assert abs(s.blockage_ratio) < 1e-9


def test_shadow_behind_the_obstacle(paper_sections):
    behind = _section_at(paper_sections, 2.95)
    assert behind.in_shadow and behind.coverage_ratio < 0.9
    assert abs(behind.blockage_ratio) < 1e-9
    # Behind the deposit's far ramp the invert is hidden too.
    assert _section_at(paper_sections, 4.35).in_shadow


def test_clean_pipe_sections(paper_sections):
    clean = simulate_scan(get_scenario("clean", **FAST), seed=1).true_sections()
    for s in clean:
        assert abs(s.blockage_ratio) < 1e-9 and s.deposit_height_ratio == 0.0
        assert not s.in_shadow
        if s.chainage_start_m >= 1.3:
            assert s.coverage_ratio > 0.98
    # The start of a forward-looking scan is not seen (blind zone, field of view).
    assert clean[0].coverage_ratio == 0.0 and clean[8].coverage_ratio < 0.7
    for chainage_m in (1.25, 2.45, 5.55):
        s = _section_at(paper_sections, chainage_m)
        assert abs(s.blockage_ratio) < 1e-9 and not s.in_shadow and s.coverage_ratio > 0.98


def test_true_sections_step_must_fit_the_grid(paper_scan):
    with pytest.raises(ValueError, match=r"multiple of 0\.01"):
        paper_scan.true_sections(0.015)
    assert len(paper_scan.true_sections(0.5)) == 13


# ------------------------------------------------------------------ archive


def test_archive_round_trip(tmp_path: Path):
    scan = simulate_scan(get_scenario("clean", travel_m=0.5, **FAST), seed=5)
    calls: list[tuple[int, int]] = []
    out = write_simulated_archive(
        scan, tmp_path / "arch", progress=lambda d, t: calls.append((d, t))
    )
    assert calls[-1] == (len(scan), len(scan)) and len(calls) == len(scan)
    with (out / "inspection.toml").open("rb") as fh:
        doc = tomllib.load(fh)
    assert doc["asset_id"] == "SIM-CLEAN" and doc["nominal_diameter_m"] == 0.5
    assert doc["inspected_at"].isoformat() == "2024-05-14T09:30:00+00:00"
    assert {"upstream_node", "downstream_node", "direction", "chainage_offset_m"} <= set(doc)
    files = sorted(p.relative_to(out).as_posix() for p in (out / "frames").iterdir())
    assert [f["file"] for f in doc["frames"]] == files
    assert len(files) == len(scan)
    np.testing.assert_allclose([f["odometer_m"] for f in doc["frames"]], scan.odometer_m)
    np.testing.assert_allclose([f["time_s"] for f in doc["frames"]], scan.times_s)
    for i in (0, len(scan) - 1):
        pts = np.load(out / files[i])
        assert pts.dtype == np.float32 and pts.ndim == 2 and pts.shape[1] == 3
        np.testing.assert_array_equal(pts, scan.frame(i).points_sensor)
    poses, sections = read_ground_truth(out)
    np.testing.assert_array_equal(poses, scan.T_world_sensor)
    assert sections == scan.true_sections(0.1)
    scenario, seed, T_world_pipe = read_simulated_scene(out)
    assert scenario == scan.scenario and seed == 5
    np.testing.assert_array_equal(T_world_pipe, scan.T_world_pipe)
    # Nothing but the archive is left beside it.
    assert [p.name for p in tmp_path.iterdir()] == ["arch"]


def test_archive_overwrite_rules(tmp_path: Path):
    scan = simulate_scan(get_scenario("clean", travel_m=0.2, **FAST), seed=0)
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(ArchiveError, match="refusing to overwrite"):
        write_simulated_archive(scan, precious)
    assert (precious / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious"]
    out = tmp_path / "sim"
    out.mkdir()  # empty: fine
    write_simulated_archive(scan, out)
    other = simulate_scan(get_scenario("clean", travel_m=0.3, **FAST), seed=1)
    write_simulated_archive(other, out)  # a previous simulated archive: replaced
    assert len(list((out / "frames").iterdir())) == len(other)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious", "sim"]


def test_archive_write_failure_leaves_nothing(tmp_path: Path):
    scan = simulate_scan(get_scenario("clean", travel_m=0.3, **FAST), seed=0)

    def boom(done: int, total: int) -> None:
        if done == 2:
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        write_simulated_archive(scan, tmp_path / "arch", progress=boom)
    assert list(tmp_path.iterdir()) == []


def test_read_ground_truth_of_a_plain_directory(tmp_path: Path):
    with pytest.raises(ArchiveError, match=r"ground_truth/poses\.csv"):
        read_ground_truth(tmp_path)


@pytest.mark.slow
def test_the_ray_caster_hits_only_the_pipes_surfaces():
    """Every third frame of the paper scan: every ray ends on one of the scene's four
    surfaces, and the last frames see the end wall. Its speed is measured by
    ``benchmarks/bench_scans.py rays``, not here."""
    s = get_scenario("paper")
    scan = simulate_scan(s, seed=0)
    for i in range(0, len(scan), 3):
        T = scan.T_pipe_sensor(i)
        d = ray_directions_sensor(s, i) @ T[:3, :3].T
        _, surface = cast_rays(s, T[:3, 3], d, min_range_m=s.blind_zone_m)
        assert np.all(np.isin(surface, [1, 2, 3, 4]))
    assert SURFACE_END_WALL in surface
