"""Repeatability: how far apart two surveys of an unchanged pipe read its blockage.

A change between surveys is only a change when it is larger than what two surveys of the same,
unchanged pipe disagree by. This script measures that: it simulates N surveys of one scene
(the paper's pipe, nothing grows between them), each with its own seed and with the sensor and
crawler effects drawn at random around their defaults (range noise, vibration, rocking,
spurious returns, odometer scale error), inspects each through the ``inspect-archive`` flow into
one database, dates them a year apart, and compares them as ``pipescan trend`` does (surveys
aligned by cross-correlation). It prints:

- the differences in blockage between every two surveys at each chainage measured in both
  (percentiles and the largest), in percentage points;
- the differences in the peak blockage between every two surveys;
- the change per year each chainage and the peak would be given (Theil-Sen), times the years
  the surveys span: the change that noise alone makes.

Usage::

    python benchmarks/bench_repeatability.py                # 5 surveys
    python benchmarks/bench_repeatability.py --surveys 3    # quicker
    python benchmarks/bench_repeatability.py --reuse DIR    # analyse an earlier run again

pipescan's threshold for "no significant change" (``pipescan.core.trends``) comes from here.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import sys
import tempfile
import time
import warnings
from datetime import UTC, datetime
from pathlib import Path

_HOME = tempfile.mkdtemp(prefix="bench-repeatability-prefect-")
os.environ.setdefault("PREFECT_HOME", _HOME)
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from pipescan.core.trends import (  # noqa: E402
    CHAINAGE_REPEATABILITY_M,
    SIGNIFICANT_CHANGE_RATIO,
    change_thresholds,
)
from pipescan.flows.inspect import InspectionParams, inspect_archive  # noqa: E402
from pipescan.settings import use_settings  # noqa: E402
from pipescan.simulator.archive import write_simulated_archive  # noqa: E402
from pipescan.simulator.scan import Effects, get_scenario, simulate_scan  # noqa: E402
from pipescan.storage.database.db import connect  # noqa: E402
from pipescan.storage.database.trends import asset_trend  # noqa: E402

ASSET = "REPEAT-1"


def random_effects(rng: np.random.Generator) -> Effects:
    """Effects drawn around the defaults: each survey meets a somewhat different sensor and
    crawler (a range of conditions, not the one the code was developed against)."""
    return dataclasses.replace(
        Effects(),
        range_noise_sigma_m=float(rng.uniform(0.002, 0.006)),
        vibration_deg=float(rng.uniform(0.1, 0.6)),
        rocking_deg=float(rng.uniform(0.3, 2.0)),
        spurious_return_ratio=float(rng.uniform(0.0, 0.015)),
        odometer_scale_error_ratio=float(rng.uniform(-0.03, 0.03)),
    )


def percentiles_pp(values_ratio: np.ndarray) -> str:
    pp = 100.0 * np.abs(values_ratio)
    p50, p95, p99 = np.percentile(pp, [50, 95, 99])
    return f"median {p50:.2f}, 95 % {p95:.2f}, 99 % {p99:.2f}, largest {pp.max():.2f} pp"


def simulate_and_inspect(args: argparse.Namespace, work: Path, db_url: str) -> None:
    from prefect.testing.utilities import prefect_test_harness

    rng = np.random.default_rng(args.seed)
    print(
        f"{args.surveys} surveys of the {args.scenario} scenario, nothing grows between them; "
        f"effects drawn around their defaults (seeds {args.seed}..{args.seed + args.surveys - 1})"
    )
    with prefect_test_harness(server_startup_timeout=120):
        for i in range(args.surveys):
            effects = random_effects(rng)
            scenario = get_scenario(
                args.scenario,
                asset_id=ASSET,
                inspected_at=datetime(2020 + i, 5, 14, 9, 30, tzinfo=UTC),
                effects=effects,
            )
            started = time.perf_counter()
            archive = write_simulated_archive(
                simulate_scan(scenario, seed=args.seed + i), work / f"survey-{i}"
            )
            with use_settings(database_url=db_url):  # a setting, not a flow parameter
                summary = inspect_archive(
                    archive=str(archive),
                    params=InspectionParams(),
                    work_dir=str(work / "scratch"),
                )
            print(
                f"  survey {i}: {summary.sections_ok} of {summary.section_count} sections "
                f"measured, peak {100 * (summary.max_blockage_ratio or 0):.2f} % "
                f"(range noise {1000 * effects.range_noise_sigma_m:.1f} mm, vibration "
                f"{effects.vibration_deg:.2f} deg, rocking {effects.rocking_deg:.2f} deg, "
                f"spurious {100 * effects.spurious_return_ratio:.1f} %, odometer scale "
                f"{100 * effects.odometer_scale_error_ratio:+.1f} %) "
                f"in {time.perf_counter() - started:.0f} s"
            )


def analyse(db_url: str) -> None:
    engine = connect(db_url)
    try:
        trend = asset_trend(engine, ASSET)
    finally:
        engine.dispose()
    values = trend.blockage_ratio  # (surveys, cells), aligned
    thresholds = change_thresholds(values, trend.step_m)
    pairs = []
    for a, b in itertools.combinations(range(values.shape[0]), 2):
        both = np.isfinite(values[a]) & np.isfinite(values[b])
        pairs.append(values[a, both] - values[b, both])
    per_cell = np.concatenate(pairs)
    peaks = np.array([s.peak_blockage_ratio for s in trend.surveys], dtype=float)
    peak_pairs = np.array([p - q for p, q in itertools.combinations(peaks, 2)])
    span_years = (
        trend.surveys[-1].inspected_at - trend.surveys[0].inspected_at
    ).total_seconds() / (365.25 * 86400.0)
    slopes = trend.change_per_year[np.isfinite(trend.change_per_year)]
    print(f"offsets found by alignment: {[round(s.offset_m, 2) for s in trend.surveys]} m")
    print(f"blockage at one chainage, survey against survey ({per_cell.size} pairs of sections):")
    print(f"  {percentiles_pp(per_cell)}")
    print(f"peak blockage, survey against survey ({peak_pairs.size} pairs):")
    print(f"  {percentiles_pp(peak_pairs)}")
    # On a ramp, the spread of the readings over the slope of the profile is how far apart
    # the surveys placed the section.
    slope = np.abs(np.gradient(values, trend.step_m, axis=1))
    with warnings.catch_warnings():  # cells no survey measured
        warnings.simplefilter("ignore", RuntimeWarning)
        spread = np.nanmax(values, axis=0) - np.nanmin(values, axis=0)
        typical_slope = np.nanmedian(slope, axis=0)
    steep = np.nan_to_num(typical_slope) > 0.5  # over 50 points a metre
    if steep.any():
        shift_cm = 100 * spread[steep] / typical_slope[steep]
        print(
            f"chainage shift implied on steep cells ({steep.sum()} cells over 50 pp/m): "
            f"largest {shift_cm.max():.1f} cm, median {np.median(shift_cm):.1f} cm"
        )
    print(f"change that noise alone gives over the {span_years:.1f} years the surveys span:")
    print(
        f"  at one chainage (slope x span, {slopes.size} chainages): "
        f"{percentiles_pp(slopes * span_years)}"
    )
    peak_slope = trend.peak_change_per_year
    if peak_slope is not None:
        print(f"  peak: {100 * peak_slope * span_years:+.2f} pp ({100 * peak_slope:+.3f} pt/yr)")
    over = np.flatnonzero(np.nan_to_num(spread) > thresholds)
    print(
        f"pipescan calls a change significant above {100 * SIGNIFICANT_CHANGE_RATIO:.1f} pp "
        "over the surveys' span, plus the profile's slope times "
        f"{100 * CHAINAGE_REPEATABILITY_M:.0f} cm at a chainage (pipescan.core.trends)"
    )
    print(f"cells whose readings spread wider than that: {len(over)}")
    for k in over:
        readings = " ".join(f"{100 * v:.2f}" for v in values[:, k])
        print(
            f"  {trend.chainage_start_m[k]:.2f} m: {readings} % "
            f"(threshold {100 * thresholds[k]:.2f} pp)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surveys", type=int, default=5)
    parser.add_argument("--scenario", default="paper")
    parser.add_argument("--seed", type=int, default=100, help="first seed; surveys use seed+i")
    parser.add_argument("--reuse", type=Path, help="analyse the database of an earlier run")
    args = parser.parse_args()
    if args.reuse is not None:
        work = args.reuse
    else:
        work = Path(tempfile.mkdtemp(prefix="bench-repeatability-"))
        simulate_and_inspect(args, work, f"sqlite:///{work / 'repeat.db'}")
    print()
    analyse(f"sqlite:///{work / 'repeat.db'}")
    print(f"(archives and database in {work})")


if __name__ == "__main__":
    main()
