"""Peak memory and outcome of every crafted input of ``tests/hostile.py``, full size.

Each input is built once, then opened and validated (``open_archive`` + ``validate_archive``,
what ``pipescan inspect`` does before any processing) in a fresh Python process, which prints
its outcome, its peak RSS (VmHWM, reset after imports) above its RSS then, what it left in the work
directory, and whether the input changed. Genuine archives are measured the same way: the
target is that no crafted input costs more than 2x the largest genuine one.

    python benchmarks/bench_hostile.py                         # this checkout
    python benchmarks/bench_hostile.py --code /tmp/old-checkout  # another version's pipescan/
    python benchmarks/bench_hostile.py --scale 0.1 --only PLY  # smaller bombs, some cases

Each child process runs under an address-space cap (``--mem-cap-gib``, default 6) and a time
limit (``--timeout-s``), so measuring an old version on a bomb cannot take the machine down;
hitting either is reported as such. Genuine inputs with a lowered cap (``limits`` in the
corpus) are run with that cap on code that has caps, and without on code that has none.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

import numpy as np  # noqa: E402

from tests.hostile import CASES, TOML, _npy_bytes, fingerprint, frame  # noqa: E402

CHILD = r"""
import json, os, resource, sys, time
cap = int(sys.argv[4])
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
import numpy, laspy, open3d  # the baseline holds every library a reader may load
from pipescan.storage.input.archive import open_archive, validate_archive
from pipescan.core.errors import PipescanError
given, work, limits_json = sys.argv[1], sys.argv[2], sys.argv[3]
kwargs = {"workdir": work}
limits = json.loads(limits_json)
try:
    from pipescan.storage.input.limits import InputLimits
    kwargs["limits"] = InputLimits(**limits)
    has_caps = True
except ImportError:
    has_caps = False
def status_kib(key):
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith(key + ":"))
# The peak RSS (VmHWM) is inherited from the parent at fork; reset it ("5" in clear_refs),
# so that it measures this process from here on.
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")
base = status_kib("VmRSS")
t0 = time.perf_counter()
try:
    with open_archive(given, **kwargs) as arc:
        summary = validate_archive(arc)
    outcome = f"accepted: {summary.point_count:,} points"
except PipescanError as exc:
    outcome = f"refused: {type(exc).__name__}: {exc.reason}"
except MemoryError as exc:
    outcome = "MemoryError (raw)"
except RecursionError as exc:
    outcome = "RecursionError (raw)"
except BaseException as exc:
    outcome = f"{type(exc).__name__} (raw): {exc}"
peak = status_kib("VmHWM")
import pipescan
print(json.dumps({"outcome": outcome, "base_kib": base, "peak_kib": peak,
                  "seconds": time.perf_counter() - t0, "caps": has_caps,
                  "code": os.path.dirname(os.path.dirname(pipescan.__file__))}))
"""


LAYER_CHILD = r"""
import json, os, resource, sys, time
cap = int(sys.argv[4])
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
import numpy, shapely, pyogrio
from pipescan.core.errors import PipescanError
from pipescan.storage.input.network_layer import read_network_layer
given, limits = sys.argv[1], json.loads(sys.argv[3])
kwargs = {}
try:
    from pipescan.storage.input.network_layer import LayerLimits
    kwargs["limits"] = LayerLimits(**limits)
except ImportError:
    pass
def status_kib(key):
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith(key + ":"))
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")
base = status_kib("VmRSS")
t0 = time.perf_counter()
try:
    layer = read_network_layer(__import__("pathlib").Path(given), id_field="FACILITYID", **kwargs)
    outcome = f"accepted: {len(layer.pipes):,} pipes ({layer.crs})"
except PipescanError as exc:
    outcome = f"refused: {type(exc).__name__}: {exc.reason}"
except MemoryError:
    outcome = "MemoryError (raw)"
except BaseException as exc:
    outcome = f"{type(exc).__name__} (raw): {exc}"
print(json.dumps({"outcome": outcome, "base_kib": base, "peak_kib": status_kib("VmHWM"),
                  "seconds": time.perf_counter() - t0, "caps": bool(kwargs)}))
