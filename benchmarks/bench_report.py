"""Render times of the PDF condition report, on synthetic inspections.

Prints, for each case, the number of sections and defects, and the time to build the context
(figures drawn with matplotlib), lay the document out and write the PDF (WeasyPrint). The
cases are the ones the issue names: a pipe with no defects, one with many, and a 100 m scan
(which must render in under 15 s), plus the network summary of a set of pipes.

    python benchmarks/bench_report.py              # full scale: 100 m scans (1000 sections)
    python benchmarks/bench_report.py --length 20  # scaled down

The machine's load changes the figures; compare cases within one run.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

from pipescan.core.model import SectionStatus
from pipescan.core.summary import peak_blockage
from pipescan.reports.context import build_context
from pipescan.reports.network import EarlierScan, NetworkInput, PipeInspection
from pipescan.reports.render import (
    _environment,
    render_network_pdf,
    render_pdf,
)
from pipescan.reports.sample import Feature, sample_input


def _many_features(length_m: float) -> list[Feature]:
    kinds = [("deposit", 0.30), ("obstacle", 0.30), ("deformation", 0.06)]
    count = max(1, int(length_m // 5))
    return [
        Feature(kinds[i % 3][0], 2.0 + i * 4.8, 2.0 + i * 4.8 + 1.0, kinds[i % 3][1])
        for i in range(count)
        if 2.0 + i * 4.8 + 1.0 < length_m
    ]


def _timed_render(label: str, inp, out_dir: Path) -> float:
    from weasyprint import HTML

    t0 = time.perf_counter()
    context = build_context(inp)
    html = _environment().get_template("inspection.html.j2").render(**context)
    t1 = time.perf_counter()
    document = HTML(string=html).render()
    t2 = time.perf_counter()
    document.write_pdf(out_dir / f"{label}.pdf")
    t3 = time.perf_counter()
    # The public entry point, end to end, as a user runs it.
    t4 = time.perf_counter()
    render_pdf(inp, out_dir / f"{label}-public.pdf")
    total_s = time.perf_counter() - t4
    print(
        f"{label:<22} {len(inp.sections):>6} {len(inp.defects):>7} {len(document.pages):>5}"
        f" {t1 - t0:>9.2f} {t2 - t1:>8.2f} {t3 - t2:>7.2f} {total_s:>9.2f}"
    )
    return total_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--length", type=float, default=100.0, help="pipe length in m")
    parser.add_argument("--pipes", type=int, default=40, help="pipes in the network summary")
    args = parser.parse_args()
    length_m = args.length
    out_dir = Path(tempfile.mkdtemp(prefix="pipescan-bench-report-"))
    unmeasured = [(length_m * 0.3, length_m * 0.3 + 1.2, SectionStatus.LOW_COVERAGE)]
    cases = {
        "no defects": sample_input(length_m, features=(), unmeasured=unmeasured, earlier=0),
        "3 defects + trend": sample_input(
            length_m,
            features=[
                Feature("deformation", length_m * 0.1, length_m * 0.1 + 1.2, 0.075),
                Feature("obstacle", length_m * 0.5, length_m * 0.5 + 1.4, 0.30),
                Feature("deposit", length_m * 0.7, length_m * 0.7 + 3.0, 0.36),
            ],
            unmeasured=unmeasured,
            earlier=2,
        ),
        "many defects + trend": sample_input(
            length_m, features=_many_features(length_m), unmeasured=unmeasured, earlier=2
        ),
    }
    print(f"report render times, {length_m:g} m pipes (seconds); PDFs in {out_dir}")
    print(
        f"{'case':<22} {'sections':>6} {'defects':>7} {'pages':>5}"
        f" {'context':>9} {'layout':>8} {'write':>7} {'total':>9}"
    )
    worst_s = max(_timed_render(label.replace(" ", "-"), inp, out_dir) for label, inp in
                  cases.items())  # fmt: skip
    verdict = "under" if worst_s < 15.0 else "OVER"
    print(f"slowest {worst_s:.2f} s: {verdict} the 15 s budget for a 100 m scan's report")

    base = cases["3 defects + trend"]
    pipes = []
    for k in range(args.pipes):
        h = base.history[0]
        pipes.append(
            PipeInspection(
                asset_id=f"MH{1000 + k}-MH{1001 + k}",
                upstream_node=f"MH{1000 + k}",
                downstream_node=f"MH{1001 + k}",
                nominal_diameter_m=0.5,
                material="concrete",
                inspection_id=k + 1,
                inspected_at=base.inspected_at,
                sections=base.sections,
                defect_count=len(base.defects),
                earlier=[EarlierScan(1000 + k, h.inspected_at, _peak(h.sections))],
            )
        )
    network = NetworkInput(pipes=pipes, generated_at=base.generated_at, software_version="bench")
    t0 = time.perf_counter()
    render_network_pdf(replace(network), out_dir / "network.pdf")
    print(
        f"network summary, {len(pipes)} pipes of {length_m:g} m: {time.perf_counter() - t0:.2f} s"
    )


def _peak(sections) -> float | None:
    peak = peak_blockage(sections)
    return None if peak is None else peak.blockage_ratio


if __name__ == "__main__":
    main()
