"""Registration: engines side by side, sections with estimated poses, parallel chunks, memory.

    python benchmarks/bench_registration.py engines     # accuracy and speed of every engine
    python benchmarks/bench_registration.py imu         # roll with and without the IMU prior
    python benchmarks/bench_registration.py sections    # defect chainages, blockage est vs true
    python benchmarks/bench_registration.py parallel    # register_chunk in 1 vs 2 threads/procs
    python benchmarks/bench_registration.py memory      # peak RSS, 100 vs 400 frames
    python benchmarks/bench_registration.py converge    # ICP stopping thresholds, short draws
    python benchmarks/bench_registration.py sweep       # issue 12's sweep through the flow
    python benchmarks/bench_registration.py sweep --layouts 12   # random defect layouts
    python benchmarks/bench_registration.py variants --variant '' source_voxel_m=0.06
                                                        # any registration parameters, same
    python benchmarks/bench_registration.py icp-work --archive DIR   # ICP's iterations a frame
    python benchmarks/bench_registration.py slips       # does the chainage ± cover unseen slips
    python benchmarks/bench_registration.py axial-error # is ICP's stated axial error honest
    python benchmarks/bench_registration.py odometer-scale  # learn the odometer's scale?
    python benchmarks/bench_registration.py pose-parts  # which pose error biases sections
    python benchmarks/bench_registration.py all

Options scale the runs down (``--travel-m``, ``--frames``). The scans are the simulator's:
`paper` (0.5 m pipe, 5 mm range noise, 1° attitude jitter, 2 % odometer scale error, full
452,000 points/s at 10 Hz) and `clean` with registration's range cut to 1.8 m, so that nothing
along the axis (not even the end wall) is in view. Speed is registration alone (frames are
generated before the clock starts) on whatever CPU this runs on; on a shared machine, compare
the rows of one run (ratios), not runs. Every figure is printed; nothing is asserted (the tests
do that on smaller cases).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from pipescan.core.registration import (
    RegistrationParams,
    Trajectory,
    chain_trajectories,
    plan_chunks,
    register_frames,
    registration_summary,
    trajectory_errors,
)
from pipescan.simulator.scan import get_scenario, simulate_scan
from pipescan.simulator.sweep import SectionScore
from pipescan.tasks import enginepool

# The sweep runs the flow on Prefect's ephemeral API, which reads this when it is imported
# (later, in the sweep): no telemetry, which without a network fails and prints a traceback
# into the benchmark's output.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

FRAME_RATE_HZ = 10.0
SECTION_RANGE_M = 5.0  # the flow's max_section_range_m

ENGINES: dict[str, RegistrationParams | str] = {
    "small_gicp gicp (default)": RegistrationParams(),
    "small_gicp gicp, source 3 cm": RegistrationParams(source_voxel_m=None),
    "small_gicp point_to_plane": RegistrationParams(method="point_to_plane"),
    "open3d point_to_plane": RegistrationParams(method="point_to_plane", engine="open3d"),
    "open3d_tensor point_to_plane": RegistrationParams(
        method="point_to_plane", engine="open3d_tensor"
    ),
    "paper point_to_point (Kabsch)": RegistrationParams(method="point_to_point"),
    "kiss-icp 1.3 (own odometry)": "kiss",
}


def _frames_in_memory(scan, *, odometer: bool = True) -> list[tuple[int, np.ndarray, float | None]]:
    return [(f.index, f.points_sensor, f.odometer_m if odometer else None) for f in scan.frames()]


def _kiss_trajectory(frames, max_range_m: float) -> Trajectory:
    """KISS-ICP's own pipeline (constant-velocity prior, no odometer, no degeneracy guard)."""
    from kiss_icp.config.config import (
        AdaptiveThresholdConfig,
        DataConfig,
        MappingConfig,
        RegistrationConfig,
    )
    from kiss_icp.config.parser import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    config = KISSConfig(
        data=DataConfig(max_range=max_range_m, min_range=0.0, deskew=False),
        mapping=MappingConfig(voxel_size=0.03, max_points_per_voxel=20),
        registration=RegistrationConfig(max_num_threads=1),
        adaptive_threshold=AdaptiveThresholdConfig(initial_threshold=0.1, min_motion_th=0.005),
    )
    odometry = KissICP(config)
    poses = []
    for _, points, _ in frames:
        odometry.register_frame(points.astype(np.float64), np.zeros(len(points)))
        poses.append(odometry.last_pose.copy())
    return Trajectory(np.asarray(poses), (), tuple(i for i, _, _ in frames), "constant_velocity")


def _run(frames, engine: RegistrationParams | str, max_range_m: float):
    started = time.perf_counter()
    if engine == "kiss":
        trajectory = _kiss_trajectory(frames, max_range_m)
    else:
        assert isinstance(engine, RegistrationParams)
        params = dataclasses.replace(engine, max_range_m=max_range_m)
        trajectory = register_frames(iter(frames), params)
    return trajectory, time.perf_counter() - started


def _row(name, scan, trajectory, seconds) -> str:
    e = trajectory_errors(trajectory.T_world_frame, scan.T_world_sensor)
    n = len(trajectory.frame_indices)
    odometer_m = abs(scan.odometer_m[-1] - scan.true_travel_m[-1])
    degenerate = sum(q.degenerate for q in trajectory.quality) if trajectory.quality else "-"
    fps = n / seconds
    return (
        f"| {name:30s} | {fps:6.0f} | {fps / FRAME_RATE_HZ:5.1f}× | {e.tilt_rms_deg:6.3f} | "
        f"{e.roll_rms_deg:5.2f} | {e.across_rms_m * 1e3:6.2f} | "
        f"{abs(e.along_final_m) * 1e3:8.1f} | "
        f"{e.along_max_m * 1e3:8.1f} | {odometer_m * 1e3:6.1f} | {degenerate!s:>5} |"
    )


HEADER = (
    "| engine                         | fr/s   | RT    | tilt°  | roll° | across | along end | "
    "along max | odo end | degen |\n"
    "|--------------------------------|-------:|------:|-------:|------:|-------:|---------:|"
    "---------:|-------:|------:|"
)


def bench_engines(args) -> None:
    cases = [
        ("paper", dict(travel_m=args.travel_m), 6.0, True),
        (
            "clean, range cut to 1.8 m (featureless)",
            dict(travel_m=min(args.travel_m, 3.0)),
            1.8,
            True,
        ),
        ("paper, no odometer", dict(travel_m=args.travel_m), 6.0, False),
    ]
    print(
        "Errors against the simulator's true poses. tilt = pitch/yaw RMS (deg), roll = roll "
        "about the axis RMS (deg), across = across-axis RMS (mm), along end/max = along-axis "
        "error at the end / largest (mm), odo end = the odometer's own error at the end (mm), "
        "degen = frames held to the prior along the axis. RT = real-time factor (recorded at "
        f"{FRAME_RATE_HZ:.0f} Hz / registration time); one thread per engine.\n"
    )
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n")
    for label, overrides, max_range_m, odometer in cases:
        name = "clean" if label.startswith("clean") else "paper"
        scan = simulate_scan(get_scenario(name, **overrides), seed=args.seed)
        frames = _frames_in_memory(scan, odometer=odometer)
        points = np.mean([len(f[1]) for f in frames])
        print(
            f"### {label}: {len(frames)} frames, {points:.0f} points/frame, "
            f"{scan.true_travel_m[-1]:.2f} m\n"
        )
        print(HEADER)
        engines = ENGINES if odometer else {k: ENGINES[k] for k in list(ENGINES)[:1]}
        for engine_name, engine in engines.items():
            if engine == "kiss" and args.no_kiss:
                continue
            trajectory, seconds = _run(frames, engine, max_range_m)
            print(_row(engine_name, scan, trajectory, seconds), flush=True)
            if not odometer and isinstance(engine, RegistrationParams):
                summary = registration_summary(trajectory, engine)
                print(f"\nstored summary: {summary.get('warning', 'no warning')}")
                for span in summary["unconstrained_spans"]:
                    print(f"  unconstrained: {span}")
        print()


