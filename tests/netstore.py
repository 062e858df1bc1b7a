"""Stores of small simulated archives for the network tests and benchmark.

Each archive is the paper's scenario over 1.3 m of travel at 100,000 points per second (about
85 frames, a few seconds to inspect), with its own asset id and seed.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pipescan.simulator.archive import write_simulated_archive
from pipescan.simulator.scan import get_scenario, simulate_scan

BAD_INSPECTION_TOML = 'asset_id = "BAD-1"\nnominal_diameter_m = 0.5\n'
"""An ``inspection.toml`` without the required ``inspected_at``: a bad archive."""


def asset_id(i: int) -> str:
    return f"NW-{i:02d}"


def write_archive(root: Path, i: int, *, travel_m: float = 1.3, kind: str = "dir") -> Path:
    """Write simulated archive ``i`` (asset ``NW-ii``, seed ``i``) under ``root``.

    ``kind`` is ``dir`` (a folder ``MHi-MHi+1``), ``zip`` or ``gztar`` (that folder packed).
    """
    scenario = get_scenario("paper", travel_m=travel_m, points_per_s=100_000, asset_id=asset_id(i))
    folder = write_simulated_archive(simulate_scan(scenario, seed=i), root / f"MH{i}-MH{i + 1}")
    if kind == "dir":
        return folder
    packed = shutil.make_archive(str(folder), kind, folder)
    shutil.rmtree(folder)
    return Path(packed)


def write_bad_archive(root: Path, name: str = "MH99-BAD") -> Path:
    """An archive folder whose metadata lacks ``inspected_at``."""
    folder = root / name
    folder.mkdir(parents=True)
    (folder / "inspection.toml").write_text(BAD_INSPECTION_TOML, encoding="utf-8")
    return folder


def write_store(root: Path, count: int, *, bad: bool = False) -> list[Path]:
    """A store of ``count`` good archive folders (and one bad one): their paths, in order."""
    root.mkdir(parents=True, exist_ok=True)
    paths = [write_archive(root, i) for i in range(count)]
    if bad:
        paths.append(write_bad_archive(root))
    return paths
