"""Which frames a run registers: every frame, or every k-th when the scan is denser in time than
the local map needs. Every frame is read and placed either way: the frames between registered
ones are tracked (:meth:`~pipescan.core.registration.FrameRegistrar.track`), so a section's
points and coverage never depend on the stride.

A crawler moving at 0.15 m/s with a 10 Hz sensor moves 15 mm a frame, and the local map groups
frames into keyframes every ``keyframe_distance`` (15 cm). Registering every k-th frame keeps
what registration rests on while **the local map** bound holds: each keyframe still groups at
least ``FRAMES_PER_KEYFRAME`` registered frames. A keyframe closes at the first frame
``keyframe_distance`` or more from the last one, so it groups ``ceil(keyframe_distance /
(k · d))`` frames: at least three while ``k < keyframe_distance / (2 d)``. A keyframe keeps
only what two of its frames saw (``seen_twice``), the filter that keeps spurious returns out
of the map; three leave one to spare.

``d`` is the odometer's travel a frame, taken at the fast end of the run (the 95th percentile
over ten-frame spans), so that the sparsest stretch still meets the bound. Without an odometer
the spacing is not known and every frame is registered. A profiler, whose frame is one ring
(its view ``L`` ≈ 0 along the pipe), registers every frame: the map behind it never holds the
ring it sees next.

Before every frame was tracked, two more bounds kept the sections' figures (the points each
section keeps, and 25 registered positions to average each section's pose error over); with
every frame placed by its own measured tilt and offset they bind nothing
(docs/registration.md, *Every frame placed*).

**Looking closer where ICP disagrees with the odometer** (:func:`frames_to_register`). A slip
is caught where ICP, with features in view, overrides the odometer through the innovation gate
(a disagreement beyond 3σ of both errors). ICP's own error along the axis varies widely from
frame to frame, and with every frame the gate gets every chance; at every k-th frame it gets
one in k. So after a frame whose ICP disagrees with the odometer by more than
``LOOK_CLOSER_SIGMAS`` (2σ: a chance of 1 in 22 without a slip), the frames up to
``LOOK_CLOSER_STRIDES`` strides further are registered one by one, as every frame would be.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from pipescan.core.registration.preprocess import estimate_normals, voxel_downsample
from pipescan.core.registration.trajectory import used_frame_indices

FRAMES_PER_KEYFRAME = 3
"""Registered frames each keyframe of the local map must still group."""

SAMPLE_FRAMES = 5
"""Frames, spread over the run, whose points give ``n`` and ``L``."""

_SPAN_FRAMES = 10
"""Frames over which the odometer's travel is averaged (its readings are quantised)."""

_PROFILE_RATIO = 0.1
"""A frame whose thinnest principal spread is under this share of the next is one ring."""


@dataclass(frozen=True)
class FrameStride:
    """Every ``stride``-th frame is read and registered; the figures behind the choice."""

    stride: int
    reason: str
    travel_per_frame_m: float | None = None
    points_per_section: float | None = None
    view_length_m: float | None = None

    def describe(self, frame_count: int) -> str:
        """One line for the log and the report."""
        used = len(used_frame_indices(frame_count, self.stride))
        if self.stride == 1:
            return f"every frame of {frame_count:,} registered ({self.reason})"
        which = f"every {_ordinal(self.stride)} frame registered, {used:,} of {frame_count:,}"
        return f"{which}, the others tracked ({self.reason})"


def _ordinal(k: int) -> str:
    return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def sample_frame_indices(frame_count: int, count: int = SAMPLE_FRAMES) -> list[int]:
    """``count`` frame indices spread evenly over the run (its ends left out)."""
    if frame_count <= 0:
        return []
    picks = np.linspace(0, frame_count - 1, count + 2)[1:-1].round().astype(int)
    return sorted(set(picks.tolist()))


def travel_per_frame(odometer_m: Sequence[float | None] | np.ndarray | None) -> float | None:
    """The odometer's travel a frame at the fast end of the run (m), or None without a usable
    odometer (missing readings, or fewer than two spans of ``_SPAN_FRAMES`` frames)."""
    if odometer_m is None:
        return None
    if any(v is None for v in odometer_m):
        return None
    odo = np.asarray(odometer_m, dtype=np.float64)
    if len(odo) <= 2 * _SPAN_FRAMES or not np.isfinite(odo).all():
        return None
    spans = np.abs(odo[_SPAN_FRAMES:] - odo[:-_SPAN_FRAMES]) / _SPAN_FRAMES
    d = float(np.percentile(spans, 95))
    return d if d > 0 else None


