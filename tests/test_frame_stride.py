"""Which frames a run reads (``choose_frame_stride``): the bounds hold on the simulator's
ground truth, a profiler and a run without odometer use every frame, and the chunks of a
strided run chain into one trajectory that keeps the run's whole length."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipescan.core.measures import MeasureParams
from pipescan.core.registration import (
    RegistrationParams,
    chunk_frame_indices,
    plan_chunks,
    used_frame_indices,
)
from pipescan.core.registration.stride import (
    FRAMES_PER_KEYFRAME,
    LOOK_CLOSER_SIGMAS,
    LOOK_CLOSER_STRIDES,
    choose_frame_stride,
    frames_to_register,
    is_stride_frame,
    sample_frame_indices,
    travel_per_frame,
    view_length,
)
from pipescan.simulator.scan import get_scenario, simulate_scan

STEP_M = 0.1
RANGE_M = 5.0


def _choose(frames, odometer, **overrides):
    kwargs = {
        "max_range_m": RANGE_M,
        "step_m": STEP_M,
        "section_points": MeasureParams().max_points,
        "keyframe_distance_m": RegistrationParams().keyframe_distance_m,
    } | overrides
    return choose_frame_stride(frames, odometer, **kwargs)


def _scan_choice(scan, frames=None, **overrides):
    frames = list(scan.frames()) if frames is None else frames
    sample = [frames[i].points_sensor for i in sample_frame_indices(len(frames))]
    return frames, _choose(sample, [f.odometer_m for f in frames], **overrides)


def _points_per_section(scan, frames, used) -> np.ndarray:
    """True points each section gets from frames ``used`` (true poses; the pipe runs along x),
    for the sections the sensor passed with the whole of its view: behind its last position,
    and 4 m beyond its first (it looks forward)."""
    xs = []
    for i in used:
        p = frames[i].points_sensor
        p = p[np.einsum("ij,ij->i", p, p) <= RANGE_M**2]
        T = scan.T_world_sensor[i]
        xs.append(p @ T[0, :3] + T[0, 3])
    x = np.concatenate(xs)
    positions = scan.T_world_sensor[list(used), 0, 3]
    start = np.ceil((positions[0] + 4.0) / STEP_M) * STEP_M
    edges = np.arange(start, positions[-1], STEP_M)
    return np.histogram(x, edges)[0]


@pytest.fixture(scope="module")
def slow_scan():
    # A slower crawler than the default: denser in time, so that a stride above 2 is allowed.
    scenario = get_scenario("paper", travel_m=5.5, speed_m_s=0.08, points_per_s=300_000)
    scan = simulate_scan(scenario, seed=3)
    return scan, list(scan.frames())


def test_the_sections_need_not_bind_the_stride(slow_scan):
    """Every frame is placed (tracked between registered ones), so the points a section keeps
    do not bound the stride: asking for twice the points chooses the same stride."""
    need = MeasureParams().max_points
    scan, frames = slow_scan
    frames, choice = _scan_choice(scan, frames)
    frames, more = _scan_choice(scan, frames, section_points=2 * need)
    assert choice.stride >= 3 and more.stride == choice.stride, (choice, more)
    assert "local map" in choice.reason


def _frames_per_keyframe(travel: np.ndarray, keyframe_m: float) -> list[int]:
    """How the local map groups frames at these positions along the pipe: a keyframe closes
    at the first frame ``keyframe_m`` or more from the last one (FrameRegistrar._add_to_map)."""
    counts, pending, last = [], 0, travel[0]
    for x in travel[1:]:
        pending += 1
        if x - last >= keyframe_m:
            counts.append(pending)
            pending, last = 0, x
    return counts


def test_the_local_map_keeps_three_frames_a_keyframe(slow_scan):
    """Against the true travel: with the stride chosen where the local map binds, every
    keyframe still groups three registered frames; one frame more skipped and some would not."""
    scan, frames = slow_scan
    frames, choice = _scan_choice(scan, frames)
    assert "local map" in choice.reason and choice.stride > 3, choice
    keyframe = RegistrationParams().keyframe_distance_m
    travel = scan.true_travel_m
    grouped = _frames_per_keyframe(travel[used_frame_indices(len(frames), choice.stride)], keyframe)
    assert min(grouped) >= FRAMES_PER_KEYFRAME, grouped
    wider = used_frame_indices(len(frames), choice.stride + 1)
    assert min(_frames_per_keyframe(travel[wider], keyframe)) < FRAMES_PER_KEYFRAME


def test_a_short_view_is_bound_by_the_local_map_only():
    """A sensor that sees 0.6 m of pipe a frame: every frame is placed, so the stride is the
    local map's (k < 0.15 m / (2 × 2 mm)), not a count of views."""
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 2 * np.pi, 60_000)
    short = np.column_stack((rng.uniform(0.3, 0.9, 60_000), 0.3 * np.cos(a), 0.3 * np.sin(a)))
    odometer = np.arange(400) * 0.002  # a slow crawler: 2 mm a frame
    choice = _choose([short] * 3, odometer)
    assert choice.view_length_m == pytest.approx(0.54, abs=0.03)  # 5-95 % of 0.6 m
    keyframe = RegistrationParams().keyframe_distance_m
    assert choice.stride == int(np.ceil(keyframe / (0.002 * (FRAMES_PER_KEYFRAME - 1)))) - 1


