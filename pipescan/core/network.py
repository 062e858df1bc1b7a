"""Where a pipe lies in the network's coordinates, and where a chainage falls on it.

A pipe's line runs from its upstream node to its downstream node, in the network's coordinate
reference system (CRS), in metres. Chainage, as everywhere in pipescan, is the distance from
the upstream node along the pipe. Placing a span of chainage on the line is **linear
referencing**: walk that far along the line's vertices.

The rules every GIS figure follows:

- **Never stretch.** A scan's chainage is a measured distance; a GIS line's length is the
  digitised one. They differ (an odometer's slip, a line drawn between manhole centres, a
  survey that stopped short). Events are placed at their measured chainage, not scaled to the
  line. Where the two lengths differ by more than :data:`LENGTH_TOLERANCE_RATIO`, the export
  says so (:func:`length_note`); an event beyond the line's end is cut at the end and says
  by how much (:meth:`PipeLine.cut`).
- **Orientation.** A GIS line may be digitised either way. It is turned upstream-first by the
  nodes' names when the layer gives them, else by node positions known from the archive's
  metadata, else taken as digitised from upstream to downstream, the usual convention; which of
  the three decided is kept with the geometry (:class:`PipeGeometry`).

Everything here is pure: arrays and small frozen dataclasses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "LENGTH_TOLERANCE_RATIO",
    "ORIENTED_BY_DIGITISING",
    "ORIENTED_BY_METADATA",
    "ORIENTED_BY_NODE_NAMES",
    "ORIENTED_BY_NODE_POSITIONS",
    "Cut",
    "LayerPipe",
    "NetworkLayer",
    "PipeGeometry",
    "PipeLine",
    "length_difference_ratio",
    "length_note",
    "orient",
]

LENGTH_TOLERANCE_RATIO = 0.02
"""Scan and GIS lengths that differ by more than this share of the GIS length are reported."""

ORIENTED_BY_NODE_NAMES = "node names"
ORIENTED_BY_NODE_POSITIONS = "node positions"
ORIENTED_BY_DIGITISING = "digitised direction (assumed upstream first)"
ORIENTED_BY_METADATA = "inspection.toml node positions"


@dataclass(frozen=True)
class Cut:
    """A span of chainage placed on a line.

    ``coords`` (M, D) are the vertices of the placed part, upstream first; ``beyond_m`` is how
    much of the span lay past the line's end (or before its start) and was cut off (0 when it
    fitted).
    """

    coords: np.ndarray = field(compare=False, repr=False)
    beyond_m: float


@dataclass(frozen=True)
class PipeLine:
    """A pipe's line, upstream node first.

    Parameters
    ----------
    coords : (N, D) float array, D = 2 or 3
        Vertices in the network's CRS, metres. With D = 3 the length includes the fall.

    Raises
    ------
    ValueError
        Fewer than two vertices, a dimension other than 2 or 3, non-finite coordinates, or a
        zero length.

    Examples
    --------
    >>> line = PipeLine(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]))
    >>> line.length_m, line.point_at(5.0).tolist()
    (7.0, [3.0, 2.0])
    >>> cut = line.cut(2.0, 4.0)
    >>> cut.coords.tolist(), cut.beyond_m
    ([[2.0, 0.0], [3.0, 0.0], [3.0, 1.0]], 0.0)
    """

    coords: np.ndarray = field(compare=False, repr=False)
    _along: np.ndarray = field(init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        coords = np.asarray(self.coords, dtype=np.float64)
        if coords.ndim != 2 or coords.shape[0] < 2 or coords.shape[1] not in (2, 3):
            raise ValueError(f"a line needs (N >= 2, 2 or 3) coordinates, got {coords.shape}")
        if not np.isfinite(coords).all():
            raise ValueError("a line's coordinates must be finite")
        steps = np.linalg.norm(np.diff(coords, axis=0), axis=1)
        if not steps.sum() > 0:
            raise ValueError("a line's length must be greater than 0")
        object.__setattr__(self, "coords", coords)
        object.__setattr__(self, "_along", np.concatenate([[0.0], np.cumsum(steps)]))

    @property
    def length_m(self) -> float:
        """Length along the vertices."""
        return float(self._along[-1])

    def reversed(self) -> PipeLine:
        """The same line walked the other way."""
        return PipeLine(self.coords[::-1].copy())

    def point_at(self, chainage_m: float) -> np.ndarray:
        """The point at a chainage, clamped to the line's ends; shape (D,)."""
        along = self._along
        s = min(max(float(chainage_m), 0.0), self.length_m)
        i = int(np.searchsorted(along, s, side="right")) - 1
        i = min(max(i, 0), len(along) - 2)
        span = along[i + 1] - along[i]
        t = 0.0 if span == 0 else (s - along[i]) / span
        return np.asarray(self.coords[i] + t * (self.coords[i + 1] - self.coords[i]))

    def cut(self, start_m: float, end_m: float) -> Cut:
        """The part of the line between two chainages (start <= end), cut at the line's ends.

        A span entirely past an end becomes the end point twice (a line of zero length), with
        ``beyond_m`` its whole length: it is still shown, at the end, and says it did not fit.
        """
        if not end_m >= start_m:
            raise ValueError(f"end {end_m} is before start {start_m}")
        length = self.length_m
        beyond = max(0.0, end_m - max(start_m, length)) + max(0.0, min(end_m, 0.0) - start_m)
        a = min(max(start_m, 0.0), length)
        b = min(max(end_m, 0.0), length)
        along = self._along
        inside = (along > a) & (along < b)
        coords = np.vstack([self.point_at(a), self.coords[inside], self.point_at(b)])
        return Cut(coords=coords, beyond_m=float(beyond))


