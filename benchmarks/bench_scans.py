"""Scans as instruments and sewers deliver them: section counts, measured share and the true
error against the stated 95 % uncertainty, per kind of scan.

    python benchmarks/bench_scans.py table            # the closing table (all kinds below)
    python benchmarks/bench_scans.py ring-sweep       # ring profilers over randomised conditions
    python benchmarks/bench_scans.py table --seeds 0 1 2
    python benchmarks/bench_scans.py rays             # the simulator's ray caster, rays a second

Kinds: dense frames (the forward-looking sensor, `paper` scenario), a 2D ring profiler
(`ring`), a sparse static terrestrial scan (`static`), water at 10 % and 30 % of the diameter
(ring profiler), and a tilted registered cloud (the `paper` scan as one cloud with GPS time, its
axis tilted 20°). Points are placed with the true poses (registration is not what is measured
here), the axis is fitted as the flow fits it, and for clouds the start is found as the flow
finds it. "Fully seen" sections are those the ground truth says nothing hid (no shadow, no
water) and that its rays hit all round (every 10° arc). Every figure is printed; nothing is
asserted (the tests do that on smaller cases).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter

import numpy as np

from pipescan.core.axis import axis_direction, fit_axis
from pipescan.core.measures import MeasureParams
from pipescan.core.model import SectionStatus
from pipescan.core.sections import measure_window, plan_windows
from pipescan.core.start import cloud_start
from pipescan.simulator.archive import world_cloud
from pipescan.simulator.scan import (
    Effects,
    Scenario,
    cast_rays,
    get_scenario,
    ray_directions_sensor,
    simulate_scan,
)
from pipescan.simulator.sensors import RingProfiler, WaterLevel

MAX_RANGE_M = 5.0


def frames_cloud(scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frames placed with the true poses in the first frame's coordinates (as
    registration gives them); the first and last sensor positions."""
    T0 = np.linalg.inv(scan.T_pipe_sensor(0))
    points = scan.points_true_poses(max_range_m=MAX_RANGE_M) @ T0[:3, :3].T + T0[:3, 3]
    last = (T0 @ scan.T_pipe_sensor(len(scan) - 1))[:3, 3]
    return points, np.zeros(3), last


def measure_cloud(points, axis, nominal_m, params=MeasureParams()):
    chain = axis.chainage(points)
    sections = []
    for w in plan_windows(max(0.0, chain.min()), chain.max(), step_m=0.1, window_m=2.0):
        sections += measure_window(points, axis, w, nominal_diameter_m=nominal_m, params=params)
    return sections


