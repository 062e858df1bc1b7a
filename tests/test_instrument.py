"""The instrument: a [sensor] profile, or what the scan itself shows, and the thresholds that
follow from it (docs/instrument.md)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipescan.core.coding import code_sections
from pipescan.core.errors import MetadataError
from pipescan.core.grading import load_table, merge_defects
from pipescan.core.instrument import (
    SENSOR_MODELS,
    SMEAR_SPREAD_RATIO,
    Instrument,
    SensorProfile,
    estimate_instrument,
    frame_diameter_m,
    instrumented,
    nearest_range_m,
    partial_view_stride,
    smear_limit_m,
    surface_noise,
    view_coverage,
    wall_noise_m,
)
from pipescan.core.measures import MeasureParams, measure_section
from pipescan.core.model import SectionMeasures, SectionStatus
from pipescan.core.registration import RegistrationParams
from pipescan.core.registration.metrics import trajectory_errors
from pipescan.core.summary import diameter_mismatch, measured_inner_diameter
from pipescan.simulator.scan import Effects, simulate_scan
from pipescan.simulator.sweep import defect_scene, register_scan, scan_instrument
from pipescan.storage.input.metadata import parse_inspection_toml

_TOML = 'asset_id = "A-B"\ninspected_at = 2024-05-17T10:00:00Z\nnominal_diameter_m = 0.6\n'


def _scene(travel_m: float = 1.5, coverage: float = 1.0, **effects):
    base = dict(range_noise_sigma_m=0.005, range_noise_growth_per_m=0.0, imu=False)
    scene = defect_scene(0.6, travel_m, effects=Effects(**(base | effects)))
    return dataclasses.replace(scene, frame_coverage_ratio=coverage)


# --------------------------------------------------------------------------- the profile


def test_sensor_table_names_a_model_and_overrides_its_figures():
    meta = parse_inspection_toml(_TOML + '[sensor]\nmodel = "Livox-HAP"\n', archive="a")
    assert meta.sensor == SENSOR_MODELS["livox-hap"]
    assert meta.sensor.min_range_m == 0.5
    own = parse_inspection_toml(
        _TOML + '[sensor]\nmodel = "livox-hap"\nmin_range_m = 0.3\n', archive="a"
    ).sensor
    assert own.min_range_m == 0.3 and own.fov_horizontal_deg == 120.0
    assert "[sensor]" in own.source
    custom = parse_inspection_toml(
        _TOML + '[sensor]\npattern = "non_repetitive"\nrange_noise_m = 0.02\n', archive="a"
    ).sensor
    assert custom.model == "custom" and custom.pattern == "non_repetitive"
    assert parse_inspection_toml(_TOML, archive="a").sensor is None


@pytest.mark.parametrize(
    ("table", "field", "words"),
    [
        ('model = "livox-happ"', "sensor.model", "did you mean 'livox-hap'"),
        ('pattern = "rosette"', "sensor.pattern", "non_repetitive"),
        ("min_range_m = 5\nmax_range_m = 1", "sensor", "below max_range_m"),
        ("noise = 0.01", "sensor.noise", "Extra inputs"),
        ("min_range_m = -1", "sensor.min_range_m", "greater than or equal"),
    ],
)
def test_a_bad_sensor_table_names_its_field(table, field, words):
    with pytest.raises(MetadataError) as info:
        parse_inspection_toml(_TOML + "[sensor]\n" + table + "\n", archive="a.zip")
    assert info.value.field == field
    assert words in str(info.value)


def test_registry_figures_are_consistent():
    for name, profile in SENSOR_MODELS.items():
        assert profile.model == name
        assert profile.min_range_m is not None and profile.range_noise_m is not None
        assert profile.source


# --------------------------------------------------------------------------- estimates


def test_nearest_range_ignores_returns_inside_the_blind_zone():
    scan = simulate_scan(
        _scene(spurious_return_ratio=0.02, spurious_range_ratio=(0.05, 1.0)), seed=3
    )
    frames = [scan.frame(i).points_sensor for i in (5, 40, 80)]
    assert min(np.linalg.norm(f, axis=1).min() for f in frames) < 0.2  # dust is there
    assert nearest_range_m(frames, max_range_m=5.0) == pytest.approx(0.5, abs=0.02)


def test_dense_dust_cut_off_from_the_wall_is_not_the_nearest_surface():
    # rosette-avia 1 (0.3 m pipe, the Avia's 1.0 m blind zone): rays whose wall lies inside
    # the blind zone come back as dust short of it, 60 returns a centimetre at 0.05-0.3 m,
    # then almost nothing, then the wall from 1.0 m. The first dense run was the dust (0.02 m).
    rng = np.random.default_rng(7)
    wall = rng.uniform(1.0, 4.5, 40_000)
    dust = np.concatenate((rng.uniform(0.05, 0.3, 1_500), rng.uniform(0.3, 0.95, 60)))
    r = np.concatenate((wall, dust))
    direction = rng.normal(size=(len(r), 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    nearest = nearest_range_m([r[:, None] * direction], max_range_m=5.0)
    assert nearest == pytest.approx(1.0, abs=0.02)


def test_wall_noise_follows_the_sensor_noise():
    quiet, noisy = (
        scan_instrument(simulate_scan(_scene(range_noise_sigma_m=s), seed=1)).wall_noise_m
        for s in (0.002, 0.012)
    )
    assert quiet is not None and noisy is not None
    assert 2.0 < noisy / quiet < 6.0  # six times the range noise; grazing incidence damps it
    rng = np.random.default_rng(0)
    a, x = rng.uniform(0, 2 * np.pi, 30_000), rng.uniform(0.5, 4, 30_000)
    r = 0.3 + rng.normal(0, 0.01, 30_000)
    tube = np.column_stack((x, r * np.cos(a), r * np.sin(a)))
    assert wall_noise_m([tube], max_range_m=5.0) == pytest.approx(0.01, rel=0.15)


def test_a_rosette_frame_covers_part_of_the_view():
    full = scan_instrument(simulate_scan(_scene(), seed=1))
    rosette = scan_instrument(simulate_scan(_scene(coverage=0.3), seed=1))
    assert full.frame_view_share > 0.9 and full.map_seed_frames == 1
    assert 0.2 < rosette.frame_view_share < 0.5
    assert rosette.map_seed_frames > 2
    assert partial_view_stride(full) is None
    assert partial_view_stride(rosette).stride == 1


def test_view_coverage_of_frames_that_each_see_everything_is_whole():
    frame = np.column_stack((np.ones(1000), np.linspace(-1, 1, 1000), np.zeros(1000)))
    assert view_coverage([frame, frame, frame]) == (1.0, 1)


def test_a_profile_states_what_the_scan_need_not_estimate():
    frames = [np.column_stack((np.linspace(0.5, 4, 2000), np.full(2000, 0.3), np.zeros(2000)))]
    stated = estimate_instrument(
        frames, frames, max_range_m=5.0, profile=SENSOR_MODELS["livox-hap"]
    )
    assert stated.min_range_m == 0.5 and stated.sources["min_range_m"] == "profile"
    assert stated.sources["frame_view_share"] == "profile"
    assert stated.model == "livox-hap"


def test_instrumented_parameters():
    reg, measure = instrumented(
        RegistrationParams(),
        MeasureParams(),
        Instrument(min_range_m=0.5, wall_noise_m=0.02, map_seed_frames=7),
    )
    assert reg.min_range_m == 0.5 and reg.map_seed_frames == 7
    assert measure.max_wall_spread_m == pytest.approx(SMEAR_SPREAD_RATIO * 0.02, rel=0.01)
    _, cloud = instrumented(RegistrationParams(), MeasureParams(), None)
    assert cloud.max_wall_spread_m is None  # a registered cloud: no frames to disagree


def test_sensor_profile_refuses_nonsense():
    with pytest.raises(ValueError, match="pattern"):
        SensorProfile(pattern="spiral")
    with pytest.raises(ValueError, match="min_range_m"):
        SensorProfile(min_range_m=float("nan"))


# --------------------------------------------------------------------------- registration


def test_returns_inside_the_blind_zone_do_not_make_frames_slide():
    scan = simulate_scan(
        _scene(2.0, spurious_return_ratio=0.02, spurious_range_ratio=(0.2, 1.0)), seed=4
    )
    params, _ = instrumented(RegistrationParams(), MeasureParams(), scan_instrument(scan))
    assert params.min_range_m == pytest.approx(0.5, abs=0.02)
    trajectory = register_scan(scan, params=params, frame_stride=1)
    slid = sum(q.fault == "slide" for q in trajectory.quality)
    assert slid <= 0.02 * len(trajectory.quality)


def test_a_seeded_map_holds_a_rosette_better_across_the_axis():
    scan = simulate_scan(_scene(1.5, coverage=0.3, vibration_deg=0.0), seed=2)
    errors = {}
    for seed in (1, scan_instrument(scan).map_seed_frames):
        trajectory = register_scan(
            scan, params=RegistrationParams(map_seed_frames=seed), frame_stride=1
        )
        truth = scan.T_world_sensor[list(trajectory.frame_indices)]
        errors[seed] = trajectory_errors(trajectory.T_world_frame, truth).across_rms_m
    one, seeded = errors.values()
    # Seeding takes a third or more off (25-35 mm -> 9-23 mm over three draws); a rosette's
    # frames are still held worse than full ones (1-2 mm): docs/instrument.md, open work.
    assert seeded < 0.75 * one


def test_a_partial_view_gate_holds_a_rosette_across_the_axis():
    scan = simulate_scan(_scene(1.5, coverage=0.3, vibration_deg=0.0), seed=2)
    params, _ = instrumented(RegistrationParams(), MeasureParams(), scan_instrument(scan))
    assert params.max_correspondence_m < RegistrationParams().max_correspondence_m
    errors = []
    for gate in (RegistrationParams().max_correspondence_m, params.max_correspondence_m):
        p = dataclasses.replace(params, max_correspondence_m=gate)
        trajectory = register_scan(scan, params=p, frame_stride=1)
        truth = scan.T_world_sensor[list(trajectory.frame_indices)]
        errors.append(trajectory_errors(trajectory.T_world_frame, truth).across_rms_m)
    wide, gated = errors
    # 23.8 mm with the 8 cm gate, 3-5 mm with the partial view's (docs/instrument.md).
    assert gated < 0.5 * wide


def test_a_frame_the_tight_gate_cannot_hold_is_registered_with_the_wide_one():
    # rosette-avia 17 (0.3 m pipe, no IMU) stopped at a chunk's third frame: "ICP found only
    # 0 correspondences" within its 3 cm gate, against a map of two partial frames.
    from pipescan.core.errors import RegistrationError
    from pipescan.core.registration import register_frames

    scan = simulate_scan(_scene(0.3, coverage=0.3), seed=1)
    frames = [(f.index, f.points_sensor, None) for f in scan.frames()][:6]
    tight = RegistrationParams(max_correspondence_m=0.002, map_seed_frames=3)
    with pytest.raises(RegistrationError, match="correspondences"):
        register_frames(frames, tight)
    both = dataclasses.replace(tight, wide_correspondence_m=0.08)
    trajectory = register_frames(frames, both)
    truth = scan.T_world_sensor[list(trajectory.frame_indices)]
    assert trajectory_errors(trajectory.T_world_frame, truth).across_rms_m < 0.02
    # The instrument sets it for a partial view only.
    partial = Instrument(map_seed_frames=7, range_noise_m=0.005)
    assert instrumented(RegistrationParams(), MeasureParams(), partial)[
        0
    ].wide_correspondence_m == pytest.approx(0.08)
    full = Instrument(map_seed_frames=1, range_noise_m=0.005)
    assert (
        instrumented(RegistrationParams(), MeasureParams(), full)[0].wide_correspondence_m is None
    )


def test_a_full_view_keeps_the_wide_gate():
    full = Instrument(map_seed_frames=1, range_noise_m=0.005)
    params, _ = instrumented(RegistrationParams(), MeasureParams(), full)
    assert params.max_correspondence_m == RegistrationParams().max_correspondence_m
    partial = dataclasses.replace(full, map_seed_frames=7)
    params, _ = instrumented(RegistrationParams(), MeasureParams(), partial)
    assert params.max_correspondence_m == pytest.approx(np.sqrt(3) / 2 * 0.03 + 0.005)


def test_the_small_sample_mad_factor_is_the_normal_distributions_and_errs_safe():
    # uncertainty.residual_sigma_m's (1 - 1.2 / n): no scanner in it, only normal samples.
    rng = np.random.default_rng(7)
    for n in (4, 6, 8, 12, 16):
        x = rng.standard_normal((40_000, n))
        mad = np.median(np.abs(x - np.median(x, axis=1, keepdims=True)), axis=1).mean()
        ratio = mad * 1.4826
        assert 1.0 - 1.2 / n <= ratio <= 1.06 * (1.0 - 1.2 / n), n


# --------------------------------------------------------------------------- the diameter


def _ring_sections(radius_m: float, count: int = 6, coverage: float = 1.0):
    t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    ring = radius_m * np.column_stack((np.cos(t), np.sin(t)))
    return [
        SectionMeasures(i / 10, i / 10 + 0.1, 0.5, SectionStatus.OK, 1000, coverage, contour_m=ring)
        for i in range(count)
    ]


def test_the_wall_contradicts_a_wrong_nominal_diameter():
    inner = measured_inner_diameter(_ring_sections(0.4))
    assert inner is not None and inner.diameter_m == pytest.approx(0.8)
    assert diameter_mismatch(inner, 0.8) is None
    assert diameter_mismatch(inner, 0.84) is None  # within a few per cent
    assert "20 % below the stated 1.000 m" in diameter_mismatch(inner, 1.0)
    assert "60 % above the stated 0.500 m" in diameter_mismatch(inner, 0.5)


def test_no_diameter_from_unseen_walls():
    assert measured_inner_diameter(_ring_sections(0.4, coverage=0.5)) is None
    assert measured_inner_diameter(_ring_sections(0.4, count=2)) is None
    assert diameter_mismatch(None, 1.0) is None


def test_a_noisy_registered_shaft_is_measured_not_smeared():
    """A DN1000 shaft, 1.6 m, vertical, 2 cm noise, 3,000 points a section, as a registered
    cloud: with no frames to disagree, its scatter is noise, which the ± carries; the 8 mm
    smear limit of frames withheld nearly every section."""
    from pipescan.core.axis import fit_axis
    from pipescan.core.sections import measure_window, plan_windows

    rng = np.random.default_rng(7)
    n = 48_000
    a, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 1.6, n)
    r = 0.5 + rng.normal(0, 0.02, n)
    cloud = np.column_stack((r * np.cos(a) + 3.0, r * np.sin(a) - 2.0, z + 100.0))
    axis = fit_axis(cloud, nominal_diameter_m=1.0)
    chain = axis.chainage(cloud)
    _, as_cloud = instrumented(RegistrationParams(), MeasureParams(), None)
    measured = {}
    for name, params in (("frames' limit", MeasureParams()), ("cloud", as_cloud)):
        sections = []
        for w in plan_windows(chain.min(), chain.max(), step_m=0.1, window_m=1.0):
            inside = (chain >= w.start_m) & (chain < w.end_m)
            sections += measure_window(
                cloud[inside], axis, w, nominal_diameter_m=1.0, params=params
            )
        measured[name] = sections
    old, new = measured["frames' limit"], measured["cloud"]
    assert sum(s.status == SectionStatus.SMEARED_WALL for s in old) > len(old) / 2
    ok = [s for s in new if s.is_ok]
    assert len(ok) >= len(new) / 2
    inner = measured_inner_diameter(new)
    assert inner is not None and inner.diameter_m == pytest.approx(1.0, rel=0.015)
    for s in ok:
        assert abs(s.blockage_ratio) <= s.blockage_uncertainty_ratio + 0.005


# --------------------------------------------------------------------------- water


def _wet(start: float, depth: float, from_surface: bool = False) -> SectionMeasures:
    # A surfaceless candidate is measured low_coverage with its level (measure_section).
    return SectionMeasures(
        start,
        round(start + 0.1, 1),
        np.pi * 0.3**2,
        SectionStatus.INVERT_UNDER_WATER if from_surface else SectionStatus.LOW_COVERAGE,
        5000,
        0.8,
        water_depth_ratio=depth,
        water_from_surface=from_surface,
    )


def test_water_without_a_surface_return_needs_a_level_run():
    from pipescan.core.water import LEVEL_RUN_SECTIONS, confirm_surfaceless_water

    level = [_wet(round(0.1 * i, 1), 0.1) for i in range(LEVEL_RUN_SECTIONS)]
    kept = confirm_surfaceless_water(level)
    assert all(s.status == SectionStatus.INVERT_UNDER_WATER for s in kept)
    short = confirm_surfaceless_water(level[:-1])
    assert all(
        s.status == SectionStatus.LOW_COVERAGE and s.water_depth_ratio is None for s in short
    )
    # Not level: the wall stops 6 cm higher in every other section (a 0.6 m pipe).
    uneven = [_wet(round(0.1 * i, 1), 0.1 + 0.1 * (i % 2)) for i in range(8)]
    assert all(s.status == SectionStatus.LOW_COVERAGE for s in confirm_surfaceless_water(uneven))
    # Water read from its surface's returns stands on its own.
    alone = confirm_surfaceless_water([_wet(0.0, 0.1, from_surface=True)])
    assert alone[0].status == SectionStatus.INVERT_UNDER_WATER


def test_a_smeared_deposit_still_casts_its_shadow():
    """Water read behind a deposit whose wall the frames smeared (``smeared_wall``: its figures
    withheld) is the deposit's shadow, as behind a measured one; with nothing standing beside
    it, the same level run stays water."""
    from pipescan.core.water import LEVEL_RUN_SECTIONS, confirm_surfaceless_water
    from pipescan.core.water import explain_invert_shadows as shadows

    run = [_wet(round(0.1 * (i + 1), 1), 0.2) for i in range(LEVEL_RUN_SECTIONS)]
    deposit = SectionMeasures(
        0.0, 0.1, np.pi * 0.3**2, SectionStatus.SMEARED_WALL, 5000, 1.0, deposit_height_ratio=0.23
    )
    taken_back = shadows(confirm_surfaceless_water([deposit, *run]))
    assert [s.status for s in taken_back[1:]] == [SectionStatus.LOW_COVERAGE] * LEVEL_RUN_SECTIONS
    assert all(s.water_depth_ratio is None for s in taken_back[1:])
    dry = dataclasses.replace(deposit, deposit_height_ratio=0.0)
    water = shadows(confirm_surfaceless_water([dry, *run]))
    assert all(s.status == SectionStatus.INVERT_UNDER_WATER for s in water[1:])


def _deposit_then_water(depth: float = 0.08, top: float = 0.27) -> list[SectionMeasures]:
    # A 0.6 m pipe: a deposit's top at 3.9-4.0 m, then surfaceless water confirmed to 6.0 m.
    deposit = SectionMeasures(
        3.9, 4.0, np.pi * 0.3**2, SectionStatus.OK, 5000, 1.0, deposit_height_ratio=top
    )
    wet = [
        dataclasses.replace(
            _wet(round(4.0 + 0.1 * i, 1), depth), status=SectionStatus.INVERT_UNDER_WATER
        )
        for i in range(20)
    ]
    return [deposit, *wet]


def _sight(last_m: float, descent_deg: float = 9.5):
    from pipescan.core.water import SensorSight

    chainage = np.arange(0.0, last_m + 1e-9, 0.05)
    return SensorSight(
        chainage_m=chainage,
        height_m=np.full_like(chainage, -0.08),
        descent_ratio=float(np.tan(np.radians(descent_deg))),
        max_range_m=5.0,
    )


def test_a_shadow_reaches_only_as_far_as_the_sensor_could_not_see_past_its_top():
    """A deposit's top 0.168 m above the invert (0.174 m with the margin) ending at 4.0 m, a
    sensor 0.08 m below the axis that looked down at most 9.5° and drove on past the
    deposit: over the top, the steepest sight reaches the invert 0.174 / tan 9.5° = 1.0 m on
    (from 3.7 m). Within that the water is the shadow's; beyond it, water."""
    from pipescan.core.water import explain_invert_shadows as shadows

    wet, low = SectionStatus.INVERT_UNDER_WATER, SectionStatus.LOW_COVERAGE
    out = shadows(_deposit_then_water(), _sight(last_m=4.4))
    assert [s.status for s in out[1:12]] == [low] * 11  # 4.0-5.1 m
    assert all(s.water_depth_ratio is None for s in out[1:12])
    assert [s.status for s in out[12:]] == [wet] * 9  # 5.1-6.0 m
    assert out[12].water_depth_ratio == 0.08
    # Looking down at 14°, the sensor saw the invert 0.174 / tan 14° = 0.7 m behind the top.
    steep = shadows(_deposit_then_water(), _sight(4.4, 14.0))
    assert [s.status for s in steep[1:9]] == [low] * 7 + [wet]
    # The section after the top read as water at the top's own height may hold the rest of
    # the top (its far side, seen only from above): the shadow begins at its end.
    at_top = _deposit_then_water()
    at_top[1] = dataclasses.replace(at_top[1], water_depth_ratio=0.265)
    longer = shadows(at_top, _sight(4.4, 14.0))
    assert [s.status for s in longer[1:10]] == [low] * 8 + [wet]
    # A sensor that stopped 2 m before the deposit saw over it only at a grazing angle: the
    # whole stretch within its 5 m range is the shadow's (and beyond that range, no figure
    # came from it).
    far = shadows(_deposit_then_water(), _sight(last_m=2.0))
    assert all(s.status == low for s in far[1:] if s.chainage_end_m <= 7.0)
    # Water over the top (a depth within 1 % of it) casts no shadow.
    drowned = shadows(_deposit_then_water(depth=0.3), _sight(last_m=4.4))
    assert all(s.status == wet for s in drowned[1:])