def view_length(points_m: np.ndarray) -> float:
    """How far along the pipe one frame's points reach (m): their 5-95 % extent along the pipe's
    axis, the direction every wall normal is square to. 0 for a frame that is one ring."""
    pts = np.asarray(points_m, dtype=np.float64)
    if len(pts) < 20:
        return 0.0
    spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    if spread[2] < _PROFILE_RATIO * spread[1]:
        return 0.0  # one ring: the sensor profiles the pipe
    thin = voxel_downsample(pts, 0.02)
    if len(thin) < 20:
        return 0.0
    normals = estimate_normals(thin)
    normals = normals[np.isfinite(normals).all(axis=1)]
    axis = np.linalg.eigh(normals.T @ normals)[1][:, 0]
    along = thin @ axis
    low, high = np.percentile(along, [5, 95])
    return float(high - low)


def choose_frame_stride(
    sample_frames: Sequence[np.ndarray],
    odometer_m: Sequence[float | None] | np.ndarray | None,
    *,
    max_range_m: float,
    step_m: float,
    section_points: int,
    keyframe_distance_m: float,
) -> FrameStride:
    """The largest stride the local map allows (the module's notes; 1 when it allows no
    more, for a profiler, or without an odometer).

    Parameters
    ----------
    sample_frames : sequence of (N, 3) float
        A few frames spread over the run (``sample_frame_indices``), sensor frame.
    odometer_m : sequence of float or None, or None
        Every frame's odometer reading, in order.
    max_range_m : float
        The sections' range: points further from the sensor are not measured.
    step_m : float
        Section length.
    section_points : int
        Points a section keeps (``MeasureParams.max_points``): reported, not bound by (every
        frame is placed).
    keyframe_distance_m : float
        ``RegistrationParams.keyframe_distance_m``.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> a = rng.uniform(0, 2 * np.pi, 30_000)
    >>> tube = np.column_stack((rng.uniform(0.3, 4.3, 30_000), 0.3 * np.cos(a),
    ...                         0.3 * np.sin(a)))
    >>> odometer = np.arange(600) * 0.015  # 0.15 m/s at 10 Hz
    >>> choice = choose_frame_stride([tube] * 3, odometer, max_range_m=5.0, step_m=0.1,
    ...                              section_points=40_000, keyframe_distance_m=0.15)
    >>> choice.stride, round(choice.view_length_m, 1)
    (4, 3.6)
    >>> ring = np.column_stack((np.zeros(30_000), 0.3 * np.cos(a), 0.3 * np.sin(a)))
    >>> choose_frame_stride([ring] * 3, odometer, max_range_m=5.0, step_m=0.1,
    ...                     section_points=40_000, keyframe_distance_m=0.15).stride
    1
    """
    d = travel_per_frame(odometer_m)
    if d is None:
        if odometer_m is None or any(v is None for v in odometer_m):
            return FrameStride(1, "no odometer: the frames' spacing is not known")
        return FrameStride(1, "too few frames, or no travel, to tell the frames' spacing")
    in_range = _in_range(sample_frames, max_range_m)
    if not in_range:
        return FrameStride(1, "no frame to sample", d)
    per_section = _points_per_section(in_range, d, step_m)
    length = float(np.median([view_length(f) for f in in_range]))
    if length == 0.0:
        return FrameStride(
            1, "one ring a frame (a profiler): every frame registered", d, per_section, length
        )
    # The largest k < keyframe_distance / (2 d) (the local map's bound).
    stride = max(1, int(np.ceil(keyframe_distance_m / (d * (FRAMES_PER_KEYFRAME - 1)) - 1e-9)) - 1)
    reason = (
        f"each section seen from about {length / d:,.0f} positions with {per_section:,.0f} "
        f"points; {d * 1000:.1f} mm of travel a frame; bound by the local map (each keyframe "
        f"groups {FRAMES_PER_KEYFRAME} or more registered frames)"
    )
    return FrameStride(stride, reason, d, per_section, length)


def _in_range(sample_frames: Sequence[np.ndarray], max_range_m: float) -> list[np.ndarray]:
    return [
        f[np.einsum("ij,ij->i", f, f) <= max_range_m**2]
        for f in (np.asarray(s, dtype=np.float64) for s in sample_frames)
    ]


def _points_per_section(in_range: list[np.ndarray], d: float, step_m: float) -> float:
    """Points an inner section gets with every frame placed: a frame's points in range (the
    sample's 25th percentile) times the frames that pass over a section (``step / d``)."""
    return float(np.percentile([len(f) for f in in_range], 25)) * step_m / d


PLACE_MARGIN = 2.0
"""How many times the points a section keeps (``MeasureParams.max_points``) an inner section
still gets when each frame's points are placed at :func:`choose_placed_share`'s share. A
section keeps a random share of its points once it holds more than it keeps
(``sections.iter_section_points``); placing a random share of each frame first draws the
same kind of sample, so the figures do not change while a section still holds more than it
keeps. Twice: the estimate is of an inner section seen as the crawler passes at its fastest,
and a section half hidden (a shadow, a stretch the crawler crossed quicker) still fills."""