def test_a_profiler_and_a_run_without_odometer_use_every_frame():
    ring = simulate_scan(get_scenario("ring", travel_m=1.5), seed=0)
    frames, choice = _scan_choice(ring, section_points=10)  # however few points it needs
    assert choice.stride == 1 and choice.view_length_m == 0.0
    paper = simulate_scan(get_scenario("paper", travel_m=2.0), seed=0)
    frames = list(paper.frames())
    sample = [frames[i].points_sensor for i in sample_frame_indices(len(frames))]
    assert _choose(sample, [f.odometer_m for f in frames]).stride > 1
    no_odometer = _choose(sample, None)
    assert no_odometer.stride == 1 and "odometer" in no_odometer.reason
    assert _choose(sample, [None] * len(frames)).stride == 1
    few = _choose(sample[:3], [0.0, 4.0, 8.0])  # a static scanner's three stations
    assert few.stride == 1 and "too few" in few.reason


@pytest.mark.parametrize("angles", [(0, 0, 0), (10, 35, 60), (80, 0, 20)])
def test_view_length_does_not_depend_on_how_the_sensor_is_mounted(angles):
    rng = np.random.default_rng(2)
    a = rng.uniform(0, 2 * np.pi, 20_000)
    tube = np.column_stack((rng.uniform(0.5, 3.5, 20_000), 0.25 * np.cos(a), 0.25 * np.sin(a)))
    turned = tube @ Rotation.from_euler("xyz", angles, degrees=True).as_matrix().T
    assert view_length(turned) == pytest.approx(2.7, abs=0.05)  # 5-95 % of 3 m


def test_travel_per_frame_takes_the_fast_end():
    slow_then_fast = np.concatenate((np.arange(200) * 0.005, 1.0 + np.arange(1, 201) * 0.02))
    assert travel_per_frame(slow_then_fast) == pytest.approx(0.02, rel=0.01)
    standing = np.zeros(100)
    assert travel_per_frame(standing) is None
    assert travel_per_frame(np.arange(15) * 0.01) is None  # too short to tell


@pytest.mark.parametrize(("count", "stride"), [(296, 2), (301, 3), (10, 4), (7, 1), (1, 3)])
def test_strided_chunks_overlap_by_one_frame_and_keep_the_last(count, stride):
    used = used_frame_indices(count, stride)
    assert used[0] == 0 and used[-1] == count - 1
    assert all(0 < b - a <= stride for a, b in itertools.pairwise(used))
    chunks = plan_chunks(count, 4, stride)
    frames = [chunk_frame_indices(a, b, stride) for a, b in chunks]
    assert all(len(f) <= 4 for f in frames)
    assert all(f[-1] == g[0] for f, g in itertools.pairwise(frames))
    chained = [i for k, f in enumerate(frames) for i in (f if k == 0 else f[1:])]
    assert chained == used


