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


def run_case(code: Path, build, limits: dict, scale: float, cap: int, timeout_s: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="pipescan-hostile-") as tmp:
        where = Path(tmp) / "inputs"
        where.mkdir()
        given = build(where, scale)
        before = fingerprint(where)
        work = Path(tmp) / "work"
        env = dict(os.environ, PYTHONPATH=str(code))
        args = [sys.executable, "-c", CHILD, given, str(work), json.dumps(limits), str(cap)]
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
        shutil.rmtree(work, ignore_errors=True)
        return result


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
    for cls, name, build, limits in cases:
        if args.only and not re.search(args.only, name):
            continue
        result = run_case(args.code, build, limits, args.scale, cap, args.timeout_s)
        peak = (result.get("peak_kib", 0) - result.get("base_kib", 0)) / 1024
        rows.append({"class": cls, "input": name, "peak_mib": peak, **result})
        print(
            f"{cls:13} {name[:52]:52} {peak:8.1f} MiB {result['seconds']:7.2f} s  "
            f"left {result['left_files']} files  "
            f"{'unchanged' if result['input_unchanged'] else 'CHANGED'}  {result['outcome'][:90]}",
            flush=True,
        )
    genuine = [r["peak_mib"] for r in rows if r["class"] == "genuine"]
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
