"""The instrument a scan was made with: its stated profile, or what the scan itself shows.

Every threshold that depends on the sensor is set from one of these, never from the
simulator's own noise:

- **the minimum range** (blind zone): returns nearer than this are the sensor's window, dust
  or a drip on it, never surface; registration drops them, and a registered cloud's first
  points lie about this far ahead of where the sensor started;
- **the wall noise**: how far a single frame's returns scatter across the wall. A section's
  wall seen by frames that agree spreads by this much; more is frames that disagree
  (:data:`SMEAR_SPREAD_RATIO`);
- **the share of the field of view one frame covers** (a non-repetitive pattern fills it
  over several frames): how many frames seed the local map
  (``RegistrationParams.map_seed_frames``), and whether a frame may be skipped at all.

:data:`SENSOR_MODELS` holds published figures of sensors used on crawlers and in shafts;
``inspection.toml``'s ``[sensor]`` table names one (``model = "livox-hap"``), gives its own
figures, or both (its own figures override the model's). What it leaves out is estimated
from the scan (:func:`estimate_instrument`), and the run says which figure came from where.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipescan.core.model import SCAN_PATTERNS as SCAN_PATTERNS
from pipescan.core.model import SensorProfile
from pipescan.core.registration.params import RegistrationParams
from pipescan.core.registration.preprocess import crop_range, early_return_mask
from pipescan.core.uncertainty import MAD_TO_SIGMA

if TYPE_CHECKING:
    from pipescan.core.measures import MeasureParams
    from pipescan.core.registration import FrameStride

SENSOR_MODELS: dict[str, SensorProfile] = {
    "livox-hap": SensorProfile(
        "livox-hap", 0.5, 150.0, 120.0, 25.0, "repetitive", 452_000.0, 0.02,
        "Livox HAP user manual (2022), table 1.2.1: blind zone 0.5 m, 2 cm 1σ at 20 m",
    ),
    "livox-avia": SensorProfile(
        "livox-avia", 1.0, 190.0, 70.4, 77.2, "non_repetitive", 240_000.0, 0.02,
        "Livox Avia user manual (2020): non-repetitive 70.4°×77.2°, 2 cm 1σ at 20 m",
    ),
    "livox-mid-360": SensorProfile(
        "livox-mid-360", 0.1, 70.0, 360.0, 59.0, "non_repetitive", 200_000.0, 0.02,
        "Livox Mid-360 user manual (2023): blind zone 0.1 m, 2 cm 1σ at 10 m",
    ),
    "ouster-os0": SensorProfile(
        "ouster-os0", 0.5, 50.0, 360.0, 90.0, "repetitive", 2_621_440.0, 0.015,
        "Ouster OS0-128 datasheet (rev 7): 2048×128 at 10 Hz, precision 1.5 cm",
    ),
    "velodyne-vlp-16": SensorProfile(
        "velodyne-vlp-16", 0.5, 100.0, 360.0, 30.0, "repetitive", 300_000.0, 0.03,
        "Velodyne VLP-16 datasheet: ±3 cm typical; minimum range as users measure it",
    ),
    "profiler-2d": SensorProfile(
        "profiler-2d", 0.06, 10.0, 270.0, None, "profiler", 43_200.0, 0.04,
        "a 2D LiDAR of the Hokuyo UST-10LX class: 270° at 40 Hz, ±40 mm",
    ),
    "terrestrial": SensorProfile(
        "terrestrial", 0.6, 70.0, 360.0, 300.0, "static", 976_000.0, 0.001,
        "a phase-based terrestrial scanner of the FARO Focus S70 class: ±1 mm ranging error",
    ),
}  # fmt: skip
"""Published figures of sensors used on pipe crawlers and in shafts (``[sensor] model``)."""


SMEAR_SPREAD_RATIO = 1.5
"""A section's wall is smeared when its points spread across it by more than this many times
what frames that agree spread it by (:func:`smear_limit_m`). Frames whose offsets spread
evenly over ``d`` add ``d²/12`` to its square, so 1.5 times is reached at ``d ≈ 3.9σ`` (a few
millimetres on a quiet sensor, centimetres on a noisy one, whose ± grows with its noise
anyway); registration's residual between frames that agree (1-2 mm across the axis on a
repetitive pattern) is within it. Measured: frames that agree read at most 1.43 times the
scan-wide wall noise, and 0.9-1.3 times the spread expected from where the sensor stood
(docs/instrument.md)."""

SMEAR_SPREAD_FLOOR_M = 0.002
"""The limit where the noise across the wall is nil: below it the spread is the section's own
quantisation (1° bins on a 0.15-0.5 m radius are 3-9 mm wide; a bin's points at different
places along it lie a millimetre or two from its median radius on an oval or
deposit-bordered wall). The quantisation adds to the noise in quadrature."""

_NOISE_NEIGHBOURS = 16
_NOISE_SAMPLE_POINTS = 20_000
_CHI2_MEDIAN_13 = 12.34
"""Median of χ² with 13 degrees of freedom: a plane fitted to 16 points with noise σ across it
leaves a smallest covariance eigenvalue whose median is σ² × 12.34 / 16."""

_DISTANCE_BIN_M = 0.25
"""Width of the bins of distance along the pipe in which a frame's noise across the surface is
read (:class:`SurfaceNoise`)."""
_CHI2_MEDIAN_10 = 9.342
"""Median of χ² with 10 degrees of freedom: a quadratic in two angles (6 coefficients) fitted
to 16 ranges with noise σ leaves a residual sum of squares whose median is σ² × 9.342."""
_SMOOTH_RSS_RATIO = 4.0
"""A fit whose residual sum of squares is over this many times its bin's median spans an edge
(χ²₁₀ exceeds 4 × its median once in about 20,000): it is left out of the bin's incidence."""
_MIN_BIN_FITS = 200
"""A distance bin with fewer fits takes the scan's range noise, not its own."""


