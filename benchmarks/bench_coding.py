"""Defect coding against ground truth: one physical feature, one defect, the right code and place.

    python benchmarks/bench_coding.py sweep          # every coding scene at 0.3-0.9 m, true poses
    python benchmarks/bench_coding.py sweep --harsh  # the same with every effect at its harsh end
    python benchmarks/bench_coding.py sweep --layouts 12  # random defect layouts, true poses
    python benchmarks/bench_coding.py estimated      # some through the whole flow (estimated poses)
    python benchmarks/bench_coding.py real           # the real S3DSS scan's defects

The scenes are ``pipescan.simulator.coding_scenes`` (each family alone, pairs side by side, a
deposit under an obstacle, ramps of 0.1-0.5 m) at 0.3, 0.5, 0.6 and 0.9 m, every sensor and
crawler effect on at its default, each scene with its own seed. Their true features come from
``pipescan.simulator.features.true_features``; ``score_defects`` says for each whether it was
found as one defect of its code, split, mis-coded, merged into another's defect or missed,
and how far the defect's clock positions are from the truth. "Over threshold" means the
feature's own figures are over the report's threshold (class 2 or worse under vsa-2023 with
the scene's pipe class, or a blockage of 10 % or more). Every figure is printed; nothing is
asserted (the tests do that on smaller cases).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from bench_sections import REAL_SCAN, measure_all, registered_cloud_true_poses

from pipescan.core.axis import fit_axis
from pipescan.core.coding import CODE_FAMILIES, code_sections
from pipescan.core.grading import choose_grading, grade_sections, load_table, merge_defects
from pipescan.settings import use_settings
from pipescan.simulator.coding_scenes import CODING_DIAMETERS_M, SCENES, coding_draws
from pipescan.simulator.features import FeatureOutcome, score_defects, true_features
from pipescan.simulator.scan import simulate_scan
from pipescan.simulator.sweep import HARSH, layout_draws

OUTCOMES = ("found", "split", "mis-coded", "merged", "missed", "not measured")


def defects_true_poses(scenario, seed: int):
    """The coded defects of a simulated scan registered with its true poses."""
    scan = simulate_scan(scenario, seed=seed)
    points, start, last = registered_cloud_true_poses(scan)
    axis = fit_axis(points, start_m=start, travel_m=last - start)
    sections = measure_all(points, axis, scenario.nominal_diameter_m, "polar")
    choice = choose_grading(scenario.material)
    table = load_table(choice.table)
    codings = code_sections(sections)
    graded = grade_sections(sections, table, pipe_class=choice.pipe_class, codings=codings)
    defects = merge_defects(graded, table, pipe_class=choice.pipe_class, codings=codings)
    return defects, table, choice.pipe_class, sections


def _clock(from_h: float | None, to_h: float | None) -> str:
    return "" if from_h is None or to_h is None else f"{from_h:.1f}-{to_h:.1f} h"


def _fmt_defect(d) -> str:
    clock = "" if d.clock_from_h is None else f" {d.clock_from_h:.1f}-{d.clock_to_h:.1f} h"
    return (
        f"{d.code} {d.chainage_start_m:.1f}-{d.chainage_end_m:.1f} m{clock} "
        f"{100 * d.peak_value:.1f} % cl {d.grade}"
    )


def _fmt_truth(f) -> str:
    clock = "" if f.clock_from_h is None else f" {f.clock_from_h:.1f}-{f.clock_to_h:.1f} h"
    span = f"{f.chainage_start_m:.2f}-{f.chainage_end_m:.2f} m"
    return f"{f.code} {span}{clock} {100 * f.peak_value:.1f} %"


def coding_table(results: list[tuple[str, list[FeatureOutcome], list]]) -> None:
    """Print the coding table: per family, over the threshold and in all."""
    print("\n## Coding table")
    print(
        "| family | features (over threshold) | found as one defect | split | mis-coded | merged |"
        " missed | not measured | clock error, mean / max (h) | spurious defects of this code |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    spurious = Counter(d.code for _, _, sp in results for d in sp)
    by_code: dict[str, list[FeatureOutcome]] = defaultdict(list)
    for _, outcomes, _ in results:
        for o in outcomes:
            by_code[o.feature.code].append(o)
    rows = []
    for code in [c for c in CODE_FAMILIES if c in by_code]:
        rows.append((code, by_code[code]))
    rows.append(("all", [o for _, os_ in rows for o in os_]))
    for code, outs in rows:
        over = [o for o in outs if o.over_threshold]
        counts = Counter(o.outcome for o in outs)
        counts_over = Counter(o.outcome for o in over)
        errors = [o.clock_error_h for o in outs if o.clock_error_h is not None]
        clock = f"{np.mean(errors):.2f} / {np.max(errors):.2f}" if errors else "-"
        cells = " | ".join(f"{counts[k]} ({counts_over[k]})" for k in OUTCOMES)
        sp = sum(spurious.values()) if code == "all" else spurious.get(code, 0)
        print(f"| {code} | {len(outs)} ({len(over)}) | {cells} | {clock} | {sp} |")
    other = {c: n for c, n in spurious.items() if c not in by_code}
    if other:
        print(f"spurious defects of codes no scene has: {dict(other)}")
    everything = [o for _, os_, _ in results for o in os_ if o.outcome != "not measured"]
    over = [o for o in everything if o.over_threshold]
    bad = sum(o.outcome in ("split", "mis-coded") for o in everything)
    unmeasured = sum(o.outcome == "not measured" for _, os_, _ in results for o in os_)
    print(
        f"\nTargets (features with a measured section over them; {unmeasured} had none): "
        f"over-threshold features found as one defect: "
        f"{sum(o.outcome == 'found' for o in over)} of {len(over)}; mis-coded or split: {bad} of "
        f"{len(everything)} (at most 1 in 50: {len(everything) / 50:.1f}); clock error within "
        f"1 h: {sum(o.clock_error_h <= 1.0 for o in everything if o.clock_error_h is not None)}"
        f" of {sum(o.clock_error_h is not None for o in everything)}"
    )


def sweep(args: argparse.Namespace) -> None:
    effects = HARSH if args.harsh else None
    names = args.scenes or list(SCENES)
    skipped: list[str] = []
    if args.layouts:
        draws = layout_draws(args.layouts, args.layout_seed)
        label = "random defect layouts, effects drawn from issue 12's ranges"
    else:
        draws = coding_draws(names, args.diameters, effects=effects, skipped=skipped)
        label = "every effect at its harsh end" if args.harsh else "every effect at its default"
    print(f"## Coding sweep: {len(draws)} scans, true poses, {label}")
    for reason in skipped:
        print(f"- not simulated: {reason}")
    print("| scan | true features | defects | outcomes | time (s) |")
    print("|---|---|---|---|---|")
    results = []
    for draw in draws:
        started = time.perf_counter()
        defects, table, pipe_class, sections = defects_true_poses(draw.scenario, draw.seed)
        truths = true_features(draw.scenario)
        outcomes, spurious = score_defects(
            defects, truths, table, pipe_class=pipe_class, sections=sections
        )
        results.append((draw.name, outcomes, spurious))
        summary = ", ".join(
            f"{o.feature.code} {o.outcome}"
            + ("" if o.clock_error_h is None else f" ({o.clock_error_h:.1f} h)")
            for o in outcomes
        )
        if spurious:
            summary += "; spurious: " + ", ".join(_fmt_defect(d) for d in spurious)
        print(
            f"| {draw.name} | {'; '.join(_fmt_truth(f) for f in truths)} |"
            f" {'; '.join(_fmt_defect(d) for d in defects)} | {summary} |"
            f" {time.perf_counter() - started:.0f} |",
            flush=True,
        )
    coding_table(results)


def estimated(args: argparse.Namespace) -> None:
    """A subset of scenes through the whole flow: archive, registration (estimated poses),
    sections, coding, the database."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from pipescan.flows.inspect import InspectionParams, inspect_archive
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import list_defects, list_sections

    names = args.scenes or [
        "deposit, 0.25 m ramps",
        "obstacle from the crown",
        "body on the invert",
        "deposit under an obstacle",
        "band beside a deposit",
        "deformation, vertical",
    ]
    draws = coding_draws(names, args.diameters)
    print(f"## Coding through the whole flow: {len(draws)} scans, estimated poses, default effects")
    print("| scan | true features | defects | outcomes |")
    print("|---|---|---|---|")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        db = f"sqlite:///{tmp}/coding.db"
        for k, draw in enumerate(draws):
            archive = Path(tmp) / f"a{k}"
            write_simulated_archive(simulate_scan(draw.scenario, seed=draw.seed), archive)
            with use_settings(database_url=db):  # a setting, not a flow parameter
                summary = inspect_archive(
                    archive=str(archive),
                    params=InspectionParams(),
                    work_dir=f"{tmp}/w",
                )
            engine = connect(db)
            defects = list_defects(engine, summary.inspection_id)
            sections = list_sections(engine, summary.inspection_id)
            engine.dispose()
            choice = choose_grading(draw.scenario.material)
            truths = true_features(draw.scenario)
            outcomes, spurious = score_defects(
                defects,
                truths,
                load_table(choice.table),
                pipe_class=choice.pipe_class,
                sections=sections,
            )
            results.append((draw.name, outcomes, spurious))
            text = ", ".join(f"{o.feature.code} {o.outcome}" for o in outcomes)
            if spurious:
                text += "; spurious: " + ", ".join(_fmt_defect(d) for d in spurious)
            print(
                f"| {draw.name} | {'; '.join(_fmt_truth(f) for f in truths)} |"
                f" {'; '.join(_fmt_defect(d) for d in defects)} | {text} |",
                flush=True,
            )
    coding_table(results)