def test_an_upstream_survey_casts_its_shadows_towards_falling_chainage():
    """The same scene surveyed the other way (chainage falling as the sensor travels): the
    deposit's top ends at 6.0 m, the shadow reaches 1.0 m on, to 5.0 m."""
    from pipescan.core.water import SensorSight
    from pipescan.core.water import explain_invert_shadows as shadows

    mirrored = [
        dataclasses.replace(
            s,
            chainage_start_m=round(10.0 - s.chainage_end_m, 1),
            chainage_end_m=round(10.0 - s.chainage_start_m, 1),
        )
        for s in _deposit_then_water()
    ]
    forward = _sight(last_m=4.4)
    sight = SensorSight(
        chainage_m=10.0 - forward.chainage_m,
        height_m=forward.height_m,
        descent_ratio=forward.descent_ratio,
        forward_sign=-1.0,
        max_range_m=5.0,
    )
    out = {round(s.chainage_start_m, 1): s.status for s in shadows(mirrored, sight)}
    assert all(out[round(x, 1)] == SectionStatus.LOW_COVERAGE for x in np.arange(4.9, 6.0, 0.1))
    assert all(
        out[round(x, 1)] == SectionStatus.INVERT_UNDER_WATER for x in np.arange(4.0, 4.85, 0.1)
    )