@dataclass(frozen=True)
class SurfaceNoise:
    """What a scan's single frames show of their noise across the surfaces they hit, by how
    far along the pipe the surface lies from the sensor.

    A return's range noise ``σ_range`` lies along its ray; across the surface it is
    ``σ_range × |cos θ|``, θ between the ray and the surface's normal. A forward-looking sensor
    in a pipe sees the wall far ahead at grazing incidence and the wall beside it more head-on,
    so a section seen by frames standing right behind it scatters more than one seen only from
    afar. The frames' fits of range against direction (:func:`surface_noise`; sensor frame,
    the sensor at the origin) give, per bin of distance along the pipe (the frame's main
    direction), the share of a frame's returns and the noise across the surface there.

    Attributes
    ----------
    distance_edges_m : tuple of float
        (K + 1,) bin edges of the distance along the pipe from the sensor, metres (negative:
        behind it).
    point_share : tuple of float
        (K,) share of a frame's returns in each bin.
    noise_across_m : tuple of float
        (K,) 1σ noise across the surface in each bin: the bin's range noise times its
        ``|cos θ|`` (from the mean of its fits' ``tan² θ``), metres.
    """

    distance_edges_m: tuple[float, ...]
    point_share: tuple[float, ...]
    noise_across_m: tuple[float, ...]

    def spread_m(self, distances_m: np.ndarray) -> float | None:
        """Robust 1σ (``MAD_TO_SIGMA`` × MAD, metres) of the returns a section pools from
        frames whose sensors stood ``distances_m`` behind it along the pipe (each frame
        contributing its share of returns at that distance, each with its noise across the
        surface there), or None when none of them saw it.

        >>> noise = SurfaceNoise((0.0, 1.0, 2.0), (0.5, 0.5), (0.004, 0.002))
        >>> round(noise.spread_m(np.array([0.5])) * 1000, 1)
        4.0
        >>> round(noise.spread_m(np.array([0.5, 1.5])) * 1000, 1)
        2.7
        >>> noise.spread_m(np.array([5.0])) is None
        True
        """
        from scipy.special import erf

        edges = np.asarray(self.distance_edges_m)
        d = np.asarray(distances_m, dtype=np.float64)
        d = d[np.isfinite(d) & (d >= edges[0]) & (d < edges[-1])]
        k = np.searchsorted(edges, d, side="right") - 1
        w = np.bincount(k, minlength=len(self.point_share)) * np.asarray(self.point_share)
        sigma = np.asarray(self.noise_across_m)
        keep = (w > 0) & (sigma > 0)
        if not keep.any():
            return None
        w, sigma = w[keep] / w[keep].sum(), sigma[keep]
        # The pooled returns' median |deviation| m: half of them within ±m (a mixture of
        # normal scatters, one per bin), found by bisection.
        lo, hi = 0.0, 5.0 * float(sigma.max())
        for _ in range(50):
            m = 0.5 * (lo + hi)
            inside = float(np.sum(w * erf(m / (sigma * math.sqrt(2.0)))))
            lo, hi = (m, hi) if inside < 0.5 else (lo, m)
        return MAD_TO_SIGMA * 0.5 * (lo + hi)

    def max_spread_m(self, distances_m: np.ndarray) -> float | None:
        """The smear limit of a section seen from ``distances_m`` (:func:`smear_limit_m` of
        :meth:`spread_m`), or None when none of those frames saw it."""
        spread = self.spread_m(distances_m)
        return None if spread is None else smear_limit_m(spread)


def smear_limit_m(noise_m: float) -> float:
    """The wall spread called smeared where the noise across the wall is ``noise_m`` (1σ):
    :data:`SMEAR_SPREAD_RATIO` times what frames that agree spread it by, the noise and the
    section's quantisation (:data:`SMEAR_SPREAD_FLOOR_M` / the ratio) added in quadrature,
    as independent scatters add.

    >>> round(smear_limit_m(0.0), 4), round(smear_limit_m(0.01), 4)
    (0.002, 0.0151)
    """
    quantisation_m = SMEAR_SPREAD_FLOOR_M / SMEAR_SPREAD_RATIO
    return SMEAR_SPREAD_RATIO * math.hypot(noise_m, quantisation_m)


_VIEW_BIN_DEG = 2.0
SEED_SEEN_TWICE_SHARE = 0.9
"""The local map is seeded by as many consecutive frames as it takes for the directions that
two of them saw (what a keyframe keeps) to reach this share of what the run's frames see:
then a frame finds most of its field of view in the map."""
FULL_VIEW_SHARE = 2.0 / 3.0
"""A frame that covers at least this share of the view is registered as it comes: it then
overlaps a one-frame map over most of its own view (measurements: docs/instrument.md)."""
_VIEW_MIN_FRAMES_RATIO = 0.1
"""A direction belongs to the view when at least this share of the consecutive frames hit it
(a rosette covering a fifth of its view a frame hits each direction in about a fifth)."""
CONSECUTIVE_FRAMES = 30
"""Consecutive frames a run reads to tell how much of the view one frame covers."""