@dataclass(frozen=True)
class PlacedShare:
    """The share of each frame's points (in the sections' range) that is placed in the
    sections, and the figures behind it."""

    share: float
    points_per_section: float | None = None
    section_points: int | None = None

    def describe(self) -> str:
        """One line for the log."""
        if self.share >= 1.0:
            return "every point of every frame placed in the sections"
        return (
            f"{100 * self.share:.0f} % of each frame's points placed in the sections, at random: "
            f"an inner section gets about {self.share * (self.points_per_section or 0):,.0f} "
            f"of its {self.points_per_section or 0:,.0f} and keeps {self.section_points:,}"
        )


def choose_placed_share(
    sample_frames: Sequence[np.ndarray],
    odometer_m: Sequence[float | None] | np.ndarray | None,
    *,
    max_range_m: float,
    step_m: float,
    section_points: int,
) -> PlacedShare:
    """The share of each frame's points to place: ``PLACE_MARGIN`` times the points a
    section keeps over the points an inner section gets with every point placed, at most 1.
    Every frame is placed either way, so a section's coverage (which frames saw which part
    of it) is what it is with every point; only the sample each section keeps is drawn
    earlier. 1 without an odometer (the frames' spacing, and so a section's points, is not
    known). Sections that few frames reach (the run's ends) hold fewer points than before
    where they held more than they keep; their ± says so.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> a = rng.uniform(0, 2 * np.pi, 30_000)
    >>> tube = np.column_stack((rng.uniform(0.5, 4.5, 30_000), 0.3 * np.cos(a),
    ...                         0.3 * np.sin(a)))
    >>> slow = np.arange(600) * 0.01  # 0.1 m/s at 10 Hz: 300,000 points a section
    >>> round(choose_placed_share([tube] * 3, slow, max_range_m=5.0, step_m=0.1,
    ...                           section_points=40_000).share, 4)  # 2 × 40,000 / 300,000
    0.2667
    >>> fast = np.arange(600) * 0.05  # 60,000 points a section: every point
    >>> choose_placed_share([tube] * 3, fast, max_range_m=5.0, step_m=0.1,
    ...                     section_points=40_000).share
    1.0
    """
    d = travel_per_frame(odometer_m)
    in_range = _in_range(sample_frames, max_range_m)
    if d is None or not in_range:
        return PlacedShare(1.0)
    per_section = _points_per_section(in_range, d, step_m)
    if per_section <= 0:
        return PlacedShare(1.0)
    share = min(1.0, PLACE_MARGIN * section_points / per_section)
    return PlacedShare(share, per_section, section_points)


LOOK_CLOSER_SIGMAS = 2.0
"""ICP's disagreement with the odometer along the axis (in σ of both errors) beyond which the
frames skipped by the stride are read (:func:`frames_to_register`)."""
LOOK_CLOSER_STRIDES = 2
"""How many strides past a disagreeing frame every frame is read."""


def frames_to_register(
    first: int, last: int, stride: int, disagreement: Callable[[], float]
) -> Iterator[int]:
    """The frames of chunk ``first..last`` to register with ``stride`` k, chosen as they go.

    Every k-th from ``first``, and ``last`` (as
    :func:`~pipescan.core.registration.trajectory.chunk_frame_indices`); and every frame for
    ``LOOK_CLOSER_STRIDES`` strides after one whose ``disagreement()`` (read after it was
    registered: ``FrameRegistrar.disagreement_sigmas``) exceeds ``LOOK_CLOSER_SIGMAS``. The
    stride's own frames are those :func:`is_stride_frame` names.

    Examples
    --------
    >>> seen = iter([0.5, 2.5])   # the second frame disagrees by 2.5σ, the others agree
    >>> list(frames_to_register(10, 23, 3, lambda: next(seen, 0.0)))
    [10, 13, 14, 15, 16, 17, 18, 19, 22, 23]
    """
    i, closer_until = first, first
    while True:
        yield i
        if i >= last:
            return
        if stride > 1 and disagreement() > LOOK_CLOSER_SIGMAS:
            closer_until = i + LOOK_CLOSER_STRIDES * stride
        on_grid = min(first + ((i - first) // stride + 1) * stride, last)
        i = i + 1 if i < closer_until else on_grid


def is_stride_frame(index: int, first: int, last: int, stride: int) -> bool:
    """Whether frame ``index`` of chunk ``first..last`` is one of the stride's own (every k-th
    from ``first``, and ``last``), not one read to look closer."""
    return index == last or (index - first) % max(1, stride) == 0