def test_a_shadow_falls_only_ahead_of_a_forward_looking_sensor():
    """Water before the deposit (on the side the sensor came from) is not its shadow; without
    the sensor's positions, the stretch beside the deposit is taken back on both sides."""
    from pipescan.core.water import explain_invert_shadows as shadows

    deposit = SectionMeasures(
        3.0, 3.1, np.pi * 0.3**2, SectionStatus.OK, 5000, 1.0, deposit_height_ratio=0.27
    )
    before = [
        dataclasses.replace(
            _wet(round(2.0 + 0.1 * i, 1), 0.08), status=SectionStatus.INVERT_UNDER_WATER
        )
        for i in range(10)
    ]
    seen = shadows([*before, deposit], _sight(last_m=2.5))
    assert all(s.status == SectionStatus.INVERT_UNDER_WATER for s in seen[:10])
    blind = shadows([*before, deposit])
    assert all(s.status == SectionStatus.LOW_COVERAGE for s in blind[:10])


def _fov_returns(rng, water: bool = True) -> np.ndarray:
    # A 120° x 25° field of view; with water, the rays down the middle return nothing.
    az = np.radians(rng.uniform(-60.0, 60.0, 20_000))
    el = np.radians(rng.uniform(-12.5, 12.5, 20_000))
    dirs = np.column_stack((np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)))
    if water:
        dirs = dirs[~((np.abs(az) < np.radians(30.0)) & (el < np.radians(-5.0)))]
    return dirs * rng.uniform(0.5, 4.0, (len(dirs), 1))