def consecutive_frame_indices(frame_count: int) -> list[int]:
    """The :data:`CONSECUTIVE_FRAMES` frames from the middle of a run of ``frame_count``
    (all of them in a shorter run) that tell how much of the view one frame covers.

    >>> consecutive_frame_indices(100)[:2], len(consecutive_frame_indices(100))
    ([35, 36], 30)
    >>> consecutive_frame_indices(4)
    [0, 1, 2, 3]
    """
    middle = max(
        0, min(frame_count - CONSECUTIVE_FRAMES, frame_count // 2 - CONSECUTIVE_FRAMES // 2)
    )
    return list(range(middle, min(frame_count, middle + CONSECUTIVE_FRAMES)))


_MIN_RANGE_DENSITY_RATIO = 0.2
_MIN_RANGE_RUN_BINS = 5
"""The nearest range actually seen: the first of five 1 cm range bins in a row that each hold
at least a fifth of the 90th-percentile bin's returns (spurious returns inside the blind zone
are sparse at every range; a surface fills every bin it spans)."""


@dataclass(frozen=True)
class Instrument:
    """The figures a run uses, each with where it came from (``profile``, ``estimated`` or
    ``default``).

    Attributes
    ----------
    min_range_m : float
    wall_noise_m : float or None
        Single-frame scatter of returns across the wall, 1σ (None: not known, no smear test
        on noise; the ``max_wall_spread_m`` given is kept). The smear limit where a section's
        incidence is not known.
    range_noise_m : float or None
        1σ range noise along the ray (:func:`surface_noise`; the profile's figure only where
        the scan gives none).
    surface_noise : SurfaceNoise or None
        Noise across the surface by distance along the pipe: each section's smear limit.
    frame_view_share : float
        Share of what the run's frames see that one frame sees (1: each frame covers it).
    map_seed_frames : int
    pattern : str or None
    model : str
    sources : dict
        Field name to ``profile``, ``estimated`` or ``default``.
    """

    min_range_m: float = 0.0
    wall_noise_m: float | None = None
    range_noise_m: float | None = None
    surface_noise: SurfaceNoise | None = None
    frame_view_share: float = 1.0
    map_seed_frames: int = 1
    pattern: str | None = None
    model: str = "unknown"
    sources: dict[str, str] = dataclasses.field(default_factory=dict)
    frame_diameter_m: float | None = None
    frame_diameter_se_m: float | None = None

    @property
    def partial_view(self) -> bool:
        """One frame covers only part of the view: the map is seeded by several frames."""
        return self.map_seed_frames > 1

    @property
    def max_wall_spread_m(self) -> float | None:
        """The smear limit for this scan (None when its noise is not known)."""
        if self.wall_noise_m is None:
            return None
        return smear_limit_m(self.wall_noise_m)

    def describe(self) -> str:
        """One line for the log and the summary."""
        noise = "unknown" if self.wall_noise_m is None else f"{self.wall_noise_m * 1000:.1f} mm"
        ranging = "unknown" if self.range_noise_m is None else f"{self.range_noise_m * 1000:.1f} mm"
        parts = [
            f"sensor {self.model}",
            f"minimum range {self.min_range_m:.2f} m ({self.sources.get('min_range_m', '?')})",
            f"range noise {ranging} ({self.sources.get('range_noise_m', '?')})",
            f"wall noise {noise} ({self.sources.get('wall_noise_m', '?')})",
            f"one frame sees {100 * self.frame_view_share:.0f} % of the view "
            f"({self.sources.get('frame_view_share', '?')})",
        ]
        if self.partial_view:
            parts.append(f"map seeded by {self.map_seed_frames} frames")
        if self.frame_diameter_m is not None:
            parts.append(f"the pipe {self.frame_diameter_m:.3f} m across in single frames")
        return "; ".join(parts)


def wall_noise_m(frames_sensor_m: Sequence[np.ndarray], *, max_range_m: float) -> float | None:
    """Single-frame scatter of returns across the surface they hit, 1σ (m), or None with too
    few points.

    Each sample frame's returns within ``max_range_m`` (at most 20,000, evenly spread) are
    fitted a plane through their 16 nearest neighbours; the median of the smallest
    covariance eigenvalue, scaled by the median of χ²₁₃ (:data:`_CHI2_MEDIAN_13`), gives σ².
    The median keeps edges, corners and stray returns out. A frame sees each surface once, so
    what is left is the sensor's noise across the surface (the wall's curvature over 16
    neighbours a centimetre or two apart adds a fraction of a millimetre).

    Parameters
    ----------
    frames_sensor_m : sequence of (N, 3) float
        Single frames, sensor frame, metres.
    max_range_m : float
        The sections' range.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> a, x = rng.uniform(0, 2 * np.pi, 30_000), rng.uniform(0.5, 4, 30_000)
    >>> r = 0.3 + rng.normal(0, 0.004, 30_000)
    >>> tube = np.column_stack((x, r * np.cos(a), r * np.sin(a)))
    >>> round(wall_noise_m([tube], max_range_m=5.0) * 1000)
    4
    """
    from scipy.spatial import cKDTree

    estimates, weights = [], []
    for frame in frames_sensor_m:
        pts = np.asarray(frame, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"A frame must have shape (N, 3), got {pts.shape}.")
        pts = pts[np.isfinite(pts).all(axis=1)]
        pts = pts[np.einsum("ij,ij->i", pts, pts) <= max_range_m**2]
        if len(pts) < 10 * _NOISE_NEIGHBOURS:
            continue
        if len(pts) > _NOISE_SAMPLE_POINTS:
            pts = pts[np.linspace(0, len(pts) - 1, _NOISE_SAMPLE_POINTS).astype(np.int64)]
        _, idx = cKDTree(pts).query(pts, k=_NOISE_NEIGHBOURS)
        nb = pts[idx] - pts[idx].mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb) / _NOISE_NEIGHBOURS
        smallest = np.linalg.eigvalsh(cov)[:, 0]
        estimates.append(float(np.median(smallest)))
        weights.append(len(pts))
    if not estimates:
        return None
    median = float(np.average(estimates, weights=weights))
    return math.sqrt(max(median, 0.0) * _NOISE_NEIGHBOURS / _CHI2_MEDIAN_13)


