"""Deskewing frames by their point times: what it costs and what it corrects.

    python benchmarks/bench_deskew.py
    python benchmarks/bench_deskew.py --speeds 0.15 0.5 --vibration 0 0.3 --travel-m 1.2
    python benchmarks/bench_deskew.py --speeds 0.5 --with-turn

Cost: :func:`~pipescan.core.registration.deskew.deskew_points` on a frame of the default
simulated sensor (452,000 points a second at 10 Hz: 45,200 points), with the simulator's 50
packet times and with every point at its own time, by a travel only (what pipescan passes) and
with a turn; the median of 20 calls.

Effect: the ``paper`` scenario from its start (the obstacle 1.4-2.9 m ahead) with
``Effects.motion_within_frame``, ideal effects but 2 mm range noise and 1° of rocking (and
``--vibration`` degrees of vibration, a new attitude every frame), 100,000 points a second,
seed 4. Every frame is registered (``register_frames``, odometer exact) and placed
(``iter_registered_points``) once without the point times and once with them; each point's
place is compared with its truth (the pose at its own time), per axis of the pipe frame (x
along the axis): RMS and the 95th percentile of the distance, mm. ``--with-turn`` deskews by
the full relative pose between frames (travel and turn) instead of pipescan's travel only
(``travel_motion``), to compare (docs/registration.md, *Deskew*).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from scipy.spatial.transform import Rotation

from pipescan.core.registration import iter_registered_points, register_frames
from pipescan.core.registration.deskew import deskew_points
from pipescan.core.registration.engines import transform
from pipescan.simulator.scan import Effects, get_scenario, simulate_scan


def cost_ms(points: int, distinct_times: int, turn: bool) -> float:
    """Median ms of 20 calls of deskew_points on a frame of ``points`` random points."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(points, 3))
    time_s = np.sort(rng.integers(0, distinct_times, points)) * (0.1 / distinct_times)
    T = np.eye(4)
    T[:3, 3] = (0.05, 0.001, -0.001)
    if turn:  # 0.3° about a skew axis
        T[:3, :3] = Rotation.from_rotvec(np.radians(0.3) * np.array([0.6, 0.0, 0.8])).as_matrix()
    runs = []
    for _ in range(20):
        start = time.perf_counter()
        deskew_points(pts, time_s, T, 0.1)
        runs.append(time.perf_counter() - start)
    return 1e3 * statistics.median(runs)


def effect(speed_m_s: float, vibration_deg: float, travel_m: float) -> None:
    effects = Effects.ideal(
        motion_within_frame=True,
        range_noise_sigma_m=0.002,
        rocking_deg=1.0,
        vibration_deg=vibration_deg,
    )
    scenario = get_scenario(
        "paper", travel_m=travel_m, speed_m_s=speed_m_s, points_per_s=100_000, effects=effects
    )
    scan = simulate_scan(scenario, seed=4)
    frames = [scan.frame(i) for i in range(len(scan))]
    times = [f.time_s for f in frames]
    T0 = scan.T_pipe_sensor(0)
    for timed in (False, True):
        point_times = [f.point_time_s if timed else None for f in frames]
        trajectory = register_frames(
            (f.index, f.points_sensor, f.odometer_m, f.gravity, t, f.time_s)
            for f, t in zip(frames, point_times, strict=True)
        )
        placed = iter_registered_points(
            ((f.index, f.points_sensor, t) for f, t in zip(frames, point_times, strict=True)),
            trajectory,
            None,
            times,
        )
        err = np.concatenate(
            [transform(T0, p) - scan.points_pipe(f) for f, p in zip(frames, placed, strict=True)]
        )
        rms = 1e3 * np.sqrt((err**2).mean(axis=0))
        p95 = 1e3 * np.percentile(np.linalg.norm(err, axis=1), 95)
        print(
            f"{speed_m_s:>5.2f} m/s  vibration {vibration_deg:.1f}°  "
            f"{'with times   ' if timed else 'without times'}  "
            f"RMS x {rms[0]:5.1f}  y {rms[1]:5.1f}  z {rms[2]:5.1f} mm  p95 {p95:5.1f} mm  "
            f"({len(frames)} frames)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.15, 0.5])
    parser.add_argument("--vibration", type=float, nargs="+", default=[0.0, 0.3])
    parser.add_argument("--travel-m", type=float, default=1.2)
    parser.add_argument("--with-turn", action="store_true")
    args = parser.parse_args()
    if args.with_turn:
        from pipescan.core.registration import registrar, trajectory
        from pipescan.core.registration.deskew import relative_motion

        registrar.travel_motion = relative_motion  # type: ignore[attr-defined]
        trajectory.travel_motion = relative_motion  # type: ignore[attr-defined]
    for distinct in (50, 45_200):
        for turn in (False, True):
            print(f"deskew_points, 45,200 points, {distinct:,} distinct times, "
                  f"{'travel and turn' if turn else 'travel only'}: "
                  f"{cost_ms(45_200, distinct, turn):.2f} ms")  # fmt: skip
    for speed in args.speeds:
        for vibration in args.vibration:
            effect(speed, vibration, args.travel_m)


if __name__ == "__main__":
    main()
