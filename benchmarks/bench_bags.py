"""Ingest speed of ROS bags: a bag of 1,000 PointCloud2 frames (the simulator's forward-looking
sensor, about 25,000 points a frame) with odometry and IMU, in each storage.

    python benchmarks/bench_bags.py                # 1,000 frames, ROS 1 / ROS 2 sqlite3 / mcap
    python benchmarks/bench_bags.py --frames 200

For each bag: the time to open the archive (the one pass that lists the frames and reads the
odometry and IMU), the time to stream every frame into (N, 3) arrays as registration reads them
(frames per second, points per second, MB/s of bag), and the peak memory of a process that
does both (one process per bag, VmHWM, so that the bag's size shows whether memory is
bounded). Nothing is asserted. The machine is shared: quote ratios, not absolute times.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _bag_size(path: Path) -> int:
    files = path.rglob("*") if path.is_dir() else [path]
    return sum(f.stat().st_size for f in files if f.is_file())


def _child(archive: str) -> dict:
    from pipescan.storage.input.archive import open_archive

    t0 = time.perf_counter()
    with open_archive(archive) as arc:
        opened = time.perf_counter() - t0
        points = 0
        t1 = time.perf_counter()
        for _, pts in arc.iter_frames():
            points += len(pts)
        streamed = time.perf_counter() - t1
        frames = arc.frame_count
        member = arc.bag.member
    return {
        "open_s": opened,
        "stream_s": streamed,
        "frames": frames,
        "points": points,
        "bytes": _bag_size(Path(archive) / member),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "_child":
        print(json.dumps(_child(sys.argv[2])))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--keep", type=Path, help="write the bags here and keep them")
    args = parser.parse_args()

    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan

    # The paper's sensor at 0.15 m/s, 10 frames a second: travel for the frames asked.
    travel = args.frames / 10.0 * 0.15
    scan = simulate_scan(get_scenario("long", travel_m=travel, points_per_s=250_000.0), seed=0)
    n = min(args.frames, len(scan))
    print(f"## ROS bag ingest: {n} frames of the simulated forward-looking sensor")
    print("| storage | bag size | open (index, odometry, IMU) | stream every frame | frames/s |"
          " points/s | MB/s | peak RSS |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        for name in ("scan.bag", "scan.db3", "scan.mcap"):
            out = base / name.replace(".", "-")
            t0 = time.perf_counter()
            write_simulated_archive(scan, out, layout="bag", bag_name=name)
            written = time.perf_counter() - t0
            result = subprocess.run(
                [sys.executable, __file__, "_child", str(out)],
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            r = json.loads(result.stdout.strip().splitlines()[-1])
            mb = r["bytes"] / 1e6
            print(
                f"| {name.split('.')[-1]} | {mb:.0f} MB | {r['open_s']:.1f} s |"
                f" {r['stream_s']:.1f} s | {r['frames'] / r['stream_s']:.0f} |"
                f" {r['points'] / r['stream_s'] / 1e6:.1f} M | {mb / r['stream_s']:.0f} |"
                f" {r['peak_rss_mb']:.0f} MB |  (written in {written:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
