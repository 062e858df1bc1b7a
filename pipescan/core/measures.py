"""Measures of one cross-section, with its coverage and an honest status.

docs/measures.md lists the measures, their names and the status rules. Ratios are fractions;
percentages exist only in reports.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from scipy.ndimage import median_filter

from pipescan.core.coding import CodingParams, WallFeature, arcs_meet, code_contour
from pipescan.core.contour import (
    CONTOUR_PARAMS,
    DEFAULT_CONTOUR_METHOD,
    check_contour_method,
    contour_method,
)
from pipescan.core.contour.base import (
    ContourResult,
    angle_bins,
    angle_from_invert_rad,
    not_veil,
    polar_coordinates,
    remove_stray_points,
)
from pipescan.core.contour.grid import GridParams
from pipescan.core.contour.polar import PolarProfile, polar_profile
from pipescan.core.errors import GeometryError
from pipescan.core.model import SectionMeasures, SectionStatus
from pipescan.core.summary import touches
from pipescan.core.uncertainty import (
    MAD_TO_SIGMA,
    Z95,
    area_uncertainty,
    diameter_uncertainty_m,
    height_uncertainty_m,
    longest_unseen_deg,
    residual_sigma_m,
    smear_bias_m2,
    unseen_area_m2,
)
from pipescan.core.water import WaterLevel, detect_water


@runtime_checkable
class SpreadModel(Protocol):
    """What a section's smear limit is read from: the scan's noise across the surface by where
    the sensor stood (:class:`pipescan.core.instrument.SurfaceNoise`)."""

    def max_spread_m(self, distances_m: np.ndarray) -> float | None:
        """The smear limit of a section seen by frames ``distances_m`` behind it (m)."""
        ...


_BIN_CHOICES = (360, 180, 120, 90, 72)
# Coarser bins for sparse sections (a ring profiler's few hundred points): at least
# _SPARSE_POINTS_PER_BIN points each, never coarser than 20°.
_SPARSE_BIN_CHOICES = (60, 48, 36, 30, 24, 20, 18)  # even: opposite bins pair up
_SPARSE_POINTS_PER_BIN = 8
# Sub-slices along a section and how many must see a bin: the first whose vote the
# section's typical bin passes (see _choose_slices).
_SLICE_CHOICES = ((4, 3), (2, 2), (1, 1))
_SLICE_VOTE_PASS_SHARE = 0.9
# Stray-point removal expects about this many neighbours on a sparse wall (its radius grows).
_STRAY_EXPECTED_NEIGHBOURS = 9.0
# Two layers in a bin lie further apart than this many times the wall's scatter (1σ).
_LAYER_GAP_SIGMAS = 6.0
# Fill lower than this is within the noise of a clean invert.
_DEPOSIT_FLOOR_M = 0.01


@dataclass(frozen=True)
class MeasureParams:
    """How sections are measured and when their figures are trusted.

    Attributes
    ----------
    method : str
        Contour method, a name in ``pipescan.core.contour.CONTOUR_METHODS``; an unknown name
        raises ``OptionError``.
    min_points : int
        Fewer points (after stray-point removal) gives ``too_few_points``, whatever their
        uncertainty.
    min_coverage_ratio : float
        Less of the perimeter seen, by angle, gives ``low_coverage``.
    max_gap_deg : float
        A single unseen arc longer than this also gives ``low_coverage``: interpolating across
        it would be a guess.
    wall_tolerance_ratio : float
        Contour radii within this share of the nominal radius count as wall when measuring
        ovality and deformation; anything further in is a deposit or an obstacle.
    stray_radius_m, stray_min_neighbours, stray_relative_density
        Stray-point removal (see ``remove_stray_points``): a point is kept when its
        neighbourhood holds at least ``stray_relative_density`` of the section's median count.
    veil_relative_density
        The same share, for the veil of mixed returns behind an edge in a dense section
        (``remove_veil_points``); 0 keeps the veil (only to measure what removing it does).
    max_points : int
        A denser section is thinned to this many points, evenly spaced: the
        per-angle medians do not need more, and the cost stays bounded.
    grid : GridParams
        Parameters of the paper's grid method.
    max_uncertainty_ratio : float
        A section whose blockage is not known to within this (95 %, ±) is not ``ok``: it is
        ``low_coverage`` when its unseen arcs (and the free space hidden beside an
        obstacle, ``PolarProfile.hidden_polygons``) make most of the uncertainty, else
        ``too_few_points`` (too few points for the wall's scatter or its edges). 2.5 pp: the
        95 % interval is then no wider than the narrowest condition class of the shipped
        table (BBE 0-5 %), so a measured figure is never more than one class off. A
        section within it but for the smear of frames that disagree
        (``uncertainty.smear_bias_m2``) is ``smeared_wall``.
    max_wall_spread_m : float or None
        A section whose wall points spread around its contour by more than this (robust 1σ,
        pooled over the wall's angle bins) is ``smeared_wall``: the frames that saw it
        disagree. Frames that agree spread the wall by the noise one frame shows across it,
        so a run sets this from the scan's own single-frame wall noise
        (:attr:`pipescan.core.instrument.Instrument.max_wall_spread_m`:
        ``SMEAR_SPREAD_RATIO`` times the noise).
        The default, 8 mm, stands only where the noise is not known. None: no smear test
        (a registered cloud: with no frames to tell apart, its spread is its noise, which
        the uncertainty carries).
    surface_noise : SpreadModel or None
        The scan's noise across the surface by distance along the pipe
        (:class:`pipescan.core.instrument.SurfaceNoise`). Where the sensor positions that saw
        a section are known (``sections.measure_window`` with a trajectory's evidence), its
        smear limit follows from them and replaces ``max_wall_spread_m``: a wall seen from
        close by is seen more head-on and shows more of the range noise.
    max_wall_behind_deg : float
        A section where a surface was seen in front of the wall across more than this arc,
        with the wall behind it seen in the same sub-slices and continuing on both sides
        (``PolarProfile.wall_behind_deg``), is ``smeared_wall`` too: no ray reaches the wall
        behind an object attached to it, so frames disagree about where the object is (a
        slide along the pipe that registration did not see puts the object where the other
        frames saw bare wall). 10°: a real object shows both layers only across its two
        edges, each within one bin and the beam's footprint (2-3° in 1° bins; the most an ok
        section read with the true poses was 4°), well under what an object moved by an
        unseen slide reads (docs/measures.md, *An object where other frames saw bare wall*).
    frame_diameter_m, frame_diameter_se_m : float or None
        The pipe's diameter as single frames see it, and that figure's standard error
        (:func:`pipescan.core.instrument.frame_diameter_m`). A section more open than that
        pipe (its diameter widened by 1.96 standard errors) gets the area it is more open by
        in the smear's part of its blockage ±: a frame cannot be misplaced against itself,
        registered frames can. None (a registered cloud, or too few frames): no such part.
    """

    method: str = DEFAULT_CONTOUR_METHOD
    min_points: int = 100
    min_coverage_ratio: float = 0.9
    max_gap_deg: float = 20.0
    wall_tolerance_ratio: float = 0.12
    stray_radius_m: float = 0.02
    stray_min_neighbours: int = 3
    stray_relative_density: float = 0.02
    veil_relative_density: float = 0.02
    max_points: int = 40_000
    grid: GridParams = field(default_factory=GridParams)
    max_wall_spread_m: float | None = 0.008
    surface_noise: SpreadModel | None = None
    frame_diameter_m: float | None = None
    frame_diameter_se_m: float | None = None
    max_wall_behind_deg: float = 10.0
    max_uncertainty_ratio: float = 0.025

    def __post_init__(self) -> None:
        check_contour_method(self.method)


def choose_bins(point_count: int, *, points_per_bin: int = 16) -> int:
    """Angular bins for a section: as fine as 1° when the points allow, never coarser than 5°."""
    for bins in _BIN_CHOICES:
        if point_count >= points_per_bin * bins:
            return bins
    return _BIN_CHOICES[-1]


def choose_sparse_bins(point_count: int) -> int:
    """Angle bins for a section too sparse for 5° bins: the finest of
    ``_SPARSE_BIN_CHOICES`` with at least 8 points each (never coarser than 20°)."""
    for bins in _SPARSE_BIN_CHOICES:
        if point_count >= _SPARSE_POINTS_PER_BIN * bins:
            return bins
    return _SPARSE_BIN_CHOICES[-1]


def _choose_slices(
    points: np.ndarray, angle_rad: np.ndarray, bins: int, length_m: float
) -> tuple[int, int]:
    """Sub-slices along the section, and how many must see a bin, for a sparse section.

    A dense scan sees every bin along the whole section, so three of four sub-slices are
    asked for. A ring profiler sees each bin only where a ring crosses it (once or twice in a
    section when its rings are a few centimetres apart or tilted), so the vote is sized to
    what the section's bins show: the first of 3-of-4, 2-of-2 and 1-of-1 that 90 % of the
    bins with points pass. A shadow has no points at all and stays unseen whatever
    the vote.
    """
    if points.shape[1] < 3 or len(points) == 0:
        return 1, 1
    b_idx = angle_bins(angle_rad, bins)
    for slices, need in _SLICE_CHOICES:
        s_idx = np.clip((points[:, 2] * slices / length_m).astype(np.int64), 0, slices - 1)
        occupied = np.zeros((bins, slices), dtype=bool)
        occupied[b_idx, s_idx] = True
        per_bin = occupied.sum(axis=1)
        if np.mean(per_bin[per_bin > 0] >= need) >= _SLICE_VOTE_PASS_SHARE:
            return slices, need
    return 1, 1


def _wall_bins(
    radii_m: np.ndarray, seen: np.ndarray, nominal_diameter_m: float, wall_tolerance_ratio: float
) -> np.ndarray:
    """Seen bins whose contour lies at the wall: within ``wall_tolerance_ratio`` of the nominal
    radius. Anything further in is a deposit or an obstacle."""
    return seen & (radii_m >= nominal_diameter_m / 2.0 * (1.0 - wall_tolerance_ratio))


def _diameter_measures(
    radii_m: np.ndarray, seen: np.ndarray, nominal_diameter_m: float, wall_tolerance_ratio: float
) -> tuple[float | None, float | None]:
    """Ovality (ASTM F1216) and deformation (EN 13508-2 BAA) from wall diameters only."""
    bins = len(radii_m)
    half = bins // 2
    wall = _wall_bins(radii_m, seen, nominal_diameter_m, wall_tolerance_ratio)
    pair = wall[:half] & wall[half:]
    if pair.sum() < max(3, half // 6):
        return None, None
    d = radii_m[:half][pair] + radii_m[half:][pair]
    d_mean = float(d.mean())
    ovality = max((float(d.max()) - d_mean) / d_mean, (d_mean - float(d.min())) / d_mean)
    deformation = max(0.0, (nominal_diameter_m - float(d.min())) / nominal_diameter_m)
    return ovality, deformation


DEPOSIT_TOP_HALF_WIDTH_RAD = math.radians(5.0)
"""A section's deposit top is read within this angle either side of straight down."""


def _deposit_height_ratio(
    profile_radii_m: np.ndarray,
    seen: np.ndarray,
    angles_rad: np.ndarray,
    nominal_diameter_m: float,
    wall_tolerance_ratio: float,
) -> float | None:
    """Height of settled material above the invert, as a share of the pipe height.

    The invert is placed at the median wall radius below the centre; the fill's top is the
    median radius within ±5° of straight down (``DEPOSIT_TOP_HALF_WIDTH_RAD``).
    """
    wall = _wall_bins(profile_radii_m, seen, nominal_diameter_m, wall_tolerance_ratio)
    down = angle_from_invert_rad(angles_rad) <= DEPOSIT_TOP_HALF_WIDTH_RAD
    bottom = down & seen
    if not bottom.any() or wall.sum() < 3:
        return None
    r_wall = float(np.median(profile_radii_m[wall]))
    r_bottom = float(np.median(profile_radii_m[bottom]))
    return max(0.0, (r_wall - r_bottom) / nominal_diameter_m)


def wall_spread_m(
    points_2d: np.ndarray,
    profile: PolarProfile,
    wall: np.ndarray,
    *,
    polar: tuple[np.ndarray, np.ndarray] | None = None,
) -> float | None:
    """Robust spread (``MAD_TO_SIGMA`` × MAD, metres) of the points of the wall's bins around their
    bin's radius: the sensor's noise where the frames agree, more where they do not. None
    without wall bins. ``polar``: the points' angles and radii, when the caller has them
    (``contour.base.polar_coordinates``)."""
    bins = len(profile.radii_m)
    ang, rad = polar_coordinates(np.asarray(points_2d)[:, :2]) if polar is None else polar
    b = angle_bins(ang, bins)
    on_wall = wall[b]
    if on_wall.sum() < 10:
        return None
    residual = rad[on_wall] - profile.radii_m[b[on_wall]]
    return float(MAD_TO_SIGMA * np.median(np.abs(residual - np.median(residual))))


def measure_section(
    points_2d: np.ndarray,
    *,
    chainage_start_m: float,
    chainage_end_m: float,
    nominal_diameter_m: float,
    params: MeasureParams = MeasureParams(),
    point_count: int | None = None,
    has_invert: bool = True,
    chainage_uncertainty_m: float | None = None,
    registration_weak: bool = False,
) -> SectionMeasures:
    """Measure one section from its projected points.

    The stages, in order: clean (``_clean``), profile (``_profile``, ``_wall_noise``), water
    (``_water``), contour (``_contour``), figures (``_figures``) and uncertainty
    (``_uncertainty``); :func:`_status` alone decides the status, from what they found.
    (Over 80 lines for its reference docstring only: the body is one call per stage.)

    Parameters
    ----------
    points_2d : (N, 2) or (N, 3) float
        The section's points projected onto the plane perpendicular to the axis, metres, the
        axis at the origin, column 0 across and column 1 up; column 2, when given, is the
        distance along the axis from the section's start (see ``polar_profile``).
    chainage_start_m, chainage_end_m : float
        The section's interval.
    nominal_diameter_m : float
        Design inner diameter.
    params : MeasureParams
    point_count : int, optional
        Points in the section before the caller thinned them (default: as given).
    has_invert : bool
        False for a vertical pipe: no deposit height and no water are read.
    chainage_uncertainty_m : float, optional
        How far the section's true place may be from its chainage (registration's).
    registration_weak : bool
        Most frames that saw the section slid along the axis, or one was extrapolated
        (``RegistrationEvidence``): the status is then ``weak_registration``.

    Returns
    -------
    SectionMeasures
        ``status`` is ``ok`` only when enough of the perimeter was seen with enough points,
        by frames that were registered and agree; else the first reason that applies
        (:func:`_status`). Figures that could be computed are kept for diagnostics even
        when the status is not ok; figures that could not are None.

    Examples
    --------
    >>> theta = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    >>> ring = 0.25 * np.column_stack((np.cos(theta), np.sin(theta)))
    >>> m = measure_section(ring, chainage_start_m=0.0, chainage_end_m=0.1,
    ...                     nominal_diameter_m=0.5)
    >>> m.status.value, round(m.blockage_ratio, 3)
    ('ok', 0.0)
    """
    raw = np.asarray(points_2d, dtype=np.float64)
    nominal_area = math.pi * nominal_diameter_m**2 / 4.0
    base: dict[str, Any] = dict(
        chainage_start_m=float(chainage_start_m),
        chainage_end_m=float(chainage_end_m),
        nominal_area_m2=nominal_area,
        point_count=len(raw) if point_count is None else point_count,
        chainage_uncertainty_m=chainage_uncertainty_m,
    )
    if len(raw) == 0:
        return SectionMeasures(status=_status(_Evidence(0), params), coverage_ratio=0.0, **base)
    length_m = chainage_end_m - chainage_start_m
    clean = _clean(raw, nominal_diameter_m, length_m, params)
    profile = _profile(clean, length_m)
    found = _Evidence(len(raw), len(clean.points), bool(profile.seen.any()))
    if found.points_kept < params.min_points or not found.seen_any:
        status = _status(found, params)
        return SectionMeasures(status=status, coverage_ratio=profile.coverage_ratio, **base)
    noise = _wall_noise(clean, profile, length_m)
    water, profile, water_depth = _water(clean, noise, nominal_diameter_m, has_invert, params)
    from_surface = None if water is None or registration_weak else water.from_surface
    water_u = None if water is None else water.uncertainty_ratio
    if registration_weak:
        water_depth = water_u = None  # withheld with the section (``_status``)
    base.update(coverage_ratio=profile.coverage_ratio, water_depth_ratio=water_depth)
    base.update(water_depth_uncertainty_ratio=water_u)
    base.update(water_from_surface=from_surface)
    found = found.profiled(profile, water, registration_weak)
    contour = _contour(clean, profile, params)
    if contour is None:
        found = dataclasses.replace(found, contour_found=False)
        return SectionMeasures(status=_status(found, params), **base)
    figures = _figures(clean, profile, contour, water, nominal_diameter_m, has_invert, params)
    u = _uncertainty(clean, profile, noise, contour, figures, nominal_diameter_m, params)
    found = found.measured(figures, u)
    if water is not None and not registration_weak:
        above = _above_water_ok(found, profile, water, noise.wall_radius_m, nominal_area, params)
        base.update(above_water_ok=above)
    return SectionMeasures(
        status=_status(found, params),
        contour_m=contour.polygon_m,
        open_area_m2=figures.open_area_m2,
        blockage_ratio=1.0 - figures.open_area_m2 / nominal_area,
        **figures.measures(),
        **u.measures(),
        **base,
    )


def _above_water_ok(
    found: _Evidence,
    profile: PolarProfile,
    water: WaterLevel,
    wall_radius_m: float,
    nominal_area_m2: float,
    params: MeasureParams,
) -> bool:
    """Whether what was seen above the water passes the rules after the water's
    (:func:`_status`): coverage and the largest gap over the arc above it, registration, the
    contour, the ± and the smear. The water's bins count as seen, and the ± leaves out what
    their arc may hide: that they were not seen is what makes the figures lower bounds, not
    an uncertainty of them."""
    seen = profile.seen.copy()
    seen[water.bins] = True
    under = (
        unseen_area_m2(profile.seen, wall_radius_m) - unseen_area_m2(seen, wall_radius_m)
    ) / nominal_area_m2
    u = found.blockage_uncertainty_ratio
    found = dataclasses.replace(
        found,
        water=None,
        coverage_ratio=float(seen.mean()),
        max_gap_deg=longest_unseen_deg(seen),
        blockage_uncertainty_ratio=None if u is None else u - under,
        blockage_uncertainty_but_smear_ratio=found.blockage_uncertainty_but_smear_ratio - under,
    )
    return _status(found, params) == SectionStatus.OK


@dataclass(frozen=True)
class _Evidence:
    """What a section's status is decided on. A stage that was not reached leaves its fields
    at their defaults, which no rule after it reads."""

    points_given: int
    points_kept: int = 0
    seen_any: bool = False
    water: WaterLevel | None = None
    coverage_ratio: float = 0.0
    max_gap_deg: float = 360.0
    registration_weak: bool = False
    contour_found: bool = True
    blockage_uncertainty_ratio: float | None = None
    blockage_uncertainty_but_smear_ratio: float = 0.0
    unseen_first: bool = False
    wall_spread_m: float | None = None
    wall_behind_deg: float | None = None

    def profiled(
        self, profile: PolarProfile, water: WaterLevel | None, registration_weak: bool
    ) -> _Evidence:
        """With what the profile (water's bins left out) and registration show."""
        return dataclasses.replace(
            self,
            water=water,
            coverage_ratio=profile.coverage_ratio,
            max_gap_deg=profile.max_gap_deg,
            registration_weak=registration_weak,
        )

    def measured(self, figures: _Figures, u: _Uncertainty) -> _Evidence:
        """With what the figures and their uncertainties show."""
        return dataclasses.replace(
            self,
            blockage_uncertainty_ratio=u.blockage_ratio,
            blockage_uncertainty_but_smear_ratio=u.blockage_but_smear_ratio,
            unseen_first=u.unseen_first,
            wall_spread_m=figures.wall_spread_m,
            wall_behind_deg=figures.wall_behind_deg,
        )


def _status(found: _Evidence, params: MeasureParams) -> SectionStatus:
    """The one place a section's status is decided: the first rule that applies, in the
    order of docs/measures.md ("Status"): points, coverage and water, registration, the
    contour, the uncertainty's bound, then the smear."""
    max_u = params.max_uncertainty_ratio
    if found.points_given == 0:
        return SectionStatus.OUTSIDE_SCAN
    if found.points_kept < params.min_points:
        return SectionStatus.TOO_FEW_POINTS
    if not found.seen_any:
        return SectionStatus.LOW_COVERAGE
    if found.water is not None and found.registration_weak:
        # Water's level is where the frames put the wall or its surface: no better than the
        # registration that placed them (a rosette's read 22-44 pp off).
        return SectionStatus.WEAK_REGISTRATION
    if found.water is not None and not found.water.from_surface:
        # Water with no return from its surface: one section cannot tell it from a view that
        # stops short of the invert. Low coverage, until the sections along the pipe agree
        # on its level (``core.water.confirm_surfaceless_water``).
        return SectionStatus.LOW_COVERAGE
    if found.water is not None:
        return SectionStatus.INVERT_UNDER_WATER
    if found.coverage_ratio < params.min_coverage_ratio or found.max_gap_deg > params.max_gap_deg:
        return SectionStatus.LOW_COVERAGE
    if found.registration_weak:
        return SectionStatus.WEAK_REGISTRATION
    if not found.contour_found:
        return SectionStatus.NO_CONTOUR
    u = found.blockage_uncertainty_ratio
    if u is not None and u > max_u:
        if found.blockage_uncertainty_but_smear_ratio > max_u:
            return (
                SectionStatus.LOW_COVERAGE if found.unseen_first else SectionStatus.TOO_FEW_POINTS
            )
        return SectionStatus.SMEARED_WALL  # known well enough, but for the smear
    # Frames that disagree smear the wall; frames that disagree along the pipe about where an
    # object is show it in front of a wall that other frames saw bare, across its width.
    spread, max_spread = found.wall_spread_m, params.max_wall_spread_m
    if spread is not None and max_spread is not None and spread > max_spread:
        return SectionStatus.SMEARED_WALL
    behind = found.wall_behind_deg
    if behind is not None and behind > params.max_wall_behind_deg:
        return SectionStatus.SMEARED_WALL
    return SectionStatus.OK


@dataclass(frozen=True)
class _CleanSection:
    """A section's points ready to profile (stage 1, :func:`_clean`).

    ``used`` is the thinned cloud before stray points were removed (water's surface returns
    are read from it); ``points`` what is left, with its polar coordinates. The angle layout
    (``bins``, the sub-slice vote) is chosen from how many points are left.
    """

    used: np.ndarray
    points: np.ndarray
    angle_rad: np.ndarray
    radius_m: np.ndarray
    sparse: bool
    bins: int
    slices: int
    min_slices: int
    min_bin_share: float

    @property
    def polar(self) -> tuple[np.ndarray, np.ndarray]:
        return self.angle_rad, self.radius_m


def _clean(
    raw: np.ndarray, nominal_diameter_m: float, length_m: float, params: MeasureParams
) -> _CleanSection:
    """Stage 1: thin the section, remove stray points, choose the angle layout, and (in a
    dense section) remove the veil behind edges."""
    # Points arrive frame after frame, so evenly spaced picks thin every frame alike. (Not a
    # whole-number stride: a section just over the limit would lose half its points.)
    used = raw
    if len(raw) > params.max_points:
        used = np.take(raw, np.linspace(0, len(raw) - 1, params.max_points).astype(np.int64), 0)
    sparse = len(used) < 16 * _BIN_CHOICES[-1]
    pts = remove_stray_points(
        used,
        radius_m=_stray_radius_m(used, nominal_diameter_m, sparse, params),
        min_neighbours=params.stray_min_neighbours,
        relative_density=params.stray_relative_density,
    )
    # Every step below reads the points' angles and radii: they are computed once per section.
    angle, radius = polar_coordinates(pts)
    if sparse:
        bins = choose_sparse_bins(len(pts))
        slices, min_slices = _choose_slices(pts, angle, bins, length_m)
        min_bin_share = 0.25 if slices == 1 else 0.0
    else:
        bins, slices, min_slices, min_bin_share = choose_bins(len(pts)), 4, 3, 0.0
    if not sparse and len(pts):
        # Rays that graze an edge leave a veil of mixed returns behind it; over many frames it
        # fills the shadow, and would count as seen wall and as blockage.
        kept = not_veil(angle, radius, bins, relative_density=params.veil_relative_density)
        pts, angle, radius = np.compress(kept, pts, axis=0), angle[kept], radius[kept]
    return _CleanSection(used, pts, angle, radius, sparse, bins, slices, min_slices, min_bin_share)


def _stray_radius_m(
    used: np.ndarray, nominal_diameter_m: float, sparse: bool, params: MeasureParams
) -> float:
    """The stray-point neighbourhood: ``params.stray_radius_m``, widened on a sparse wall so
    that a wall point still has neighbours to count (its perimeter is about π diameters)."""
    if not sparse:
        return params.stray_radius_m
    d_m = nominal_diameter_m
    if not math.isfinite(d_m):
        d_m = 2.0 * float(np.median(np.hypot(used[:, 0], used[:, 1])))
    per_m = len(used) / (math.pi * d_m)
    return max(params.stray_radius_m, _STRAY_EXPECTED_NEIGHBOURS / (3.0 * per_m))


def _profile(
    clean: _CleanSection, length_m: float, *, layer_gap_m: float | None = None
) -> PolarProfile:
    """Stage 2: the radius per angle bin (``polar_profile``) in the section's layout."""
    gap: dict[str, Any] = {} if layer_gap_m is None else {"layer_gap_m": layer_gap_m}
    return polar_profile(
        clean.points,
        bins=clean.bins,
        slices=clean.slices,
        min_slices=clean.min_slices,
        section_length_m=length_m,
        min_bin_share=clean.min_bin_share,
        polar=clean.polar,
        **gap,
    )


@dataclass(frozen=True)
class _WallNoise:
    """A section's profile with the wall's scatter (stage 2, :func:`_wall_noise`)."""

    profile: PolarProfile
    sigma_bins_m: np.ndarray
    """(B,) the scatter of each bin's points around its radius, metres (1σ)."""
    sigma_m: float
    """The median of ``sigma_bins_m``."""
    wall_radius_m: float
    """The median radius of the seen bins, before water's bins are left out."""


def _wall_noise(clean: _CleanSection, profile: PolarProfile, length_m: float) -> _WallNoise:
    """The wall's scatter per bin. A noisy sparse wall's own scatter would split a bin into
    two layers (and open pockets that are not there), so such a section is profiled again
    with two layers further apart than ``_LAYER_GAP_SIGMAS`` times the scatter."""
    point_bin = angle_bins(clean.angle_rad, clean.bins)
    sigma_bins = residual_sigma_m(clean.radius_m, point_bin, profile.radii_m)
    sigma_m = float(np.median(sigma_bins))
    if clean.sparse and _LAYER_GAP_SIGMAS * sigma_m > profile.layer_gap_m:
        profile = _profile(clean, length_m, layer_gap_m=_LAYER_GAP_SIGMAS * sigma_m)
        sigma_bins = residual_sigma_m(clean.radius_m, point_bin, profile.radii_m)
        sigma_m = float(np.median(sigma_bins))
    wall_radius_m = float(np.median(profile.radii_m[profile.seen]))
    return _WallNoise(profile, sigma_bins, sigma_m, wall_radius_m)


def _invert_bins(angles_rad: np.ndarray) -> np.ndarray:
    """(B,) bool: the bins within 5° of straight down (or the one bin there, when wider)."""
    return angle_from_invert_rad(angles_rad) <= max(
        DEPOSIT_TOP_HALF_WIDTH_RAD, np.pi / len(angles_rad)
    )


def _water(
    clean: _CleanSection,
    noise: _WallNoise,
    nominal_diameter_m: float,
    has_invert: bool,
    params: MeasureParams,
) -> tuple[WaterLevel | None, PolarProfile, float | None]:
    """Stage 3: water over the invert (``detect_water``), the profile without the bins under
    it, and the water's depth ratio (0.0 where the invert was seen dry, None where it is not
    known)."""
    profile, water = noise.profile, None
    if has_invert and math.isfinite(nominal_diameter_m):
        water = detect_water(
            clean.points,
            profile.angles_rad,
            profile.seen,
            profile.counts,
            profile.radii_m,
            noise.wall_radius_m,
            nominal_diameter_m,
            noise.sigma_m,
            min_coverage_ratio=params.min_coverage_ratio,
            max_gap_deg=params.max_gap_deg,
            surface_points=clean.used,
        )
    if water is None:
        dry = has_invert and bool(profile.seen[_invert_bins(profile.angles_rad)].all())
        return None, profile, 0.0 if dry else None
    # The wall under water was not seen; a sparse line on the surface is not a contour.
    radii = profile.radii_m.copy()
    radii[water.bins] = np.nan
    far = None if profile.far_radii_m is None else profile.far_radii_m.copy()
    if far is not None:
        far[water.bins] = np.nan
    profile = dataclasses.replace(profile, radii_m=radii, far_radii_m=far)
    return water, profile, water.depth_ratio


def _contour(
    clean: _CleanSection, profile: PolarProfile, params: MeasureParams
) -> ContourResult | None:
    """Stage 4: the contour by the run's method, with only that method's parameters; None
    when the method finds no closed contour."""
    own = CONTOUR_PARAMS.get(params.method)
    try:
        return contour_method(params.method)(
            clean.points, profile, None if own is None else getattr(params, own)
        )
    except GeometryError:
        return None


@dataclass(frozen=True)
class _Figures:
    """A section's figures (stage 5, :func:`_figures`)."""

    open_area_m2: float
    hidden_half_m2: float
    radii_smooth_m: np.ndarray
    wall_seen: np.ndarray
    """(B,) bool: seen bins above any deposit's top, which the wall's diameters are read on."""
    deposit_height_ratio: float | None
    ovality_ratio: float | None
    deformation_ratio: float | None
    wall_spread_m: float | None
    wall_behind_deg: float | None

    def measures(self) -> dict[str, Any]:
        """The ``SectionMeasures`` fields these figures fill, but the open area."""
        return dict(
            wall_spread_m=self.wall_spread_m,
            wall_behind_deg=self.wall_behind_deg,
            ovality_ratio=self.ovality_ratio,
            deformation_ratio=self.deformation_ratio,
            deposit_height_ratio=self.deposit_height_ratio,
        )


def _figures(
    clean: _CleanSection,
    profile: PolarProfile,
    contour: ContourResult,
    water: WaterLevel | None,
    nominal_diameter_m: float,
    has_invert: bool,
    params: MeasureParams,
) -> _Figures:
    """Stage 5: open area, deposit height, ovality, deformation and the smear's two signs."""
    d_m, tolerance = nominal_diameter_m, params.wall_tolerance_ratio
    # Beside an overhanging obstacle's edge, free space that no ray reached counts as blocked
    # in the contour; the obstacle's side decides how much of it is free. The figure is the
    # middle of the two ends (the side along the line of sight: none free; at right angles to
    # the obstacle's face: all of it), and the ± spans both (``hidden_m2``).
    hidden_half = 0.5 * profile.hidden_area_m2()
    open_area = contour.area_m2 + hidden_half
    # A 5-bin running median keeps single noisy bins from setting D_min or D_max.
    radii_smooth = median_filter(contour.radii_m, size=5, mode="wrap")
    deposit = None
    if has_invert and water is None:
        deposit = _deposit_height_ratio(
            radii_smooth, profile.seen, profile.angles_rad, d_m, tolerance
        )
    # The deposit's flat top meets the wall at a shallow angle, so bins just above the wall
    # tolerance can still be fill: leave everything at or below the fill's top out of the
    # wall's diameters.
    wall_seen = profile.seen.copy()
    if deposit is not None and deposit * d_m > _DEPOSIT_FLOOR_M:
        y_top = -d_m / 2.0 + deposit * d_m
        y = radii_smooth * np.sin(profile.angles_rad)
        wall_seen &= y > y_top + _DEPOSIT_FLOOR_M
    ovality, deformation = _diameter_measures(radii_smooth, wall_seen, d_m, tolerance)
    # Only a dense section can show frames that disagree: a sparse one (a ring profiler's)
    # sees each bin once, so its spread is the range noise, which the uncertainty carries.
    spread = behind = None
    if not clean.sparse:
        wall = _wall_bins(profile.radii_m, wall_seen, d_m, tolerance)
        spread = wall_spread_m(clean.points, profile, wall, polar=clean.polar)
        behind = profile.wall_behind_deg()
    return _Figures(
        open_area,
        hidden_half,
        radii_smooth,
        wall_seen,
        deposit,
        ovality,
        deformation,
        spread,
        behind,
    )


@dataclass(frozen=True)
class _Uncertainty:
    """A section's uncertainties, 95 % (stage 6, :func:`_uncertainty`)."""

    blockage_ratio: float | None
    blockage_but_smear_ratio: float
    """The blockage's, without the smear's part."""
    unseen_first: bool
    """The unseen arcs (and the free space hidden beside an obstacle) make most of it."""
    ovality_ratio: float | None
    deformation_ratio: float | None
    deposit_height_ratio: float | None

    def measures(self) -> dict[str, Any]:
        """The ``SectionMeasures`` fields these uncertainties fill."""
        return dict(
            blockage_uncertainty_ratio=self.blockage_ratio,
            ovality_uncertainty_ratio=self.ovality_ratio,
            deformation_uncertainty_ratio=self.deformation_ratio,
            deposit_height_uncertainty_ratio=self.deposit_height_ratio,
        )


def _uncertainty(
    clean: _CleanSection,
    profile: PolarProfile,
    noise: _WallNoise,
    contour: ContourResult,
    figures: _Figures,
    nominal_diameter_m: float,
    params: MeasureParams,
) -> _Uncertainty:
    """Stage 6: the figures' uncertainties (``core.uncertainty``)."""
    nominal_area = math.pi * nominal_diameter_m**2 / 4.0
    sigma_m, wall_radius_m = noise.sigma_m, noise.wall_radius_m
    wall = _wall_bins(
        figures.radii_smooth_m, figures.wall_seen, nominal_diameter_m, params.wall_tolerance_ratio
    )
    area_u = area_uncertainty(
        contour.radii_m,
        profile.seen,
        profile.counts,
        noise.sigma_bins_m,
        wall_radius_m,
        slice_radii_m=profile.slice_radii_m,
    )
    if not clean.sparse:
        # Frames that disagree read more open; a sparse section sees each bin once, so its
        # scatter is the range noise, which the noise part carries.
        smear = smear_bias_m2(figures.open_area_m2, noise.sigma_bins_m[wall], wall_radius_m)
        area_u = dataclasses.replace(area_u, smear_m2=smear)
    area_u = dataclasses.replace(area_u, hidden_m2=figures.hidden_half_m2)
    if params.frame_diameter_m is not None:
        # Rule: a section more open than the pipe its single frames see (beyond their
        # median's 95 %) adds that much area to the smear's part. Why: a frame cannot be
        # misplaced against itself; registered frames can, and a wall they push out or blur
        # reads open.
        pipe_m2 = math.pi / 4.0 * params.frame_diameter_m**2
        allowed = params.frame_diameter_m + Z95 * (params.frame_diameter_se_m or 0.0)
        if figures.open_area_m2 > math.pi / 4.0 * allowed**2:
            extra = figures.open_area_m2 - pipe_m2
            area_u = dataclasses.replace(area_u, smear_m2=area_u.smear_m2 + extra)
    per_bin = float(np.median(profile.counts[profile.seen]))
    half = clean.bins // 2
    diameter_u = diameter_uncertainty_m(sigma_m, per_bin, int((wall[:half] & wall[half:]).sum()))
    deposit_u = None
    if figures.deposit_height_ratio is not None:
        low = _invert_bins(profile.angles_rad) & profile.seen
        height_u = height_uncertainty_m(
            sigma_m, float(profile.counts[low].sum()), float(profile.counts[wall].sum())
        )
        deposit_u = _finite(height_u / nominal_diameter_m)
    return _Uncertainty(
        blockage_ratio=_finite(area_u.total_m2 / nominal_area),
        blockage_but_smear_ratio=(area_u.total_m2 - area_u.smear_m2) / nominal_area,
        unseen_first=(
            area_u.unseen_m2 + area_u.hidden_m2 >= area_u.noise_m2 + area_u.resolution_m2
        ),
        ovality_ratio=None
        if figures.ovality_ratio is None
        else _finite(diameter_u / (2.0 * wall_radius_m)),
        deformation_ratio=None
        if figures.deformation_ratio is None
        else _finite(diameter_u / nominal_diameter_m),
        deposit_height_ratio=deposit_u,
    )


def withhold_smeared_object_edges(
    sections: Sequence[SectionMeasures],
    params: MeasureParams = MeasureParams(),
    coding: CodingParams = CodingParams(),
    *,
    slack_deg: float = 5.0,
) -> list[SectionMeasures]:
    """Withhold an ok section that holds the edge of an object whose next section is
    ``smeared_wall`` because the object was seen where other frames saw bare wall.

    Such an object (``SectionMeasures.wall_behind_deg`` over ``params.max_wall_behind_deg``)
    is where frames that disagree along the pipe placed it: a box seen before an unseen slide
    and again after it is drawn twice, and the copy where the pipe is clear is a ghost. The
    section that straddles the ghost's front or rear edge holds the ghost in only some of its
    sub-slices, so it cannot show the two layers itself, and it reads a blockage where there
    is none. The doubt is the object's, not the section's: a section that touches the
    smeared one (no chainage between them) and whose displaced wall meets the object's (the
    coder's displaced arcs, :func:`pipescan.core.coding.code_section`, overlapping within
    ``slack_deg``) is ``smeared_wall`` too. Only the sections next to one smeared by the
    object rule are withheld, not their neighbours in turn: an object seen bare-walled
    along its body is smeared in each of those sections by the rule itself.

    Deformations (which move the whole ring, no arc) never carry it. Sections are returned
    in the order given; only statuses change.
    """
    order = sorted(range(len(sections)), key=lambda i: sections[i].chainage_start_m)
    arcs: dict[int, list[WallFeature]] = {}

    def object_arcs(i: int) -> list[WallFeature]:
        if i not in arcs:
            coded = code_contour(sections[i], coding)
            found = coded.features if coded is not None else []
            arcs[i] = [f for f in found if f.arc_from_rad is not None]
        return arcs[i]

    slack = math.radians(slack_deg)
    withheld: set[int] = set()
    for k, i in enumerate(order):
        s = sections[i]
        if not (
            s.status == SectionStatus.SMEARED_WALL
            and s.wall_behind_deg is not None
            and s.wall_behind_deg > params.max_wall_behind_deg
        ):
            continue
        for j in (order[k - 1] if k > 0 else None, order[k + 1] if k + 1 < len(order) else None):
            if j is None or not sections[j].is_ok:
                continue
            n = sections[j]
            if not (
                touches(n.chainage_end_m, s.chainage_start_m)
                or touches(s.chainage_end_m, n.chainage_start_m)
            ):
                continue
            if any(arcs_meet(f, g, slack) for f in object_arcs(i) for g in object_arcs(j)):
                withheld.add(j)
    return [
        dataclasses.replace(s, status=SectionStatus.SMEARED_WALL) if i in withheld else s
        for i, s in enumerate(sections)
    ]


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None
