"""Reading frames' point times from PCD, PLY and ROS bag frames: what it costs.

    python benchmarks/bench_point_times.py
    python benchmarks/bench_point_times.py --points 45200 --repeats 20

A frame of ``--points`` random points (sensor frame, 1-3 m away) is written four ways: a
binary PCD with float32 x, y, z without and with Ouster's uint32 ``t`` (ns since the frame's
start), a binary PLY of doubles without and with a double ``time`` (s), and a ROS 1 bag of
three such frames as PointCloud2 without and with ``t``. Each is read as the run reads it
(``read_timed_frame`` with the frame interval; a bag through ``ScanArchive.iter_timed_frames``)
``--repeats`` times; the median ms per frame is printed, and the unit each time field was read
in (``point_times_s``: the frame's span against its interval).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from pipescan.storage.input.archive import open_archive
from pipescan.storage.input.pointfiles import read_timed_frame, write_points
from pipescan.storage.input.readers.bags import write_bag

INTERVAL_S = 0.1
TOML = 'asset_id = "MH1-MH2"\ninspected_at = 2024-05-17\nnominal_diameter_m = 0.5\n'


def _frame(n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = direction * rng.uniform(1.0, 3.0, (n, 1))
    t_ns = np.sort(rng.integers(0, 99_000_000, n)).astype(np.uint32)
    return points.astype(np.float32).astype(np.float64), t_ns


def _pcd(path: Path, points: np.ndarray, t_ns: np.ndarray | None) -> None:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + (
        [("t", "<u4")] if t_ns is not None else []
    )
    rows = np.empty(len(points), dtype=fields)
    rows["x"], rows["y"], rows["z"] = points.T
    names, sizes, types = "x y z", "4 4 4", "F F F"
    if t_ns is not None:
        rows["t"] = t_ns
        names, sizes, types = names + " t", sizes + " 4", types + " U"
    counts = " ".join("1" * len(fields))
    n = len(points)
    head = (
        f"VERSION 0.7\nFIELDS {names}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    path.write_bytes(head.encode("ascii") + rows.tobytes())


def _median_ms(read, repeats: int) -> float:
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        read()
        runs.append(1e3 * (time.perf_counter() - start))
    return statistics.median(runs)


def _bag_archive(root: Path, points: np.ndarray, t_ns: np.ndarray | None) -> Path:
    root.mkdir()
    (root / "inspection.toml").write_text(TOML, encoding="utf-8")
    t0 = 1_700_000_000 * 10**9
    frames = [(t0 + k * 10**8, points, t_ns) for k in range(3)]
    write_bag(root / "scan.bag", frames)
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=45_200)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    points, t_ns = _frame(args.points)
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        print(f"{args.points:,} points a frame, median of {args.repeats} reads, ms per frame")
        for name, write in (
            ("PCD", lambda p, t: _pcd(p, points, t)),
            ("PLY", lambda p, t: write_points(p, points, time_s=None if t is None else t / 1e9)),
        ):
            suffix = name.lower()
            for label, t in (("without times", None), ("with times", t_ns)):
                path = tmp_path / f"{label.replace(' ', '_')}.{suffix}"
                write(path, t)
                _, time_s = read_timed_frame(path, interval_s=INTERVAL_S)
                ms = _median_ms(
                    lambda path=path: read_timed_frame(path, interval_s=INTERVAL_S), args.repeats
                )
                span = "" if time_s is None else f", span {np.ptp(time_s) * 1e3:.1f} ms"
                print(f"  {name} {label}: {ms:.2f} ms{span}")
        for label, t in (("without times", None), ("with times", t_ns)):
            root = _bag_archive(tmp_path / label.replace(" ", "_"), points, t)
            with open_archive(root) as arc:
                _, _, time_s = next(arc.iter_timed_frames([1]))

                def read(arc=arc):
                    for _ in arc.iter_timed_frames([0, 1, 2]):
                        pass

                ms = _median_ms(read, args.repeats) / 3
            span = "" if time_s is None else f", span {np.ptp(time_s) * 1e3:.1f} ms"
            print(f"  bag (ROS 1) {label}: {ms:.2f} ms{span}")


if __name__ == "__main__":
    main()
