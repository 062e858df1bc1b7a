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
from pipescan.core.registration.preprocess import crop_range

if TYPE_CHECKING:
    from pipescan.core.measures import MeasureParams
    from pipescan.core.registration import FrameStride, RegistrationParams

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
the scan's single-frame wall noise. Frames that agree spread the wall by the noise of one
frame; frames whose offsets spread evenly over ``d`` add ``d²/12`` to its square, so 1.5
times the noise is reached at ``d ≈ 3.9σ`` (a few millimetres on a quiet sensor, centimetres
on a noisy one, whose ± grows with its noise anyway). Measured: frames that agree read at
most 1.43 times (docs/instrument.md)."""

SMEAR_SPREAD_FLOOR_M = 0.002
"""The least wall spread called smeared, whatever the noise: below it the spread is the
section's own quantisation (1° bins on a 0.15-0.5 m radius are 3-9 mm wide; a bin's points
at different places along it lie a millimetre or two from its median radius on an oval or
deposit-bordered wall)."""

_NOISE_NEIGHBOURS = 16
_NOISE_SAMPLE_POINTS = 20_000
_CHI2_MEDIAN_13 = 12.34
"""Median of χ² with 13 degrees of freedom: a plane fitted to 16 points with noise σ across it
leaves a smallest covariance eigenvalue whose median is σ² × 12.34 / 16."""

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
        on noise; the ``max_wall_spread_m`` given is kept).
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
    frame_view_share: float = 1.0
    map_seed_frames: int = 1
    pattern: str | None = None
    model: str = "unknown"
    sources: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def partial_view(self) -> bool:
        """One frame covers only part of the view: the map is seeded by several frames."""
        return self.map_seed_frames > 1

    @property
    def max_wall_spread_m(self) -> float | None:
        """The smear limit for this scan (None when its noise is not known)."""
        if self.wall_noise_m is None:
            return None
        return max(SMEAR_SPREAD_FLOOR_M, SMEAR_SPREAD_RATIO * self.wall_noise_m)

    def describe(self) -> str:
        """One line for the log and the summary."""
        noise = "unknown" if self.wall_noise_m is None else f"{self.wall_noise_m * 1000:.1f} mm"
        parts = [
            f"sensor {self.model}",
            f"minimum range {self.min_range_m:.2f} m ({self.sources.get('min_range_m', '?')})",
            f"wall noise {noise} ({self.sources.get('wall_noise_m', '?')})",
            f"one frame sees {100 * self.frame_view_share:.0f} % of the view "
            f"({self.sources.get('frame_view_share', '?')})",
        ]
        if self.partial_view:
            parts.append(f"map seeded by {self.map_seed_frames} frames")
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
    return round(float(first[0] * 0.01), 2) if len(first) else None


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

    noise = wall_noise_m(beyond_min_range(sample_frames), max_range_m=max_range_m)
    sources["wall_noise_m"] = "estimated" if noise is not None else "default"
    if stated.pattern in ("repetitive", "profiler", "static"):
        share, seed, sources["frame_view_share"] = 1.0, 1, "profile"
    else:
        share, seed = view_coverage(beyond_min_range(consecutive_frames))
        sources["frame_view_share"] = "estimated"
    return Instrument(
        min_range_m=float(min_range),
        wall_noise_m=noise,
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
    minimum range, its map seed, and its smear limit (:data:`SMEAR_SPREAD_RATIO` times its
    wall noise). ``None`` (a registered cloud): no smear test, the registration parameters as
    given.

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
    )
    if instrument.max_wall_spread_m is not None:
        measure = dataclasses.replace(measure, max_wall_spread_m=instrument.max_wall_spread_m)
    return registration, measure


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
        "max_wall_spread_m": instrument.max_wall_spread_m,
        "frame_view_share": instrument.frame_view_share,
        "map_seed_frames": instrument.map_seed_frames,
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