"""


def layer_cases() -> list[tuple[str, object]]:
    """GIS layers for ``pipescan network import`` (issue 56): each must be refused."""
    import sqlite3
    import zipfile

    import shapely

    from tests import test_gis

    def legit(where: Path, name: str = "net.gpkg", **kwargs) -> Path:
        lines, fields = test_gis.network_lines(), test_gis.network_fields()
        return test_gis.write_layer(where / name, lines, fields, **kwargs)

    def view_of_zeroblobs(where: Path, scale: float) -> str:
        path = legit(where)
        size = max(64 << 20, int((1 << 30) * scale))
        with sqlite3.connect(path) as conn:
            conn.executescript(
                'ALTER TABLE "pipes" RENAME TO "pipe_rows"; CREATE VIEW "pipes" AS SELECT fid, '
                f'FACILITYID, zeroblob({size}) AS geom FROM "pipe_rows";'
            )
        return str(path)

    def zipped_padding(where: Path, scale: float) -> str:
        path = legit(where)
        size = max(64 << 20, int((4300 << 20) * scale))
        packed = where / "net.zip"
        with (
            zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as zf,
            zf.open("net.gpkg", "w", force_zip64=True) as fh,
        ):
            fh.write(path.read_bytes())
            block = bytes(1 << 20)
            for _ in range(size >> 20):
                fh.write(block)
        path.unlink()
        return str(packed)

    def long_line(where: Path, scale: float) -> str:
        n = max(100_000, int(10_000_000 * scale))
        x = test_gis.X0 + np.arange(n) * 0.001
        line = shapely.linestrings(np.column_stack([x, np.full(n, test_gis.Y0)]))
        path = where / "long.gpkg"
        test_gis.write_layer(path, [], {"FACILITYID": ["SW-1"]}, geometries=[line])
        return str(path)

    def feet(where: Path, scale: float) -> str:
        return str(legit(where, crs="EPSG:2227"))

    def ed50_degrees(where: Path, scale: float) -> str:
        return str(legit(where, crs="EPSG:4230"))

    return [
        ("layer: GeoPackage view of 1 GiB zeroblobs", view_of_zeroblobs),
        ("layer: zipped GeoPackage unpacking to 4.3 GB", zipped_padding),
        ("layer: one line of 10 M vertices", long_line),
        ("layer: CRS in US survey feet (EPSG:2227)", feet),
        ("layer: CRS in degrees (EPSG:4230)", ed50_degrees),
    ]


def legit_cases() -> list[tuple[str, object]]:
    """Genuine archives, the reference for "the largest legitimate allocation"."""

    def frames_zip(where: Path, scale: float) -> str:
        import zipfile

        path = where / "frames.zip"
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("inspection.toml", TOML)
            for i in range(20):
                zf.writestr(f"frames/{i:06d}.npy", _npy_bytes(frame(200_000, seed=i)))
        return str(path)

    def cloud_laz(where: Path, scale: float) -> str:
        from pipescan.storage.input.pointfiles import write_points

        root = where / "scan"
        root.mkdir()
        (root / "inspection.toml").write_bytes(TOML)
        rng = np.random.default_rng(0)
        n = 5_000_000
        angle = rng.uniform(0, 2 * np.pi, n)
        pts = np.column_stack([rng.uniform(0, 100, n), 0.25 * np.cos(angle), 0.25 * np.sin(angle)])
        write_points(root / "cloud.laz", pts)
        return str(root)

    def cloud_ply(where: Path, scale: float) -> str:
        from pipescan.storage.input.pointfiles import write_points

        root = where / "scan"
        root.mkdir()
        (root / "inspection.toml").write_bytes(TOML)
        write_points(root / "cloud.ply", frame(5_000_000))
        return str(root)

    return [
        ("genuine: 20 frames of 200k points, .npy in a zip", frames_zip),
        ("genuine: a 5 M-point cloud.laz", cloud_laz),
        ("genuine: a 5 M-point cloud.ply", cloud_ply),
    ]


def run_case(
    code: Path, build, limits: dict, scale: float, cap: int, timeout_s: float, child: str = CHILD
) -> dict:
    with tempfile.TemporaryDirectory(prefix="pipescan-hostile-") as tmp:
        where = Path(tmp) / "inputs"
        where.mkdir()
        given = build(where, scale)
        before = fingerprint(where)
        work = Path(tmp) / "work"
        child_tmp = Path(tmp) / "tmpdir"  # the child's $TMPDIR: what it leaves there is counted
        child_tmp.mkdir()
        env = dict(os.environ, PYTHONPATH=str(code), TMPDIR=str(child_tmp))
        args = [sys.executable, "-c", child, given, str(work), json.dumps(limits), str(cap)]
        started = time.perf_counter()
        try:
            # cwd elsewhere: "python -c" puts the working directory first on sys.path.
            done = subprocess.run(
                args,
                env=env,
                cwd=tmp,
                capture_output=True,
                text=True,
                timeout=timeout_s,
                check=False,
            )
            lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
            if lines:
                result = json.loads(lines[-1])
            else:
                tail = (done.stderr.strip().splitlines() or ["?"])[-1]
                result = {"outcome": f"crashed (exit {done.returncode}): {tail[:120]}"}
        except subprocess.TimeoutExpired:
            result = {"outcome": f"timeout after {timeout_s:.0f} s"}
        result.setdefault("seconds", time.perf_counter() - started)
        left = list(work.rglob("*")) if work.exists() else []
        result["left_files"] = sum(1 for p in left if p.is_file())
        result["left_bytes"] = sum(p.stat().st_size for p in left if p.is_file())
        result["input_unchanged"] = fingerprint(where) == before
        result["left_tmp"] = sum(1 for p in child_tmp.rglob("*") if not p.is_dir())
        shutil.rmtree(work, ignore_errors=True)
        return result


def _met(row: dict) -> bool:
    """Issue 56's targets for one crafted input."""
    return (
        row["outcome"].startswith("refused")
        and row["peak_mib"] < 1024
        and row["seconds"] < 60
        and row["left_files"] == 0
        and row.get("left_tmp", 0) == 0
        and row["input_unchanged"]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", type=Path, default=ROOT, help="folder holding pipescan/")
    parser.add_argument("--scale", type=float, default=1.0, help="size of the bombs (1: full)")
    parser.add_argument("--only", default="", help="regex: only cases whose name matches")
    parser.add_argument("--mem-cap-gib", type=float, default=6.0)
    parser.add_argument("--timeout-s", type=float, default=180.0)
    parser.add_argument("--json", type=Path, help="also write the rows to this file")
    args = parser.parse_args()
    cap = int(args.mem_cap_gib * (1 << 30))
    rows = []
    cases = [(c.cls, c.name, c.build, c.limits) for c in CASES]
    cases += [("genuine", name, build, {}) for name, build in legit_cases()]
    cases += [("layer", name, build, {}) for name, build in layer_cases()]
    for cls, name, build, limits in cases:
        if args.only and not re.search(args.only, name):
            continue
        child = LAYER_CHILD if cls == "layer" else CHILD
        result = run_case(args.code, build, limits, args.scale, cap, args.timeout_s, child)
        peak = (result.get("peak_kib", 0) - result.get("base_kib", 0)) / 1024
        rows.append({"class": cls, "input": name, "peak_mib": peak, **result})
        print(
            f"{cls:13} {name[:52]:52} {peak:8.1f} MiB {result['seconds']:7.2f} s  "
            f"left {result['left_files']} files {result['left_tmp']} tmp  "
            f"{'unchanged' if result['input_unchanged'] else 'CHANGED'}  {result['outcome'][:90]}",
            flush=True,
        )
    genuine = [r["peak_mib"] for r in rows if r["class"] == "genuine"]
    over = [r for r in rows if r["class"] != "genuine" and not _met(r)]
    print(
        f"\n{len(rows) - len(over)} of {len(rows)} inputs within the targets (refused in one "
        "line, peak < 1 GiB, < 60 s, nothing left in the work folder or $TMPDIR, input "
        "unchanged)"
    )
    for r in over:
        print(f"  NOT MET: {r['input']}: {r['outcome'][:100]}")
    crafted = [r for r in rows if r["class"] != "genuine"]
    if genuine and crafted:
        worst = max(crafted, key=lambda r: r["peak_mib"])
        print(
            f"\nlargest genuine: {max(genuine):.1f} MiB; largest crafted: {worst['peak_mib']:.1f} "
            f"MiB ({worst['input']}): {worst['peak_mib'] / max(genuine):.2f}x"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
