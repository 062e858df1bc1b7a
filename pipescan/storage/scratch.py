"""Scratch space of one inspection run: registered points bucketed by chainage window.

Registration streams frames once and writes each frame chunk's registered points into one file
per chainage window (``win_<start_mm>/chunk_<first>.npy``). A window task then reads only its own
files, so peak memory is set by the window, not by the length of the pipe, and chunks never
append to a shared file (they can run in parallel, on other machines).

Points are stored as float32 offsets from the axis origin: float32 keeps 0.1 mm at 1 km from the
origin, and offsets stay small even for georeferenced clouds with large coordinates.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipescan.core.axis import PipeAxis
from pipescan.core.sections import ChainageWindow

RUN_MARKER = ".pipescan-run"
"""The file that marks a directory as a run's scratch space, created by pipescan."""

log = logging.getLogger(__name__)


def create_run_dir(work_dir: Path) -> Path:
    """Create a new, empty scratch directory for one run under ``work_dir`` and mark it.

    Only a directory carrying the marker is ever deleted by :func:`remove_workspace`, so a
    user's folder can never be removed by mistake, whatever it is called.
    """
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    while True:
        run_dir = work_dir / f"run-{time.time_ns():x}-{os.getpid()}"
        try:
            run_dir.mkdir()
        except FileExistsError:
            continue
        (run_dir / RUN_MARKER).write_text(f"pid {os.getpid()}\n", encoding="utf-8")
        return run_dir


def window_dir(bucket_root: Path, window: ChainageWindow) -> Path:
    return Path(bucket_root) / f"win_{window.start_mm:09d}"


def write_buckets(
    points_world_m: np.ndarray,
    axis: PipeAxis,
    windows: Sequence[ChainageWindow],
    bucket_root: Path,
    tag: str,
) -> int:
    """Split registered points by chainage window and write one file per window.

    Parameters
    ----------
    points_world_m : (N, 3) float
        Registered points, world frame, metres.
    axis : PipeAxis
    windows : sequence of ChainageWindow
        Consecutive windows; points outside all of them are dropped.
    bucket_root : Path
        The run's bucket directory.
    tag : str
        Unique per writer (e.g. the chunk's first frame), so parallel writers never collide.

    Returns
    -------
    int
        Points written.
    """
    if len(points_world_m) == 0 or not windows:
        return 0
    chain_mm = axis.chainage(points_world_m) * 1000.0
    edges = np.array([w.start_mm for w in windows] + [windows[-1].end_mm], dtype=np.float64)
    which = np.searchsorted(edges, chain_mm, side="right") - 1
    keep = (which >= 0) & (which < len(windows))
    offsets = (points_world_m - axis.origin_m).astype(np.float32)
    written = 0
    for w_index in np.unique(which[keep]):
        sel = which == w_index
        out_dir = window_dir(bucket_root, windows[int(w_index)])
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = out_dir / f".{tag}.npy.tmp"
        with tmp.open("wb") as fh:
            np.save(fh, offsets[sel])
        tmp.replace(out_dir / f"{tag}.npy")
        written += int(sel.sum())
    return written


def read_window_offsets(bucket_root: Path, window: ChainageWindow) -> np.ndarray:
    """All registered points of one window as float32 offsets from the axis origin, (N, 3),
    metres: pass them on with ``relative=True``."""
    files = sorted(window_dir(bucket_root, window).glob("*.npy"))
    if not files:
        return np.empty((0, 3), dtype=np.float32)
    return np.concatenate([np.load(f) for f in files])


def remove_workspace(path: Path) -> None:
    """Delete a run's scratch directory made by :func:`create_run_dir` (safe if it does not
    exist). A directory without the run marker, or a symlink, is left alone and logged: it
    was not made by pipescan."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    if path.is_symlink() or not (path / RUN_MARKER).is_file():
        log.warning("not deleting %s: it is not a pipescan run directory", path)
        return
    shutil.rmtree(path, ignore_errors=True)
