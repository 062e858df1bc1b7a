"""Sections and measures: accuracy against ground truth, throughput, and memory.

    python benchmarks/bench_sections.py accuracy      # both contour methods, simulator, true poses
    python benchmarks/bench_sections.py obstacles     # polar method, obstacles of other shapes
    python benchmarks/bench_sections.py real          # the real S3DSS scan (800 mm concrete pipe)
    python benchmarks/bench_sections.py throughput    # points/s through slicing, contour, measures
    python benchmarks/bench_sections.py memory        # peak RSS of the section stage, 10 m vs 100 m
    python benchmarks/bench_sections.py veil          # mixed pixels behind edges, removed or kept
    python benchmarks/bench_sections.py all

Every figure is printed; nothing is asserted (the tests do that on smaller cases).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipescan.core.axis import fit_axis
from pipescan.core.contour import CONTOUR_METHODS
from pipescan.core.measures import MeasureParams
from pipescan.core.sections import measure_window, plan_windows
from pipescan.simulator.scan import BoxObstacle, get_scenario, simulate_scan

ROOT = Path(__file__).resolve().parents[1]
REAL_SCAN = (
    Path(os.environ.get("PIPESCAN_REALDATA_DIR") or ROOT.parent / "shared" / "realdata")
    / "s3dss-real459-16k"
    / "real_459_full.txt"
)
MAX_RANGE_M = 5.0


def registered_cloud_true_poses(scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scan's frames placed with the true poses, within ``MAX_RANGE_M``, in the first
    frame's coordinates (as registration gives them).

    Returns the points (N, 3), the first and the last sensor positions.
    """
    T0 = np.linalg.inv(scan.T_pipe_sensor(0))
    points = scan.points_true_poses(max_range_m=MAX_RANGE_M) @ T0[:3, :3].T + T0[:3, 3]
    last = T0 @ scan.T_pipe_sensor(len(scan) - 1)
    return points, np.zeros(3), last[:3, 3]


def split_windows(points, axis, step_m=0.1):
    """Window by window float32 offsets from the axis origin, as the flow's bucket files hold
    them (registration writes them once, as frames stream in)."""
    chain = axis.chainage(points)
    offsets = (points - axis.origin_m).astype(np.float32)
    windows = plan_windows(max(0.0, chain.min()), chain.max(), step_m=step_m, window_m=2.0)
    return [(w, offsets[(chain >= w.start_m) & (chain < w.end_m)]) for w in windows]


def measure_split(split, axis, nominal_m, method):
    sections = []
    for w, offsets in split:
        sections += measure_window(
            offsets,
            axis,
            w,
            nominal_diameter_m=nominal_m,
            params=MeasureParams(method=method),
            relative=True,
        )
    return sections


def measure_all(points, axis, nominal_m, method, step_m=0.1):
    return measure_split(split_windows(points, axis, step_m), axis, nominal_m, method)