def _pitched_up(deg: float) -> np.ndarray:
    p = np.radians(deg)
    return np.array([[np.cos(p), 0.0, -np.sin(p)], [0.0, 1.0, 0.0], [np.sin(p), 0.0, np.cos(p)]])


@pytest.mark.parametrize("pitch_up_deg", [3.0, -4.0, 0.0])
def test_the_steepest_sight_is_the_field_of_views_lower_edge_ahead(pitch_up_deg):
    """A 120° x 25° field of view pitched nose up (or down): the steepest sight ahead is
    12.5° less the pitch, though the rays down the middle hit water and return nothing."""
    from pipescan.core.water import steepest_descent_ratio

    rng = np.random.default_rng(3)
    got = steepest_descent_ratio(_fov_returns(rng), _pitched_up(pitch_up_deg))
    assert np.degrees(np.arctan(got)) == pytest.approx(12.5 - pitch_up_deg, abs=0.1)


def test_the_sensor_sight_keeps_the_least_steep_frame_and_refuses_a_backward_look():
    """Frames pitched 2-4° nose up along a straight pipe: the sight is the least steep frame's
    (12.5 - 4°), at the sensor's heights; a sensor turned round (looking back along its
    travel) gives none, and the shadow rule keeps to the stretch beside the top."""
    from pipescan.core.axis import PipeAxis
    from pipescan.core.water import sensor_sight

    axis = PipeAxis(
        origin_m=np.zeros(3), direction=np.array([1.0, 0.0, 0.0]), up=np.array([0.0, 0.0, 1.0])
    )
    rng = np.random.default_rng(4)
    pitches = [2.0, 4.0, 3.0]
    T = np.stack([np.eye(4)] * 3)
    for r, deg in enumerate(pitches):
        T[r, :3, :3] = _pitched_up(deg)
        T[r, :3, 3] = (0.5 * r, 0.0, -0.05)
    frames = [(r, _fov_returns(rng)) for r in range(3)]
    sight = sensor_sight(axis, T, frames, max_range_m=5.0)
    assert sight is not None and sight.forward_sign == 1.0
    assert np.degrees(np.arctan(sight.descent_ratio)) == pytest.approx(8.5, abs=0.1)
    assert np.allclose(sight.height_m, -0.05) and np.allclose(sight.chainage_m, [0.0, 0.5, 1.0])
    turned = T.copy()
    turned[:, :3, :3] = turned[:, :3, :3] @ np.diag([-1.0, -1.0, 1.0])
    assert sensor_sight(axis, turned, frames, max_range_m=5.0) is None