# --------------------------------------------------------------------------- imu


def bench_imu(args) -> None:
    """The default engine on `paper`, with and without the simulated IMU's gravity prior."""
    scan = simulate_scan(get_scenario("paper", travel_m=args.travel_m), seed=args.seed)
    frames = _frames_in_memory(scan)
    print(
        f"### paper, IMU gravity prior: {len(frames)} frames, {scan.true_travel_m[-1]:.2f} m, "
        f"IMU noise {scan.scenario.imu_noise_deg}° per axis; "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n"
    )
    print(HEADER)
    for label, imu in (("small_gicp gicp, no IMU", False), ("small_gicp gicp + IMU", True)):
        rows = [(*f, scan.gravity_sensor[f[0]] if imu else None) for f in frames]
        started = time.perf_counter()
        trajectory = register_frames(iter(rows), RegistrationParams())
        print(_row(label, scan, trajectory, time.perf_counter() - started), flush=True)
    print()


# --------------------------------------------------------------------------- sections


def _cloud(frames, poses) -> np.ndarray:
    parts = []
    for (_, points, _), T in zip(frames, poses, strict=True):
        p = points.astype(np.float64)
        p = p[np.einsum("ij,ij->i", p, p) <= SECTION_RANGE_M**2]
        parts.append(p @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(parts)


def _measure(frames, poses):
    from pipescan.core.axis import fit_axis
    from pipescan.core.sections import measure_window, plan_windows

    points = _cloud(frames, poses)
    axis = fit_axis(points, start_m=poses[0][:3, 3], travel_m=poses[-1][:3, 3] - poses[0][:3, 3])
    chain = axis.chainage(points)
    sections = {}
    for w in plan_windows(max(0.0, chain.min()), chain.max(), step_m=0.1, window_m=2.0):
        inside = (chain >= w.start_m) & (chain < w.end_m)
        for s in measure_window(points[inside], axis, w, nominal_diameter_m=0.5):
            sections[round(s.chainage_start_m, 3)] = s
    return axis, sections


def bench_sections(args) -> None:
    scan = simulate_scan(get_scenario("paper", travel_m=args.travel_m), seed=args.seed)
    frames = _frames_in_memory(scan)
    true_poses = np.einsum(
        "ij,fjk->fik", np.linalg.inv(scan.T_world_sensor[0]), scan.T_world_sensor
    )
    s = scan.scenario
    defects = [("deformation", d) for d in s.deformations]
    defects += [("obstacle", b) for b in s.obstacles] + [("deposit", f) for f in s.deposits]
    for label, params in (
        ("small_gicp gicp (default)", RegistrationParams()),
        ("open3d point_to_plane", RegistrationParams(method="point_to_plane", engine="open3d")),
        ("paper point_to_point", RegistrationParams(method="point_to_point")),
    ):
        trajectory, seconds = _run(frames, params, params.max_range_m)
        est = trajectory.T_world_frame
        axis_est, sec_est = _measure(frames, est)
        _, sec_true = _measure(frames, true_poses)
        print(f"### {label} ({seconds:.1f} s)\n")
        # Where the pipeline puts each defect's ends: the true point on the invert at the
        # defect's start and end, seen from every frame 0.5-5 m before it, mapped through that
        # frame's estimated pose and the axis fitted on the estimated cloud.
        T_pipe_world0 = np.linalg.inv(scan.T_world_pipe) @ scan.T_world_sensor[0]
        print("| defect | true start-end (m) | located start-end (m) | worst error (m) |")
        print("|---|---|---|---|")
        for name, d in defects:
            located = []
            for x in (d.start_m, d.end_m):
                p_pipe = np.array([x, 0.0, -s.radius_m, 1.0])
                p_world0 = np.linalg.inv(T_pipe_world0) @ p_pipe
                seen = (scan.true_travel_m > x - 5.0) & (scan.true_travel_m < x - 0.5)
                ch = []
                for k in np.flatnonzero(seen):
                    p_sensor = np.linalg.inv(true_poses[k]) @ p_world0
                    ch.append(axis_est.chainage((est[k] @ p_sensor)[None, :3])[0])
                located.append(float(np.mean(ch)) if ch else float("nan"))
            worst = max(abs(located[0] - d.start_m), abs(located[1] - d.end_m))
            print(
                f"| {name} | {d.start_m:.2f}-{d.end_m:.2f} | {located[0]:.3f}-{located[1]:.3f} "
                f"| {worst:.3f} |"
            )
        both = [
            (c, sec_est[c], sec_true[c])
            for c in sorted(sec_est)
            if c in sec_true and sec_est[c].is_ok and sec_true[c].is_ok
        ]
        if not both:
            print("\nno section is ok with both the estimated and the true poses\n")
            continue
        diffs = np.array([abs(a.blockage_ratio - b.blockage_ratio) for _, a, b in both])
        truth = {round(t.chainage_start_m, 3): t for t in scan.true_sections()}
        print(
            f"\nblockage, estimated vs true poses, {len(both)} sections ok in both: "
            f"max |Δ| {diffs.max() * 100:.2f} pp, mean {diffs.mean() * 100:.2f} pp, "
            f"{int((diffs > 0.005).sum())} above 0.5 pp"
        )
        print("largest differences (pp; simulator truth beside them):")
        for i in np.argsort(diffs)[::-1][:6]:
            c, a, b = both[i]
            t = truth[c].blockage_ratio if c in truth else float("nan")
            print(
                f"  {c:5.1f} m: est poses {a.blockage_ratio * 100:5.2f}  true poses "
                f"{b.blockage_ratio * 100:5.2f}  truth {t * 100:5.2f}"
            )
        print()


# --------------------------------------------------------------------------- parallel


def _staged(root: str):
    """The archive as the flow's staging leaves it, once per run (it validates every frame's
    path; the chunk tasks then reopen it without doing so again)."""
    from pipescan.storage.input.archive import open_archive
    from pipescan.tasks.inspection import StagedArchive

    with open_archive(root) as arc:
        return StagedArchive(
            arc.name, Path(root), arc.meta, arc.content_hash, arc.frame_count, None
        )


def _register_chunk_in_worker(
    staged,
    first: int,
    last: int,
    params: RegistrationParams,
    engine_processes: int = 0,
    stride: int = 1,
):
    """The flow's register-chunk task body (``register_chunk.fn``): stream, register; with
    ``engine_processes``, in the engine pool's worker processes as the flow does."""
    from pipescan.tasks.inspection import register_chunk

    return register_chunk.fn(
        staged, first, last, params, engine_processes=engine_processes, stride=stride
    )


def _warm(_: int) -> int:
    import pipescan.tasks.inspection  # noqa: F401  (the imports a worker pays once)

    return os.getpid()


def _cpu_s() -> float:
    """CPU seconds of this process, of its children that ended and of those still running
    (the engine pool's workers; Linux ``/proc``)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime + _live_children_cpu_s()


def _live_children_cpu_s() -> float:
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/children") as fh:
                children = fh.read().split()
        except OSError:
            continue
        for child in children:
            try:
                with open(f"/proc/{child}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return total


def _gil_table() -> None:
    """Whether each heavy call lets a second Python thread run: CPU time per wall second of
    two threads against one (about 2× when the GIL is released and two cores are free)."""
    import threading

    import open3d as o3d
    import small_gicp

    rng = np.random.default_rng(0)
    target = rng.normal(size=(40_000, 3))
    source = target[:5_000] + 0.001
    cloud = small_gicp.PointCloud(target)
    tree = small_gicp.KdTree(cloud)
    small_gicp.estimate_normals_covariances(cloud, tree, 12)
    src = small_gicp.PointCloud(source)
    small_gicp.estimate_covariances(src, small_gicp.KdTree(src), 12)
    o3d_target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    o3d_target.estimate_normals()
    o3d_source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    reg = o3d.pipelines.registration

    def sg():
        for _ in range(20):
            small_gicp.align(cloud, src, tree, registration_type="GICP", max_iterations=10)

    def o3d_icp():
        for _ in range(10):
            reg.registration_icp(
                o3d_source, o3d_target, 0.5, np.eye(4),
                reg.TransformationEstimationPointToPlane(),
                reg.ICPConvergenceCriteria(max_iteration=10),
            )  # fmt: skip

    def o3d_voxel():
        for _ in range(60):
            o3d_target.voxel_down_sample(0.1)

    print("| call | CPU/wall, 1 thread | CPU/wall, 2 threads | GIL released |")
    print("|---|---:|---:|---|")
    for name, fn in (
        ("small_gicp.align (GICP)", sg),
        ("open3d registration_icp", o3d_icp),
        ("open3d voxel_down_sample", o3d_voxel),
    ):
        ratios = []
        for n_threads in (1, 2):
            threads = [threading.Thread(target=fn) for _ in range(n_threads)]
            wall, cpu = time.perf_counter(), time.process_time()
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            ratios.append((time.process_time() - cpu) / (time.perf_counter() - wall))
        released = "yes" if ratios[1] > 1.4 * ratios[0] else "no"
        print(f"| {name} | {ratios[0]:.2f} | {ratios[1]:.2f} | {released} |")


def bench_parallel(args) -> None:
    from pipescan.simulator.archive import write_simulated_archive

    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n")
    _gil_table()
    scan = simulate_scan(get_scenario("paper", travel_m=args.travel_m), seed=args.seed)
    params = RegistrationParams()
    with tempfile.TemporaryDirectory() as tmp:
        # Staged once, outside the timings: the flow stages before it registers (its own
        # stage in bench_chain), and each chunk task reopens the staged archive.
        staged = _staged(str(write_simulated_archive(scan, Path(tmp) / "scan")))
        n = len(scan.times_s)
        chunks = plan_chunks(n, (n + 1) // 2 + 1)
        _warm(0)
        rows = {}
        wall, cpu = time.perf_counter(), _cpu_s()
        serial = [_register_chunk_in_worker(staged, a, b, params) for a, b in chunks]
        rows["1 worker (serial)"] = (time.perf_counter() - wall, _cpu_s() - cpu)
        wall, cpu = time.perf_counter(), _cpu_s()
        one_two = [
            _register_chunk_in_worker(staged, a, b, dataclasses.replace(params, num_threads=2))
            for a, b in chunks
        ]
        rows["1 worker, small_gicp num_threads=2"] = (time.perf_counter() - wall, _cpu_s() - cpu)
        with ThreadPoolExecutor(2) as pool:
            wall, cpu = time.perf_counter(), _cpu_s()
            threaded = list(
                pool.map(lambda c: _register_chunk_in_worker(staged, *c, params), chunks)
            )
            rows["2 threads"] = (time.perf_counter() - wall, _cpu_s() - cpu)
            # What the inspect flow does on its thread pool (small_gicp holds the GIL, so each
            # call gets the pool's cores instead): pipescan.flows.runners.engine_threads.
            two = dataclasses.replace(params, num_threads=2)
            wall, cpu = time.perf_counter(), _cpu_s()
            threaded_two = list(
                pool.map(lambda c: _register_chunk_in_worker(staged, *c, two), chunks)
            )
            rows["2 threads, small_gicp num_threads=2 (engine_processes = false)"] = (
                time.perf_counter() - wall,
                _cpu_s() - cpu,
            )
            # What the inspect flow does on its thread pool: each chunk's task hands the chunk
            # to one of two lean worker processes (pipescan.tasks.enginepool), started while
            # the archive is staged.
            started = time.perf_counter()
            for ready in enginepool.prestart(2):
                ready.result()
            warm = time.perf_counter() - started
            cpu = _cpu_s()
            wall = time.perf_counter()
            processed = list(
                pool.map(lambda c: _register_chunk_in_worker(staged, *c, params, 2), chunks)
            )
            wall = time.perf_counter() - wall
            # CPU: this process's and the workers' while registering (not their start-up).
            rows["2 engine processes (the flow)"] = (wall, _cpu_s() - cpu)
            # The flow as it runs by default: every k-th frame, k chosen from the scan.
            from pipescan.flows.inspect import InspectionParams
            from pipescan.tasks.inspection import survey_scan

            cpu, wall = _cpu_s(), time.perf_counter()
            stride = survey_scan.fn(staged, **InspectionParams().stride_bounds()).stride
            strided_chunks = plan_chunks(n, (n // stride.stride + 1) // 2 + 1, stride.stride)
            strided = list(
                pool.map(
                    lambda c: _register_chunk_in_worker(staged, *c, params, 2, stride.stride),
                    strided_chunks,
                )
            )
            rows[f"2 engine processes, every {stride.stride} frames (the flow's default)"] = (
                time.perf_counter() - wall,
                _cpu_s() - cpu,
            )
            # The same without the early-return filter: what the filter costs.
            unfiltered = dataclasses.replace(params, early_return_ratio=0.0)
            cpu, wall = _cpu_s(), time.perf_counter()
            list(pool.map(lambda c: _register_chunk_in_worker(staged, *c, unfiltered, 2), chunks))
            rows["2 engine processes, early returns kept"] = (
                time.perf_counter() - wall,
                _cpu_s() - cpu,
            )
        print(f"\n{n} frames of the paper scan from an archive, chunks {chunks}\n")
        print("| workers | wall time (s) | speed-up | frames/s | real-time factor | cores used |")
        print("|---|---:|---:|---:|---:|---:|")
        base = rows["1 worker (serial)"][0]
        for name, (t, c) in rows.items():
            print(
                f"| {name} | {t:.2f} | {base / t:.2f}× | {n / t:.0f} | "
                f"{n / t / FRAME_RATE_HZ:.1f}× | {c / t:.2f} |"
            )
        print(f"\n(engine pool start-up and imports, paid once per process: {warm:.1f} s)")
        whole = register_frames((f.index, f.points_sensor, f.odometer_m) for f in scan.frames())
        parts_by = (
            ("serial", serial), ("num_threads=2", one_two), ("threads", threaded),
            ("threads, num_threads=2", threaded_two), ("engine processes", processed),
            (f"every {stride.stride} frames", strided),
        )  # fmt: skip
        for name, parts in parts_by:
            chained = chain_trajectories(parts)
            e = trajectory_errors(
                chained.T_world_frame, scan.T_world_sensor[list(chained.frame_indices)]
            )
            print(
                f"chained {name}: tilt {e.tilt_rms_deg:.3f}°, "
                f"across {e.across_rms_m * 1e3:.2f} mm, along end {e.along_final_m * 1e3:+.1f} mm"
            )
        e = trajectory_errors(whole.T_world_frame, scan.T_world_sensor)
        print(
            f"one chunk: tilt {e.tilt_rms_deg:.3f}°, across {e.across_rms_m * 1e3:.2f} mm, "
            f"along end {e.along_final_m * 1e3:+.1f} mm"
        )


# --------------------------------------------------------------------------- sweep


@dataclasses.dataclass
class DrawFigures:
    name: str
    frames: int
    """Frames registered (the flow's stride: every k-th of ``all_frames``)."""
    all_frames: int
    odometer_error_ratio: float
    travel_error_ratio: float
    score: SectionScore
    realtime: float
    seconds: float
    weak: int = 0
    smeared: int = 0
    stretches_worse: str = ""


def _flow_sections(archive: Path, work: Path):
    """Run the inspect-archive flow on the archive; its stored inspection."""
    from pipescan.flows.inspect import InspectionParams, inspect_archive
    from pipescan.flows.runners import make_task_runner
    from pipescan.settings import use_settings
    from pipescan.tasks.network import load_stored_inspection

    db_url = f"sqlite:///{work / 'sweep.db'}"
    flow = inspect_archive.with_options(task_runner=make_task_runner("threads", 2))
    with use_settings(database_url=db_url):  # a setting, not a flow parameter
        summary = flow(
            archive=str(archive),
            params=InspectionParams(),
            work_dir=str(work / "scratch"),
        )
    return load_stored_inspection.fn(db_url, summary.inspection_id)


def _registered(archive: Path, params: RegistrationParams):
    """The flow's registration, chunk by chunk in one thread, on the frames the flow uses
    (its stride chosen as the flow chooses it): trajectory and seconds (choosing included)."""
    from pipescan.core.instrument import instrumented
    from pipescan.flows.inspect import InspectionParams
    from pipescan.storage.input.archive import open_archive
    from pipescan.tasks.inspection import StagedArchive, register_chunk, survey_scan

    with open_archive(archive) as arc:
        staged = StagedArchive(
            arc.name, Path(archive), arc.meta, arc.content_hash, arc.frame_count, None
        )
    flow = InspectionParams()
    started = time.perf_counter()
    survey = survey_scan.fn(
        staged, **dataclasses.replace(flow, registration=params).stride_bounds()
    )
    # As the flow registers: with the scan's instrument (its blind zone, its map seed).
    params = instrumented(params, flow.measure, survey.instrument)[0]
    stride = survey.stride.stride
    chunks = plan_chunks(staged.frame_count, flow.chunk_frames, stride)
    parts = [register_chunk.fn(staged, a, b, params, stride=stride) for a, b in chunks]
    return chain_trajectories(parts), time.perf_counter() - started


def evaluate_draw(draw, work: Path) -> DrawFigures:
    """Simulate one draw, inspect it with the flow, and score its sections against the truth."""
    from pipescan.flows.inspect import InspectionParams
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.sweep import (
        TrueBlockage,
        along_axis_travel,
        score_sections,
        stretches_worse_than_odometer,
        true_shifts,
    )

    scan = simulate_scan(draw.scenario, draw.seed)
    archive = write_simulated_archive(scan, work / "archive")
    started = time.perf_counter()
    trajectory, reg_seconds = _registered(archive, RegistrationParams())
    stored = _flow_sections(archive, work)
    shifts = true_shifts(scan, trajectory, max_range_m=InspectionParams().max_section_range_m)
    score = score_sections(stored.sections, TrueBlockage(scan), shifts)
    travel = float(along_axis_travel(trajectory, scan)[1][-1])
    true_travel = float(scan.true_travel_m[-1])
    duration_s = len(scan) / scan.scenario.frame_rate_hz
    return DrawFigures(
        name=draw.name,
        frames=len(trajectory.frame_indices),
        all_frames=len(scan),
        odometer_error_ratio=float(scan.odometer_m[-1] / true_travel - 1.0),
        travel_error_ratio=travel / true_travel - 1.0,
        score=score,
        realtime=duration_s / reg_seconds,
        seconds=time.perf_counter() - started,
        weak=sum(s.status.value == "weak_registration" for s in stored.sections),
        smeared=sum(s.status.value == "smeared_wall" for s in stored.sections),
        stretches_worse="{}/{}".format(*stretches_worse_than_odometer(trajectory, scan)),
    )


SWEEP_HEADER = (
    "| draw | frames | odometer err % | travel err % | ok | ok away from edges | "
    "mean pp | max pp | dishonest (>2 pp within ±u) | dishonest at same chainage | "
    "worst pp | ok off beyond their blockage ± (+0.1 pp) | "
    "shadows ok (off beyond their ±)/all | shadows ok at their true place | u max m | "
    "ok beyond their ±u (most, m) | RT 1 core | weak reg. | smeared | "
    "0.5 m stretches worse than the odometer |\n"
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
)


def _sweep_row(f: DrawFigures) -> str:
    sc = f.score
    return (
        f"| {f.name} | {f.frames} of {f.all_frames} | {100 * f.odometer_error_ratio:+.2f} | "
        f"{100 * f.travel_error_ratio:+.2f} | {sc.ok} | {sc.ok_away} | {sc.mean_pp:.2f} | "
        f"{sc.max_pp:.2f} | {sc.dishonest} | {sc.dishonest_naive} | {sc.worst_pp:.1f} | "
        f"{sc.beyond_stated} | {sc.shadows_ok} ({sc.shadows_ok_wrong})/{sc.shadows} | "
        f"{sc.shadows_ok_true} | "
        f"{sc.u_max_m:.3f} | {sc.beyond_u} ({sc.beyond_u_max_m:.2f}) | "
        f"{f.realtime:.1f}× | {f.weak} | {f.smeared} | {f.stretches_worse} |"
    )


def bench_sweep(args) -> None:
    """Seeded draws over effects × scenes (pipescan.simulator.sweep), each inspected by the
    flow and scored against the simulator's truth."""
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    from prefect.testing.utilities import prefect_test_harness

    from pipescan.simulator.sweep import DISHONEST_PP, FLAT_PP, layout_draws, sweep_draws

    if args.layouts:
        draws = layout_draws(args.layouts, args.layout_seed)
    else:
        draws = sweep_draws(random_draws=args.random_draws, long_run=not args.no_long)
    if args.only:
        draws = [d for d in draws if any(o in d.name for o in args.only)]
    print(
        f"{len(draws)} draws; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs. "
        "ok away from edges: ok sections whose true blockage varies by less than "
        f"{FLAT_PP} pp within ±u (their chainage uncertainty); mean/max pp: their |error| at "
        f"the same chainage. dishonest: ok sections off by more than {DISHONEST_PP} pp from "
        "the truth anywhere within ±u; off beyond their blockage ±: ok sections whose stated "
        "95 % blockage uncertainty, plus 0.1 pp (the report's resolution), reaches the truth "
        "nowhere within ±u (one in twenty may). "
        "RT 1 core: seconds recorded / seconds registering "
        "(reading, filtering, ICP), one thread.\n"
    )
    print(SWEEP_HEADER, flush=True)
    figures = []
    with prefect_test_harness(server_startup_timeout=180):
        for draw in draws:
            with tempfile.TemporaryDirectory() as tmp:
                f = evaluate_draw(draw, Path(tmp))
            figures.append(f)
            print(_sweep_row(f), flush=True)
    worst = max(figures, key=lambda f: (f.score.dishonest, f.score.max_pp))
    print(f"\nworst draw: {worst.name} ({worst.seconds:.0f} s)")
    total_dishonest = sum(f.score.dishonest for f in figures)
    print(f"dishonest ok sections over all draws: {total_dishonest}")


# --------------------------------------------------------------------------- ICP's work


def bench_icp_work(args) -> None:
    """How much small_gicp iterates on a scan's frames: every second 60-frame chunk of an
    archive registered in memory on one thread, small_gicp's calls counted and timed. The
    count of iterations does not depend on the machine's load; the times do. Run it from two
    checkouts (``PYTHONPATH=<checkout>``) to compare versions."""
    import small_gicp

    from pipescan.storage.input.archive import open_archive
    from pipescan.tasks.staged import StagedArchive, register_staged_frames

    if not args.archive:
        sys.exit("icp-work: give --archive DIR (python benchmarks/bench_chain.py prepare)")
    iterations: list[int] = []
    align_cpu = [0.0]
    align = small_gicp.align

    def counted(*a, **k):
        started = time.thread_time()
        result = align(*a, **k)
        align_cpu[0] += time.thread_time() - started
        iterations.append(result.iterations)
        return result

    small_gicp.align = counted
    try:
        with open_archive(args.archive) as arc:
            staged = StagedArchive(
                name=arc.name, root=Path(args.archive), meta=arc.meta, content_hash="",
                frame_count=arc.frame_count, cloud_member=arc.cloud_member,
            )  # fmt: skip
        params = registration_params(args.set)
        register_staged_frames(staged, 0, 3, params)  # imports, first calls
        iterations.clear()
        align_cpu[0] = 0.0
        frames = 0
        started = time.process_time()
        for first in range(0, staged.frame_count - 60, 120):
            register_staged_frames(staged, first, first + 59, params)
            frames += 60
        cpu = time.process_time() - started
    finally:
        small_gicp.align = align
    print(
        f"{args.archive}: {frames} frames in {frames // 60} chunks, one thread, "
        f"registration {args.set or 'defaults'}, load "
        f"{os.getloadavg()[0]:.1f}\n"
        f"  small_gicp calls a frame       {len(iterations) / frames:.2f}\n"
        f"  iterations a frame (reported)  {sum(iterations) / frames:.2f}\n"
        f"  small_gicp CPU ms a frame      {1000 * align_cpu[0] / frames:.1f}\n"
        f"  registration CPU ms a frame    {1000 * cpu / frames:.1f} (reading included)"
    )


# --------------------------------------------------------------------------- convergence


def registration_params(variant: str) -> RegistrationParams:
    """``RegistrationParams`` with the fields a variant names changed: ``""`` for the
    defaults, else ``key=value`` pairs separated by commas (``none`` for None)."""
    defaults = RegistrationParams()
    changes: dict[str, object] = {}
    for item in filter(None, variant.split(",")):
        key, sep, value = item.partition("=")
        if not sep or not hasattr(defaults, key):
            sys.exit(f"variant {variant!r}: {item!r} is not FIELD=VALUE of RegistrationParams")
        default = getattr(defaults, key)
        if value.lower() == "none":
            changes[key] = None
        elif isinstance(default, str):
            changes[key] = value
        elif default is None:
            changes[key] = int(value) if value.isdigit() else float(value)
        else:
            changes[key] = type(default if default is not None else 0.0)(value)
    return dataclasses.replace(defaults, **changes)


def _variant_draw(job: tuple[str, str, int, int]) -> tuple[str, dict]:
    """One draw registered and measured in memory (the flow's stages without Prefect) with
    the registration parameters of a variant; its row and its figures."""
    from pipescan.core.registration import trajectory_errors
    from pipescan.simulator.sweep import (
        TrueBlockage,
        along_axis_travel,
        layout_draws,
        measure_scan,
        score_sections,
        stretches_worse_than_odometer,
        sweep_draws,
    )

    name, variant, layouts, layout_seed = job
    draws = layout_draws(layouts, layout_seed) if layouts else sweep_draws(long_run=False)
    draw = next(d for d in draws if d.name == name)
    scan = simulate_scan(draw.scenario, draw.seed)
    params = registration_params(variant)
    started = time.process_time()
    trajectory, sections = measure_scan(scan, params=params)
    cpu_s = time.process_time() - started
    score = score_sections(sections, TrueBlockage(scan))
    errors = trajectory_errors(
        trajectory.T_world_frame, scan.T_world_sensor[list(trajectory.frame_indices)]
    )
    worse, stretches = stretches_worse_than_odometer(trajectory, scan)
    _, est, true = along_axis_travel(trajectory, scan)
    travel_pct = 100 * ((est[-1] - est[0]) / (true[-1] - true[0]) - 1)
    frames = len(trajectory.frame_indices)
    row = (
        f"| {variant or 'defaults'} | {name} | {frames} | {travel_pct:+.2f} | "
        f"{1000 * errors.across_rms_m:.2f} | {errors.tilt_rms_deg:.3f} | {score.ok} | "
        f"{score.mean_pp:.2f} | {score.max_pp:.2f} | {score.dishonest} | {worse}/{stretches} |"
    )
    return row, {
        "frames": frames, "cpu_s": cpu_s, "worse": worse, "stretches": stretches,
        "max_pp": score.max_pp, "mean_pp": score.mean_pp, "dishonest": score.dishonest,
        "across_mm": 1000 * errors.across_rms_m, "ok": score.ok, "travel_pct": travel_pct,
    }  # fmt: skip


def _names(draws, only: list[str] | None) -> list[str]:
    """The draws' names, only those that contain one of ``only`` when given (``--only``)."""
    names = [d.name for d in draws]
    return [n for n in names if any(o in n for o in only)] if only else names


def bench_variants(args, variants: list[str] | None = None) -> None:
    """The sweep's short draws registered with several sets of registration parameters, in
    memory, two draws at a time: accuracy against the truth, and the CPU the whole of each
    draw's in-memory chain took (registration is most of it)."""
    from pipescan.simulator.sweep import layout_draws, sweep_draws

    layouts, seed = getattr(args, "layouts", 0), getattr(args, "layout_seed", 2026)
    draws = layout_draws(layouts, seed) if layouts else sweep_draws(long_run=False)
    names = _names(draws, args.only)
    variants = args.variant if variants is None else variants
    for variant in variants:
        registration_params(variant)  # a typo stops the run here, not an hour in
    print(
        f"{len(names)} draws × {len(variants)} variants; load average "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs. travel: registered against true "
        "travel along the axis, first to last frame; across/tilt: RMS pose error against the "
        "truth; mean/max pp: ok sections away from defect edges; dishonest: ok sections "
        "> 2 pp off within ±u; worse: 0.5 m stretches worse than the odometer by > 1 cm.\n"
    )
    print(
        "| registration | draw | frames | travel % | across rms mm | tilt rms ° | ok | mean pp"
        " | max pp | dishonest | worse |\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    totals = []
    with ProcessPoolExecutor(2) as pool:
        for variant in variants:
            figures = []
            jobs = [(n, variant, layouts, seed) for n in names]
            for row, f in pool.map(_variant_draw, jobs):
                print(row, flush=True)
                figures.append(f)
            totals.append((variant, figures))
    print(
        "\n| registration | CPU ms a frame (whole in-memory chain) | ok sections | worse "
        "stretches | max pp | largest mean pp | mean across mm | largest travel error % | "
        "dishonest |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    for variant, figures in totals:
        frames = sum(f["frames"] for f in figures)
        print(
            f"| {variant or 'defaults'} | "
            f"{1000 * sum(f['cpu_s'] for f in figures) / frames:.1f} | "
            f"{sum(f['ok'] for f in figures)} | "
            f"{sum(f['worse'] for f in figures)}/{sum(f['stretches'] for f in figures)} | "
            f"{max(f['max_pp'] for f in figures):.2f} | "
            f"{max(f['mean_pp'] for f in figures):.2f} | "
            f"{np.mean([f['across_mm'] for f in figures]):.2f} | "
            f"{max(abs(f['travel_pct']) for f in figures):.2f} | "
            f"{sum(f['dishonest'] for f in figures)} |"
        )


def bench_converge(args) -> None:
    """``variants`` over ICP's convergence thresholds (``--converged``)."""
    variants = []
    for setting in args.converged:
        rotation, translation = setting.split(",")
        variants.append(f"converged_rotation_rad={rotation},converged_translation_m={translation}")
    bench_variants(args, variants)


# --------------------------------------------------------------------------- slips


def _registered_in_memory(scan, params: RegistrationParams, frame_stride: int | None = 1):
    """A simulated scan registered in memory as the flow chunks it (60 used frames), chained:
    every ``frame_stride``-th frame (and the last), the flow's own choice when None."""
    from pipescan.simulator.sweep import register_scan

    return register_scan(scan, params=params, frame_stride=frame_stride)


def _slip_draw(job: tuple[str, int | None, float]) -> str:
    """One draw registered in memory as the flow registers it (every k-th frame, k the flow's
    choice unless given; the crawler's largest unseen slip stated as given, 0 for none); its
    row of ``bench_slips``."""
    from pipescan.simulator.sweep import (
        along_axis_travel,
        chainage_bound_misses,
        slip_draws,
        sweep_draws,
    )

    name, stride, stated_slip_m = job
    draw = next(d for d in [*slip_draws(), *sweep_draws(long_run=False)] if d.name == name)
    scan = simulate_scan(draw.scenario, draw.seed)
    params = RegistrationParams(odometer_slip_m=stated_slip_m)
    trajectory = _registered_in_memory(scan, params, stride)
    idx, est, true = along_axis_travel(trajectory, scan)
    error = est - true
    k = int(np.median(np.diff(idx))) if len(idx) > 1 else 1
    beyond, most = chainage_bound_misses(trajectory, scan)
    slips = trajectory.odometer_slips_m
    held = np.mean([q.degenerate for q in trajectory.quality])
    caught = f"{len(slips)} ({100 * max(slips):.0f} cm)" if slips else "0"
    return (
        f"| {name} | {len(idx)} of {scan.n_frames} (every {k}) | {len(scan.slip_frames)} | "
        f"{caught} | {100 * held:.0f} % | "
        f"{np.abs(error).max():.2f} | {trajectory.quality[-1].chainage_uncertainty_m:.2f} | "
        f"{beyond} | {most:.3f} |"
    )


def bench_slips(args) -> None:
    """Does the chainage uncertainty cover the odometer's unseen slips? Draws whose odometer
    slips often, and the sweep's short draws, registered in memory two at a time as the flow
    registers them (every k-th frame; ``--frame-stride`` sets k; ``--odometer-slip-m`` states
    the crawler's largest unseen slip, as ``inspection.toml`` can); each frame's registered
    position along the axis against the truth and its stated ±."""
    from pipescan.simulator.sweep import slip_draws, sweep_draws

    names = _names([*slip_draws(), *sweep_draws(long_run=False)], args.only)
    stated = f"{args.odometer_slip_m:g} m" if args.odometer_slip_m else "none"
    print(
        f"{len(names)} draws; stated slip (odometer_slip_m): {stated}; "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs. "
        "slip frames: frames during which the simulated odometer slipped; caught: slips the "
        "registration caught against features (the largest); held: frames resting on the "
        "odometer; beyond: frames further off along the axis than their chainage ± by more "
        "than 5 mm.\n"
    )
    print(
        "| draw | frames | slip frames | caught | held | max error m | ± at the end m | "
        "frames beyond their ± | most beyond m |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    rows = []
    with ProcessPoolExecutor(2) as pool:
        jobs = [(n, args.frame_stride, args.odometer_slip_m) for n in names]
        for row in pool.map(_slip_draw, jobs):
            print(row, flush=True)
            rows.append(row.split(" | "))
    caught = [r for r in rows if r[3] != "0"]
    missed = [r for r in caught if int(r[7]) > 0]
    worst = max((float(r[8].rstrip(" |")) for r in caught), default=0.0)
    print(
        f"\ndraws with a slip caught: {len(caught)}; with frames beyond their ±: {len(missed)} "
        f"(most beyond: {worst:.3f} m)"
    )


# --------------------------------------------------------------------------- odometer scale


SCALE_WINDOW_M = 0.5
"""Odometer travel over which ``odometer-scale`` takes one ratio of registered to odometer
travel (the slide window's length)."""


def _learned_scale_travel(est, odo, held, *, mode: str, clamp: float | None) -> np.ndarray:
    """Positions along the axis (m) with each held frame's odometer step multiplied by the
    scale learned so far from the frames ICP anchored: ``naive``, their registered travel
    over their odometer travel; ``median``, the median of that ratio over each
    ``SCALE_WINDOW_M`` of anchored odometer travel. Nothing is learned before 1 m of anchored
    travel; ``clamp`` bounds the scale to 1 ± the odometer's stated scale error."""
    d_est, d_odo = np.diff(est), np.diff(odo)
    anchored = ~held[1:]
    correction = np.zeros(len(est))
    ratios: list[float] = []
    num = den = win_est = win_odo = 0.0
    for i in range(len(d_est)):
        if mode == "naive":
            scale = num / den if den >= 1.0 else 1.0
        else:
            scale = float(np.median(ratios)) if den >= 1.0 and ratios else 1.0
        if clamp is not None:
            scale = min(max(scale, 1.0 - clamp), 1.0 + clamp)
        if anchored[i]:
            num, den = num + d_est[i], den + d_odo[i]
            win_est, win_odo = win_est + d_est[i], win_odo + d_odo[i]
            if win_odo >= SCALE_WINDOW_M:
                ratios.append(win_est / win_odo)
                win_est = win_odo = 0.0
        else:
            correction[i + 1] = (scale - 1.0) * d_odo[i]
    return est + np.cumsum(correction)


def _scale_draw(name: str) -> str:
    """One short sweep draw registered in memory as the flow chunks it; its row of
    ``bench_odometer_scale``."""
    from pipescan.simulator.sweep import along_axis_travel, sweep_draws

    draw = next(d for d in sweep_draws(long_run=False) if d.name == name)
    scan = simulate_scan(draw.scenario, draw.seed)
    params = RegistrationParams()
    trajectory = _registered_in_memory(scan, params)
    idx, est, true = along_axis_travel(trajectory, scan)
    odo = scan.odometer_m[idx] - scan.odometer_m[idx[0]]
    held = np.array([q.degenerate for q in trajectory.quality])
    cells = []
    for travel in (
        est,
        _learned_scale_travel(est, odo, held, mode="naive", clamp=None),
        _learned_scale_travel(
            est, odo, held, mode="median", clamp=params.odometer_scale_error_ratio
        ),
    ):
        cells.append(
            f"{100 * (travel[-1] / true[-1] - 1):+.2f} % / {np.abs(travel - true).max():.3f}"
        )
    return (
        f"| {name} | {100 * (odo[-1] / true[-1] - 1):+.2f} % | {100 * held.mean():.0f} % | "
        + " | ".join(cells)
        + " |"
    )


def bench_odometer_scale(args) -> None:
    """Would learning the odometer's scale where ICP anchors the frames help where it does
    not? The sweep's short draws registered in memory, two at a time; the frames held to the
    odometer then moved by the scale learned so far (causal, after the fact: registration
    itself is unchanged). An experiment, not what pipescan does."""
    from pipescan.simulator.sweep import sweep_draws

    names = _names(sweep_draws(long_run=False), args.only)
    print(
        f"{len(names)} draws; held: frames resting on the odometer. Each cell: travel error at "
        "the end / the largest error along the axis of any frame (m). naive: registered over "
        "odometer travel of the anchored frames so far; median: the median of that ratio per "
        f"{SCALE_WINDOW_M} m of anchored travel, clamped to the odometer's stated ±3 %.\n"
    )
    print(
        "| draw | odometer err | held | as registered | naive scale | median, clamped |\n"
        "|---|---:|---:|---:|---:|---:|"
    )
    with ProcessPoolExecutor(2) as pool:
        for row in pool.map(_scale_draw, names):
            print(row, flush=True)


# --------------------------------------------------------------------------- pose parts


def _clean_section_bias(scan, trajectory, poses: dict) -> str:
    """The sections of a scan whose frames are placed with ``poses`` (frame index → 4×4, in
    the trajectory's frame), measured as the flow does (``fit_axis``, ``measure_window``);
    the mean signed error of the ok sections where the truth is a clean pipe (0 %, flat
    within 0.15 m), and how many of them miss by more than their ± plus 0.1 pp."""
    from pipescan.core.axis import fit_axis
    from pipescan.core.sections import measure_window, plan_windows
    from pipescan.flows.inspect import InspectionParams
    from pipescan.simulator.sweep import FLAT_PP, STATED_TOLERANCE, TrueBlockage

    truth = TrueBlockage(scan)
    max_range_m = InspectionParams().max_section_range_m
    parts = []
    for frame in scan.frames():
        if frame.index not in poses:
            continue
        pts = frame.points_sensor.astype(np.float64)
        pts = pts[np.einsum("ij,ij->i", pts, pts) <= max_range_m**2]
        T = poses[frame.index]
        parts.append(pts @ T[:3, :3].T + T[:3, 3])
    points = np.concatenate(parts)
    positions = trajectory.positions_m()
    axis = fit_axis(points, start_m=positions[0], travel_m=positions[-1] - positions[0])
    chain = axis.chainage(points)
    errors, missed = [], 0
    for w in plan_windows(max(0.0, float(chain.min())), float(chain.max()), step_m=0.1):
        inside = (chain >= w.start_m) & (chain < w.end_m)
        for sec in measure_window(
            points[inside], axis, w, nominal_diameter_m=scan.scenario.nominal_diameter_m
        ):
            start = round(sec.chainage_start_m, 3)
            if not sec.is_ok or sec.blockage_ratio is None:
                continue
            flat = truth.variation(start, 0.15) * 100 <= FLAT_PP
            if float(truth.section(np.array([start]))[0]) != 0.0 or not flat:
                continue
            errors.append(sec.blockage_ratio)
            stated = sec.blockage_uncertainty_ratio or 0.0
            missed += abs(sec.blockage_ratio) > stated + STATED_TOLERANCE
    return f"{100 * np.mean(errors):+.3f} pp | {missed} of {len(errors)}"


def _placed(frame_indices, true: dict, rotation: dict, offsets=None) -> dict:
    """Poses with ``rotation``'s rotations and the true translations plus ``offsets`` (F, 3)."""
    poses = {}
    for k, i in enumerate(frame_indices):
        T = true[i].copy()
        T[:3, :3] = rotation[i][:3, :3]
        if offsets is not None:
            T[:3, 3] += offsets[k]
        poses[i] = T
    return poses


def bench_pose_parts(args) -> None:
    """Which part of the registered poses makes clean sections read more open than the
    truth? Each short sweep draw (``--only``) registered in memory as the flow chunks it;
    its frames then placed with a mix of the true and the registered poses, and with
    synthetic errors across the axis, and its clean sections measured."""
    from pipescan.simulator.sweep import sweep_draws

    names = _names(sweep_draws(long_run=False), args.only or ["random 0"])
    for name in names:
        draw = next(d for d in sweep_draws(long_run=False) if d.name == name)
        scan = simulate_scan(draw.scenario, draw.seed)
        trajectory = _registered_in_memory(scan, RegistrationParams())
        first = np.linalg.inv(scan.T_pipe_sensor(trajectory.frame_indices[0]))
        true = {i: first @ scan.T_pipe_sensor(i) for i in trajectory.frame_indices}
        est = dict(zip(trajectory.frame_indices, trajectory.T_world_frame, strict=True))
        axis = first[:3, :3] @ np.array([1.0, 0.0, 0.0])  # the simulator's pipe runs along x
        across_1 = np.cross(axis, [0.0, 0.0, 1.0])
        across_1 /= np.linalg.norm(across_1)
        across_2 = np.cross(axis, across_1)
        error = np.array([est[i][:3, 3] - true[i][:3, 3] for i in trajectory.frame_indices])
        along = np.outer(error @ axis, axis)
        across = error - along
        window = 31
        smooth = np.column_stack(
            [
                np.convolve(across @ b, np.ones(window) / window, mode="same")
                for b in (across_1, across_2)
            ]
        )
        smooth = smooth[:, :1] * across_1 + smooth[:, 1:] * across_2
        travelled = np.array([true[i][:3, 3] @ axis for i in trajectory.frame_indices])

        rms = np.sqrt((across**2).sum(axis=1).mean())
        rows = [
            ("true poses", _placed(trajectory.frame_indices, true, true)),
            ("registered poses", est),
            ("registered rotation, true translation", _placed(trajectory.frame_indices, true, est)),
            (
                "true rotation, registered translation",
                _placed(trajectory.frame_indices, true, true, error),
            ),
            (
                "only the along-axis part of the translation error",
                _placed(trajectory.frame_indices, true, true, along),
            ),
            (
                f"only the across-axis part ({1e3 * rms:.1f} mm RMS)",
                _placed(trajectory.frame_indices, true, true, across),
            ),
            (
                f"its smooth part ({window}-frame running mean)",
                _placed(trajectory.frame_indices, true, true, smooth),
            ),
            (
                "its frame-to-frame part",
                _placed(trajectory.frame_indices, true, true, across - smooth),
            ),
        ]
        per_axis = np.sqrt(np.mean(np.sum(across**2, axis=1)) / 2.0)
        jitter = np.random.default_rng(7).normal(0.0, per_axis, (len(across), 2))
        jitter = np.outer(jitter[:, 0], across_1) + np.outer(jitter[:, 1], across_2)
        rows.append(
            (
                f"independent shifts across the axis, {1e3 * per_axis:.2f} mm per axis",
                _placed(trajectory.frame_indices, true, true, jitter),
            )
        )
        amplitude = [np.sqrt(2.0 * np.mean((across @ b) ** 2)) for b in (across_1, across_2)]
        for period in (1.0, 3.0, 10.0):
            phase = 2.0 * np.pi * travelled / period
            drift = amplitude[0] * np.outer(np.sin(phase), across_1) + amplitude[1] * np.outer(
                np.sin(phase + 1.0), across_2
            )
            label = f"a sine across the axis, period {period:g} m, the same RMS"
            rows.append((label, _placed(trajectory.frame_indices, true, true, drift)))
        print(
            f"### {name}\n\nclean ok sections: mean signed error, and those off by more than "
            "their ± plus 0.1 pp\n\n| frames placed with | mean | beyond their ± |\n"
            "|---|---:|---:|",
            flush=True,
        )
        for label, poses in rows:
            print(f"| {label} | {_clean_section_bias(scan, trajectory, poses)} |", flush=True)


# --------------------------------------------------------------------------- axial error


def _axial_error_draw(name: str) -> dict:
    """One short sweep draw registered as the flow chunks it, recording for every frame with
    information along the axis ICP's own solution there (before the fusion weighs it) and its
    stated error ``1/√I``; returns the errors against the truth and the stated errors (m)."""
    from pipescan.core.registration.registrar import FrameRegistrar
    from pipescan.simulator.sweep import sweep_draws

    class Recording(FrameRegistrar):
        """Keeps ICP's solution and its information along the axis, frame by frame (a
        benchmark's view into the filter: ``_fuse`` is where the two are weighed)."""

        def __init__(self, params: RegistrationParams) -> None:
            super().__init__(params)
            self.icp: dict[int, tuple[np.ndarray, float]] = {}

        def _fuse(self, matches, pred, T, step_bound):
            self.icp[self.count] = (T[:3, 3].copy(), self._evidence(matches, T, pred)[0])
            return super()._fuse(matches, pred, T, step_bound)

    draw = next(d for d in sweep_draws(long_run=False) if d.name == name)
    scan = simulate_scan(draw.scenario, draw.seed)
    frames = [(f.index, f.points_sensor, f.odometer_m, f.gravity) for f in scan.frames()]
    errors, stated, anchored = [], [], []
    for a, b in plan_chunks(len(frames), 60):
        reg = Recording(RegistrationParams())
        poses, faults, weights = [], [], []
        for _, points, odometer, gravity in frames[a : b + 1]:
            T, quality = reg.add(points, odometer, gravity)
            poses.append(T[:3, 3])
            faults.append(quality.fault)
            weights.append(quality.along_axis_weight)
        # The truth in the chunk's frame: travel along the pipe axis from its first frame.
        axis = scan.T_world_sensor[a, :3, :3].T @ scan.T_world_pipe[:3, 0]
        true = scan.true_travel_m[a : b + 1] - scan.true_travel_m[a]
        error = np.asarray(poses) @ axis - true
        for k, (position, information) in reg.icp.items():
            if information <= 0 or faults[k] is not None:
                continue
            # ICP's solution against the truth, from where the frame before it was: the map
            # it aligned to carries the error the frames before it left.
            errors.append(position @ axis - true[k] - error[k - 1])
            stated.append(1.0 / np.sqrt(information))
            # Anchored: ICP carried the frames before it (mean weight of the last ten at
            # least ½), so the frame before it sits where the map's features put it.
            anchored.append(k > _ANCHOR_FRAMES and np.mean(weights[k - _ANCHOR_FRAMES : k]) >= 0.5)
    return {
        "name": name,
        "errors": np.asarray(errors),
        "stated": np.asarray(stated),
        "anchored": np.asarray(anchored, dtype=bool),
    }


def _axial_error_row(name: str, errors: np.ndarray, stated: np.ndarray, anchored) -> str:
    if len(errors) == 0:
        return f"| {name} | 0 | - | - | - | - | - | - | 0 | - |"
    z = np.abs(errors / stated)
    za = z[anchored]
    anchored_z = f"{len(za)} | {np.median(za):.2f}" if len(za) else "0 | -"
    return (
        f"| {name} | {len(z)} | {1000 * np.median(stated):.1f} | "
        f"{1000 * np.median(np.abs(errors)):.1f} | {1000 * np.sqrt(np.mean(errors**2)):.1f} | "
        f"{np.median(z):.2f} | {np.median(z) / _HONEST_MEDIAN_Z:.1f} | "
        f"{100 * np.mean(z > 3):.0f} % | {anchored_z} |"
    )


_HONEST_MEDIAN_Z = 0.6745  # the median of |z| for a standard normal error
_ANCHOR_FRAMES = 10


def bench_axial_error(args) -> None:
    """Is ICP's stated error along the axis honest? The fusion weighs ICP's correction along
    the axis by its information ``I`` (its stated error ``1/√I``) against the odometer's. On
    the sweep's short draws, registered as the flow does, each frame's ICP solution along the
    axis is compared with the truth: if ``1/√I`` is honest, the median of ``|error| / (1/√I)``
    is 0.67 and 0.3 % of frames lie beyond 3."""
    from pipescan.simulator.sweep import layout_draws, sweep_draws

    layouts, seed = getattr(args, "layouts", 0), getattr(args, "layout_seed", 2026)
    draws = layout_draws(layouts, seed) if layouts else sweep_draws(long_run=False)
    names = _names(draws, args.only)
    print(
        f"{len(names)} draws; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs. "
        "Frames with information along the axis, no fault; error: ICP's solution along the "
        "axis against the truth, from where the frame before it was; z: error over the stated "
        "error; too confident: the median |z| over an honest one's (0.67); anchored: frames whose "
        "ten frames before them ICP carried (mean weight ≥ ½), so that the frame before sits "
        "where the map's features put it.\n"
    )
    print(
        "| draw | frames | stated error, median mm | error, median mm | error, RMS mm | "
        "median z | too confident × | beyond 3 | anchored frames | anchored: median z |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    pooled: dict[str, list[np.ndarray]] = {"errors": [], "stated": [], "anchored": []}
    with ProcessPoolExecutor(2) as pool:
        for f in pool.map(_axial_error_draw, names):
            print(_axial_error_row(**f), flush=True)
            for key, values in pooled.items():
                values.append(f[key])
    print(_axial_error_row("all draws", **{k: np.concatenate(v) for k, v in pooled.items()}))


# --------------------------------------------------------------------------- memory


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _memory_child(frames: int) -> None:
    import threading

    speed = get_scenario("paper").speed_m_s
    scan = simulate_scan(get_scenario("paper", travel_m=frames * speed / FRAME_RATE_HZ), seed=1)
    # Warm up the imports and the first allocations, then sample the resident set while
    # registering (the peak of ru_maxrss is the imports', not registration's).
    register_frames(
        (f.index, f.points_sensor, f.odometer_m) for f in (scan.frame(0), scan.frame(1))
    )
    baseline = _rss_mib()
    peak = [baseline]
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], _rss_mib())
            time.sleep(0.005)

    sampler = threading.Thread(target=sample)
    sampler.start()
    trajectory = register_frames((f.index, f.points_sensor, f.odometer_m) for f in scan.frames())
    done.set()
    sampler.join()
    print(len(trajectory.frame_indices), f"{baseline:.1f}", f"{peak[0]:.1f}")


def bench_memory(args) -> None:
    print("| frames | RSS before (MiB) | peak RSS while registering (MiB) | growth (MiB) |")
    print("|---:|---:|---:|---:|")
    for frames in args.frames:
        out = subprocess.run(
            [sys.executable, __file__, "memory-child", "--frames", str(frames)],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.split()
        n, before, after = int(out[-3]), float(out[-2]), float(out[-1])
        print(f"| {n} | {before:.0f} | {after:.0f} | {after - before:.0f} |")
    print(
        "\nFrames are streamed from the simulator one at a time; what is kept is the local map "
        "(8 keyframes), the keyframe being grouped and the poses (128 bytes a frame). RSS is "
        "sampled every 5 ms."
    )


STEPS = {
    "engines": bench_engines,
    "imu": bench_imu,
    "sections": bench_sections,
    "parallel": bench_parallel,
    "memory": bench_memory,
    "sweep": bench_sweep,
    "converge": bench_converge,
    "variants": bench_variants,
    "icp-work": bench_icp_work,
    "slips": bench_slips,
    "odometer-scale": bench_odometer_scale,
    "pose-parts": bench_pose_parts,
    "axial-error": bench_axial_error,
}
"""Each benchmark by the name it is run with."""

ON_DEMAND = (
    "sweep",
    "converge",
    "variants",
    "icp-work",
    "slips",
    "odometer-scale",
    "pose-parts",
    "axial-error",
)
"""The benchmarks ``all`` leaves out: they simulate and register many draws (tens of minutes)
or need an archive of their own."""


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("what", choices=[*STEPS, "all", "memory-child"])
    parser.add_argument("--random-draws", type=int, default=8, help="sweep: random draws")
    parser.add_argument("--no-long", action="store_true", help="sweep: leave the 30 m run out")
    parser.add_argument(
        "--layouts",
        type=int,
        default=0,
        help="sweep, variants: run this many random defect layouts (layout_draws) instead "
        "of the sweep's draws",
    )
    parser.add_argument(
        "--layout-seed", type=int, default=2026, help="sweep, variants: seed of --layouts"
    )
    parser.add_argument(
        "--only",
        nargs="+",
        help="sweep, converge, variants, slips, odometer-scale, pose-parts, axial-error: "
        "draws named with one of these",
    )
    parser.add_argument(
        "--converged",
        nargs="+",
        default=["1e-4,1e-4", "5e-4,5e-4", "1.745e-3,1e-3"],
        help="converge: ICP stopping steps, ROTATION_RAD,TRANSLATION_M each",
    )
    parser.add_argument(
        "--variant",
        nargs="+",
        default=[""],
        help="variants: registration parameters, FIELD=VALUE[,FIELD=VALUE] each ('' = defaults)",
    )
    parser.add_argument(
        "--set",
        default="",
        help="icp-work: registration parameters, FIELD=VALUE[,FIELD=VALUE]",
    )
    parser.add_argument("--archive", help="icp-work: an archive of frames")
    parser.add_argument("--travel-m", type=float, default=4.5, help="length of the paper scan")
    parser.add_argument("--frames", type=int, nargs="+", default=[100, 400], help="memory runs")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument(
        "--frame-stride",
        type=int,
        default=None,
        help="slips: register every k-th frame (default: the flow's choice for each scan)",
    )
    parser.add_argument(
        "--odometer-slip-m",
        type=float,
        default=0.0,
        help="slips: the crawler's largest unseen slip, stated (inspection.toml's "
        "odometer_slip_m; default 0, none stated)",
    )
    parser.add_argument("--no-kiss", action="store_true", help="leave kiss-icp out")
    args = parser.parse_args()
    if args.what == "memory-child":
        _memory_child(args.frames[0])
        return
    for name, step in STEPS.items():
        if args.what == name or (args.what == "all" and name not in ON_DEMAND):
            print(f"\n## {name}\n", flush=True)
            step(args)


if __name__ == "__main__":
    main()