@dataclass(frozen=True)
class PipeGeometry:
    """Where an asset's pipe lies: its line (upstream first), its CRS, and where both came from.

    ``gis_id`` is the id in an imported network layer (None for geometry from the archive's
    metadata); ``source`` names the layer or says ``inspection.toml``; ``oriented_by`` says
    what decided which end is upstream (the ``ORIENTED_BY_*`` texts).
    """

    asset_id: str
    line: PipeLine
    crs: str
    source: str
    oriented_by: str
    gis_id: str | None = None


@dataclass(frozen=True)
class LayerPipe:
    """One pipe of a network layer as read: its GIS id, what names its asset, its line as
    digitised (not yet oriented).

    ``asset_ref`` is the pipescan asset id it stands for (the GIS id itself unless the layer
    has a field for it); ``from_node`` and ``to_node`` are the layer's names of the nodes at
    the first and last vertex, when it gives them.
    """

    gis_id: str
    asset_ref: str
    from_node: str | None
    to_node: str | None
    line: PipeLine


@dataclass(frozen=True)
class NetworkLayer:
    """A network layer as read: its pipes, its CRS (an authority code such as ``EPSG:25832``,
    or WKT) and where it came from (file and layer name)."""

    pipes: tuple[LayerPipe, ...]
    crs: str
    source: str


def orient(
    coords: np.ndarray,
    *,
    from_node: str | None,
    to_node: str | None,
    upstream_node: str | None,
    downstream_node: str | None,
    upstream_xyz: Sequence[float] | None = None,
    downstream_xyz: Sequence[float] | None = None,
) -> tuple[PipeLine, str]:
    """A layer's line turned upstream-first, and what decided it (see the module's rules).

    Parameters
    ----------
    coords : (N, D) float array
        The line as digitised.
    from_node, to_node
        The layer's names of the nodes at its first and last vertex, if it gives them.
    upstream_node, downstream_node
        The asset's node names.
    upstream_xyz, downstream_xyz
        The asset's node positions in the layer's CRS, if known.

    Examples
    --------
    >>> line, why = orient(np.array([[0.0, 0.0], [10.0, 0.0]]), from_node="B", to_node="A",
    ...                    upstream_node="A", downstream_node="B")
    >>> line.coords[0].tolist(), why
    ([10.0, 0.0], 'node names')
    """
    line = PipeLine(coords)
    if upstream_node is not None and downstream_node is not None:
        if (from_node, to_node) == (upstream_node, downstream_node):
            return line, ORIENTED_BY_NODE_NAMES
        if (from_node, to_node) == (downstream_node, upstream_node):
            return line.reversed(), ORIENTED_BY_NODE_NAMES
    if upstream_xyz is not None and downstream_xyz is not None:
        d = min(line.coords.shape[1], len(upstream_xyz), len(downstream_xyz))
        first, last = line.coords[0, :d], line.coords[-1, :d]
        up, down = np.asarray(upstream_xyz[:d]), np.asarray(downstream_xyz[:d])
        same = np.linalg.norm(first - up) + np.linalg.norm(last - down)
        swapped = np.linalg.norm(first - down) + np.linalg.norm(last - up)
        return (line if same <= swapped else line.reversed()), ORIENTED_BY_NODE_POSITIONS
    return line, ORIENTED_BY_DIGITISING


def length_difference_ratio(scan_length_m: float, gis_length_m: float) -> float:
    """(scan - GIS) / GIS: positive when the scan reaches further than the line is long.

    >>> round(length_difference_ratio(41.0, 40.0), 3)
    0.025
    """
    return (scan_length_m - gis_length_m) / gis_length_m


def length_note(scan_length_m: float, gis_length_m: float) -> str | None:
    """The words an export and a report give when the two lengths disagree by more than
    :data:`LENGTH_TOLERANCE_RATIO`; None when they agree.

    >>> length_note(40.5, 40.0) is None
    True
    >>> print(length_note(36.0, 40.0))  # doctest: +NORMALIZE_WHITESPACE
    the scan reaches 36.00 m from the upstream node, the GIS line is 40.00 m long (-10.0 %):
    events are placed at their measured chainage, not stretched
    """
    ratio = length_difference_ratio(scan_length_m, gis_length_m)
    if not math.isfinite(ratio) or abs(ratio) <= LENGTH_TOLERANCE_RATIO:
        return None
    return (
        f"the scan reaches {scan_length_m:.2f} m from the upstream node, the GIS line is "
        f"{gis_length_m:.2f} m long ({100 * ratio:+.1f} %): events are placed at their "
        "measured chainage, not stretched"
    )