def test_the_flow_reads_the_sight_from_every_registered_frame_it_kept(tmp_path):
    """``read_sensor_sight`` reads the frames registration kept (two chunks sharing a frame),
    one at a time, and gives the core's sight: the least steep frame's, 12.5 - 4°."""
    from pipescan.core.axis import PipeAxis
    from pipescan.core.model import FrameQuality
    from pipescan.core.registration import Trajectory
    from pipescan.storage.scratch import FrameStore
    from pipescan.tasks.inspection import read_sensor_sight

    rng = np.random.default_rng(5)
    frames = {i: _fov_returns(rng).astype(np.float32) for i in range(5)}
    store = FrameStore(tmp_path / "frames")
    for first, last in ((0, 2), (2, 4)):
        with store.writer(first) as w:
            for i in range(first, last + 1):
                w.add(i, frames[i])
    T = np.stack([np.eye(4)] * 3)
    for r, deg in enumerate([2.0, 4.0, 3.0]):
        T[r, :3, :3] = _pitched_up(deg)
        T[r, :3, 3] = (0.5 * r, 0.0, -0.05)
    trajectory = Trajectory(
        T_world_frame=T,
        quality=tuple(FrameQuality(i, 1.0, 0.001, False) for i in (0, 2, 4)),
        frame_indices=(0, 2, 4),
    )
    axis = PipeAxis(
        origin_m=np.zeros(3), direction=np.array([1.0, 0.0, 0.0]), up=np.array([0.0, 0.0, 1.0])
    )
    sight = read_sensor_sight.fn(store, [(0, 2), (2, 4)], trajectory, axis, 5.0)
    assert sight is not None
    assert np.degrees(np.arctan(sight.descent_ratio)) == pytest.approx(8.5, abs=0.1)
    assert np.allclose(sight.chainage_m, [0.0, 0.5, 1.0])


