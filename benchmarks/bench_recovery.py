"""Crash recovery of a scheduled network run: the kill matrix.

For each scenario (``worker``, ``flow``, ``both``, ``server``; see ``tests/kill_matrix.py``) a
fresh Prefect server, ``pipescan deploy``, a worker and a run of the deployment over a store of
simulated archives processed one at a time; once the first inspection is stored, a SIGKILL.
Then nobody does anything (a killed worker or server is started again after 5 s, as a
supervisor would) until every archive has its inspection and no run is active.

The outages (``db45``, ``db120``, ``db600``: the database refusing connections for that many
seconds from the same moment; ``dbstart30``: refusing for 30 s when the run starts;
``server105``: the Prefect server down for 105 s; ``pg20``: a PostgreSQL cluster holding
pipescan's database and Prefect's, started by the bench from Debian's binaries in a temporary
folder, stopped for 20 s) end by themselves; a run that ends Failed (not green, naming what
is missing) also ends the wait. ``cancel`` cancels the run at that moment, and ends when the
run is Cancelled and its processes are gone.

Prints, per scenario: the final state of the network run and its sub-flows, the inspections
stored (and distinct identities), the seconds from the kill (or outage) until the work was
finished, the task runs left active, the silent-run automation's acts on ended runs, and what
``pipescan runs`` says of the run.

Usage::

    python benchmarks/bench_recovery.py                    # 4 archives, every kill scenario
    python benchmarks/bench_recovery.py --scenarios both --archives 3 --time-limit 300
    python benchmarks/bench_recovery.py --scenarios db45 dbstart30 server105
    python benchmarks/bench_recovery.py --scenarios db600 --time-limit 1500   # 12 min
    python benchmarks/bench_recovery.py --scenarios pg20 cancel
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.kill_matrix import CANCEL, OUTAGES, SCENARIOS, format_outcome, run_scenario
from tests.netstore import write_store


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--archives", type=int, default=4)
    parser.add_argument(
        "--scenarios", nargs="+", choices=[*SCENARIOS, *OUTAGES, CANCEL], default=list(SCENARIOS)
    )
    parser.add_argument("--time-limit", type=float, default=600, help="seconds after the kill")
    parser.add_argument("--keep", action="store_true", help="keep the run folders (logs)")
    args = parser.parse_args()

    root = Path(tempfile.mkdtemp(prefix="bench-recovery-"))
    store = root / "store"
    write_store(store, args.archives)
    print(f"{args.archives} archives, one at a time; runs under {root}", flush=True)
    for scenario in args.scenarios:
        started = time.monotonic()
        outcome = run_scenario(
            scenario, root / scenario, store, args.archives, time_limit_s=args.time_limit
        )
        print(format_outcome(outcome), flush=True)
        for line in outcome.timeline:
            print(f"    {line}", flush=True)
        print(f"    (scenario took {time.monotonic() - started:.0f} s)", flush=True)
    if not args.keep:
        import shutil

        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