def real(args: argparse.Namespace) -> None:
    print("## The real scan: S3DSS real_459 (FARO Focus S, 800 mm concrete pipe)")
    data = np.loadtxt(REAL_SCAN)
    points = data[:, :3]
    axis = fit_axis(points)
    sections = measure_all(points, axis, 0.8, "polar")
    table = load_table()
    codings = code_sections(sections)
    graded = grade_sections(sections, table, pipe_class="rigid", codings=codings)
    print("| chainage (m) | x (m) | status | blockage | features (code, clock, lost area, rule) |")
    print("|---|---|---|---|---|")
    for s, c in zip(sections, codings, strict=True):
        x = float(axis.point_at(s.chainage_start_m + 0.05, 0.0, 0.0)[0])
        feats = "; ".join(
            f"{f.code} {_clock(f.clock_from_h, f.clock_to_h)}"
            f" {100 * f.lost_area_m2 / s.nominal_area_m2:.1f} % ({f.rule})"
            for f in (c.features if c else ())
        )
        b = "-" if s.blockage_ratio is None else f"{100 * s.blockage_ratio:.2f} %"
        print(f"| {s.chainage_start_m:.1f} | {x:+.2f} | {s.status.value} | {b} | {feats} |")
    print("\nDefects (concrete: rigid pipe):")
    for d in merge_defects(graded, table, pipe_class="rigid", codings=codings):
        print(f"- {_fmt_defect(d)}")
    worst = min((s.grade for s in graded if s.grade is not None), default=None)
    print(f"worst section class: {worst}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("sweep", "estimated", "real"))
    parser.add_argument("--harsh", action="store_true", help="every effect at its harsh end")
    parser.add_argument("--scenes", nargs="*", help="scene names (default: all)")
    parser.add_argument(
        "--diameters",
        nargs="*",
        type=float,
        default=list(CODING_DIAMETERS_M),
        help="pipe sizes (m)",
    )
    parser.add_argument(
        "--layouts",
        type=int,
        default=0,
        help="sweep: this many random defect layouts (layout_draws) instead of the scenes",
    )
    parser.add_argument("--layout-seed", type=int, default=2026, help="seed of --layouts")
    args = parser.parse_args()
    {"sweep": sweep, "estimated": estimated, "real": real}[args.what](args)


if __name__ == "__main__":
    main()