@pytest.mark.slow
def test_water_is_read_beyond_a_deposits_shadow_and_a_dry_pipe_reads_none():
    """A 0.6 m pipe, 4.4 m of travel, the deposit 28.5 % high at 3.4-4.3 m, water 8 % deep
    whose surface returns nothing: the water is read before the deposit and from 1.2 m past
    its end on, at its depth, and not in the deposit's shadow just behind it. The same pipe
    dry reads no water at all (the shadow is not water)."""
    from pipescan.simulator.sensors import WaterLevel
    from pipescan.simulator.sweep import measure_scan

    dry = defect_scene(0.6, 4.4, effects=Effects())
    wet_scene = dataclasses.replace(dry, water=WaterLevel(0.08, surface_return_ratio=0.0))
    _, sections = measure_scan(simulate_scan(wet_scene, seed=2))
    wet = [s for s in sections if s.status == SectionStatus.INVERT_UNDER_WATER]
    beyond = [s for s in wet if s.chainage_start_m >= 5.5]
    before = [s for s in wet if s.chainage_end_m <= 2.5]
    assert len(beyond) >= 20 and len(before) >= 5
    assert np.median([s.water_depth_ratio for s in beyond]) == pytest.approx(0.08, abs=0.015)
    assert not [s for s in wet if 4.3 <= s.chainage_start_m < 4.9]
    # The obstacle (2.6-2.9 m, 16.8 %) stands in the water: coded, at least its figure.
    codings = code_sections(sections)
    obstacle = [
        d for d in merge_defects(sections, load_table(), codings=codings) if d.code == "BBE"
    ]
    assert len(obstacle) == 1 and obstacle[0].lower_bound
    assert 0.12 <= obstacle[0].peak_value <= 0.168 + 0.02
    _, dry_sections = measure_scan(simulate_scan(dry, seed=2))
    assert not [s for s in dry_sections if s.status == SectionStatus.INVERT_UNDER_WATER]


def test_water_whose_surface_returns_nothing_is_read_with_its_depth():
    from pipescan.simulator.sensors import WaterLevel
    from pipescan.simulator.sweep import measure_cloud_scan, smooth_scene

    scene = dataclasses.replace(
        smooth_scene(0.6, 3.0, effects=Effects(imu=False)),
        water=WaterLevel(0.1, surface_return_ratio=0.0),
    )
    sections = measure_cloud_scan(simulate_scan(scene, seed=1))
    wet = [s for s in sections if s.status == SectionStatus.INVERT_UNDER_WATER]
    assert len(wet) >= len(sections) / 2
    assert np.median([s.water_depth_ratio for s in wet]) == pytest.approx(0.1, abs=0.01)
    dry = measure_cloud_scan(simulate_scan(smooth_scene(0.6, 3.0), seed=1))
    assert not any(s.status == SectionStatus.INVERT_UNDER_WATER for s in dry)


def test_the_instrument_sweep_draws_sensors_as_well_as_effects():
    from pipescan.simulator.sweep import INSTRUMENT_MODELS, instrument_draws

    draws = instrument_draws(32)
    assert len(draws) >= 30
    assert {d.name.split()[0] for d in draws} == set(INSTRUMENT_MODELS)
    assert any(d.scenario.frame_coverage_ratio < 0.3 for d in draws)
    assert any(d.scenario.effects.spurious_range_ratio for d in draws)
    assert any(not d.scenario.effects.imu for d in draws)
    assert any(d.scenario.water is not None for d in draws)
    assert instrument_draws(4)[3].name == draws[3].name  # a draw does not change with count


def test_the_report_cover_names_the_measured_inner_diameter():
    from types import SimpleNamespace

    from pipescan.reports.context import _measured_diameter

    stored = SimpleNamespace(registration={"measured_inner_diameter_m": 0.7996})
    assert _measured_diameter(stored) == "0.800 m (the wall's median)"
    assert _measured_diameter(SimpleNamespace(registration={})) is None  # stored before it was


def test_a_partial_view_scan_gives_no_figure_until_its_registration_is_trusted():
    from pipescan.core.instrument import registration_trusted
    from pipescan.simulator.sweep import measure_scan

    assert registration_trusted(scan_instrument(simulate_scan(_scene(1.5), seed=1)))
    assert registration_trusted(None)  # a registered cloud: placed by whoever registered it
    scan = simulate_scan(_scene(1.5, coverage=0.3), seed=1)
    assert not registration_trusted(scan_instrument(scan))
    _, sections = measure_scan(scan)
    assert sections and not any(s.is_ok for s in sections)
    assert any(s.status == SectionStatus.WEAK_REGISTRATION for s in sections)


# --------------------------------------------------------------------------- noise across a surface


def _forward_tube(range_noise_m: float, radius_m: float = 0.3, seed: int = 0) -> np.ndarray:
    """One frame of a forward-looking sensor on a tube's axis (120° × 24°, a ray every 0.25°),
    ``range_noise_m`` along each ray: far ahead the rays graze the wall."""
    rng = np.random.default_rng(seed)
    az, el = np.meshgrid(np.radians(np.arange(-60, 60, 0.25)), np.radians(np.arange(-12, 12, 0.25)))
    ray = np.column_stack((np.cos(az.ravel()), np.sin(az.ravel()), np.sin(el.ravel())))
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    across = np.hypot(ray[:, 1], ray[:, 2])
    ray = ray[across > 0]
    tube = ray * (radius_m / np.hypot(ray[:, 1], ray[:, 2]))[:, None]
    return tube + ray * rng.normal(0, range_noise_m, (len(ray), 1))


@pytest.mark.parametrize("range_noise_m", [0.003, 0.008, 0.018])
def test_range_noise_is_recovered_where_the_rays_graze(range_noise_m):
    frame = _forward_tube(range_noise_m)
    sigma, by_distance = surface_noise([frame], max_range_m=5.0)
    assert sigma == pytest.approx(range_noise_m, rel=0.2)
    # The plane fits read a fraction of it across the wall, less the noisier the scan.
    assert wall_noise_m([frame], max_range_m=5.0) < 0.6 * range_noise_m
    # Across the wall the noise is σ |cos θ|: the wall 0.5-0.75 m ahead (cos θ 0.39-0.51)
    # against 2-2.25 m ahead (0.13-0.15).
    edges = np.array(by_distance.distance_edges_m)
    near = by_distance.noise_across_m[int(np.searchsorted(edges, 0.5))]
    far = by_distance.noise_across_m[int(np.searchsorted(edges, 2.0))]
    assert near == pytest.approx(range_noise_m * 0.45, rel=0.25)
    assert far == pytest.approx(range_noise_m * 0.14, rel=0.35)


def test_range_noise_of_a_simulated_scan():
    """The simulator's noise along the ray, without its growth with range and towards grazing
    incidence, is read from the scan within 20 %; the plane fits read under half of it."""
    scene = _scene(range_noise_sigma_m=0.015, grazing_noise_max_factor=1.0)
    instrument = scan_instrument(simulate_scan(scene, seed=1))
    assert instrument.range_noise_m == pytest.approx(0.015, rel=0.2)
    assert instrument.sources["range_noise_m"] == "estimated"
    assert instrument.wall_noise_m < 0.5 * instrument.range_noise_m


