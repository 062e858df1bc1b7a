"""Trajectories: the poses and quality of registered frames, split into chunks and chained."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from pipescan.core.errors import RegistrationError
from pipescan.core.model import FrameQuality
from pipescan.core.registration.engines import transform
from pipescan.core.registration.fusion import (
    slip_could_hide,
    slips_out_of_view,
    standstill_allowance,
    unseen_slip_allowance,
)
from pipescan.core.registration.params import AlongAxisPrior


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

    def positions_m(self) -> np.ndarray:
        """Sensor positions in the world frame, (F, 3)."""
        return self.T_world_frame[:, :3, 3]


def plan_chunks(frame_count: int, chunk_frames: int, stride: int = 1) -> list[tuple[int, int]]:
    """Split frames into chunks ``[first, last]`` (inclusive) that overlap by one frame.

    The shared frame lets consecutive chunks, registered independently and in parallel, be
    chained into one trajectory. With ``stride`` k, a chunk holds at most ``chunk_frames``
    of the frames used (every k-th, and the last: :func:`chunk_frame_indices`). The chunks
    are as few as that allows, and as equal as they can be: a short last chunk would leave a
    core idle at the end of registration while another chunk finishes.

    Examples
    --------
    >>> plan_chunks(10, 4)
    [(0, 3), (3, 6), (6, 9)]
    >>> plan_chunks(12, 5)
    [(0, 4), (4, 7), (7, 11)]
    """
    if frame_count <= 0:
        return []
    chunk_frames = max(2, chunk_frames)
    used = used_frame_indices(frame_count, stride)
    steps = len(used) - 1  # frame-to-frame steps; each chunk takes a run of them
    count = max(1, -(-steps // (chunk_frames - 1)))
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
    for chunk in chunks[1:]:
        if chunk.frame_indices[0] != indices[-1]:
            raise RegistrationError(
                f"chunks do not overlap: frame {indices[-1]} then {chunk.frame_indices[0]}"
            )
        T_world_shared = poses[-1][-1]
        poses.append(np.einsum("ij,fjk->fik", T_world_shared, chunk.T_world_frame[1:]))
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
    )  # fmt: skip


def iter_registered_points(
    frames: Iterable[tuple[int, np.ndarray]], trajectory: Trajectory
) -> Iterator[np.ndarray]:
    """Transform frames into the world frame, one at a time, (N, 3) each.

    Frames that slid along the axis (``fault == "slide"``) are left out: their place is not
    known, and the sections are seen from many other frames.
    """
    pose_of = dict(zip(trajectory.frame_indices, trajectory.T_world_frame, strict=True))
    slid = {q.index for q in trajectory.quality if q.fault == "slide"}
    for frame_index, points in frames:
        if frame_index in slid:
            continue
        yield transform(pose_of[frame_index], np.asarray(points, dtype=np.float64))