def test_chunks_are_as_few_as_allowed_and_as_equal_as_they_can_be():
    """A short last chunk would leave a core idle while another chunk finishes: the chunks'
    frame counts differ by at most one, and there are no more of them than needed."""
    rng = np.random.default_rng(12)
    for _ in range(300):
        count, chunk_frames, stride = (
            int(rng.integers(1, 3000)),
            int(rng.integers(2, 80)),
            int(rng.integers(1, 5)),
        )
        used = used_frame_indices(count, stride)
        sizes = [
            len(chunk_frame_indices(a, b, stride))
            for a, b in plan_chunks(count, chunk_frames, stride)
        ]
        assert max(sizes) <= chunk_frames
        assert max(sizes) - min(sizes) <= 1, (count, chunk_frames, stride, sizes)
        steps = len(used) - 1
        assert len(sizes) == max(1, -(-steps // (chunk_frames - 1)))  # the fewest that fit
    assert [b for _, b in plan_chunks(2011, 60, 3)] == [
        used_frame_indices(2011, 3)[round(i * 670 / 12)] for i in range(1, 13)
    ]  # the 30 m benchmark scan: 12 chunks of 56-57 frames, not 11 of 60 and one of 23


def test_the_in_memory_registration_reads_what_the_flow_reads():
    """``register_scan`` (the benchmarks' and studies' registration) uses the flow's stride
    unless told otherwise, and keeps the run's last frame."""
    from pipescan.simulator.sweep import register_scan

    scan = simulate_scan(get_scenario("paper", travel_m=1.0), seed=0)
    frames = list(scan.frames())
    sample = [frames[i].points_sensor for i in sample_frame_indices(len(frames))]
    stride = _choose(sample, [f.odometer_m for f in frames]).stride
    assert stride > 1
    strided = register_scan(scan, chunk_frames=20)
    assert set(used_frame_indices(len(frames), stride)) <= set(strided.frame_indices)
    assert len(strided.frame_indices) < len(frames)
    every = register_scan(scan, chunk_frames=40, frame_stride=1)
    assert list(every.frame_indices) == list(range(len(frames)))


@pytest.mark.parametrize("stride", [2, 3, 4])
@pytest.mark.parametrize("seed", range(4))
def test_frames_read_to_look_closer_follow_a_disagreement(stride, seed):
    """Every frame of the stride is read; the others only within ``LOOK_CLOSER_STRIDES``
    strides after a frame whose ICP disagreed with the odometer beyond the threshold."""
    rng = np.random.default_rng(seed)
    first, last = 7, 7 + int(rng.integers(20, 80))
    shown = {}

    def disagreement():
        value = float(rng.choice([0.0, 1.0, 1.9, 2.1, 5.0], p=[0.5, 0.2, 0.1, 0.1, 0.1]))
        shown[len(shown)] = value
        return value

    read = list(frames_to_register(first, last, stride, disagreement))
    assert read == sorted(set(read)) and read[0] == first and read[-1] == last
    assert set(chunk_frame_indices(first, last, stride)) <= set(read)
    for i in read:
        if is_stride_frame(i, first, last, stride):
            continue
        before = [j for n, j in enumerate(read[:-1]) if j < i and shown[n] > LOOK_CLOSER_SIGMAS]
        assert before and i - before[-1] <= LOOK_CLOSER_STRIDES * stride
    always = list(frames_to_register(first, last, stride, lambda: 3.0))
    assert always == list(range(first, last + 1))
    never = list(frames_to_register(first, last, stride, lambda: 0.0))
    assert never == chunk_frame_indices(first, last, stride)


@pytest.mark.slow
def test_looking_closer_catches_the_slips_every_frame_catches():
    """A crawler whose odometer slips often (slip draw 11, a 0.6 m pipe, read every 4th frame):
    the slips that registering every frame catches against features are caught at the
    flow's stride too (every 4th frame alone once caught one of two). Which slips a run
    catches depends on the map's state each frame meets, so on the chunks: with the equal
    chunks of ``plan_chunks`` every frame catches one (at frame 39), the stride two (44 and
    209). And every frame lies within its chainage ±: the second slip went out of view while
    the crawler still stood (sized 13 cm, 20 cm in truth), and 29 frames lay beyond their ±
    by up to 11 cm until such a slip counted once more (``slips_out_of_view``)."""
    from pipescan.simulator.sweep import chainage_bound_misses, register_scan, slip_draws

    draw = next(d for d in slip_draws() if d.name.startswith("slips: draw 11,"))
    scan = simulate_scan(draw.scenario, draw.seed)
    every = register_scan(scan, frame_stride=1)
    strided = register_scan(scan)
    assert len(strided.frame_indices) < len(every.frame_indices) / 3
    caught = [q.index for q in every.quality if q.fault == "odometer_slip"]
    caught_strided = [q.index for q in strided.quality if q.fault == "odometer_slip"]
    assert caught
    for i in caught:
        assert any(abs(i - j) <= 8 for j in caught_strided)
    assert chainage_bound_misses(strided, scan) == (0, 0.0)