def test_a_section_seen_from_close_by_may_spread_more():
    """A section the sensor passed over was seen head-on from beside it; one seen only from
    afar, at grazing incidence: its frames that agree spread it less, and so does its limit."""
    _, by_distance = surface_noise([_forward_tube(0.015)], max_range_m=5.0)
    passed = by_distance.spread_m(np.arange(0.0, 5.0, 0.05))
    ahead = by_distance.spread_m(np.arange(3.0, 5.0, 0.05))
    assert passed > 2.0 * ahead
    assert by_distance.max_spread_m(np.arange(0.0, 5.0, 0.05)) == smear_limit_m(passed)
    assert by_distance.spread_m(np.array([-2.0, 6.0])) is None  # no frame saw it


def _pooled_section(by_distance, distances_m, range_noise_m, *, deposit_ratio, seed=0):
    """The points a 0.1 m section of a 0.6 m pipe pools from frames standing ``distances_m``
    behind it, each frame's share as ``by_distance`` has it, each point off the surface along
    its ray by ``range_noise_m`` (the wall's radius, a deposit's flat top's height): frames
    that agree, no smear."""
    rng = np.random.default_rng(seed)
    radius, parts = 0.3, []
    top_y = -radius + deposit_ratio * 2 * radius
    edges = np.asarray(by_distance.distance_edges_m)
    for d in distances_m:
        k = int(np.searchsorted(edges, d, side="right")) - 1
        if not 0 <= k < len(by_distance.point_share):
            continue
        n = round(60_000 * by_distance.point_share[k] / len(distances_m) * 10)
        if n == 0:
            continue
        a = rng.uniform(0, 2 * np.pi, n)
        along = rng.uniform(0, 0.1, n)
        on_wall = np.sin(a) * radius > top_y + 0.005
        x, y = radius * np.cos(a), radius * np.sin(a)
        y = np.where(on_wall, y, top_y)
        x = np.where(on_wall, x, rng.uniform(-1, 1, n) * np.sqrt(radius**2 - top_y**2))
        # Off the surface along the ray from the sensor, d behind on the axis: radially on the
        # wall by σ r/√(d² + r²), vertically on the deposit's top by σ |y|/√(d² + |y|²).
        rho = np.hypot(x, y)
        cos_incidence = np.where(on_wall, rho, np.abs(y)) / np.hypot(d, np.where(on_wall, rho, y))
        off = rng.normal(0, range_noise_m, n) * cos_incidence
        x = np.where(on_wall, x * (1 + off / rho), x)
        y = np.where(on_wall, y * (1 + off / rho), y - off)
        parts.append(np.column_stack((x, y, along)))
    return np.vstack(parts)


def _seen_from(chainages: np.ndarray):
    """A trajectory's evidence with frames at ``chainages``, none weak or slid, seen from 5 m."""
    from pipescan.core.registration.metrics import RegistrationEvidence

    n = len(chainages)
    return RegistrationEvidence(chainages, np.zeros(n), np.zeros(n, bool), np.zeros(n, bool), 5.0)


def test_a_deposit_seen_head_on_is_not_smeared():
    """At 15 mm of range noise, a section with a deposit seen from close behind (the run began
    1.5 m before it), pooled from frames that agree, is measured under the limit from where
    the sensor stood; the scan-wide limit (1.5 × the plane fits' wall noise, read where most
    rays graze) calls it smeared."""
    from pipescan.core.registration.metrics import RegistrationEvidence
    from pipescan.core.sections import section_params

    frame = _forward_tube(0.015)
    sigma, by_distance = surface_noise([frame], max_range_m=5.0)
    chainages = np.arange(1.5, 4.0, 0.05)
    evidence = _seen_from(chainages)
    points = _pooled_section(by_distance, 3.05 - chainages, sigma, deposit_ratio=0.2)
    scan_wide = MeasureParams(
        max_wall_spread_m=SMEAR_SPREAD_RATIO * wall_noise_m([frame], max_range_m=5.0)
    )
    own = section_params(
        dataclasses.replace(scan_wide, surface_noise=by_distance), evidence, 3.0, 3.1
    )
    assert own.max_wall_spread_m > scan_wide.max_wall_spread_m
    kw = dict(chainage_start_m=3.0, chainage_end_m=3.1, nominal_diameter_m=0.6)
    measured = measure_section(points, params=own, **kw)
    assert measured.status == SectionStatus.OK
    assert measured.deposit_height_ratio == pytest.approx(0.2, abs=0.02)
    assert measure_section(points, params=scan_wide, **kw).status == SectionStatus.SMEARED_WALL
    # A registered cloud (no frames' places): the limit given stands.
    cloud = section_params(
        dataclasses.replace(scan_wide, surface_noise=by_distance),
        RegistrationEvidence.uniform(0.4),
        3.0,
        3.1,
    )
    assert cloud.max_wall_spread_m == scan_wide.max_wall_spread_m


def test_frames_that_disagree_still_smear_a_section_seen_head_on():
    """The same section, its frames split in two halves 5 cm apart across the pipe (a
    registration error): smeared under its own limit."""
    from pipescan.core.sections import section_params

    sigma, by_distance = surface_noise([_forward_tube(0.015)], max_range_m=5.0)
    chainages = np.arange(0.0, 4.0, 0.05)
    evidence = _seen_from(chainages)
    points = _pooled_section(by_distance, 3.05 - chainages, sigma, deposit_ratio=0.2)
    half = np.arange(len(points)) % 2 == 0
    points[half, 0] += 0.05
    own = section_params(MeasureParams(surface_noise=by_distance), evidence, 3.0, 3.1)
    measured = measure_section(
        points, params=own, chainage_start_m=3.0, chainage_end_m=3.1, nominal_diameter_m=0.6
    )
    assert measured.status == SectionStatus.SMEARED_WALL