def accuracy(seeds: list[int]) -> None:
    print("## Accuracy against ground truth: paper scenario, true poses, 5 mm range noise")
    print(
        "| method | seed | ok sections | mean abs error (pp) | max abs error (pp) |"
        " Table 1 range: mean / max (pp) | >=5 % true reported >=5 % | shadow sections ok |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        scan = simulate_scan(get_scenario("paper"), seed=seed)
        truth = {round(t.chainage_start_m, 1): t for t in scan.true_sections()}
        points, start, last = registered_cloud_true_poses(scan)
        axis = fit_axis(points, start_m=start, travel_m=last - start)
        for method in CONTOUR_METHODS:
            t0 = time.perf_counter()
            sections = measure_all(points, axis, scan.scenario.nominal_diameter_m, method)
            elapsed = time.perf_counter() - t0
            rows = [(s, truth.get(round(s.chainage_start_m, 1))) for s in sections]
            rows = [(s, t) for s, t in rows if t is not None]
            ok = [(s, t) for s, t in rows if s.is_ok]
            err = np.array([100 * abs(s.blockage_ratio - t.blockage_ratio) for s, t in ok])
            table1 = np.array(
                [
                    100 * abs(s.blockage_ratio - t.blockage_ratio)
                    for s, t in ok
                    if 0.025 <= t.blockage_ratio <= 0.235
                ]
            )
            big = [(s, t) for s, t in ok if t.blockage_ratio >= 0.05]
            found = sum(s.blockage_ratio >= 0.05 for s, _ in big)
            shadow_ok = sum(
                1 for s, t in rows if t.in_shadow and t.coverage_ratio < 0.95 and s.is_ok
            )
            shadows = sum(1 for _, t in rows if t.in_shadow and t.coverage_ratio < 0.95)
            worst = ok[int(np.argmax(err))][0].chainage_start_m
            print(
                f"| {method} | {seed} | {len(ok)}/{len(rows)} | {err.mean():.2f} |"
                f" {err.max():.2f} at {worst:.1f} m |"
                f" {table1.mean():.2f} / {table1.max():.2f} (n={len(table1)}) |"
                f" {found}/{len(big)} | {shadow_ok} of {shadows} |"
                f"  ({elapsed:.1f} s, {len(points) / elapsed / 1e6:.1f} M points/s)"
            )


# Obstacles at 2.6-2.9 m, scanned from 3 m of travel: the paper's box hanging from the crown,
# wider and narrower ones, and one jutting from the side at the axis's height.
OBSTACLE_SHAPES = {
    "paper box, crown, 0.28 m wide": BoxObstacle(2.6, 2.9, -0.14, 0.14, 0.1184, 0.35),
    "wide box, crown, 0.40 m wide": BoxObstacle(2.6, 2.9, -0.20, 0.20, 0.10, 0.35),
    "narrow box, crown, 0.12 m wide": BoxObstacle(2.6, 2.9, -0.06, 0.06, 0.12, 0.35),
    "box from the side, 0.16 m high": BoxObstacle(2.6, 2.9, 0.12, 0.35, -0.08, 0.08),
}


def obstacles(seeds: list[int]) -> None:
    print("## Obstacles of other shapes: polar method, true poses, 5 mm range noise")
    print(
        "| obstacle | seed | true blockage | read at 2.6 / 2.7 / 2.8 m | ok sections |"
        " mean / max abs error (pp) | most negative error (pp) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, box in OBSTACLE_SHAPES.items():
        for seed in seeds:
            scenario = get_scenario(
                "paper", travel_m=3.0, deformations=(), deposits=(), obstacles=(box,)
            )
            scan = simulate_scan(scenario, seed=seed)
            truth = {round(t.chainage_start_m, 1): t for t in scan.true_sections()}
            points, start, last = registered_cloud_true_poses(scan)
            axis = fit_axis(points, start_m=start, travel_m=last - start)
            sections = measure_all(points, axis, scenario.nominal_diameter_m, "polar")
            pairs = [(s, truth.get(round(s.chainage_start_m, 1))) for s in sections]
            ok = [(s, t) for s, t in pairs if t is not None and s.is_ok]
            err = np.array([100 * (s.blockage_ratio - t.blockage_ratio) for s, t in ok])
            over = [
                f"{100 * s.blockage_ratio:.2f}" if s.is_ok else s.status.value
                for s, t in pairs
                if t is not None and round(s.chainage_start_m, 1) in (2.6, 2.7, 2.8)
            ]
            print(
                f"| {name} | {seed} | {100 * truth[2.7].blockage_ratio:.2f} % |"
                f" {' / '.join(over)} | {len(ok)} | {np.abs(err).mean():.2f} /"
                f" {np.abs(err).max():.2f} | {err.min():.2f} |"
            )


def real_scan() -> None:
    print("## Real scan: S3DSS real_459 (FARO Focus S, 800 mm concrete pipe, 16,384 points)")
    data = np.loadtxt(REAL_SCAN)
    points = data[:, :3]
    axis = fit_axis(points)
    print(
        f"axis direction {np.round(axis.direction, 3).tolist()}, wall radius {axis.radius_m:.4f} m"
    )
    for method in CONTOUR_METHODS:
        sections = measure_all(points, axis, 0.8, method)
        print(f"\n### {method}")
        print(
            "| chainage (m) | x (m) | status | points | coverage | blockage % |"
            " equivalent diameter (m) |"
        )
        print("|---|---|---|---|---|---|---|")
        for s in sections:
            x = float(axis.point_at(s.chainage_start_m + 0.05, 0.0, 0.0)[0])
            deq = 2 * np.sqrt(s.open_area_m2 / np.pi) if s.open_area_m2 else float("nan")
            b = "-" if s.blockage_ratio is None else f"{100 * s.blockage_ratio:.2f}"
            print(
                f"| {s.chainage_start_m:.1f} | {x:+.2f} | {s.status.value} | {s.point_count} |"
                f" {s.coverage_ratio:.2f} | {b} | {deq:.4f} |"
            )
        ok = [s for s in sections if s.is_ok]
        worst = max(ok, key=lambda s: s.blockage_ratio)
        clean = [2 * np.sqrt(s.open_area_m2 / np.pi) for s in ok if s.blockage_ratio < 0.015]
        print(
            f"clean ok sections: {len(clean)}, diameter {min(clean):.4f}-{max(clean):.4f} m "
            f"(mean {np.mean(clean):.4f}); largest blockage {100 * worst.blockage_ratio:.2f} % at "
            f"x = {float(axis.point_at(worst.chainage_start_m + 0.05, 0, 0)[0]):+.2f} m"
        )


def throughput() -> None:
    print("## Throughput: slicing + contour + measures, one core, paper scenario (true poses)")
    scan = simulate_scan(get_scenario("paper"), seed=0)
    points, start, last = registered_cloud_true_poses(scan)
    axis = fit_axis(points, start_m=start, travel_m=last - start)
    recording_s = len(scan.times_s) / scan.scenario.frame_rate_hz
    split = split_windows(points, axis)
    for method in CONTOUR_METHODS:
        walls, cpus = [], []
        for _ in range(3):
            t0, c0 = time.perf_counter(), time.process_time()
            sections = measure_split(split, axis, 0.5, method)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        n = len(points)
        print(
            f"{method}: {n:,} points, {len(sections)} sections; best of 3: {min(walls):.2f} s wall,"
            f" {min(cpus):.2f} s CPU = {n / min(cpus) / 1e6:.1f} M points per CPU-second"
            f" (median {n / np.median(cpus) / 1e6:.1f}); real-time factor on one core"
            f" {recording_s / min(cpus):.0f}x (recording {recording_s:.0f} s)"
        )


def _memory_child(travel_m: float) -> dict:
    """Run the section stage the way the flow does (bucket per chunk, then window by window)."""
    from pipescan.storage.scratch import read_window_rows, write_buckets

    scan = simulate_scan(get_scenario("long", travel_m=travel_m), seed=0)
    T0 = np.linalg.inv(scan.T_world_sensor[0])
    positions = np.einsum("ij,fjk->fik", T0, scan.T_world_sensor)[:, :3, 3]
    # The axis from a sample of frames, as the flow's fit-axis task does.
    sample = []
    for i in range(0, len(scan.times_s), max(1, len(scan.times_s) // 40)):
        f = scan.frame(i)
        T = T0 @ f.T_world_sensor
        p = f.points_sensor.astype(np.float64)[:5000]
        sample.append(p @ T[:3, :3].T + T[:3, 3])
    axis = fit_axis(
        np.concatenate(sample), start_m=positions[0], travel_m=positions[-1] - positions[0]
    )
    windows = plan_windows(0.0, travel_m + MAX_RANGE_M, step_m=0.1, window_m=2.0)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        chunk, first = [], 0
        for f in scan.frames():
            p = f.points_sensor.astype(np.float64)
            p = p[np.einsum("ij,ij->i", p, p) <= MAX_RANGE_M**2]
            T = T0 @ f.T_world_sensor
            chunk.append(p @ T[:3, :3].T + T[:3, 3])
            if len(chunk) == 60:
                write_buckets(np.concatenate(chunk), axis, windows, Path(tmp), f"chunk_{first:07d}")
                chunk, first = [], f.index + 1
        if chunk:
            write_buckets(np.concatenate(chunk), axis, windows, Path(tmp), f"chunk_{first:07d}")
        n_sections = 0
        for w in windows:
            rows = read_window_rows(Path(tmp), w)
            n_sections += len(
                measure_window(rows, axis, w, nominal_diameter_m=0.5, section_rows=rows)
            )
    return {
        "travel_m": travel_m,
        "frames": len(scan.times_s),
        "sections": n_sections,
        "seconds": time.perf_counter() - t0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def memory(lengths: list[float]) -> None:
    print("## Memory: peak RSS of bucketing + window-by-window measuring (one process per run)")
    results = []
    for travel in lengths:
        out = subprocess.run(
            [sys.executable, __file__, "_memory_child", str(travel)],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        results.append(r)
        print(
            f"{r['travel_m']:.0f} m: {r['frames']} frames, {r['sections']} sections, "
            f"{r['seconds']:.0f} s, peak RSS {r['peak_rss_mb']:.0f} MB"
        )
    if len(results) >= 2:
        print(
            f"ratio {results[-1]['travel_m']:.0f} m / {results[0]['travel_m']:.0f} m: "
            f"{results[-1]['peak_rss_mb'] / results[0]['peak_rss_mb']:.2f}x"
        )


def _veil_section(rng, veil_points: int, tail_points: int) -> np.ndarray:
    """A 0.5 m pipe's section seen by 40,000 points, its crown (60-120°) in an obstacle's
    shadow: ``tail_points`` on the crown from the few frames that saw past the obstacle, and a
    veil of ``veil_points`` mixed returns between the edge (0.1 m from the axis) and the wall
    (the same section as ``tests/test_measures.py``'s)."""
    radius = 0.25
    theta = rng.uniform(0.0, 2.0 * np.pi, 40_000)
    theta = theta[(theta < np.radians(60.0)) | (theta > np.radians(120.0))]
    crown = rng.uniform(np.radians(60.0), np.radians(120.0), tail_points + veil_points)
    r = np.concatenate(
        (
            radius + rng.normal(0.0, 0.002, len(theta) + tail_points),
            rng.uniform(0.10, radius - 0.01, veil_points),
        )
    )
    theta = np.concatenate((theta, crown))
    pts = np.column_stack((r * np.cos(theta), r * np.sin(theta)))
    return np.column_stack((pts, rng.uniform(0.0, 0.1, len(pts))))


def veil(names: list[str]) -> None:
    """What removing the veil of mixed pixels does: the sweep's draws measured with the true
    poses with and without it, section by section, against the simulator's truth; then the
    densest veil it removes, on a synthetic section."""
    from pipescan.core.measures import measure_section
    from pipescan.simulator.sweep import TrueBlockage, sweep_draws

    kept, removed = MeasureParams(veil_relative_density=0.0), MeasureParams()
    print("\n## veil: sweep draws, true poses, with the veil kept -> removed\n")
    print("Changed: sections whose status changed or whose error moved by over 0.2 pp.\n")
    print("| draw | ok | ok mean / max error pp | ok beyond their ± | measuring CPU s | changed |")
    print("|---|---:|---:|---:|---:|---|")
    draws = [d for d in sweep_draws(long_run=False) if any(n in d.name for n in names)]
    for draw in draws:
        scan = simulate_scan(draw.scenario, draw.seed)
        # In the pipe's frame, where the truth is; chainage from the first sensor position.
        points = scan.points_true_poses(max_range_m=MAX_RANGE_M)
        start = scan.T_pipe_sensor(0)[:3, 3]
        axis = fit_axis(
            points, start_m=start, travel_m=scan.T_pipe_sensor(len(scan) - 1)[:3, 3] - start
        )
        nominal = scan.scenario.nominal_diameter_m
        split = split_windows(points, axis)
        truth = TrueBlockage(scan)
        runs = []
        for params in (kept, removed):
            t0 = time.process_time()
            secs = []
            for w, offsets in split:
                secs += measure_window(
                    offsets, axis, w, nominal_diameter_m=nominal, params=params, relative=True
                )
            cpu = time.process_time() - t0
            rows = {}
            for sec in secs:
                c = round(sec.chainage_start_m, 3)
                true = float(truth.section(np.array([c]))[0])
                rows[c] = (
                    sec.status.value,
                    sec.blockage_ratio,
                    true,
                    sec.blockage_uncertainty_ratio,
                )
            runs.append((rows, cpu))
        cells, changed = [], []
        for rows, _ in runs:
            ok = [(abs(b - t), u or 0.0) for st, b, t, u in rows.values() if st == "ok"]
            err = np.array([e for e, _ in ok]) * 100
            beyond = sum(e > u + 0.001 for e, u in ok)
            cells.append((len(ok), f"{err.mean():.3f} / {err.max():.2f}", beyond))
        (a, cpu_a), (b, cpu_b) = runs
        for c in sorted(set(a) & set(b)):
            ea = abs(a[c][1] - a[c][2]) * 100 if a[c][1] is not None else float("nan")
            eb = abs(b[c][1] - b[c][2]) * 100 if b[c][1] is not None else float("nan")
            if a[c][0] != b[c][0] or abs(ea - eb) > 0.2:
                changed.append(f"{c:.1f}: {a[c][0]} {ea:.2f} -> {b[c][0]} {eb:.2f} pp")
        print(
            f"| {draw.name} | {cells[0][0]} -> {cells[1][0]} | {cells[0][1]} -> {cells[1][1]} "
            f"| {cells[0][2]} -> {cells[1][2]} | {cpu_a:.1f} -> {cpu_b:.1f} "
            f"| {'; '.join(changed) or '-'} |",
            flush=True,
        )
    print("\n## veil: synthetic shadowed section, 5 seeds (truth: 0 % blocked)\n")
    print("| veil points (a degree; the wall: 111) | crown tail points | kept | removed |")
    print("|---:|---:|---|---|")
    for tail in (400, 0):
        for n in (250, 500, 750, 1000, 1500):
            cells = []
            for params in (kept, removed):
                oks, worst = 0, 0.0
                for seed in range(5):
                    m = measure_section(
                        _veil_section(np.random.default_rng(seed), n, tail),
                        chainage_start_m=1.0,
                        chainage_end_m=1.1,
                        nominal_diameter_m=0.5,
                        params=params,
                    )
                    if m.status.value == "ok":
                        oks += 1
                        worst = max(worst, abs(m.blockage_ratio) * 100)
                cells.append(f"{oks}/5 ok, {worst:.2f} pp")
            print(f"| {n} ({n / 60:.0f}) | {tail} | {cells[0]} | {cells[1]} |", flush=True)


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "_memory_child":
        print(json.dumps(_memory_child(float(sys.argv[2]))))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "what", choices=["accuracy", "obstacles", "real", "throughput", "memory", "veil", "all"]
    )
    parser.add_argument(
        "--draws",
        nargs="+",
        default=["combined", "mixed pixels"],
        help="veil: the sweep's draws whose names contain one of these",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--lengths", type=float, nargs="+", default=[10.0, 100.0])
    args = parser.parse_args()
    if args.what in ("accuracy", "all"):
        accuracy(args.seeds)
    if args.what in ("obstacles", "all"):
        obstacles(args.seeds)
    if args.what in ("real", "all"):
        real_scan()
    if args.what in ("throughput", "all"):
        throughput()
    if args.what in ("memory", "all"):
        memory(args.lengths)
    if args.what in ("veil", "all"):
        veil(args.draws)


if __name__ == "__main__":
    main()