def _range_fits(frame_sensor_m: np.ndarray, *, max_range_m: float) -> tuple[np.ndarray, ...]:
    """Local fits of range against direction in one frame (sensor frame, the sensor at the
    origin): for each sampled return (at most :data:`_NOISE_SAMPLE_POINTS`, evenly spread)
    and its 16 nearest neighbours *by direction*, the range fitted as a quadratic in the
    direction (two angles across the neighbourhood's mean ray; the quadratic terms take the
    range's curvature, steep where the rays graze, out of the residual).

    Neighbours are chosen by direction, not in space, so their ranges' scatter is not
    selected against: a plane fitted through the nearest points in space reads less than the
    noise once the noise is as large as the neighbourhood (a tube seen from its axis with
    18 mm of range noise: the plane fits read 4.6 mm, where the wall 0.25-0.5 m ahead has
    11 mm across it).

    Returns ``(point_m, rss_m2, tan2_incidence)``: (N, 3) the returns, (N,) the fits' residual
    sums of squares (σ² χ²₁₀), (N,) ``tan² θ`` from the range's gradient (a surface at
    incidence θ recedes by ``r tan θ`` per radian). The noise's share of the fitted
    gradient's square, ``σ² trace((XᵀX)⁻¹)`` over its two slopes, is taken off, so that a
    noisy fit does not read the surface as more grazing than it is: the square is then
    unbiased, and not always positive.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(frame_sensor_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"A frame must have shape (N, 3), got {pts.shape}.")
    pts = pts[np.isfinite(pts).all(axis=1)]
    r = np.linalg.norm(pts, axis=1)
    in_range = (r > 0) & (r <= max_range_m)
    pts, r = pts[in_range], r[in_range]
    if len(pts) < 10 * _NOISE_NEIGHBOURS:
        return np.empty((0, 3)), np.empty(0), np.empty(0)
    if len(pts) > _NOISE_SAMPLE_POINTS:
        pick = np.linspace(0, len(pts) - 1, _NOISE_SAMPLE_POINTS).astype(np.int64)
        pts, r = pts[pick], r[pick]
    ray = pts / r[:, None]
    _, idx = cKDTree(ray).query(ray, k=_NOISE_NEIGHBOURS)
    mean_ray = ray[idx].mean(axis=1)
    mean_ray /= np.linalg.norm(mean_ray, axis=1, keepdims=True)
    # Two unit vectors across the mean ray: the neighbours' directions in radians along them.
    helper = np.where(np.abs(mean_ray[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(mean_ray, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(mean_ray, e1)
    a = np.einsum("nki,ni->nk", ray[idx], e1)
    b = np.einsum("nki,ni->nk", ray[idx], e2)
    a -= a.mean(1, keepdims=True)
    b -= b.mean(1, keepdims=True)
    # In units of the neighbourhood's own angular size (radians / scale), so that the normal
    # equations are well conditioned; the quadratic terms take the range's curvature (steep
    # where the rays graze) out of the residual.
    scale = np.sqrt(np.mean(a**2 + b**2, axis=1, keepdims=True))
    scale = np.maximum(scale, 1e-12)
    a, b = a / scale, b / scale
    design = np.stack((np.ones_like(a), a, b, a * a, a * b, b * b), -1)
    y = r[idx]
    normal = np.einsum("nki,nkj->nij", design, design)
    rhs = np.einsum("nki,nk->ni", design, y)
    ok = np.linalg.cond(normal) < 1e8
    coef = np.zeros((len(pts), design.shape[2]))
    coef[ok] = np.linalg.solve(normal[ok], rhs[ok][:, :, None])[:, :, 0]
    resid = y - np.einsum("nki,ni->nk", design, coef)
    rss = np.einsum("nk,nk->n", resid, resid)
    slopes_var = np.zeros(len(pts))
    slopes_var[ok] = np.trace(np.linalg.inv(normal[ok])[:, 1:3, 1:3], axis1=1, axis2=2)
    dof = _NOISE_NEIGHBOURS - design.shape[2]
    gradient2 = (coef[:, 1] ** 2 + coef[:, 2] ** 2 - rss / dof * slopes_var) / scale[:, 0] ** 2
    tan2 = gradient2 / np.maximum(coef[:, 0], 1e-9) ** 2
    return pts[ok], rss[ok], tan2[ok]


def surface_noise(
    frames_sensor_m: Sequence[np.ndarray], *, max_range_m: float
) -> tuple[float, SurfaceNoise] | None:
    """The sensor's range noise (1σ along the ray, m) and its noise across the surface by
    distance along the pipe (:class:`SurfaceNoise`), from single frames; None with too few
    returns.

    A smooth surface's range is, over a few neighbouring rays, a quadratic function of their
    direction; what the range scatters about it is the range noise (:func:`_range_fits`: 16
    neighbours, 6 coefficients, so the residual sum of squares is σ² χ²₁₀, whose median is
    σ² × 9.342, :data:`_CHI2_MEDIAN_10`). The median over the fits leaves edges and stray
    returns out. The range's gradient gives the incidence θ, and the noise across the surface
    is ``σ × |cos θ|``. Both are read per bin of distance along the pipe
    (:data:`_DISTANCE_BIN_M`, along the frame's main direction: a pipe's returns stretch along
    it), where a sensor's noise grows with the range and the incidence changes; a bin with
    fewer than :data:`_MIN_BIN_FITS` fits takes the whole scan's range noise.

    Parameters
    ----------
    frames_sensor_m : sequence of (N, 3) float
        Single frames, sensor frame (the sensor at the origin), metres.
    max_range_m : float
        The sections' range.

    Examples
    --------
    A tube seen from its axis, 8 mm of noise along each ray: across the wall, where the rays
    graze it, a frame shows a fraction of it.

    >>> rng = np.random.default_rng(0)
    >>> az, el = np.radians(np.mgrid[-59.9:60:0.4, -11.9:12:0.4]).reshape(2, -1)
    >>> ray = np.column_stack((np.cos(az), np.sin(az), np.sin(el)))
    >>> ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    >>> tube = ray * (0.3 / np.hypot(ray[:, 1], ray[:, 2]))[:, None]
    >>> tube += ray * rng.normal(0, 0.008, (len(ray), 1))
    >>> round(wall_noise_m([tube], max_range_m=5.0) * 1000)
    3
    >>> sigma, by_distance = surface_noise([tube], max_range_m=5.0)
    >>> round(sigma * 1000)
    8
    """
    point, rss, tan = [], [], []
    for frame in frames_sensor_m:
        p, s, t = _range_fits(frame, max_range_m=max_range_m)
        if len(p) == 0:
            continue
        # The frame's main direction (a pipe's returns stretch along it), pointing where most
        # of them lie: each return's distance along the pipe from the sensor.
        centred = p - p.mean(axis=0)
        along = np.linalg.eigh(centred.T @ centred)[1][:, -1]
        d = p @ along
        point.append(d if np.median(d) >= 0 else -d)
        rss.append(s)
        tan.append(t)
    if not point or sum(len(d) for d in point) < _MIN_BIN_FITS:
        return None
    d, s, t = np.concatenate(point), np.concatenate(rss), np.concatenate(tan)
    range_var = float(np.median(s)) / _CHI2_MEDIAN_10
    edges = np.arange(
        math.floor(-max_range_m / _DISTANCE_BIN_M) * _DISTANCE_BIN_M,
        max_range_m + _DISTANCE_BIN_M,
        _DISTANCE_BIN_M,
    )
    k = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, len(edges) - 2)
    share, across = [], []
    for b in range(len(edges) - 1):
        here = k == b
        share.append(float(here.sum()) / len(d))
        if not here.any():
            across.append(0.0)
            continue
        var = (
            float(np.median(s[here])) / _CHI2_MEDIAN_10
            if here.sum() >= _MIN_BIN_FITS
            else range_var
        )
        # The mean of the unbiased squares (a median of them is not unbiased), over the fits
        # on a smooth surface: an edge's fit has a large residual, and a steep gradient.
        smooth = here & (s <= _SMOOTH_RSS_RATIO * float(np.median(s[here])))
        cos = 1.0 / math.sqrt(1.0 + max(0.0, float(np.mean(t[smooth]))))
        across.append(math.sqrt(max(var, 0.0)) * cos)
    return math.sqrt(max(range_var, 0.0)), SurfaceNoise(
        tuple(edges.tolist()), tuple(share), tuple(across)
    )


def _view_bins(frame: np.ndarray) -> np.ndarray:
    """The direction bins (azimuth × elevation, :data:`_VIEW_BIN_DEG`) a frame's returns hit."""
    pts = np.asarray(frame, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    r = np.linalg.norm(pts, axis=1)
    pts, r = pts[r > 0], r[r > 0]
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    el = np.degrees(np.arcsin(np.clip(pts[:, 2] / r, -1.0, 1.0)))
    ia = np.floor((az + 180.0) / _VIEW_BIN_DEG).astype(np.int64)
    ie = np.floor((el + 90.0) / _VIEW_BIN_DEG).astype(np.int64)
    return np.unique(ia * 1000 + ie)


def view_coverage(consecutive_frames: Sequence[np.ndarray]) -> tuple[float, int]:
    """How much of the view one frame covers, and how many consecutive frames seed the map.

    Returns ``(share, seed_frames)``: the median share of the direction bins the run of
    frames hit (at least a tenth of them) that a single frame hits, and the fewest
    consecutive frames whose bins hit by at least two of them reach
    :data:`SEED_SEEN_TWICE_SHARE` of that (1 when a frame covers :data:`FULL_VIEW_SHARE`).

    Examples
    --------
    >>> az = np.radians(np.arange(-60, 60, 0.5))
    >>> el = np.radians(np.arange(-12, 12, 0.5))
    >>> A, E = np.meshgrid(az, el)
    >>> full = np.column_stack((np.cos(A.ravel()), np.sin(A.ravel()), np.sin(E.ravel())))
    >>> view_coverage([full] * 6)
    (1.0, 1)
    >>> thirds = [full[(np.arange(len(full)) + k * 40) % 120 < 40] for k in range(6)]
    >>> share, seed = view_coverage(thirds)
    >>> round(share, 1), seed
    (0.3, 6)
    """
    sets = [_view_bins(f) for f in consecutive_frames]
    sets = [s for s in sets if len(s)]
    if len(sets) < 2:
        return 1.0, 1
    # The view: directions at least a tenth of the frames hit. Directions a frame or two hit
    # (the field of view's rim as the sensor rocks, rays that end inside the blind zone but
    # for an early return) are not what one frame failed to cover.
    bins, hits = np.unique(np.concatenate(sets), return_counts=True)
    every = bins[hits >= max(2, math.ceil(_VIEW_MIN_FRAMES_RATIO * len(sets)))]
    if len(every) == 0:
        return 1.0, 1
    sets = [np.intersect1d(s, every, assume_unique=True) for s in sets]
    share = float(np.median([len(s) / len(every) for s in sets]))
    if share >= FULL_VIEW_SHARE:
        return min(1.0, share), 1
    counts: dict[int, int] = {}
    for g, s in enumerate(sets, start=1):
        for b in s.tolist():
            counts[b] = counts.get(b, 0) + 1
        twice = sum(1 for c in counts.values() if c >= 2)
        if twice >= SEED_SEEN_TWICE_SHARE * len(every):
            return share, g
    return share, len(sets)


def nearest_range_m(frames_sensor_m: Sequence[np.ndarray], *, max_range_m: float) -> float | None:
    """The nearest range at which the frames' returns are dense (m), or None without returns.

    Returns within ``max_range_m`` are binned by range (1 cm); the first bin holding at least
    :data:`_MIN_RANGE_DENSITY_RATIO` of the 90th-percentile bin's count, five in a row, is
    where surfaces begin. Returns nearer than that are sparse: a sensor's window, dust, a drip.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> wall = rng.uniform(0.5, 4.0, 30_000)[:, None] * [[1.0, 0.0, 0.0]]
    >>> dust = rng.uniform(0.02, 0.5, 150)[:, None] * [[1.0, 0.0, 0.0]]
    >>> nearest_range_m([np.vstack((wall, dust))], max_range_m=5.0)
    0.5
    """
    ranges = [np.linalg.norm(np.asarray(f, dtype=np.float64), axis=1) for f in frames_sensor_m]
    r = np.concatenate(ranges) if ranges else np.empty(0)
    r = r[np.isfinite(r) & (r <= max_range_m)]
    if len(r) < 100:
        return None
    counts = np.bincount(np.floor(r / 0.01).astype(np.int64))
    reference = np.percentile(counts[counts > 0], 90)
    dense = counts >= _MIN_RANGE_DENSITY_RATIO * reference
    # The first of _MIN_RANGE_RUN_BINS dense bins in a row: dust is sparse at every range.
    run = np.convolve(dense.astype(np.int64), np.ones(_MIN_RANGE_RUN_BINS, np.int64), "valid")
    first = np.flatnonzero(run == _MIN_RANGE_RUN_BINS)
    if not len(first):
        return None
    # Rule: the start of the dense run that holds the densest ranges, where dense returns
    # nearer than it are cut off from it by sparse bins. Why: rays whose wall lies inside the
    # blind zone come back as dust from every range short of it, dense where no wall is
    # seen at all (a rosette's on `rosette-avia 1`: 60 returns a centimetre at 0.05-0.3 m,
    # 1-4 at 0.3-0.95 m, the wall from 1.0 m), and the first dense run was that dust.
    mode = int(np.argmax(np.convolve(counts, np.ones(_MIN_RANGE_RUN_BINS), "same")))
    begins = first[np.diff(first, prepend=-2) > 1]  # where each dense run starts
    starts = begins[begins <= mode]
    return round(float((starts[-1] if len(starts) else first[0]) * 0.01), 2)


FRAME_DIAMETER_POINTS = 1500
"""Points a frame's cylinder is fitted to (drawn at random, seeded): enough for a radius known to
a fraction of a millimetre; the fit takes 10-40 ms a frame (38 on `slow30-npy`'s)."""


def frame_diameter_m(
    frames_sensor_m: Sequence[np.ndarray],
    *,
    max_range_m: float,
    early_return_ratio: float = RegistrationParams.early_return_ratio,
) -> tuple[float, float] | None:
    """The pipe's inner diameter as single frames see it, and the standard error of that
    figure (m), or None with fewer than five frames that hold a pipe.

    A frame is not registered against anything: its own returns cannot be misplaced against
    each other, so a cylinder fitted to one frame measures the pipe free of registration. Each
    frame's returns within ``max_range_m``, less its early returns
    (:func:`~pipescan.core.registration.preprocess.early_return_mask`, with the registration's
    ``early_return_ratio``), at most
    :data:`FRAME_DIAMETER_POINTS` of them, get a cylinder (:func:`_cylinder_radius_m`); the
    figure is twice the median radius over the frames, its standard error 1.2533 × the
    radii's robust σ / √n (a median's).
    """
    radii = []
    for k, frame in enumerate(frames_sensor_m):
        pts = crop_range(frame, max_range_m)
        pts = pts[early_return_mask(pts, early_return_ratio)]
        if len(pts) < 500:
            continue
        if len(pts) > FRAME_DIAMETER_POINTS:
            pick = np.random.default_rng(k).choice(len(pts), FRAME_DIAMETER_POINTS, replace=False)
            pts = pts[pick]
        radius = _cylinder_radius_m(pts)
        if radius is not None:
            radii.append(radius)
    if len(radii) < 5:
        return None
    r = np.asarray(radii)
    spread = MAD_TO_SIGMA * float(np.median(np.abs(r - np.median(r))))
    return 2.0 * float(np.median(r)), 2.0 * 1.2533 * spread / math.sqrt(len(r))


def _cylinder_radius_m(points_m: np.ndarray) -> float | None:
    """The radius of the cylinder through ``points_m`` (N, 3), or None where the fit fails:
    robust least squares (scipy's ``least_squares``, ``soft_l1`` at 1 cm), the axis started
    along the points' main direction through their centre, then fitted again (twice at most)
    on the points within three robust σ of it: early returns the cell test kept and an
    object's face lie off it by far more than the noise."""
    from scipy.optimize import least_squares

    centre = points_m.mean(axis=0)
    _, _, vt = np.linalg.svd(points_m - centre, full_matrices=False)
    along, u, v = vt[0], vt[1], vt[2]

    def residual(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
        d = along + q[0] * u + q[1] * v
        d = d / np.linalg.norm(d)
        rel = pts - (centre + q[2] * u + q[3] * v)
        perp = rel - np.outer(rel @ d, d)
        return np.sqrt(np.einsum("ij,ij->i", perp, perp)) - q[4]

    pts = points_m
    q = np.zeros(5)
    q[4] = float(np.median(residual(q, pts)))
    for _ in range(3):
        fit = least_squares(residual, q, loss="soft_l1", f_scale=0.01, args=(pts,))
        q = fit.x
        off = residual(q, pts)
        keep = np.abs(off) <= max(3.0 * MAD_TO_SIGMA * float(np.median(np.abs(off))), 1e-3)
        if keep.all() or keep.sum() < 300:
            break
        pts = pts[keep]
    return float(q[4]) if fit.success and q[4] > 0 else None


def estimate_instrument(
    sample_frames: Sequence[np.ndarray],
    consecutive_frames: Sequence[np.ndarray],
    *,
    max_range_m: float,
    profile: SensorProfile | None = None,
) -> Instrument:
    """The run's instrument: the profile's figures where it states them, the scan's own
    otherwise.

    Parameters
    ----------
    sample_frames : sequence of (N, 3) float
        A few frames spread over the run (sensor frame): the wall noise and the nearest range.
    consecutive_frames : sequence of (N, 3) float
        A run of consecutive frames (about :data:`CONSECUTIVE_FRAMES`): what one frame covers.
    max_range_m : float
        The sections' range.
    profile : SensorProfile, optional
    """
    sources: dict[str, str] = {}
    stated = profile or SensorProfile(model="unknown", source="none")
    if stated.min_range_m is not None:
        min_range, sources["min_range_m"] = stated.min_range_m, "profile"
    else:
        seen = nearest_range_m(sample_frames, max_range_m=max_range_m)
        min_range, sources["min_range_m"] = (seen, "estimated") if seen else (0.0, "default")

    def beyond_min_range(frames: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [crop_range(f, math.inf, min_range) for f in frames]

    sampled = beyond_min_range(sample_frames)
    noise = wall_noise_m(sampled, max_range_m=max_range_m)
    sources["wall_noise_m"] = "estimated" if noise is not None else "default"
    # The scan's own range noise even where the profile states one: a maker's figure is at its
    # test range and target, and a limit looser than the scan's noise passes frames that
    # disagree.
    across = surface_noise(sampled, max_range_m=max_range_m)
    ranging: float | None
    if across is not None:
        (ranging, by_distance), sources["range_noise_m"] = across, "estimated"
    else:
        ranging, by_distance = stated.range_noise_m, None
        sources["range_noise_m"] = "profile" if ranging is not None else "default"
    if stated.pattern in ("repetitive", "profiler", "static"):
        share, seed, sources["frame_view_share"] = 1.0, 1, "profile"
    else:
        share, seed = view_coverage(beyond_min_range(consecutive_frames))
        sources["frame_view_share"] = "estimated"
    across_pipe = frame_diameter_m(
        [*sampled, *beyond_min_range(consecutive_frames[::6])], max_range_m=max_range_m
    )
    return Instrument(
        frame_diameter_m=None if across_pipe is None else across_pipe[0],
        frame_diameter_se_m=None if across_pipe is None else across_pipe[1],
        min_range_m=float(min_range),
        wall_noise_m=noise,
        range_noise_m=ranging,
        surface_noise=by_distance,
        frame_view_share=share,
        map_seed_frames=seed,
        pattern=stated.pattern,
        model=stated.model,
        sources=sources,
    )


def instrumented(
    registration: RegistrationParams, measure: MeasureParams, instrument: Instrument | None
) -> tuple[RegistrationParams, MeasureParams]:
    """The registration and measure parameters for a scan made with ``instrument``: its
    minimum range, its map seed, its ICP gate (:func:`partial_view_gate_m`) and its smear
    limit (:data:`SMEAR_SPREAD_RATIO` times its wall noise). ``None`` (a registered cloud):
    no smear test, the registration parameters as given.

    >>> from pipescan.core.measures import MeasureParams
    >>> from pipescan.core.registration import RegistrationParams
    >>> reg, mp = instrumented(RegistrationParams(), MeasureParams(),
    ...                        Instrument(min_range_m=0.5, wall_noise_m=0.01))
    >>> reg.min_range_m, round(mp.max_wall_spread_m, 3)
    (0.5, 0.015)
    """
    if instrument is None:
        return registration, dataclasses.replace(measure, max_wall_spread_m=None)
    registration = dataclasses.replace(
        registration,
        min_range_m=min(instrument.min_range_m, registration.max_range_m / 2),
        map_seed_frames=instrument.map_seed_frames,
        max_correspondence_m=partial_view_gate_m(instrument, registration),
        wide_correspondence_m=registration.max_correspondence_m
        if instrument.partial_view
        else None,
    )
    if instrument.max_wall_spread_m is not None:
        measure = dataclasses.replace(measure, max_wall_spread_m=instrument.max_wall_spread_m)
    if instrument.surface_noise is not None:
        measure = dataclasses.replace(measure, surface_noise=instrument.surface_noise)
    if instrument.frame_diameter_m is not None:
        measure = dataclasses.replace(
            measure,
            frame_diameter_m=instrument.frame_diameter_m,
            frame_diameter_se_m=instrument.frame_diameter_se_m,
        )
    return registration, measure


def partial_view_gate_m(instrument: Instrument, registration: RegistrationParams) -> float:
    """ICP's correspondence distance for a scan made with ``instrument``.

    Where one frame covers only part of the view, the local map does not cover all that a
    frame sees, and a frame's points beyond the map's edge find the edge's points within a
    wide gate: one-sided pulls, which tilt the frame toward what the map holds, and the
    next keyframe carries that on. A true correspondence lies within the map's sampling
    (a voxel's half-diagonal, √3/2 × ``voxel_m``) and the range noise (1σ: a noisier true
    match gated out drops evenly from either side; a false one admitted pulls one way;
    measured: docs/instrument.md). A full view keeps the parameters' gate, which is ICP's
    reach under the crawler's vibration.

    >>> from pipescan.core.registration import RegistrationParams
    >>> round(partial_view_gate_m(Instrument(map_seed_frames=7, range_noise_m=0.01),
    ...                           RegistrationParams()), 4)
    0.036
    >>> partial_view_gate_m(Instrument(), RegistrationParams())
    0.08
    """
    wide = registration.max_correspondence_m
    if not instrument.partial_view:
        return wide
    noise = instrument.range_noise_m or instrument.wall_noise_m or 0.0
    return min(wide, math.sqrt(3.0) / 2.0 * registration.voxel_m + noise)


def partial_view_stride(instrument: Instrument | None) -> FrameStride | None:
    """Every frame registered, when one frame covers only part of the field of view: the
    local map is built from registered frames only, and a map of every k-th frame's part of
    the view leaves the others' parts, and what tracking would align them with, unmapped.
    None when the stride may be chosen (``choose_frame_stride``). Every frame is placed
    either way."""
    from pipescan.core.registration.stride import FrameStride

    if instrument is None or not instrument.partial_view:
        return None
    return FrameStride(
        1,
        f"one frame sees {100 * instrument.frame_view_share:.0f} % of the view "
        "(a non-repetitive pattern): the local map needs every frame's part of it",
    )


def instrument_summary(instrument: Instrument | None) -> dict:
    """The instrument's figures as the run stores them with its registration summary."""
    if instrument is None:
        return {}
    return {
        "sensor_model": instrument.model,
        "min_range_m": instrument.min_range_m,
        "wall_noise_m": instrument.wall_noise_m,
        "range_noise_m": instrument.range_noise_m,
        "max_wall_spread_m": instrument.max_wall_spread_m,
        "frame_view_share": instrument.frame_view_share,
        "map_seed_frames": instrument.map_seed_frames,
        "frame_diameter_m": instrument.frame_diameter_m,
        "frame_diameter_se_m": instrument.frame_diameter_se_m,
        "instrument_sources": dict(instrument.sources),
        "instrument": instrument.describe(),
    }


def registration_trusted(instrument: Instrument | None) -> bool:
    """Whether frames registered from this instrument may carry figures.

    Not where one frame covers only part of the view (a map seeded by several frames): on
    the sweep over instruments, such scans registered consistently but wrongly. Their
    sections agreed with each other (no smear) and read 2-4 pp off the truth, which the same
    scans placed with their true poses measured within 0.3 pp
    (docs/instrument.md, *Open work*). Their sections are ``weak_registration``: no figure,
    rather than a wrong one, until registration of a partial view is right. A registered
    cloud (None) is placed by whoever registered it.
    """
    return instrument is None or not instrument.partial_view