def _water_section(radius: float = 0.2, depth: float = 0.06) -> np.ndarray:
    """A 0.4 m section with 7 mm of noise across the wall, water ``depth`` of the diameter
    deep with no return from its surface."""
    rng = np.random.default_rng(3)
    level = -radius + depth * 2 * radius
    angles = rng.uniform(0, 2 * np.pi, 40_000)
    r = radius + rng.normal(0, 0.007, len(angles))
    xy = np.column_stack((r * np.cos(angles), r * np.sin(angles)))
    along = rng.uniform(0, 0.1, len(angles))
    return np.column_stack((xy, along))[radius * np.sin(angles) > level]


def test_surfaceless_water_is_read_at_the_walls_median_edge_not_its_lowest_point():
    # The level is where the wall stops, whatever its scatter.
    section = measure_section(
        _water_section(), chainage_start_m=0.0, chainage_end_m=0.1, nominal_diameter_m=0.4
    )
    # One section cannot tell water from a view that stops short: a candidate depth.
    assert section.water_from_surface is False
    assert section.water_depth_ratio == pytest.approx(0.06, abs=0.01)


def test_water_is_withheld_where_the_registration_is_weak():
    from pipescan.core.water import confirm_surfaceless_water

    # Where the frames that placed the wall are not trusted, neither is the water's level.
    weak = measure_section(
        _water_section(),
        chainage_start_m=0.0,
        chainage_end_m=0.1,
        nominal_diameter_m=0.4,
        registration_weak=True,
    )
    assert weak.status == SectionStatus.WEAK_REGISTRATION and weak.water_depth_ratio is None
    run = [dataclasses.replace(weak, chainage_start_m=0.1 * i) for i in range(6)]
    assert all(s.status == SectionStatus.WEAK_REGISTRATION for s in confirm_surfaceless_water(run))


def test_stray_returns_in_the_open_pipe_are_no_water_surface():
    # Early returns from dust or spray, 1.5 % of the section, scattered through the open
    # pipe: some land on the chord where the view stops short, but no more than anywhere.
    rng = np.random.default_rng(4)
    points = _water_section()
    n = int(0.015 * len(points))
    r = 0.2 * np.sqrt(rng.uniform(0, 0.9, n))
    a = rng.uniform(0, 2 * np.pi, n)
    stray = np.column_stack((r * np.cos(a), r * np.sin(a), rng.uniform(0, 0.1, n)))
    kw = dict(chainage_start_m=0.0, chainage_end_m=0.1, nominal_diameter_m=0.4)
    dusty = measure_section(np.vstack((points, stray)), **kw)
    assert dusty.water_from_surface is False  # a candidate, for the pipe to confirm
    # A surface's returns along the chord stand out of the strays.
    level = -0.2 + 0.06 * 0.4
    half = np.sqrt(0.2**2 - level**2) - 0.02
    x = rng.uniform(-half, half, 150)
    surface = np.column_stack((x, level + rng.normal(0, 0.003, 150), rng.uniform(0, 0.1, 150)))
    wet = measure_section(np.vstack((points, stray, surface)), **kw)
    assert wet.water_from_surface is True
    assert wet.water_depth_ratio == pytest.approx(0.06, abs=0.01)


def _tube_frame(rng, radius_m: float, noise_m: float, early: float) -> np.ndarray:
    """One forward-looking frame in a tube whose axis is 3° off the sensor's and 2 cm beside
    it: returns with ``noise_m`` along their rays, ``early`` of them cut short (20-80 % of
    their range, as dust and spray return)."""
    n = 20_000
    a, x = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.6, 4.5, n)
    wall = np.column_stack((x, 0.02 + radius_m * np.cos(a), radius_m * np.sin(a)))
    tilt = np.radians(3.0)
    turn = np.array([[np.cos(tilt), -np.sin(tilt), 0], [np.sin(tilt), np.cos(tilt), 0], [0, 0, 1]])
    wall = wall @ turn.T
    rays = np.linalg.norm(wall, axis=1)
    wall *= ((rays + rng.normal(0, noise_m, n)) / rays)[:, None]
    cut = rng.random(n) < early
    wall[cut] *= rng.uniform(0.2, 0.8, cut.sum())[:, None]
    return wall


def test_single_frames_measure_the_pipe_free_of_registration():
    rng = np.random.default_rng(4)
    frames = [_tube_frame(rng, 0.2, 0.01, 0.01) for _ in range(8)]
    measured = frame_diameter_m(frames, max_range_m=5.0)
    assert measured is not None
    diameter, se = measured
    assert diameter == pytest.approx(0.4, rel=0.005)
    assert 0 < se < 0.002
    assert frame_diameter_m(frames[:4], max_range_m=5.0) is None  # too few frames to tell


def test_a_wall_wider_than_the_frames_pipe_widens_the_blockage_plus_minus():
    # A ring 1 % wider than the pipe the single frames saw: the registered frames pushed it
    # out, and it reads 2 pp too open. The ± takes that in; a ring of the frames' own
    # diameter gets nothing.
    def section(radius_m: float, params: MeasureParams):
        rng = np.random.default_rng(2)
        a = rng.uniform(0, 2 * np.pi, 40_000)
        r = radius_m + rng.normal(0, 0.002, len(a))
        pts = np.column_stack((r * np.cos(a), r * np.sin(a), rng.uniform(0, 0.1, len(a))))
        return measure_section(
            pts, chainage_start_m=0, chainage_end_m=0.1, nominal_diameter_m=0.4, params=params
        )

    plain = MeasureParams()
    held = dataclasses.replace(plain, frame_diameter_m=0.4, frame_diameter_se_m=0.0003)
    wide_plain, wide_held = section(0.202, plain), section(0.202, held)
    assert wide_held.blockage_ratio == pytest.approx(wide_plain.blockage_ratio)
    error = abs(wide_held.blockage_ratio)
    assert error > 0.015
    assert wide_plain.blockage_uncertainty_ratio < error <= wide_held.blockage_uncertainty_ratio
    same = section(0.2, held)
    assert same.blockage_uncertainty_ratio == pytest.approx(
        section(0.2, plain).blockage_uncertainty_ratio, abs=0.001
    )