def _seen_all_round(scan, group_deg: float = 10.0) -> dict[float, bool]:
    """Per 0.1 m section (pipe-frame start), whether some noise-free ray hit the wall in
    every ``group_deg`` arc round it: seen all round at the sensor's own resolution (a
    profiler with a 3° step never hits every 2° bin of the truth's grid)."""
    from pipescan.simulator.scan import COVERAGE_BIN_DEG, COVERAGE_CHAINAGE_BIN_M

    full, _ = scan._coverage_grids()  # the truth's hit grid: 1 cm x 2°
    per_section = round(0.1 / COVERAGE_CHAINAGE_BIN_M)
    group = round(group_deg / COVERAGE_BIN_DEG)
    out = {}
    for j in range(full.shape[0] // per_section):
        hit = full[j * per_section : (j + 1) * per_section].any(axis=0)
        out[round(j * 0.1, 1)] = bool(hit.reshape(-1, group).any(axis=1).all())
    return out


def evaluate(scan, *, as_cloud: bool = False, tilt_deg: float = 0.0) -> dict:
    """Measure a simulated scan and compare with its ground truth."""
    s = scan.scenario
    truth = {round(t.chainage_start_m, 1): t for t in scan.true_sections()}
    source = "first frame"
    if as_cloud:
        points, time_s = world_cloud(scan)
        if tilt_deg:
            # Tilt the whole cloud about the world y axis, as a steep pipe would be.
            a = np.radians(tilt_deg)
            rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
            points = points @ rot.T
        first = scan.T_world_sensor[0][:3, 3]
        last = scan.T_world_sensor[-1][:3, 3]
        if tilt_deg:
            first, last = first @ rot.T, last @ rot.T
        start = cloud_start(points, axis_direction(points, s.nominal_diameter_m), time_s=time_s)
        by_time = fit_axis(
            points,
            start_m=start.start_m,
            travel_m=start.travel_m,
            nominal_diameter_m=s.nominal_diameter_m,
        )
        travelled = last - first
        source = (
            f"{start.source}: {'right' if by_time.direction @ travelled > 0 else 'WRONG'}"
            f" way; the first sensor position at chainage"
            f" {float(by_time.chainage(first[None])[0]):+.2f} m (chainage 0: the cloud's end)"
        )
        # The figures are compared with the truth from the sensor's first position, as
        # start_xyz gives it: the truth's sections start there.
        axis = fit_axis(
            points, start_m=first, travel_m=travelled, nominal_diameter_m=s.nominal_diameter_m
        )
    else:
        points, first, last = frames_cloud(scan)
        axis = fit_axis(points, start_m=first, travel_m=last - first)
    sections = measure_cloud(points, axis, s.nominal_diameter_m)
    rows = [(m, truth.get(round(m.chainage_start_m, 1))) for m in sections]
    rows = [(m, t) for m, t in rows if t is not None and t.chainage_end_m <= s.travel_m + 1e-9]
    seen_all_round = _seen_all_round(scan)
    full = [
        (m, t)
        for m, t in rows
        if not t.in_shadow
        and t.water_depth_ratio == 0
        and seen_all_round.get(round(t.chainage_start_m - s.chainage_offset_m, 1), False)
    ]
    ok = [(m, t) for m, t in rows if m.is_ok]
    err = np.array([abs(m.blockage_ratio - t.blockage_ratio) for m, t in ok])
    unc = np.array([m.blockage_uncertainty_ratio for m, t in ok])
    wet = [(m, t) for m, t in rows if t.water_depth_ratio > 0]
    water_err = [
        abs(m.water_depth_ratio - t.water_depth_ratio)
        for m, t in wet
        if m.water_depth_ratio is not None and m.water_depth_ratio > 0
    ]
    return {
        "sections": len(rows),
        "fully_seen": len(full),
        "fully_seen_ok": sum(m.is_ok for m, _ in full),
        "ok": len(ok),
        "statuses": Counter(m.status.value for m, _ in rows),
        "within": int((err <= unc).sum()) if len(err) else 0,
        "mean_err_pp": 100 * float(err.mean()) if len(err) else float("nan"),
        "max_err_pp": 100 * float(err.max()) if len(err) else float("nan"),
        "mean_u_pp": 100 * float(unc.mean()) if len(unc) else float("nan"),
        "wet": len(wet),
        "water_found": len(water_err),
        "water_status": sum(m.status == SectionStatus.INVERT_UNDER_WATER for m, _ in wet),
        "water_err_pp": 100 * float(np.max(water_err)) if water_err else float("nan"),
        "wet_ok": sum(m.is_ok for m, _ in wet),
        "source": source,
        "points_per_section": float(np.median([m.point_count for m, _ in rows])),
    }


def kinds(seed: int) -> dict[str, tuple]:
    ring = get_scenario("ring")
    return {
        "dense frames (paper)": (get_scenario("paper"), {}),
        "ring profiler": (ring, {}),
        "sparse static scan": (get_scenario("static"), {}),
        "water 10 % (ring)": (dataclasses.replace(ring, water=WaterLevel(0.10)), {}),
        "water 30 % (ring)": (dataclasses.replace(ring, water=WaterLevel(0.30)), {}),
        "tilted registered cloud (paper, 20°)": (
            get_scenario("paper"),
            {"as_cloud": True, "tilt_deg": 20.0},
        ),
    }


def table(seeds: list[int]) -> None:
    print("## Per kind of scan: true poses (registration not measured), polar method")
    print(
        "| kind | seed | points/section | sections | fully seen: measured | all ok |"
        " true error within stated 95 % U | mean / max error (pp) | mean U (pp) |"
        " water: sections / found / status / worst depth error (pp) | start source |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        for name, (scenario, how) in kinds(seed).items():
            t0 = time.perf_counter()
            r = evaluate(simulate_scan(scenario, seed=seed), **how)
            water = (
                f"{r['wet']} / {r['water_found']} / {r['water_status']} / {r['water_err_pp']:.1f}"
                if r["wet"]
                else "-"
            )
            print(
                f"| {name} | {seed} | {r['points_per_section']:.0f} | {r['sections']} |"
                f" {r['fully_seen_ok']} of {r['fully_seen']}"
                f" ({100 * r['fully_seen_ok'] / max(1, r['fully_seen']):.0f} %) | {r['ok']} |"
                f" {r['within']} of {r['ok']}"
                f" ({100 * r['within'] / max(1, r['ok']):.0f} %) |"
                f" {r['mean_err_pp']:.2f} / {r['max_err_pp']:.2f} | {r['mean_u_pp']:.2f} |"
                f" {water} | {r['source']} |  ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )


def random_ring(rng: np.random.Generator) -> Scenario:
    """A ring profiler under randomised conditions around "about 300 points a section and
    15 mm of noise": 60-360 points a turn, rings 1-8 cm apart, tilted up to 10°, 8-20 mm of
    noise, pipes of 0.6-1.2 m."""
    diameter = float(rng.uniform(0.6, 1.2))
    per_turn = int(rng.integers(60, 361))
    per_section = float(rng.uniform(220, 420))
    speed = 0.3
    turns_per_s = per_section * speed / 0.1 / per_turn
    return dataclasses.replace(
        get_scenario("ring"),
        nominal_diameter_m=diameter,
        frame_rate_hz=turns_per_s,
        points_per_s=turns_per_s * per_turn,
        speed_m_s=speed,
        mount_offset_z_m=-0.1 * diameter,
        sensor=RingProfiler(points_per_revolution=per_turn, tilt_deg=float(rng.uniform(-10, 10))),
        effects=Effects(range_noise_sigma_m=float(rng.uniform(0.008, 0.02)),
                        range_noise_growth_per_m=0.0),
        obstacles=(),
        deposits=(),
    )  # fmt: skip


def ring_sweep(count: int, seed: int) -> None:
    print("## Ring profilers, randomised conditions (true poses)")
    print("| run | D (m) | points/turn | tilt | noise (mm) | points/section | fully seen:"
          " measured | within U |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(seed)
    totals = Counter()
    for run in range(count):
        scenario = random_ring(rng)
        r = evaluate(simulate_scan(scenario, seed=run))
        totals.update(
            fully_seen=r["fully_seen"], fully_seen_ok=r["fully_seen_ok"], ok=r["ok"],
            within=r["within"],
        )  # fmt: skip
        print(
            f"| {run} | {scenario.nominal_diameter_m:.2f} |"
            f" {scenario.sensor.points_per_revolution} | {scenario.sensor.tilt_deg:+.1f}° |"
            f" {1000 * scenario.effects.range_noise_sigma_m:.0f} |"
            f" {r['points_per_section']:.0f} | {r['fully_seen_ok']} of {r['fully_seen']} |"
            f" {r['within']} of {r['ok']} |",
            flush=True,
        )
    print(
        f"all: {totals['fully_seen_ok']} of {totals['fully_seen']} fully seen sections measured"
        f" ({100 * totals['fully_seen_ok'] / max(1, totals['fully_seen']):.1f} %); true error"
        f" within the stated 95 % uncertainty in {totals['within']} of {totals['ok']}"
        f" ({100 * totals['within'] / max(1, totals['ok']):.1f} %)"
    )


def rays(runs: int) -> None:
    """The simulator's ray caster on the paper scan (every third frame, the sensor's own ray
    pattern), one thread: rays cast a second, in each of ``runs`` runs, and their median."""
    s = get_scenario("paper")
    scan = simulate_scan(s, seed=0)
    poses = [scan.T_pipe_sensor(i) for i in range(0, len(scan), 3)]
    directions = [ray_directions_sensor(s, i) for i in range(0, len(scan), 3)]
    rates = []
    for run in range(runs):
        n, start = 0, time.perf_counter()
        for T, d in zip(poses, directions, strict=True):
            cast_rays(s, T[:3, 3], d @ T[:3, :3].T, min_range_m=s.blind_zone_m)
            n += d.shape[0]
        rates.append(n / (time.perf_counter() - start))
        print(f"run {run + 1}: {len(poses)} frames, {n:,} rays, {rates[-1] / 1e6:.2f} M rays/s")
    median = np.median(rates) / 1e6
    print(f"median: {median:.2f} M rays/s (one thread; the machine's load moves it)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=["table", "ring-sweep", "rays"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--runs", type=int, default=20)
    args = parser.parse_args()
    if args.what == "table":
        table(args.seeds)
    elif args.what == "rays":
        rays(3)
    else:
        ring_sweep(args.runs, args.seeds[0])


if __name__ == "__main__":
    main()
