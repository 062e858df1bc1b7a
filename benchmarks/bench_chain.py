"""The whole chain, archive to stored sections, timed stage by stage against the recording.

    python benchmarks/bench_chain.py prepare --out /tmp/chain-scans --lengths 10 30
    python benchmarks/bench_chain.py run /tmp/chain-scans/long10-laz /tmp/chain-scans/long30-laz
    python benchmarks/bench_chain.py run --profile /tmp/chain-profile /tmp/chain-scans/long30-laz
    python benchmarks/bench_chain.py run --sections /tmp/chain-sections /tmp/chain-scans/long10-npy
    python benchmarks/bench_chain.py run --baseline /tmp/pipescan-main /tmp/chain-scans/long30-laz

``prepare`` simulates the ``long`` scenario (a forward-looking sensor, 10 frames a second, about
25k points a frame in a 0.5 m pipe, 0.15 m/s) over each length once as ``.npy`` frames, then
writes the same frames as LAZ and LAS (0.1 mm grid) and the same scan as one registered cloud
(``cloud.laz``, with GPS time; 49 M points for 30 m). ``--cloud-points 30e6`` also writes
each cloud thinned to 30 M points (``long30-cloud30M``: the same pipe and recording, a regular
share of the points kept). ``--slow`` also writes ``slow<L>-npy`` and ``slow<L>-laz``: the
same sensor and defects in a 0.6 m pipe at 0.1035 m/s, the kind of scan issue 16 was measured
on (30 m: 2,903 frames, 290 s). Scans are large (30 m: 2,000 frames, 0.6 GB as ``.npy``): write
them outside the repository.

``run`` runs ``pipescan inspect`` on each archive in a fresh process (SQLite database and work
directory in a temporary directory) and prints, per archive, the wall and CPU time of each
stage, the real-time factor (recording time / wall time) and the peak resident memory of the
process tree (pipescan, its task workers and the Prefect API server it starts). CPU time is
pipescan's process tree's and, apart, the Prefect API server's (without the benchmark's own
sampling of the tree); the chain's, surveyed to stored, is summed for both. Stages are
read from pipescan's own log lines, so what is timed is the command a user runs:

- ``start``: process start to the archive staged;
- ``surveyed``: the scan's instrument and stride chosen, by the first task: the Prefect API
  server is up (the chain is timed from here);
- ``register``: frames registered (all chunks);
- ``axis``: the pipe axis fitted;
- ``first window``: the first chainage window measured;
- ``sections``: every window measured, graded and stored.

With ``--baseline DIR`` (another pipescan checkout, e.g. ``git archive main | tar -x -C DIR``),
each scan runs under that version and then under this one, back to back: on a shared machine
the two rows of a pair are what can be compared. Each run's sections are exported (to a
scratch directory, or with ``--sections DIR`` to ``DIR/<scan>.csv``, ``-baseline.csv``), and
where the scan has ground truth each speed is printed beside the sections' mean coverage and
the share of the sections fully seen in truth that are measured (ok).

With ``--profile DIR``, each run is recorded by py-spy (all processes, 100 samples a second)
and the top 10 functions by cumulative time are printed (``DIR/<archive>.txt`` keeps the raw
collapsed stacks). Figures are printed, and each run is marked against issue 16's targets
(chain >= 10x, registration >= 20x; peak RSS of the longest scan of a kind over the
shortest <= 1.2x); nothing is asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from collections import Counter
from pathlib import Path

STAGES = (
    ("staged", re.compile(r"^archive .*: asset ")),
    # The scan's instrument, logged by the first task: the Prefect API is up by then. The
    # archive is staged before the API starts, so without this mark the API's start (8-10 s
    # on an idle machine) would be counted as registration.
    ("surveyed", re.compile(r"^sensor .*; minimum range ")),
    ("registered", re.compile(r"^(registered \d+ (of \d+ )?frames|axis fitted)")),
    ("axis", re.compile(r"^axis fitted")),
    ("first window", re.compile(r"^measured ")),
    ("stored", re.compile(r"^stored inspection ")),
)
PIPESCAN = (sys.executable, "-m", "pipescan.cli")


# --- prepare ----------------------------------------------------------------------------------


def _simulate(out: Path, length_m: float, layout: str) -> None:
    if (out / "inspection.toml").is_file():
        print(f"{out}: exists, kept")
        return
    print(f"simulating {length_m:g} m ({layout}) into {out} ...", flush=True)
    options = ["--scenario", "long", "--travel-m", str(length_m), "--layout", layout]
    subprocess.run(
        [*PIPESCAN, "simulate", str(out), *options],
        check=True,
        stdout=subprocess.DEVNULL,
    )


def _convert_frames(src: Path, dst: Path, suffix: str) -> None:
    """The same archive with every ``.npy`` frame written as ``suffix`` (LAS/LAZ: 0.1 mm)."""
    import numpy as np

    from pipescan.storage.input.pointfiles import write_points

    tmp = _start_derived(dst)
    if tmp is None:
        return
    (tmp / "frames").mkdir()
    for f in sorted((src / "frames").glob("*.npy")):
        write_points(tmp / "frames" / (f.stem + suffix), np.load(f).astype(np.float64))
    text = (src / "inspection.toml").read_text(encoding="utf-8")
    (tmp / "inspection.toml").write_text(
        re.sub(r'(file = "frames/\d+)\.npy"', rf'\1{suffix}"', text), encoding="utf-8"
    )
    _finish_derived(src, tmp, dst)


def _start_derived(dst: Path) -> Path | None:
    """The empty folder an archive derived from another is written in before it is renamed
    to ``dst``, or None when ``dst`` is already there (kept)."""
    if (dst / "inspection.toml").is_file():
        print(f"{dst}: exists, kept")
        return None
    print(f"writing {dst} ...", flush=True)
    tmp = dst.with_name(dst.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    return tmp


def _finish_derived(src: Path, tmp: Path, dst: Path) -> None:
    """``src``'s ground truth beside the derived archive in ``tmp``, renamed into ``dst``."""
    shutil.copytree(src / "ground_truth", tmp / "ground_truth")
    tmp.rename(dst)


