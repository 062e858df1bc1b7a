"""The ``polar`` contour method, pipescan's own.

A robust radius per angle bin around the pipe centre (the median of the bin's radii, which is
the wall surface under symmetric range noise), with unseen bins kept as gaps rather than
guessed, and the free space that the sensor saw behind the edge of an overhanging obstacle
added as pockets (so the contour need not be star-shaped).

The same :class:`PolarProfile` also judges every section's coverage (which angles were seen),
whatever its contour method: ``pipescan.core.measures`` builds it once per section.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from pipescan.core.contour.base import ContourResult, angle_bins, polar_coordinates
from pipescan.core.errors import GeometryError
from pipescan.core.uncertainty import longest_unseen_deg


@dataclass(frozen=True)
class PolarProfile:
    """Robust radius per angle bin around the section centre.

    Attributes
    ----------
    angles_rad : (B,) float
        Bin centres, counter-clockwise from the ``right`` axis.
    radii_m : (B,) float
        Radius of the nearest surface in each bin (the median of its layer); NaN where the bin
        has fewer points than required (unseen).
    counts : (B,) int
        Points per bin.
    far_radii_m : (B,) float, optional
        Where the sensor also saw a surface beyond the nearest one (the wall behind the edge
        of an obstacle that overhangs it), that surface's radius; NaN elsewhere.
    layer_gap_m : float
        The radial jump that separated the two layers (see ``polar_profile``).
    """

    angles_rad: np.ndarray
    radii_m: np.ndarray
    counts: np.ndarray
    far_radii_m: np.ndarray | None = None
    layer_gap_m: float = 0.03
    slice_radii_m: np.ndarray | None = field(default=None, repr=False, compare=False)
    """(B, S) each sub-slice's radius per bin (NaN where it did not see the bin), for the
    uncertainty from the section changing along its length."""
    both_layers: np.ndarray | None = field(default=None, repr=False, compare=False)
    """(B,) bool: bins where the near surface and the far layer behind it were both seen in
    the same sub-slices, in as many as a bin needs to be seen (``wall_behind_deg``)."""

    @property
    def seen(self) -> np.ndarray:
        return ~np.isnan(self.radii_m)

    @property
    def coverage_ratio(self) -> float:
        """Share of the perimeter, by angle, that has measured points."""
        return float(self.seen.mean())

    @property
    def max_gap_deg(self) -> float:
        """The longest run of unseen bins, in degrees (wrapping around)."""
        return longest_unseen_deg(self.seen)

    def filled_radii(self) -> np.ndarray:
        """Radii of the nearest surface, with unseen bins linearly interpolated around the circle.

        Only for drawing and for figures whose status already says the gap is small; a gap
        never becomes a confident number through this.
        """
        seen = self.seen
        if not seen.any():
            raise GeometryError("no bin of the section has points")
        a = self.angles_rad
        return np.interp(a, a[seen], self.radii_m[seen], period=2.0 * np.pi)

    def star_area_m2(self) -> float:
        """Area inside the nearest surface, by the polar integral ``½ Σ r² Δθ`` (gaps
        interpolated).

        Exact for a circle at any bin count, where a polygon through the bin radii falls short
        by ``(2π/B)² / 6`` of the area (0.13 % at 72 bins).
        """
        r = self.filled_radii()
        return float(0.5 * np.sum(r * r) * 2.0 * np.pi / len(r))

    def star_polygon(self) -> np.ndarray:
        """The nearest surface as a polygon (B, 2), gaps interpolated (see ``filled_radii``)."""
        r = self.filled_radii()
        return np.column_stack((r * np.cos(self.angles_rad), r * np.sin(self.angles_rad)))

    @cached_property
    def _two_layers(self) -> np.ndarray:
        """(B,) bool: the seen bins with a far layer ``layer_gap_m`` or more beyond the near
        one (none without far radii)."""
        if self.far_radii_m is None:
            return np.zeros(len(self.radii_m), dtype=bool)
        near, far = self.radii_m, self.far_radii_m
        two = self.seen & np.isfinite(far)
        two[two] = far[two] - near[two] >= self.layer_gap_m
        return two

    def _two_layer_runs(self) -> list[tuple[np.ndarray, bool, bool]]:
        """Runs of consecutive bins that hold two layers (a far layer ``layer_gap_m`` beyond
        the near one), each with whether the wall continues from the open bin before its
        first bin and after its last (the open bin reaches the far layer's radius within
        ``layer_gap_m``). Bins in circular order; none when no bin, or every bin, holds two."""
        if self.far_radii_m is None:
            return []
        near, far, seen, layer_gap_m = self.radii_m, self.far_radii_m, self.seen, self.layer_gap_m
        bins = len(near)
        two = self._two_layers
        if not two.any() or two.all():
            return []

        def wall_beside(neighbour: int, edge: int) -> bool:
            return bool(
                seen[neighbour]
                and not two[neighbour]
                and abs(near[neighbour] - far[edge]) <= layer_gap_m
            )

        runs = []
        start = int(np.argmin(two))  # a bin outside every run
        idx = np.roll(np.arange(bins), -start)
        flags = two[idx]
        i = 0
        while i < bins:
            if not flags[i]:
                i += 1
                continue
            j = i
            while j + 1 < bins and flags[j + 1]:
                j += 1
            run = idx[i : j + 1]
            before, after = idx[i - 1], idx[(j + 1) % bins]
            runs.append((run, wall_beside(before, run[0]), wall_beside(after, run[-1])))
            i = j + 1
        return runs

    def wall_behind_deg(self) -> float:
        """The widest run of bins where a surface was seen in front of the wall across its
        whole width, and the wall behind it in the same sub-slices, in degrees (0 when none):
        the bins of such a run where both layers were seen in the same sub-slices
        (``both_layers``; a face across the axis that a section straddles holds its two
        layers in different sub-slices, the wall before it and the face after).

        The wall behind an object attached to it (a box hanging from the crown, a root, a
        deposit) lies inside the object: no ray reaches it. Beside the object's edge it can
        be seen (a pocket, ``pocket_polygons``), but then the run of two-layer bins starts at
        that edge and ends where the object meets the wall. A run with the wall continuing on
        both sides is an object floating in front of a wall seen whole behind it: frames that
        disagree about where the object is (one registered too far along the pipe places it
        where the others saw the wall), not a surface in the pipe.
        """
        if self.both_layers is None:
            return 0.0
        widths = [
            int(self.both_layers[run].sum())
            for run, first, last in self._two_layer_runs()
            if first and last
        ]
        return 360.0 * max(widths, default=0) / len(self.radii_m)

    def pocket_polygons(self) -> list[np.ndarray]:
        """Free space seen behind the edge of an overhanging obstacle, one polygon per pocket.

        An obstacle that hangs from the crown (or juts from the side) can have free space
        beside it that a ray from the centre would only reach through the obstacle. The
        sensor, looking past the obstacle's edge from elsewhere, still sees the wall there:
        those bins hold two layers, the obstacle's near face and the wall beyond it. A pocket
        is a run of such bins that starts at the obstacle's edge, where the wall continues
        from the open bins beside it. Its polygon runs from the edge, out along the wall
        that was seen, and back to the edge in a straight line: the wall further on, which no
        ray reached, counts as blocked. A run that does not start at a visible edge (a hole,
        or an island such as a root seen from below, whose far side is unseen) is left out:
        it stays blocked (and a section with the wall seen behind an island across its whole
        width is not ``ok``: ``wall_behind_deg``). The far layer must lie ``layer_gap_m``
        beyond the near one, and the open bin beside the run must reach the far layer's radius
        within ``layer_gap_m``.

        Returns
        -------
        list of (M, 2) float
        """
        near, far, bins = self.radii_m, self.far_radii_m, len(self.radii_m)
        if far is None:
            return []  # one layer: no run has a far side (``_two_layer_runs``)
        half_bin = np.pi / bins
        pockets = []
        for run, edge_first, edge_last in self._two_layer_runs():
            if edge_first == edge_last:
                continue
            wall = (run[0] - 1) % bins if edge_first else (run[-1] + 1) % bins
            if edge_last:
                run = run[::-1]
            theta_edge = self.angles_rad[run[0]] + (-half_bin if edge_first else half_bin)
            # The edge bin can straddle the obstacle's edge (its sub-slices disagree, and
            # its near radius is halfway out): the edge is the nearer of the first two.
            # From there the pocket starts at the open bin's wall point, a vertex of the
            # nearest-surface polygon, so that their union has no notch.
            r_edge = float(near[run[:2]].min())
            theta = np.concatenate(([theta_edge, self.angles_rad[wall]], self.angles_rad[run]))
            radius = np.concatenate(([r_edge, near[wall]], far[run]))
            pockets.append(np.column_stack((radius * np.cos(theta), radius * np.sin(theta))))
        return pockets

    def hidden_polygons(self) -> list[np.ndarray]:
        """Free space that may lie hidden beside an overhanging obstacle's edge, one polygon per
        edge: what the contour counts as blocked only because no ray reached it.

        Beside the edge of an obstacle that stands off the wall (a box hanging from the crown,
        a body on the invert, a lateral), the contour runs from the edge to the last wall point
        seen beyond it (the far end of its pocket, ``pocket_polygons``, or the open bin's wall
        point when no pocket was seen) and counts everything past that line as blocked. How
        much of it is free depends on the obstacle's side, which no ray reached. The model
        stated here: the side leaves the edge at right angles to the obstacle's near face (a
        box's side to its underside) and runs to the wall. Its polygon runs from the edge
        along that side to the wall, along the wall back to the last wall point seen, and back
        to the edge. A side that slants back under the obstacle hides more; one along the line
        of sight hides nothing (the contour's own count).

        An edge is a step inwards by more than ``layer_gap_m`` from a bin on the wall (within
        ``layer_gap_m`` of the section's median radius) to the next seen bin. The near face
        is the first run of at least three bins, up to 10°, that follow on without such a
        step, after the bin at the edge (and the next, when the run cannot start there: both
        straddle the edge, their radii anywhere between the wall's and the face's). The wall
        there is the open bin's radius. The face's line, continued to the open bin, must stay
        inside the wall there by more than ``layer_gap_m``: a surface that runs on into the
        wall (a deposit's top, seen in coarse bins) steps in the same way but hides nothing.

        Returns
        -------
        list of (M, 2) float
        """
        near, seen = self.radii_m, self.seen
        if seen.sum() < 3:
            return []
        gap = self.layer_gap_m
        wall = seen & (near >= float(np.median(near[seen])) - gap)
        polygons = []
        for d in (1, -1):
            with np.errstate(invalid="ignore"):
                steps_in = near - np.roll(near, -d) > gap
            for o in np.flatnonzero(wall & (~np.roll(seen, -d) | steps_in)):
                polygon = self._hidden_beside(int(o), d)
                if polygon is not None:
                    polygons.append(polygon)
        return polygons

    def _face_after(self, o: int, d: int) -> list[int]:
        """The near face past the edge that follows the wall bin ``o`` going ``d`` (±1): the
        bins of the first run of three or more, up to 10°, that follow on without a step,
        after the first seen bin (and after the next, when the run cannot start there: both
        straddle the edge); [] when there is no such face or no step in from the wall."""
        near, seen, bins, gap = self.radii_m, self.seen, len(self.radii_m), self.layer_gap_m
        e, skipped = (o + d) % bins, 0  # an unseen arc may lie between the wall and the face
        while not seen[e] and skipped < bins // 4:
            e, skipped = (e + d) % bins, skipped + 1
        if not seen[e] or near[o] - near[e] <= gap:
            return []
        longest = max(3, round(bins * 10.0 / 360.0))
        for start in ((e + d) % bins, (e + 2 * d) % bins):
            if not seen[start]:
                continue
            face, k = [start], start
            while len(face) < longest:
                nxt = (k + d) % bins
                if not seen[nxt] or abs(near[nxt] - near[k]) > gap:
                    break
                face.append(nxt)
                k = nxt
            if len(face) >= 3:
                # The face must stand in from the wall where it starts.
                return face if near[o] - near[start] > gap else []
        return []

    def _hidden_beside(self, o: int, d: int) -> np.ndarray | None:
        """The hidden polygon beside the edge after wall bin ``o`` going ``d`` (see
        ``hidden_polygons``), or None when nothing is hidden there."""
        near, bins, angles = self.radii_m, len(self.radii_m), self.angles_rad
        face = self._face_after(o, d)
        if not face:
            return None
        # The last wall point seen past the edge: the far end of the pocket (the run of bins
        # from the first seen one past the wall bin, with the wall seen behind the face), else
        # the wall bin's own.
        last, k = None, (o + d) % bins
        while not self.seen[k] and k != o:
            k = (k + d) % bins
        while self._two_layers[k] and k != o:
            last, k = k, (k + d) % bins
        theta_last, r_last = angles[o], float(near[o])
        if last is not None and self.far_radii_m is not None:
            theta_last, r_last = angles[last], float(self.far_radii_m[last])
        xy = near[face, None] * np.column_stack((np.cos(angles[face]), np.sin(angles[face])))
        centre = xy.mean(axis=0)
        along = np.linalg.svd(xy - centre, full_matrices=False)[2][0]
        side = np.array([-along[1], along[0]])
        offset = float(centre @ side)  # the face's line: {p : p · side = offset}
        # The edge: where the face's line meets the ray through the first bin wholly on the
        # face. The corner lies within the bins before it, which straddle it: this is the
        # innermost place it can be, so that the hidden region is not under-counted (at most
        # a bin's worth over).
        theta_edge = angles[face[0]]
        ray = np.array([np.cos(theta_edge), np.sin(theta_edge)])
        towards = np.array([np.cos(angles[o]), np.sin(angles[o])])
        if abs(ray @ side) < 1e-9 or abs(towards @ side) < 1e-9:
            return None
        edge = ray * offset / float(ray @ side)
        if not 0.0 < float(edge @ ray) < near[o]:
            return None
        # A surface that runs on into the wall (a deposit's top meeting it at a shallow angle,
        # seen in coarse bins) is no overhang: continued to the wall bin, its line must stay
        # inside the wall there by more than the layer gap.
        reach = offset / float(towards @ side)
        if reach <= 0.0 or reach >= near[o] - self.layer_gap_m:
            return None
        side = side if side @ edge > 0 else -side
        radius = float(near[o])
        b = float(side @ edge)
        disc = b * b - (float(edge @ edge) - radius * radius)
        if disc <= 0:
            return None
        meets = edge + (-b + np.sqrt(disc)) * side
        beyond = _wrapped(float(np.arctan2(meets[1], meets[0])) - theta_edge) * d
        reached = _wrapped(theta_last - theta_edge) * d
        if beyond <= reached:
            return None
        arc = theta_edge + d * np.linspace(beyond, reached, 16)
        along_wall = radius * np.column_stack((np.cos(arc), np.sin(arc)))
        along_wall[-1] = r_last * np.array([np.cos(theta_last), np.sin(theta_last)])
        return np.vstack((edge, along_wall))

    def hidden_area_m2(self) -> float:
        """Area of the free space that may lie hidden beside overhanging obstacles
        (``hidden_polygons``), outside the contour's free region, m²."""
        polygons = self.hidden_polygons()
        if not polygons:
            return 0.0
        import shapely

        hidden = shapely.union_all([shapely.make_valid(shapely.Polygon(p)) for p in polygons])
        free = (
            self._free_region[1]
            if self._free_region is not None
            else shapely.Polygon(self.star_polygon())
        )
        return float(shapely.difference(hidden, shapely.make_valid(free)).area)

    @cached_property
    def _free_region(self):
        """The nearest-surface polygon and its union with the pockets, as shapely geometries;
        None when there is no pocket (most sections: no polygon work at all then)."""
        pockets = self.pocket_polygons()
        if not pockets:
            return None
        import shapely

        star = shapely.Polygon(self.star_polygon())
        parts = [shapely.make_valid(shapely.Polygon(p)) for p in pockets]
        return star, shapely.union_all([star, *parts])

    def area_m2(self) -> float:
        """Open area: inside the nearest surface (``star_area_m2``) plus the pockets seen
        behind overhanging obstacles (``pocket_polygons``) that the nearest surface leaves out.
        """
        area = self.star_area_m2()
        if self._free_region is None:
            return area
        star, free = self._free_region
        return area + float(free.area - star.area)

    def polygon(self) -> np.ndarray:
        """The contour polygon (M, 2): the nearest surface, gaps interpolated (see
        ``filled_radii``), with any pockets seen behind overhanging obstacles added."""
        if self._free_region is None:
            return self.star_polygon()
        import shapely

        _, free = self._free_region
        if not isinstance(free, shapely.Polygon):
            free = max(shapely.get_parts(free), key=lambda g: g.area)
        return np.asarray(free.exterior.coords, dtype=np.float64)[:-1]


def polar_profile(
    points: np.ndarray,
    *,
    bins: int = 360,
    slices: int = 4,
    min_slices: int = 3,
    section_length_m: float | None = None,
    centre: np.ndarray | None = None,
    layer_gap_m: float = 0.03,
    min_layer_points: int = 3,
    min_cell_share: float = 0.25,
    min_bin_share: float = 0.0,
    polar: tuple[np.ndarray, np.ndarray] | None = None,
) -> PolarProfile:
    """Robust radius per angle bin, judged along the section's length.

    (Over 80 lines for this reference docstring only: the body is about 60, its steps named:
    ``_sorted_by_cell``, ``_near_layer_length``, ``_voting_cells``, ``_far_layer``.)

    The section is split into ``slices`` sub-slices along the axis. Each (bin, sub-slice) cell
    gets the median radius of its points; a bin is seen when at least ``min_slices`` of its
    sub-slices have points (each at least ``min_cell_share`` of their median count), and its
    radius is the median of those sub-slice radii. So a face
    perpendicular to the axis (an obstacle's front, the pipe's end wall), which lies in one
    sub-slice, is outvoted by the wall behind it; and a few points that leak across the
    section's boundary from a neighbour cannot make an unseen arc (a shadow) look seen.

    A cell whose sorted radii jump by more than ``layer_gap_m``, with at least
    ``min_layer_points`` on each side of the jump, holds two layers: the near face of an
    obstacle and, beyond it, the wall the sensor saw past the obstacle's edge. The cell's
    radius is then the near layer's median. The points more than ``layer_gap_m`` beyond the
    bin's near surface make its far layer, seen when ``min_slices`` sub-slices have such
    points; its radius is the median of their sub-slice medians. ``PolarProfile.pocket_polygons``
    uses it to count the free space behind an obstacle's edge that the sensor actually saw.

    Parameters
    ----------
    points : (N, 2) or (N, 3) float
        Section points, metres: columns 0-1 in the section plane with the axis at the origin,
        column 2 (optional) the distance along the axis from the section's start. Without it,
        the whole section counts as one sub-slice.
    bins : int
        Number of equal angle bins around the centre.
    slices, min_slices : int
        Sub-slices along the section, and how many must have points for a bin to be seen.
    section_length_m : float, optional
        Length of the section (default: the span of column 2).
    centre : (2,) float, optional
        Centre of the profile; default the origin (the fitted axis).
    min_cell_share : float
        A sub-slice sees a bin only when it holds at least this share of the median count of
        the bin's sub-slices.
    layer_gap_m : float
        Radial jump, metres, that separates two layers in a cell (several times the range
        noise).
    min_layer_points : int
        Points each layer needs, so that a few stray returns cannot make a layer.
    min_bin_share : float
        A bin holding fewer than this share of the median count of the section's bins with
        points is unseen (for sparse sections cut into few sub-slices, where the sub-slice
        vote cannot tell a few leaked points from a seen wall). 0: no such test.
    polar : ((N,), (N,)) float, optional
        The points' angles and radii about the origin (``base.polar_coordinates``), when the
        caller has them already; only with the default ``centre``.

    Returns
    -------
    PolarProfile
    """
    pts = np.asarray(points, dtype=np.float64)
    if polar is None:
        c = np.zeros(2) if centre is None else np.asarray(centre, dtype=np.float64)
        polar = polar_coordinates(pts[:, :2] - c)
    elif centre is not None:
        raise ValueError("polar_profile: pass polar coordinates only about the origin")
    ang, rad = polar
    b_idx = angle_bins(ang, bins)
    if pts.shape[1] >= 3 and len(pts):
        length = section_length_m or max(float(np.ptp(pts[:, 2])), 1e-9)
        s_idx = np.clip((pts[:, 2] * slices / length).astype(np.int64), 0, slices - 1)
    else:
        slices, min_slices = 1, 1
        s_idx = np.zeros(len(pts), dtype=np.int64)
    counts = np.bincount(b_idx * slices + s_idx, minlength=bins * slices)
    sorted_rad, starts = _sorted_by_cell(b_idx * slices + s_idx, rad, counts)
    near_median = np.full(bins * slices, np.nan)
    if len(pts):
        good = np.flatnonzero(counts > 0)
        lo, n = starts[good], counts[good]
        near_median[good] = _run_median(
            sorted_rad, lo, _near_layer_length(sorted_rad, lo, n, layer_gap_m, min_layer_points)
        )
    per_cell = counts.reshape(bins, slices)
    near_per_bin = _voting_cells(near_median.reshape(bins, slices), per_cell, min_cell_share)
    seen = np.isfinite(near_per_bin).sum(axis=1) >= min_slices
    if min_bin_share > 0:
        per_bin = per_cell.sum(axis=1)
        if (per_bin > 0).any():
            seen &= per_bin >= min_bin_share * float(np.median(per_bin[per_bin > 0]))
    radii = np.full(bins, np.nan)
    far_radii = np.full(bins, np.nan)
    both = np.zeros(bins, dtype=bool)
    if seen.any():
        radii[seen] = np.nanmedian(near_per_bin[seen], axis=1)
        far_radii, both = _far_layer(
            sorted_rad, starts, counts, radii, near_per_bin, seen, layer_gap_m, min_slices
        )
    angles = (np.arange(bins) + 0.5) * 2.0 * np.pi / bins
    return PolarProfile(
        angles_rad=angles,
        radii_m=radii,
        counts=counts.reshape(bins, slices).sum(1),
        far_radii_m=far_radii,
        layer_gap_m=layer_gap_m,
        slice_radii_m=near_per_bin,
        both_layers=both,
    )


def _sorted_by_cell(
    cell: np.ndarray, rad: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The radii sorted by (cell, radius), so that a cell's points are one run in order of
    radius, and where each cell's run starts."""
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    if not len(rad):
        return rad, starts
    # One float key (the cell plus the radius as a fraction below 1) sorts about ten times
    # faster than ``np.lexsort`` on the two.
    order = np.argsort(cell + rad / (float(rad.max()) * (1.0 + 1e-9) + 1e-300))
    return rad[order], starts


def _voting_cells(
    near_per_bin: np.ndarray, per_cell: np.ndarray, min_cell_share: float
) -> np.ndarray:
    """(B, S) each cell's near radius, NaN where the cell does not vote.

    A sub-slice that holds only a few points where the others hold many (the edge of a
    deposit's plateau leaking past the place where its hidden downstream ramp begins) did not
    see that bin: it does not vote. Relative to the bin's median sub-slice (not its densest: a
    face across the axis packs one sub-slice), so it holds at any point density.
    """
    typical = np.median(per_cell, axis=1, keepdims=True)
    return np.where(per_cell < min_cell_share * typical, np.nan, near_per_bin)


def _far_layer(
    sorted_rad: np.ndarray,
    starts: np.ndarray,
    counts: np.ndarray,
    radii: np.ndarray,
    near_per_bin: np.ndarray,
    seen: np.ndarray,
    layer_gap_m: float,
    min_slices: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(B,) the far layer's radius (NaN where none was seen) and (B,) bool, the bins where
    the near surface and a far layer were seen in the same sub-slices.

    The far layer: the points of each cell beyond the bin's near surface by more than the
    gap, a suffix of the cell's sorted run. Pooled by bin, as it is sparse.
    """
    bins, slices = near_per_bin.shape
    good = np.flatnonzero(counts > 0)
    cell_of = np.repeat(good, counts[good])
    with np.errstate(invalid="ignore"):
        beyond = sorted_rad >= radii[cell_of // slices] + layer_gap_m
    far_n = np.bincount(cell_of[beyond], minlength=bins * slices)
    has_far = far_n > 0
    far_median = np.full(bins * slices, np.nan)
    far_median[has_far] = _run_median(
        sorted_rad, (starts + counts - far_n)[has_far], far_n[has_far]
    )
    far_per_bin = far_median.reshape(bins, slices)
    far_seen = seen & (np.isfinite(far_per_bin).sum(axis=1) >= min_slices)
    far_radii = np.full(bins, np.nan)
    if far_seen.any():
        far_radii[far_seen] = np.nanmedian(far_per_bin[far_seen], axis=1)
    # Sub-slices that hold the bin's near surface and, in the same cell, a far layer.
    with np.errstate(invalid="ignore"):
        near_here = np.abs(near_per_bin - radii[:, None]) < layer_gap_m
    both = (near_here & np.isfinite(far_per_bin)).sum(axis=1) >= min_slices
    return far_radii, both


def _wrapped(angle_rad: float) -> float:
    """An angle difference in (-π, π]."""
    return float(np.angle(np.exp(1j * angle_rad)))


def _run_median(sorted_values: np.ndarray, lo: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Median of each run ``sorted_values[lo : lo + n]`` (every run sorted, n >= 1)."""
    return 0.5 * (sorted_values[lo + (n - 1) // 2] + sorted_values[lo + n // 2])


def _near_layer_length(
    sorted_rad: np.ndarray, lo: np.ndarray, n: np.ndarray, gap_m: float, min_points: int
) -> np.ndarray:
    """How many of each cell's sorted radii belong to its nearest layer.

    The runs ``[lo, lo + n)`` must cover ``sorted_rad`` in order. A cell whose largest jump
    between consecutive radii is at least ``gap_m``, with ``min_points`` or more on each side,
    holds two layers, and its near layer ends at that jump; otherwise the whole run is one
    layer.
    """
    gaps = np.empty_like(sorted_rad)
    gaps[:-1] = np.diff(sorted_rad)
    gaps[lo + n - 1] = -np.inf  # no jump from a cell's last point to the next cell's first
    cell_max = np.maximum.reduceat(gaps, lo)
    at_max = np.flatnonzero(gaps == np.repeat(cell_max, n))
    owner = np.repeat(np.arange(len(lo)), n)[at_max]
    first = np.unique(owner, return_index=True)[1]  # the first largest jump of every cell
    near_n = at_max[first] - lo + 1
    two = (cell_max >= gap_m) & (near_n >= min_points) & (n - near_n >= min_points)
    return np.where(two, near_n, n)


def contour(points: np.ndarray, profile: PolarProfile, params: None = None) -> ContourResult:
    """The polar method: the section profile's own contour (see :class:`PolarProfile`).

    ``points`` are not needed beyond the profile, which was built from them; the method has
    no parameters of its own.
    """
    return ContourResult(
        polygon_m=profile.polygon(), area_m2=profile.area_m2(), radii_m=profile.filled_radii()
    )
