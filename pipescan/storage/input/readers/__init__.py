"""Point readers, one module per format, in a registry keyed by file suffix.

Each format module provides ``check(path, where)`` (parse the header and check every
declared count against the bytes present, allocating nothing the file does not back; returns
the point count), ``read(path, where)`` (the points, ``(N, 3)`` float64 in metres) and,
optionally, ``write(path, points, time_s=None)``, ``read_time(path, where)`` (each point's
capture time, for where a registered cloud starts: docs/archive.md) and
``iter_chunks(path, where, chunk_points=..., with_time=...)`` (the points, and their time, a
chunk at a time: a registered cloud of any size is then read with one chunk in memory).
:func:`pipescan.storage.input.pointfiles.read_points`
picks the reader by suffix and adds the checks common to every format (no points, NaN,
millimetres); an unknown suffix is refused, never read as text.

Adding a format is one new module here and one line in :data:`FORMATS`; docs/security.md
says what its ``check`` must guarantee.

What is here:

- ``ascii``, ``e57`` (with ``_e57file``, its layout check), ``las``, ``npy``, ``pcd``,
  ``ply``: the point formats in :data:`FORMATS`; ``_common`` holds what they share
  (:class:`Where`, the errors naming the file).
- ``bags``: ROS bags (``.bag``, ``.db3``, ``.mcap``, ROS 2 bag folders). A bag is not a point
  file but a whole scan's frames, so it is not in :data:`FORMATS`:
  :mod:`pipescan.storage.input.archive` opens it as an archive's content.
  ``bagguard`` bounds what ``rosbags`` may decompress or read for a bag.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from pipescan.storage.input.readers import ascii, e57, las, npy, pcd, ply
from pipescan.storage.input.readers._common import Where

__all__ = ["FORMATS", "READERS", "PointFormat", "Where"]


@dataclass(frozen=True)
class PointFormat:
    """One point-file format: its suffixes, and how to check, read and (optionally) write
    its files."""

    name: str
    suffixes: tuple[str, ...]
    check: Callable[[Path, Where], int]
    read: Callable[[Path, Where], np.ndarray]
    write: Callable[..., None] | None = None
    read_time: Callable[[Path, Where], np.ndarray | None] | None = None
    """Each point's capture time (N,) in seconds, or None when the file holds none; None for
    a format that never has one."""
    iter_chunks: Callable[..., Iterator[tuple[np.ndarray, np.ndarray | None]]] | None = None
    """The points (and, with ``with_time=True``, their time) in chunks of at most
    ``chunk_points``, without the whole file in memory; None for a format read whole."""

    @classmethod
    def from_module(cls, name: str, module: ModuleType) -> PointFormat:
        """The format a reader module defines (``SUFFIXES``, ``check``, ``read``, and
        optionally ``write`` and ``read_time``)."""
        return cls(
            name,
            module.SUFFIXES,
            module.check,
            module.read,
            getattr(module, "write", None),
            getattr(module, "read_time", None),
            getattr(module, "iter_chunks", None),
        )


FORMATS: tuple[PointFormat, ...] = (
    PointFormat.from_module("LAS/LAZ", las),
    PointFormat.from_module("PLY", ply),
    PointFormat.from_module("PCD", pcd),
    PointFormat.from_module("NumPy .npy", npy),
    PointFormat.from_module("ASCII x y z", ascii),
    PointFormat.from_module("E57", e57),
)
"""Every format pipescan reads: a new one is one module above and one line here."""

READERS: dict[str, PointFormat] = {s: f for f in FORMATS for s in f.suffixes}
"""Lower-case suffix -> format; its keys are ``pointfiles.POINT_SUFFIXES``."""
