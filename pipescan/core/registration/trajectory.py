"""Trajectories: the poses and quality of registered frames, split into chunks and chained."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pipescan.core.errors import RegistrationError
from pipescan.core.model import FrameQuality
from pipescan.core.registration.deskew import deskew_points, frame_intervals, travel_motion
from pipescan.core.registration.engines import transform
from pipescan.core.registration.fusion import (
    slip_could_hide,
    slips_out_of_view,
    standstill_allowance,
    unseen_slip_allowance,
)
from pipescan.core.registration.params import AlongAxisPrior
from pipescan.core.registration.preprocess import early_return_mask


@dataclass(frozen=True)
class Trajectory:
    """Poses of consecutive frames and their registration quality.

    Attributes
    ----------
    T_world_frame : (F, 4, 4) float
        Poses; the first is the identity unless the trajectory was chained.
    quality : tuple of FrameQuality
        One per frame (the first frame's fitness is 1 by definition). ``degenerate`` marks
        frames whose along-axis position the geometry hardly constrained: they were held to
        the prior (``along_axis_prior``); ``chainage_uncertainty_m`` bounds each frame's
        along-axis position; ``fault`` marks slides and odometer slips.
    frame_indices : tuple of int
        Archive frame indices of the poses.
    along_axis_prior : {"odometer", "constant_velocity", "mixed"}
        What held degenerate frames: the odometer, or without one a constant-velocity
        extrapolation (which is not a measurement: such frames were *not* registered along
        the axis), or a mix when only some frames had an odometer reading.
    odometer_slips_m : tuple of float
        Sizes (m) of the odometer slips registration saw against features in view, one per
        slip; they tell how the odometer slips where nothing could see it
        (:func:`~pipescan.core.registration.fusion.unseen_slip_allowance`).
    slip_window_m : float
        The travel over which registration compared itself with the odometer (a stretch held
        to the odometer for less than this could not hide a slip).
    unseen_slips_m : float
        What the chainage uncertainty at the end allows for odometer slips that nothing could
        see (m; 0 where no slip was caught or stated, or no stretch held long enough to hide
        one), set when chunks are chained (:func:`chain_trajectories`).
    stated_slip_m : float
        The largest unseen slip the crawler's operator stated (``odometer_slip_m``; 0: none).
    standstill_m : float
        What the chainage uncertainty at the end allows for the crawler moving on while the
        odometer's count stood and the frames rested on it (m;
        :func:`~pipescan.core.registration.fusion.standstill_allowance`), set when chunks
        are chained.
    standstill_frames : int
        The registered frames over which the count stood so.
    tracked_indices : tuple of int
        Archive indices of the frames between registered ones that were tracked
        (:meth:`~pipescan.core.registration.FrameRegistrar.track`): placed, not registered.
    T_world_tracked : (T, 4, 4) float
        Their poses (NaN where tracking failed: such a frame is not placed).
    """

    T_world_frame: np.ndarray
    quality: tuple[FrameQuality, ...]
    frame_indices: tuple[int, ...]
    along_axis_prior: AlongAxisPrior = "odometer"
    odometer_slips_m: tuple[float, ...] = ()
    slip_window_m: float = 0.5
    unseen_slips_m: float = 0.0
    stated_slip_m: float = 0.0
    standstill_m: float = 0.0
    standstill_frames: int = 0
    tracked_indices: tuple[int, ...] = ()
    T_world_tracked: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4, 4)))

    def positions_m(self) -> np.ndarray:
        """Sensor positions in the world frame, (F, 3)."""
        return self.T_world_frame[:, :3, 3]

    @property
    def frames_not_tracked(self) -> int:
        """Frames between registered ones whose tracking failed (not placed)."""
        return int((~np.isfinite(self.T_world_tracked).all(axis=(1, 2))).sum())


def plan_chunks(
    frame_count: int, chunk_frames: int, stride: int = 1, workers: int = 1
) -> list[tuple[int, int]]:
    """Split frames into chunks ``[first, last]`` (inclusive) that overlap by one frame.

    The shared frame lets consecutive chunks, registered independently and in parallel, be
    chained into one trajectory. With ``stride`` k, a chunk holds at most ``chunk_frames``
    of the frames used (every k-th, and the last: :func:`chunk_frame_indices`). The chunks
    are as few as that allows and as equal as they can be, and where there are more than
    one, their count is a multiple of ``workers`` (the chunks registered at once): a short
    last chunk, or a last round with fewer chunks than workers, would leave a core idle at
    the end of registration while another chunk finishes (7 chunks on 2 workers: a core
    idle for an eighth of the time).

    Examples
    --------
    >>> plan_chunks(10, 4)
    [(0, 3), (3, 6), (6, 9)]
    >>> plan_chunks(12, 5)
    [(0, 4), (4, 7), (7, 11)]
    >>> plan_chunks(12, 5, workers=2)
    [(0, 3), (3, 6), (6, 8), (8, 11)]
    >>> plan_chunks(4, 5, workers=2)  # one chunk is not split
    [(0, 3)]
    """
    if frame_count <= 0:
        return []
    chunk_frames = max(2, chunk_frames)
    used = used_frame_indices(frame_count, stride)
    steps = len(used) - 1  # frame-to-frame steps; each chunk takes a run of them
    count = max(1, -(-steps // (chunk_frames - 1)))
    if count > 1 and workers > 1:
        count = min(steps, -(-count // workers) * workers)
    bounds = [round(i * steps / count) for i in range(count + 1)]
    return [(used[a], used[b]) for a, b in itertools.pairwise(bounds)]


def used_frame_indices(frame_count: int, stride: int = 1) -> list[int]:
    """The frames a run reads with ``stride`` k: every k-th from the first, and the last (so
    that the run keeps its whole length)."""
    used = list(range(0, frame_count, max(1, stride)))
    if used and used[-1] != frame_count - 1:
        used.append(frame_count - 1)
    return used


def chunk_frame_indices(first: int, last: int, stride: int = 1) -> list[int]:
    """The frames of chunk ``[first, last]`` of :func:`plan_chunks` with ``stride``."""
    return [i + first for i in used_frame_indices(last - first + 1, stride)]


def chain_trajectories(chunks: list[Trajectory]) -> Trajectory:
    """Chain chunk trajectories that overlap by one frame into one trajectory.

    Chunk k's first frame is chunk k−1's last; its poses are re-expressed in the world frame
    of chunk 0: ``T_world_frame = T_world_shared @ T_chunk_frame``. Chainage uncertainties
    add up: chunk k's start where chunk k−1 ended. Once the whole run is known, the slips the
    odometer made where features were in view are allowed for wherever it was alone
    (:func:`~pipescan.core.registration.fusion.unseen_slip_allowance`): chain a run once.
    """
    if not chunks:
        raise RegistrationError("no chunks to chain")
    poses = [chunks[0].T_world_frame]
    quality = list(chunks[0].quality)
    indices = list(chunks[0].frame_indices)
    tracked = [chunks[0].T_world_tracked]
    for chunk in chunks[1:]:
        if chunk.frame_indices[0] != indices[-1]:
            raise RegistrationError(
                f"chunks do not overlap: frame {indices[-1]} then {chunk.frame_indices[0]}"
            )
        T_world_shared = poses[-1][-1]
        poses.append(np.einsum("ij,fjk->fik", T_world_shared, chunk.T_world_frame[1:]))
        tracked.append(np.einsum("ij,fjk->fik", T_world_shared, chunk.T_world_tracked))
        offset = quality[-1].chainage_uncertainty_m
        quality.extend(
            dataclasses.replace(q, chainage_uncertainty_m=q.chainage_uncertainty_m + offset)
            for q in chunk.quality[1:]
        )
        indices.extend(chunk.frame_indices[1:])
    priors = {c.along_axis_prior for c in chunks}
    prior: AlongAxisPrior = priors.pop() if len(priors) == 1 else "mixed"
    T = np.concatenate(poses)
    slips = tuple(s for c in chunks for s in c.odometer_slips_m)
    window = max(c.slip_window_m for c in chunks)
    positions = T[:, :3, 3]
    steps = np.linalg.norm(np.diff(positions, axis=0, prepend=positions[:1]), axis=1)
    held = slip_could_hide(
        np.array([q.degenerate for q in quality]),
        np.array([q.gate_sigma_m for q in quality]),
        steps,
    )
    caught = np.array([q.fault == "odometer_slip" for q in quality])
    overrode = np.array([q.overrode for q in quality])
    out_of_view = slips_out_of_view(caught, overrode, held, steps, window)
    stated = max(c.stated_slip_m for c in chunks)
    allowance = unseen_slip_allowance(steps, held, slips, window, out_of_view, stated)
    gaps = np.diff(np.asarray(indices), prepend=indices[0])
    # Along the run, signed: over a stand the count's reading noise cancels, where the
    # lengths of the steps would add it up as travel counted.
    travel = positions[-1] - positions[0]
    length = float(np.linalg.norm(travel))
    along = positions @ (travel / length if length > 0 else T[0, :3, 0])
    stood_m, stood_frames = standstill_allowance(np.diff(along, prepend=along[0]), gaps, held)
    unseen = float(allowance.max()) if len(allowance) else 0.0
    # Where the count stood, the crawler may have gone on: the odometer reads short by up to
    # the standstills' allowance. Slips the rate allows for either way; those that read
    # long (the count running on) are what it adds beyond the standstills. The two err in
    # opposite directions, so the error stays within the larger of them, not their sum.
    allowance = np.maximum(allowance, stood_m)
    quality = [
        dataclasses.replace(q, chainage_uncertainty_m=q.chainage_uncertainty_m + float(a))
        if a > 0
        else q
        for q, a in zip(quality, allowance, strict=True)
    ]
    standstill = float(stood_m[-1]) if len(stood_m) else 0.0
    return Trajectory(
        T, tuple(quality), tuple(indices), prior, slips, window, unseen, stated,
        standstill, stood_frames,
        tracked_indices=tuple(i for c in chunks for i in c.tracked_indices),
        T_world_tracked=np.concatenate(tracked),
    )  # fmt: skip


def share_of_way(along: Sequence[float | None] | None, index: int, a: int, b: int) -> float:
    """Frame ``index``'s share of the way from frame ``a`` to frame ``b`` (``a < index < b``):
    measured in ``along`` (the frames' times or odometer readings, by frame index) where it
    gives all three and moves between ``a`` and ``b``, else in frame indices."""
    if along is not None:
        ends = (along[a], along[b], along[index])
        if all(v is not None and np.isfinite(v) for v in ends) and ends[1] != ends[0]:
            t = (ends[2] - ends[0]) / (ends[1] - ends[0])
            if 0.0 <= t <= 1.0:
                return float(t)
    return (index - a) / (b - a)


def interpolate_pose(T_a: np.ndarray, T_b: np.ndarray, t: float) -> np.ndarray:
    """The pose ``t`` of the way from ``T_a`` to ``T_b``: translation linearly, rotation by
    slerp."""
    T = np.eye(4)
    rotations = Rotation.from_matrix(np.stack((T_a[:3, :3], T_b[:3, :3])))
    T[:3, :3] = Slerp([0.0, 1.0], rotations)(t).as_matrix()
    T[:3, 3] = (1.0 - t) * T_a[:3, 3] + t * T_b[:3, 3]
    return T


class FramePoses:
    """Every frame's pose from a trajectory: a registered frame its own, a tracked frame its
    own (a frame between registered ones whose tilt and offset ICP measured against the local
    map: :meth:`~pipescan.core.registration.FrameRegistrar.track`), and any other frame between
    two registered ones interpolated between them (:func:`interpolate_pose`, at
    :func:`share_of_way` along ``along``).

    Registration needs only some frames (keyframes); the sections need every frame's points,
    so that a section's coverage never depends on which frames were registered.

    A frame is not placed (:meth:`pose` None) when it lies outside the registered frames,
    next to a registered frame that slid along the axis (whose place is not known), or where
    its tracking failed.

    Parameters
    ----------
    trajectory : Trajectory
    along : sequence of float or None, optional
        Per archive frame (indexed by frame index), what a frame's share of the way between
        registered frames is measured in (:meth:`along_from`).

    Examples
    --------
    >>> T = np.repeat(np.eye(4)[None], 2, axis=0)
    >>> T[1, :3, 3] = (0.4, 0.0, 0.0)
    >>> q = (FrameQuality(0, 1.0, 0.0, False), FrameQuality(4, 1.0, 0.0, False))
    >>> traj = Trajectory(T, q, (0, 4))
    >>> FramePoses(traj).pose(1)[:3, 3].tolist()
    [0.1, 0.0, 0.0]
    >>> FramePoses(traj, along=[0.0, 0.3, 0.35, 0.4, 0.4]).pose(1)[:3, 3].round(3).tolist()
    [0.3, 0.0, 0.0]
    >>> FramePoses(traj).pose(5) is None
    True
    """

    def __init__(self, trajectory: Trajectory, along: Sequence[float | None] | None = None):
        self.trajectory = trajectory
        self.indices = np.asarray(trajectory.frame_indices, dtype=np.int64)
        self.along = along
        self.slid = np.array([q.fault == "slide" for q in trajectory.quality], dtype=bool)
        self.tracked = dict(
            zip(trajectory.tracked_indices, trajectory.T_world_tracked, strict=True)
        )

    @staticmethod
    def along_from(
        time_s: Sequence[float | None], odometer_m: Sequence[float | None]
    ) -> list[float | None] | None:
        """What frames are placed along between registered frames: their times where every
        frame has one (between two registered frames, a fraction of a second apart, the
        crawler's speed hardly changes, while the odometer's count is quantised and can stand
        as it moves), else their odometer readings, else None (their indices: frames come
        at a steady rate)."""
        for column in (time_s, odometer_m):
            if len(column) and all(v is not None for v in column):
                return list(column)
        return None

    def pose(self, index: int) -> np.ndarray | None:
        """Frame ``index``'s pose ``T_world_frame`` (4×4), or None when it is not placed."""
        k = int(np.searchsorted(self.indices, index))
        if k < len(self.indices) and self.indices[k] == index:
            return None if self.slid[k] else self.trajectory.T_world_frame[k]
        if k == 0 or k == len(self.indices) or self.slid[k - 1] or self.slid[k]:
            return None
        if index in self.tracked:
            T = self.tracked[index]
            return T if np.isfinite(T).all() else None
        a, b = int(self.indices[k - 1]), int(self.indices[k])
        ends = self.trajectory.T_world_frame[k - 1 : k + 1]
        return interpolate_pose(ends[0], ends[1], share_of_way(self.along, index, a, b))


def iter_registered_points(
    frames: Iterable[tuple[int, np.ndarray] | tuple[int, np.ndarray, np.ndarray | None]],
    trajectory: Trajectory,
    along: Sequence[float | None] | None = None,
    frame_time_s: Sequence[float | None] | None = None,
    *,
    placed_share: float = 1.0,
    early_return_ratio: float = 0.0,
) -> Iterator[np.ndarray]:
    """Transform frames into the world frame, one at a time, (N, 3) each: registered frames
    by their own pose, the frames between them by an interpolated one (:class:`FramePoses`,
    with ``along``).

    With ``placed_share`` under 1, each frame's points are a random share of them (drawn with
    the frame's index as the seed: a run places the same points each time; the share's rule:
    :func:`~pipescan.core.registration.stride.choose_placed_share`). With
    ``early_return_ratio`` over 0, the returns that came back early (in front of what the rays
    around them hit: :func:`~pipescan.core.registration.preprocess.early_return_mask`) are left
    out: such a return lies inside the pipe, in a section the ray only passed through.

    A frame given as ``(index, points, point_time_s)`` with times (N,) s is deskewed first
    (:func:`~pipescan.core.registration.deskew.deskew_points`) by the registered travel
    (:func:`~pipescan.core.registration.deskew.travel_motion`) from its pose to the next
    frame's over their ``frame_time_s`` (every frame's time, s; from the previous frame's for
    the last), so that each point is placed from where the sensor was when it was captured.
    Without times, or without the frames' times, it is placed as is.

    Frames that slid along the axis (``fault == "slide"``), and the frames next to them, are
    left out: their place is not known, and the sections are seen from many other frames.
    So are frames outside the registered ones.
    """
    poses = FramePoses(trajectory, along)
    for frame_index, points, *rest in frames:
        pose = poses.pose(frame_index)
        if pose is None:
            continue
        point_time_s = rest[0] if rest else None
        keep = _placed_points(points, frame_index, placed_share, early_return_ratio)
        if keep is not None:
            points = np.compress(keep, points, axis=0)
            if point_time_s is not None:
                point_time_s = np.compress(keep, point_time_s)
        pts = np.asarray(points, dtype=np.float64)
        if point_time_s is not None and frame_time_s is not None:
            motion = _registered_motion(poses, frame_index, frame_time_s)
            if motion is not None:
                pts = deskew_points(pts, point_time_s, *motion)
        yield transform(pose, pts)


def _placed_points(
    points: np.ndarray, frame_index: int, placed_share: float, early_return_ratio: float
) -> np.ndarray | None:
    """Which of a frame's points :func:`iter_registered_points` places, (N,) bool (None:
    every one): its random share, less its early returns among them."""
    keep = None
    if placed_share < 1.0:
        keep = np.random.default_rng(frame_index).random(len(points)) < placed_share
    if early_return_ratio > 0.0:
        if keep is None:
            return early_return_mask(points, early_return_ratio)
        which = np.flatnonzero(keep)
        keep[which] = early_return_mask(np.take(points, which, axis=0), early_return_ratio)
    return keep


def _registered_motion(
    poses: FramePoses, index: int, frame_time_s: Sequence[float | None]
) -> tuple[np.ndarray, float] | None:
    """The travel over frame ``index`` from the placed poses: to the next frame's pose, or
    from the previous one's (as a pose, and its time, s); None where neither is placed."""
    for a, b, period_s in frame_intervals(index, frame_time_s):
        T_a, T_b = poses.pose(a), poses.pose(b)
        if T_a is not None and T_b is not None:
            return travel_motion(T_a, T_b), period_s
    return None