def _thin_cloud(src: Path, dst: Path, points: int) -> None:
    """The same archive with a regular ``points`` of the cloud's points kept, in their order
    (row i is kept where ``(i + 1) points // total > i points // total``), with their
    GPS times: the same pipe and recording, scanned less densely."""
    import laspy
    import numpy as np

    tmp = _start_derived(dst)
    if tmp is None:
        return
    with laspy.open(src / "cloud.laz") as reader:
        total = reader.header.point_count
        if points >= total:
            raise SystemExit(f"--cloud-points {points:,}: the cloud has only {total:,}")
        header = laspy.LasHeader(
            point_format=reader.header.point_format.id, version=reader.header.version
        )
        header.scales, header.offsets = reader.header.scales, reader.header.offsets
        first = 0
        with laspy.open(tmp / "cloud.laz", mode="w", header=header, do_compress=True) as writer:
            for chunk in reader.chunk_iterator(2_000_000):
                i = np.arange(first, first + len(chunk), dtype=np.int64)
                writer.write_points(chunk[(i + 1) * points // total > i * points // total])
                first += len(chunk)
    shutil.copy(src / "inspection.toml", tmp / "inspection.toml")
    _finish_derived(src, tmp, dst)


SLOW_DIAMETER_M = 0.6
SLOW_SPEED_M_S = 0.1035
"""The ``slow`` scans: the ``long`` scenario's sensor and defects in a 0.6 m pipe at
0.1035 m/s, 290 s for 30 m (the scan issue 16 was measured on: 0.6 m, 2,895 frames, 290 s)."""


def _simulate_slow(out: Path, length_m: float) -> None:
    """The ``long`` scenario in a :data:`SLOW_DIAMETER_M` pipe at :data:`SLOW_SPEED_M_S`, as
    ``.npy`` frames (the CLI has no option for either, so it is written here)."""
    if (out / "inspection.toml").is_file():
        print(f"{out}: exists, kept")
        return
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan

    print(f"simulating {length_m:g} m, slow ({SLOW_DIAMETER_M} m pipe) into {out} ...", flush=True)
    scene = get_scenario(
        "long", travel_m=length_m, nominal_diameter_m=SLOW_DIAMETER_M, speed_m_s=SLOW_SPEED_M_S
    )
    write_simulated_archive(simulate_scan(scene, seed=0), out, layout="frames")


ROSETTE_SHARE = 0.3
"""The ``rosette`` scans: the ``long`` scenario seen by a non-repetitive pattern, one frame
covering this share of the field of view (the simulator's default effects otherwise)."""


def _simulate_rosette(out: Path, length_m: float, share: float) -> None:
    """The ``long`` scenario with a non-repetitive (rosette) pattern, as ``.npy`` frames."""
    if (out / "inspection.toml").is_file():
        print(f"{out}: exists, kept")
        return
    print(f"simulating {length_m:g} m, rosette ({share:.0%} a frame) into {out} ...", flush=True)
    options = ["--scenario", "long", "--travel-m", str(length_m), "--frame-coverage", str(share)]
    subprocess.run(
        [*PIPESCAN, "simulate", str(out), *options], check=True, stdout=subprocess.DEVNULL
    )


def prepare(
    out: Path,
    lengths: list[float],
    cloud: bool,
    cloud_points: list[float] = (),
    slow: bool = False,
    rosette: bool = False,
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for length in lengths:
        name = f"long{length:g}"
        npy = out / f"{name}-npy"
        _simulate(npy, length, "frames")
        _convert_frames(npy, out / f"{name}-laz", ".laz")
        _convert_frames(npy, out / f"{name}-las", ".las")
        if slow:
            slow_npy = out / f"slow{length:g}-npy"
            _simulate_slow(slow_npy, length)
            _convert_frames(slow_npy, out / f"slow{length:g}-laz", ".laz")
        if rosette:
            rosette_npy = out / f"rosette{length:g}-npy"
            _simulate_rosette(rosette_npy, length, ROSETTE_SHARE)
            _convert_frames(rosette_npy, out / f"rosette{length:g}-laz", ".laz")
        if cloud:
            _simulate(out / f"{name}-cloud", length, "cloud")
            for n in cloud_points:
                thinned = out / f"{name}-cloud{n / 1e6:g}M"
                _thin_cloud(out / f"{name}-cloud", thinned, int(n))


# --- run --------------------------------------------------------------------------------------


def _recording_s(archive: Path) -> float:
    """Seconds of recording: first to last frame time, or the cloud's GPS-time span."""
    with (archive / "inspection.toml").open("rb") as fh:
        doc = tomllib.load(fh)
    frames = doc.get("frames") or []
    if frames:
        return float(frames[-1]["time_s"] - frames[0]["time_s"])
    from pipescan.storage.input.pointfiles import read_point_time

    cloud = next(p for p in archive.iterdir() if p.name.startswith("cloud."))
    t = read_point_time(cloud)
    return float(t.max() - t.min()) if t is not None else float("nan")


def _child(archive: str, out_json: str) -> None:
    """Run ``pipescan inspect`` in this process, sampling the process tree, and write the
    stage marks and peaks to ``out_json``."""
    import logging

    import psutil

    me = psutil.Process()
    t0 = time.perf_counter()
    marks: dict[str, tuple[float, float]] = {}
    peak = {"tree_rss": 0, "main_rss": 0}
    stage_peak: dict[str, int] = {}  # the pipescan process's peak within each stage
    dead_cpu = {"s": 0.0}
    seen: dict[int, float] = {}
    api_cpu: dict[int, float] = {}  # the Prefect API server's CPU, as last read
    sampler_cpu = {"s": 0.0}

    def tree_cpu() -> tuple[float, float]:
        """CPU seconds of this process and its children, live or finished, without the Prefect
        API server (it serves the run; it is not the chain's work) and without this script's
        own sampling thread (listing the process tree reads every process of the machine);
        and, apart, the API server's CPU seconds."""
        total = sum(me.cpu_times()[:4]) - sampler_cpu["s"]
        live = {}
        for child in me.children(recursive=True):
            try:
                if "uvicorn" in " ".join(child.cmdline()) or "prefect" in child.name():
                    api_cpu[child.pid] = sum(child.cpu_times()[:2])
                    continue
                live[child.pid] = sum(child.cpu_times()[:2])
            except psutil.Error:
                continue
        for pid, cpu in seen.items():
            if pid not in live:
                dead_cpu["s"] += cpu
        seen.clear()
        seen.update(live)
        return total + sum(live.values()) + dead_cpu["s"], sum(api_cpu.values())

    def sample() -> None:
        while not done.is_set():
            started_cpu = time.thread_time()
            try:
                rss = me.memory_info().rss
                peak["main_rss"] = max(peak["main_rss"], rss)
                stage = next((s for s, _ in STAGES if s not in marks), "end")
                stage_peak[stage] = max(stage_peak.get(stage, 0), rss)
                for child in me.children(recursive=True):
                    with contextlib.suppress(psutil.Error):
                        rss += child.memory_info().rss
                peak["tree_rss"] = max(peak["tree_rss"], rss)
            except psutil.Error:
                pass
            sampler_cpu["s"] += time.thread_time() - started_cpu
            done.wait(0.25)  # listing the process tree costs ~3 % of a run at 0.1 s

    class Marks(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            message = record.getMessage()
            for stage, pattern in STAGES:
                if stage not in marks and pattern.search(message):
                    marks[stage] = (time.perf_counter() - t0, *tree_cpu())

    done = threading.Event()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    from pipescan.cli import _app, app

    setup_logging = _app._setup_logging

    def with_marks(verbose: bool) -> None:  # the CLI sets pipescan's handlers: add ours after
        setup_logging(verbose)
        logging.getLogger("pipescan").addHandler(Marks())

    _app._setup_logging = with_marks

    try:
        app(["inspect", archive, "--json"], standalone_mode=False)
    finally:
        done.set()
        sampler.join()
    marks["end"] = (time.perf_counter() - t0, *tree_cpu())
    Path(out_json).write_text(
        json.dumps(
            {
                "marks": marks,
                "peak": peak,
                "stage_peak": stage_peak,
                "sampler_cpu_s": sampler_cpu["s"],
            }
        ),
        encoding="utf-8",
    )


def _run_one(
    archive: Path,
    profile_dir: Path | None,
    sections_dir: Path | None,
    source: Path | None = None,
    tag: str = "",
    env_extra: dict | None = None,
) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-chain-") as tmp:
        env = dict(os.environ)
        if source is not None:  # another pipescan checkout, ahead of the installed one
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(source), env.get("PYTHONPATH")]))
        env.update(
            PREFECT_SERVER_ANALYTICS_ENABLED="false",
            PIPESCAN_DATABASE_URL=f"sqlite:///{tmp}/bench.db",
            PIPESCAN_WORK_DIR=f"{tmp}/work",
            PREFECT_HOME=f"{tmp}/prefect",
        )
        env.update(env_extra or {})
        out_json = Path(tmp) / "marks.json"
        cmd = [sys.executable, __file__, "_child", str(archive), str(out_json)]
        raw = None
        if profile_dir is not None:
            profile_dir.mkdir(parents=True, exist_ok=True)
            raw = profile_dir / f"{archive.name}{tag}.txt"
            py_spy = str(Path(sys.executable).with_name("py-spy"))
            if not Path(py_spy).is_file():
                raise SystemExit(
                    f"--profile needs py-spy beside {sys.executable}: "
                    "pip install -e '.[bench]' (or pip install py-spy)"
                )
            options = ["record", "--subprocesses", "--rate", "100", "--format", "raw"]
            cmd = [py_spy, *options, "--output", str(raw), "--", *cmd]
        started = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - started
        if proc.returncode != 0 or not out_json.is_file():
            print(proc.stdout[-3000:], proc.stderr[-3000:], sep="\n", file=sys.stderr)
            raise SystemExit(f"{archive}: pipescan inspect failed ({proc.returncode})")
        result = json.loads(out_json.read_text(encoding="utf-8"))
        summary = json.JSONDecoder().raw_decode(proc.stdout[proc.stdout.index("{") :])[0]
        if sections_dir is not None:  # the figures, to compare runs of two versions
            sections_dir.mkdir(parents=True, exist_ok=True)
            subprocess.run(
                [
                    *PIPESCAN,
                    "export",
                    "sections",
                    "-o",
                    str(sections_dir / f"{archive.name}{tag}.csv"),
                ],
                env=env,
                check=True,
            )
        result.update(process_wall=wall, summary=summary, raw_profile=str(raw) if raw else None)
        return result


_PLUMBING = re.compile(
    r"\((threading|concurrent/futures/|prefect/|anyio/|asyncio/|runpy|typer/|click/|"
    r"<frozen|bench_chain|pipescan/cli/|contextlib|site-packages/uvicorn|multiprocessing/|"
    r"<string>|pipescan/tasks/enginepool)"
)
"""Frames of the machinery around the work (threads, worker processes, the task engine, the
CLI): on every stack, they would fill the top of a cumulative list."""


SKIP = ("process ", "thread ")


def top_cumulative(raw: Path, n: int = 10) -> list[tuple[str, float]]:
    """The ``n`` functions with the largest share of samples on the stack (cumulative),
    from py-spy's collapsed stacks, leaving out the machinery around the work
    (:data:`_PLUMBING`); idle threads (waiting on a lock, a queue, a socket or a sleep) are
    left out, so shares are of the samples where work was done."""
    idle = re.compile(r"\b(wait|_wait_for_tstate_lock|select|poll|sleep|acquire|recv|get)\b")
    totals: Counter[str] = Counter()
    busy = 0
    for line in raw.read_text(encoding="utf-8", errors="replace").splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        frames = stack.split(";")
        leaf = frames[-1].split(" (")[0]
        if idle.search(leaf):
            continue
        busy += int(count)
        # A frame reads "function (file:line)": one function, whatever line it was on.
        names = {re.sub(r":\d+\)$", ")", f) for f in frames if not f.startswith(SKIP)}
        # (A spawned worker's command line holds a ';' and so reads as a frame of its own.)
        names = {f for f in names if not _PLUMBING.search(f) and "multiprocessing-fork" not in f}
        for name in names:
            totals[name] += int(count)
    return [(name, count / max(busy, 1)) for name, count in totals.most_common(n)]


def truth_errors(sections_csv: Path, archive: Path) -> str:
    """The exported sections against the simulator's ground truth: how many are ``ok``, and
    the error of their blockage, deposit height and deformation (percentage points: mean,
    95th percentile, max), and how often the blockage is within its stated 95 % uncertainty."""
    import csv

    import numpy as np

    from pipescan.simulator.archive import read_ground_truth

    _, truth = read_ground_truth(archive)
    true_by_start = {round(t.chainage_start_m, 1): t for t in truth}
    with sections_csv.open(encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r["status"] == "ok"]
    rows = [r for r in rows if round(float(r["chainage_start_m"]), 1) in true_by_start]
    parts = [f"{len(rows)} ok sections"]
    if not rows:
        return parts[0]
    for column in ("blockage_ratio", "deposit_height_ratio", "deformation_ratio"):
        err = np.array(
            [
                100
                * abs(
                    float(r[column])
                    - getattr(true_by_start[round(float(r["chainage_start_m"]), 1)], column)
                )
                for r in rows
                if r[column] != ""  # a figure a section does not have (e.g. no deposit)
            ]
        )
        name = column.removesuffix("_ratio").replace("_", " ")
        parts.append(
            f"{name} error mean {err.mean():.2f} / p95 {np.percentile(err, 95):.2f} / "
            f"max {err.max():.2f} pp"
        )
    within = np.mean(
        [
            abs(
                float(r["blockage_ratio"])
                - true_by_start[round(float(r["chainage_start_m"]), 1)].blockage_ratio
            )
            <= float(r["blockage_uncertainty_ratio"])
            for r in rows
        ]
    )
    parts.append(f"blockage within its stated uncertainty: {100 * within:.0f} %")
    return "; ".join(parts)


FULLY_SEEN = 0.999
"""A section the sensor saw all the way round, in truth (the simulator's coverage)."""

SECTION_RANGE_M = 5.0
"""pipescan's section range (``InspectionParams.max_section_range_m``)."""


def seen_and_measured(sections_csv: Path, archive: Path) -> dict:
    """The run's mean section coverage, and the share of the sections fully seen in truth
    that it measured (``ok``)."""
    import csv

    import numpy as np

    from pipescan.simulator.archive import read_ground_truth

    _, truth = read_ground_truth(archive)
    # Within the section range (5 m) of the sensor's last position (its true travel: the
    # sensor starts at the pipe's chainage 0): the truth's coverage counts returns up to the
    # sensor's own range.
    with (archive / "ground_truth" / "poses.csv").open(encoding="utf-8") as fh:
        travel_m = float(list(csv.DictReader(fh))[-1]["true_travel_m"])
    reach = truth[0].chainage_start_m + travel_m + SECTION_RANGE_M
    seen = {
        round(t.chainage_start_m, 1)
        for t in truth
        if t.coverage_ratio >= FULLY_SEEN and t.chainage_end_m <= reach
    }
    with sections_csv.open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    coverage = [float(r["coverage_ratio"]) for r in rows if r["coverage_ratio"] != ""]
    ok = {round(float(r["chainage_start_m"]), 1) for r in rows if r["status"] == "ok"}
    return {
        "coverage": float(np.mean(coverage)) if coverage else float("nan"),
        "seen": len(seen),
        "measured_share": len(ok & seen) / len(seen) if seen else float("nan"),
    }


def every_frame_lines(rows: list[dict]) -> list[str]:
    """Each run beside the same scan registering every frame: speed, coverage and the share of
    fully seen sections measured; a speed-up that loses more than ``SHARE_LOSS_MAX_PP`` of
    that share is not one."""
    lines = [
        "| scan | chain x | every frame x | speed-up | coverage | every frame | fully seen "
        "| measured | every frame | verdict |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    every = {r["scan"].removesuffix(" (every frame)"): r for r in rows if "(every" in r["scan"]}
    for r in rows:
        e = every.get(r["scan"].removesuffix(" (baseline)"))
        if e is None or e is r or "measured_share" not in r:
            continue
        loss = 100 * (e["measured_share"] - r["measured_share"])
        verdict = (
            "holds" if loss <= SHARE_LOSS_MAX_PP else f"NOT a speed-up: {loss:.1f} points lost"
        )
        lines.append(
            f"| {r['scan']} | {r['rt_chain']:.1f} | {e['rt_chain']:.1f} "
            f"| {r['rt_chain'] / e['rt_chain']:.2f} | {100 * r['coverage']:.1f} % "
            f"| {100 * e['coverage']:.1f} % | {r['seen']} | {100 * r['measured_share']:.1f} % "
            f"| {100 * e['measured_share']:.1f} % | {verdict} |"
        )
    return lines


STAGE_PATTERNS = (
    (
        "decoding",
        re.compile(
            r"laspy|lazrs|read_points|pointfiles|npyheader|numpy/lib/_npyio|"
            r"iter_frames \(pipescan/storage"
        ),
    ),
    (
        "filtering",
        re.compile(
            r"preprocess|voxel_downsample|crop_range|drop_early_returns|"
            r"seen_twice|remove_isolated|track_source"
        ),
    ),
    (
        "ICP",
        re.compile(
            r"small_gicp|_icp |_matches|_evidence|_fuse|track \(|add_keyframe|"
            r"registrar"
        ),
    ),
    ("placing", re.compile(r"write_buckets|iter_registered_points|FramePoses|scratch\.py")),
    ("axis", re.compile(r"fit_axis|fit_pipe_axis")),
    ("measuring", re.compile(r"measure_window|measure_section|measures\.py|contour|water\.py")),
    ("grading, storing, report", re.compile(r"grading|coding|repository|sqlalchemy|reports/")),
    ("Prefect, start-up", re.compile(r"prefect/|anyio/|uvicorn|importlib|<frozen")),
)
"""The stage a sample counts for: the first pattern, in this order, that a frame of its stack
matches (a stack from leaf up; ``other`` when none does)."""


def stage_shares(raw: Path) -> list[tuple[str, float]]:
    """Busy samples (as :func:`top_cumulative` counts them) by stage: each sample counts once,
    for the stage of the innermost frame that names one."""
    idle = re.compile(r"\b(wait|_wait_for_tstate_lock|select|poll|sleep|acquire|recv|get)\b")
    totals: Counter[str] = Counter()
    for line in raw.read_text(encoding="utf-8", errors="replace").splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        frames = stack.split(";")
        if idle.search(frames[-1].split(" (")[0]):
            continue
        stage = "other"
        for frame in reversed(frames):
            hit = next((name for name, pattern in STAGE_PATTERNS if pattern.search(frame)), None)
            if hit is not None:
                stage = hit
                break
        totals[stage] += int(count)
    busy = sum(totals.values()) or 1
    return [(stage, n / busy) for stage, n in totals.most_common()]


def _fmt_mb(b: float) -> str:
    return f"{b / 2**20:,.0f}"


EVERY_FRAME = {"PIPESCAN_FRAME_STRIDE": "1", "PIPESCAN_PLACED_SHARE": "1"}
"""The environment of a run that registers every frame and places every point of it: what a
speed-up is compared with."""

SHARE_LOSS_MAX_PP = 1.0
"""A speed-up that measures a share of the fully seen sections more than this many points
below registering every frame is not a speed-up."""


def run(
    archives: list[Path],
    profile_dir: Path | None,
    sections_dir: Path | None,
    baseline: Path | None = None,
    every_frame: bool = False,
) -> None:
    rows = []
    # With a baseline checkout, each scan runs under it and then under this pipescan, one
    # after the other: on a shared machine, compare the two rows of a pair. With
    # ``every_frame``, each scan also runs registering every frame, right after.
    variants = [("-baseline", baseline, None)] if baseline else []
    variants.append(("", None, None))
    if every_frame:
        variants.append(("-every-frame", None, EVERY_FRAME))
    scratch = None
    # The sections are always exported (to a scratch directory unless asked for): every
    # speed is printed beside the coverage and the share of fully seen sections measured.
    if sections_dir is None:
        scratch = tempfile.TemporaryDirectory(prefix="bench-chain-sections-")
        sections_dir = Path(scratch.name)
    runs = [(a, v) for a in archives for v in variants]
    for archive, (tag, source, env_extra) in runs:
        label = f" with {source}" if source else " registering every frame" if env_extra else ""
        print(f"running {archive}{label} ...", flush=True)
        result = _run_one(archive, profile_dir, sections_dir, source, tag, env_extra)
        recording = _recording_s(archive)
        marks = result["marks"]
        print(f"\n{archive.name}: {result['summary']['frame_count']} frames, "
              f"{result['summary']['point_count']:,} points, {recording:.0f} s recorded, "
              f"{result['summary']['section_count']} sections "
              f"({result['summary']['sections_ok']} ok)")  # fmt: skip
        print(f"  {'stage':<14}{'ends at s':>10}{'wall s':>9}{'CPU s':>8}{'API CPU s':>10}"
              f"{'peak RSS MB':>13}")  # fmt: skip
        prev_t, prev_c, prev_a = 0.0, 0.0, 0.0
        order = [s for s, _ in STAGES] + ["end"]
        for stage in order:
            if stage not in marks:
                continue
            t, c, a = marks[stage]
            stage_mb = result.get("stage_peak", {}).get(stage, 0) / 2**20
            print(f"  {stage:<14}{t:>10.1f}{t - prev_t:>9.1f}{c - prev_c:>8.1f}{a - prev_a:>10.1f}"
                  f"{stage_mb:>13,.0f}")  # fmt: skip
            prev_t, prev_c, prev_a = t, c, a
        # The chain starts once the archive is staged and the Prefect API is up (a frames
        # archive: its survey; a cloud: staged).
        start_t = marks.get("surveyed", marks["staged"])[0]
        chain = marks["stored"][0] - start_t
        frames = result["summary"]["frame_count"]
        reg = marks.get("registered", marks["axis"])[0] - start_t if frames else float("nan")
        peak = result["peak"]
        row = {
            "scan": archive.name
            + {"-baseline": " (baseline)", "-every-frame": " (every frame)"}.get(tag, ""),
            "frames": frames,
            "points": result["summary"]["point_count"],
            "recorded_s": recording,
            "start_s": start_t,
            "register_s": reg,
            "sections_s": marks["stored"][0] - marks.get("registered", marks["axis"])[0],
            "chain_s": chain,
            "total_s": marks["end"][0],
            "rt_register": recording / reg,
            "rt_chain": recording / chain,
            "rt_total": recording / marks["end"][0],
            "tree_rss_mb": peak["tree_rss"] / 2**20,
            "main_rss_mb": peak["main_rss"] / 2**20,
        }
        rows.append(row)
        print(f"  real time / chain (staged to stored): {row['rt_chain']:.1f}x; "
              f"registration {row['rt_register']:.1f}x; "
              f"with start-up {row['rt_total']:.1f}x")  # fmt: skip
        start = marks.get("surveyed", marks["staged"])
        chain_cpu = marks["stored"][1] - start[1]
        chain_api = marks["stored"][2] - start[2]
        row.update(chain_cpu_s=chain_cpu, chain_api_cpu_s=chain_api)
        print(f"  CPU, surveyed to stored: {chain_cpu:.1f} s pipescan (its process tree) + "
              f"{chain_api:.1f} s Prefect API server = {chain_cpu + chain_api:.1f} s, "
              f"{1e3 * (chain_cpu + chain_api) / max(frames, 1):.1f} ms a frame; whole run "
              f"{marks['end'][1] + marks['end'][2]:.1f} s (the benchmark's own sampling, "
              f"{result.get('sampler_cpu_s', 0.0):.1f} s, left out)")  # fmt: skip
        print(f"  peak RSS: process tree {_fmt_mb(peak['tree_rss'])} MB, "
              f"pipescan process {_fmt_mb(peak['main_rss'])} MB")  # fmt: skip
        if sections_dir is not None and (archive / "ground_truth").is_dir():
            csv_name = f"{archive.name}{tag}.csv"
            print("  against ground truth:", truth_errors(sections_dir / csv_name, archive))
            row.update(seen_and_measured(sections_dir / csv_name, archive))
            share = 100 * row["measured_share"]
            print(f"  coverage {100 * row['coverage']:.1f} %; of the {row['seen']} sections "
                  f"fully seen in truth, {share:.1f} % measured (ok)")  # fmt: skip
        if result["raw_profile"]:
            print("  where the time went, by stage (share of busy samples, all processes):")
            for stage, share in stage_shares(Path(result["raw_profile"])):
                print(f"    {100 * share:5.1f} %  {stage}")
            print("  top 10 by cumulative share of busy samples:")
            for name, share in top_cumulative(Path(result["raw_profile"])):
                print(f"    {100 * share:5.1f} %  {name}")
    print(TABLE_HEAD)
    for r in rows:
        print(TABLE_ROW.format(**r).replace("nan", "-"))
    print()
    measured = [r for r in rows if "measured_share" in r]
    if measured:
        print("| scan | register x | chain x | coverage | fully seen | measured |")
        print("|---|---:|---:|---:|---:|---:|")
        for r in measured:
            print(f"| {r['scan']} | {r['rt_register']:.1f} | {r['rt_chain']:.1f} "
                  f"| {100 * r['coverage']:.1f} % | {r['seen']} "
                  f"| {100 * r['measured_share']:.1f} % |")  # fmt: skip
        print()
    if every_frame:
        for line in every_frame_lines(rows):
            print(line)
        print()
    if scratch is not None:
        scratch.cleanup()
    for line in target_lines([r for r in rows if not r["scan"].endswith(")")]):
        print(line)


CHAIN_TARGET_X = 10.0
"""The whole chain, staged to stored, at least this many times faster than the recording."""
REGISTER_TARGET_X = 20.0
"""Registration alone (archives of frames), at least this many times faster."""
MEMORY_GROWTH_MAX = 1.2
"""Peak RSS of the longest scan of a kind over that of the shortest, at most."""


def _met(value: float, ok: bool, digits: int = 1) -> str:
    return f"{value:.{digits}f}x ({'met' if ok else 'NOT MET'})"


def target_lines(rows: list[dict]) -> list[str]:
    """Each run against the throughput targets, and memory growth between the longest and
    shortest scans of one kind (scans named ``<name><length>-<format>``, as ``prepare`` writes
    them: the same name and format at another length)."""
    lines = [f"targets: chain >= {CHAIN_TARGET_X:g}x, registration >= {REGISTER_TARGET_X:g}x, "
             f"peak RSS longest / shortest scan of a kind <= {MEMORY_GROWTH_MAX:g}x"]  # fmt: skip
    for r in rows:
        verdict = f"  {r['scan']}: chain {_met(r['rt_chain'], r['rt_chain'] >= CHAIN_TARGET_X)}"
        if r["frames"]:
            ok = r["rt_register"] >= REGISTER_TARGET_X
            verdict += f", registration {_met(r['rt_register'], ok)}"
        lines.append(verdict)
    kinds: dict[str, list[dict]] = {}
    for r in rows:
        # long10-laz and long100-laz are one kind (long-laz); issue30-laz is another.
        kinds.setdefault(re.sub(r"\d+(\.\d+)?(?=-)", "", r["scan"], count=1), []).append(r)
    for kind, same in sorted(kinds.items()):
        if len({r["recorded_s"] for r in same}) < 2:
            continue
        short = min(same, key=lambda r: r["recorded_s"])
        long = max(same, key=lambda r: r["recorded_s"])
        for what, key in (("process tree", "tree_rss_mb"), ("pipescan process", "main_rss_mb")):
            growth = long[key] / short[key]
            lines.append(
                f"  {kind}: peak RSS {long['scan']} / {short['scan']}, {what}: "
                f"{_met(growth, growth <= MEMORY_GROWTH_MAX, digits=2)}"
            )
    return lines


TABLE_HEAD = """
| scan | frames | points | recorded s | start-up s | register s | axis to stored s | chain s \
| total s | register x | chain x | total x | peak RSS tree MB | peak RSS pipescan MB |
|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|""".replace("\\\n", "")
TABLE_ROW = (
    "| {scan} | {frames:,} | {points:,} | {recorded_s:.0f} | {start_s:.1f} | {register_s:.1f} "
    "| {sections_s:.1f} | {chain_s:.1f} | {total_s:.1f} | {rt_register:.1f} | {rt_chain:.1f} "
    "| {rt_total:.1f} | {tree_rss_mb:,.0f} | {main_rss_mb:,.0f} |"
)
"""Columns: start-up is process start to the archive staged and the Prefect API up (imports,
staging, the API's start; for frames, up to the scan's survey, the first task's log line);
register is from there to every frame registered; axis to stored is the axis fit, placing,
measuring, grading and storing; chain is from the end of start-up to stored (the real-time
factors: recorded over these)."""


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "_child":
        _child(sys.argv[2], sys.argv[3])
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("prepare", help="simulate the scans once (outside the repository)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--lengths", type=float, nargs="+", default=[10.0, 30.0])
    p.add_argument("--no-cloud", action="store_true", help="skip the registered clouds")
    p.add_argument(
        "--cloud-points",
        type=float,
        nargs="*",
        default=[],
        help="also write each cloud thinned to this many points, as <scan>-cloud<N>M "
        "(30e6: the 30 M-point cloud of issue 16)",
    )
    p.add_argument(
        "--rosette",
        action="store_true",
        help=f"also write rosette<L>-npy and rosette<L>-laz: the long scenario seen by a "
        f"non-repetitive pattern, {ROSETTE_SHARE:.0%}% of the view a frame",
    )
    p.add_argument(
        "--slow",
        action="store_true",
        help="also write slow<L>-npy and slow<L>-laz: a 0.6 m pipe at 0.1035 m/s (290 s for "
        "30 m, as the scan of issue 16)",
    )
    r = sub.add_parser("run", help="time pipescan inspect on archives")
    r.add_argument("archives", type=Path, nargs="*")
    r.add_argument(
        "--baseline",
        type=Path,
        default=None,
        help="a checkout of another pipescan version: each scan runs under it, then this one",
    )
    r.add_argument("--profile", type=Path, default=None, help="record with py-spy into DIR")
    r.add_argument(
        "--top", type=Path, default=None, help="only print the top 10 of a recorded profile"
    )
    r.add_argument(
        "--sections", type=Path, default=None, help="export each run's sections as DIR/<scan>.csv"
    )
    r.add_argument(
        "--every-frame",
        action="store_true",
        help="also run each scan registering every frame and placing every point "
        "(PIPESCAN_FRAME_STRIDE=1, PIPESCAN_PLACED_SHARE=1), and compare coverage and the share "
        "of fully seen sections measured",
    )
    args = parser.parse_args()
    if args.command == "prepare":
        prepare(
            args.out, args.lengths, not args.no_cloud, args.cloud_points, args.slow, args.rosette
        )
    elif args.top is not None:
        for name, share in top_cumulative(args.top):
            print(f"{100 * share:5.1f} %  {name}")
    else:
        run(args.archives, args.profile, args.sections, args.baseline, args.every_frame)


if __name__ == "__main__":
    main()
