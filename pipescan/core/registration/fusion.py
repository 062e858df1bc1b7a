"""Fusing ICP with the odometer along the pipe axis and with the IMU about it.

In a smooth straight pipe the wall tells ICP nothing about where along the axis a frame
sits, nor how it is rolled about the axis. Both are weighed, not switched:

Along the axis
    ICP's information along the axis is read off the point-to-plane Hessian of the frame at
    its solution: ``Σ (n_i·a)² / σ_r²`` over its correspondences (``a`` the axis, ``n_i`` the
    map normals, ``σ_r`` the residuals' robust spread). The wall's own normals tilt by the
    range noise and fake some of it; what a smooth wall fakes is estimated from the frame
    itself (a multiple of the median per-point share) and taken off. The odometer's stated
    uncertainty (``odometer_scale_error_ratio`` of the distance since ICP last had
    information, plus its reading noise) is the prior's. The frame's along-axis correction is
    ICP's times ``w = P² / (P² + 1/I)``: weak or fake geometry can never move a frame along
    the axis further than its information warrants (:class:`AxialFilter`).
Slides
    Over a window of travel (``slide_window_m``), the registered travel must agree with the
    odometer's within the odometer's error. If it does not while ICP carried little weight, ICP
    slid (a fault, not a measurement): the frame goes back to the odometer and the map is
    restarted. If ICP carried the weight throughout (features in view), the odometer slipped
    (the crawler stuck on debris, or sliding) and ICP stands (:class:`SlideDetector`).
Unseen slips
    Where the frames were held to the odometer, a slip leaves no trace. The slips seen where
    features were in view tell how often and how far this odometer slips; the chainage
    uncertainty allows for as many there as that rate gives with 95 % probability
    (:func:`unseen_slip_allowance`).
About the axis
    Roll is held where the Hessian is degenerate (rotation-dominated eigenvectors below
    ``degeneracy_ratio`` of the largest), at the previous attitude turned to agree with the
    IMU's gravity when the frame carries it (:func:`gravity_corrected`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from pipescan.core.uncertainty import MAD_TO_SIGMA

# Gravity says nothing about roll about an axis within ~6° of vertical (a shaft): there the
# components of gravity across the axis are below this and the IMU correction is skipped.
_MIN_GRAVITY_ACROSS_AXIS = 0.1
# A surface faces along the axis when it rises at least 14.5° across it (|n·a| ≥ 0.25). The
# wall's own normals, tilted by range noise and the voxel grid, read |n·a| of 0.01-0.02 (their
# median on the simulator's scans, from ideal to the harsh end of noise): 14.5° is ten times
# that. An end wall, an obstacle's face and a deposit's ramp rise further: the paper's deposit
# (28.5 % of the height over 0.25 m) rises at 19° in a 0.3 m pipe and 34° in a 0.6 m one.
FACING_COS = 0.25
"""A surface faces along the axis when its normal is within 75.5° of it (``|n·a| ≥ 0.25``)."""
# A map point lies on a surface when its neighbourhood is a slab: the smallest eigenvalue of
# its covariance at most this share of their sum (a slab a third as thick as it is wide; a
# blob is 1/3). A face with noise σ across a patch of radius r (24 neighbours at 3 cm: ~8 cm)
# reads σ² / (σ² + r²/2): 0.05 is σ ≈ 13 mm. Noisier faces overlap blobs of spurious returns
# (0.13-0.23, median) and are not counted: the odometer holds there, the safe side. Measured
# (paper scene, map of six frames): 38 / 45 / 3 % of facing points pass at 3 / 10 / 20 mm.
_MAX_SURFACE_VARIATION = 0.05
MIN_FACING_SUPPORT = 10
"""Correspondences on surfaces facing along the axis below which there is no information.
Set as ten map points at 3 cm spacing, a patch of ~1 dm², the smallest face worth the name;
the correspondences are the frame's points, though, voxelised at ``source_voxel_m`` (4.5 cm
by default), so ten of them cover ~2 dm² of a face seen head-on (the half tried:
docs/history/code-comments.md, *Facing support*)."""
FACE_PATCH_M = 0.1
"""The side of the patch (~1 dm², the smallest face, :data:`MIN_FACING_SUPPORT`) whose points
count as one observation along the axis: their errors are not independent."""
# A residual spread below this is not believed (a perfect match of few points): it would make
# the information, and ICP's weight, arbitrarily large.
_MIN_RESIDUAL_SIGMA_M = 0.001
# Without an odometer the prior along the axis is the last velocity; a crawler's speed varies,
# so that prior is given this uncertainty per step (its own size).
_CONSTANT_VELOCITY_STEP_RATIO = 1.0
# ICP and the odometer disagree when ICP's correction exceeds this many σ of both together.
_INNOVATION_SIGMAS = 3.0
# How many standard deviations of the noise terms a slide must exceed on top of the
# odometer's scale error: 3σ false alarms are one window in 370.
_SLIDE_SIGMAS = 3.0
# ICP carried the weight over a window when its mean weight is at least this: then a
# disagreement with the odometer is the odometer's (slip), not ICP's.
_ICP_CARRIED_WEIGHT = 0.5

# The chainage uncertainty allows for as many unseen odometer slips as the rate caught gives
# with this probability (:func:`unseen_slip_allowance`): the 2σ of the rest of the bound.
SLIP_CONFIDENCE = 0.95

Fault = Literal["slide", "odometer_slip"]


def point_to_plane_hessian(source_m: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Gauss-Newton Hessian ``Σ J_iᵀ J_i`` of point-to-plane ICP, (6, 6), order (rot, trans).

    ``J_i = [(p_i × n_i)ᵀ, n_iᵀ]`` for a source point p_i matched to a target point with
    normal n_i, both in one frame; rotation is about that frame's origin. Pass points in the
    sensor frame (normals rotated into it) to get the Hessian of a perturbation about the
    sensor, ``T = T_pred @ exp(δ)``.
    """
    j = np.hstack((np.cross(source_m, normals), normals))
    return j.T @ j


def degenerate_directions(
    hessian: np.ndarray, length_m: float, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """Weak directions of a point-to-plane Hessian, in unit-balanced coordinates.

    The rotation part is scaled by ``length_m`` (the points' RMS distance from the rotation
    centre) so that both parts are in metres and one eigenvalue ratio means the same for
    both. In a smooth pipe the two weak modes are the translation along the axis and the roll
    about it.

    Returns
    -------
    weak : (6, W) float
        Orthonormal weak directions (W = 0 when the geometry constrains every direction).
    scale : (6,) float
        Multiply ``(rotvec_rad, translation_m)`` by it to reach the balanced coordinates.
    """
    scale = np.array([length_m] * 3 + [1.0] * 3)
    balanced = hessian / np.outer(scale, scale)
    evals, evecs = np.linalg.eigh(balanced)
    return evecs[:, evals < ratio * evals[-1]], scale


def axial_information(
    normals_sensor: np.ndarray,
    surface_variation: np.ndarray,
    residuals_m: np.ndarray,
    axis_sensor: np.ndarray,
    points_sensor: np.ndarray,
) -> float:
    """ICP's information about the translation along the pipe axis, 1/m².

    (Over 80 lines for this reference docstring only: why each test is what it is; the body
    is 15 lines.)

    The axial entry of the point-to-plane Hessian, ``Σ (n_i·a)² / σ²``, over the
    correspondences whose map point lies on a surface that faces along the axis (rising at
    least 14.5° across it, ``|n_i·a| ≥ 0.25``: an end wall, an obstacle's face, a deposit's
    ramp) and is a surface (the neighbourhood's ``surface_variation`` at most 0.05: a slab
    at most a third as thick as it is wide). ``σ`` is those correspondences' own robust
    residual spread (at least 1 mm).

    Why not the whole Hessian: a smooth wall's normals tilt by the range noise and by the
    voxel grid, and a blob of spurious returns has normals in every direction; both put
    information along the axis into the Hessian that the geometry does not have, and ICP
    then slides (on the simulator, 97 % of a 3 m run with no noise at all). The wall's
    normals tilt by 1° or so, ten times less than a facing surface must; a blob is no slab.
    Fewer than :data:`MIN_FACING_SUPPORT` such correspondences are no surface: no
    information.

    Why per patch, not per point: the points of one face do not err independently. The
    face's place in the map was averaged from the same few frames, whose own error along the
    axis it carries whole, and its edges share their mixed pixels. Summed point by point, the
    information claimed 0.6-2.5 mm along the axis where the corrections scattered by 1-2 cm,
    and the innovation gate then believed a weak face over a right odometer
    (``docs/registration.md``, *Correlated points*). So the points in each ``FACE_PATCH_M``
    cube (the smallest face, ~1 dm²) count once: ``mean (n_i·a)² · patches / σ²``. Over the
    sweep's 23 short draws in memory this took the 0.5 m stretches worse than the odometer by
    more than 1 cm from 12 to 9 of 299 (six gone, three new); no ok section was off by more
    than 2 pp in either run.

    Why divided by the patches' χ²: the residual spread says how well each patch is placed,
    not whether the patches agree. Against the simulator's truth ICP's stated error along the
    axis was 1.5× too small over the sweep, and 3.7× under 2 % spurious returns
    (``bench_registration.py axial-error``). Where the patches' own shifts scatter beyond
    their stated errors, the information is divided by their reduced χ²
    (:func:`_patches_disagree`). ``docs/registration.md`` (*Where the remaining stretches
    are*) has the sweep's figures with and without it.

    Parameters
    ----------
    normals_sensor : (N, 3) float
        Unit normals of the map points matched by the frame, in the sensor frame.
    surface_variation : (N,) float
        Those map points' ``λ_min / Σλ`` (see ``LocalMap``).
    residuals_m : (N,) float
        Point-to-plane residuals of those matches at the solution.
    axis_sensor : (3,) float
        The pipe axis in the sensor frame (unit).
    points_sensor : (N, 3) float
        The frame's matched points, in the sensor frame (m).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> wall = rng.normal(0, 0.05, (2000, 3)); wall[:, 1] = 1.0   # a smooth wall's normals
    >>> wall /= np.linalg.norm(wall, axis=1, keepdims=True)
    >>> flat, r = np.full(2000, 0.01), rng.normal(0, 0.005, 2000)
    >>> at = rng.uniform(-1, 1, (2100, 3))                        # where the points are
    >>> axial_information(wall, flat, r, np.array([1.0, 0, 0]), at[:2000])
    0.0
    >>> face = np.vstack((wall, np.tile([1.0, 0, 0], (100, 1))))   # plus an end wall,
    >>> at[2000:] = [2.05, 0, 0] + rng.uniform(0, 0.2, (100, 3)) * [0, 1, 1]  # 0.2 m square
    >>> info = axial_information(face, np.resize(flat, 2100), np.resize(r, 2100),
    ...                          np.array([1.0, 0, 0]), at)
    >>> 0.5 < info * 0.005**2 / 4 < 2   # 5 mm noise, four 1 dm² patches: four observations
    True
    """
    signed = normals_sensor @ axis_sensor
    facing = np.abs(signed)
    use = (facing >= FACING_COS) & (surface_variation <= _MAX_SURFACE_VARIATION)
    if use.sum() < MIN_FACING_SUPPORT:
        return 0.0
    r = residuals_m[use]
    sigma = max(MAD_TO_SIGMA * float(np.median(np.abs(r - np.median(r)))), _MIN_RESIDUAL_SIGMA_M)
    # One observation per patch of the smallest face: mean (n·a)² times the patches.
    _, patch = np.unique(
        np.floor(points_sensor[use] / FACE_PATCH_M).astype(np.int64), axis=0, return_inverse=True
    )
    patch = patch.ravel()
    count = np.bincount(patch)
    information = float(np.mean(facing[use] ** 2)) * len(count) / sigma**2
    return information / _patches_disagree(patch, count, signed[use], r, sigma)


def _patches_disagree(
    patch: np.ndarray, count: np.ndarray, f: np.ndarray, r: np.ndarray, sigma: float
) -> float:
    """How much more the facing patches disagree about the shift along the axis than their
    stated errors allow: the reduced χ² of each patch's own shift about their weighted mean,
    at least 1.

    Each patch alone says the frame sits ``-mean(f r) / mean(f²)`` along the axis from the
    solution (``f = n·a``), with weight ``mean(f²) / σ²``. If the patches scatter more than
    that, the faces in the map or the points on them carry an error the residual spread does
    not show (a spurious blob that looks like a face, a face placed by frames that slid), and
    ICP's error along the axis is that much larger: the information is divided by the ratio.
    """
    if len(count) < 2:
        return 1.0
    f2 = np.bincount(patch, f**2) / count
    shift = -(np.bincount(patch, f * r) / count) / f2
    weight = f2 / sigma**2
    mean = float(np.sum(weight * shift) / np.sum(weight))
    return max(1.0, float(np.sum(weight * (shift - mean) ** 2)) / (len(count) - 1))


def small_motion(T: np.ndarray) -> np.ndarray:
    """(rotation vector, translation) of a small relative motion."""
    return np.concatenate((Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]))


def from_small_motion(x: np.ndarray) -> np.ndarray:
    """The 4×4 pose of a (rotation vector, translation)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


def gravity_corrected(
    pred: np.ndarray, gravity_sensor: np.ndarray, axis_world: np.ndarray, down_world: np.ndarray
) -> np.ndarray:
    """Turn a predicted attitude about the pipe axis so that it agrees with the IMU.

    The world "down" seen from the prediction should read as this frame's measured gravity.
    The roll about the axis that best aligns them is the signed angle between the two
    directions' components across the axis (both in the sensor frame); the predicted attitude
    is turned by it about the sensor. Pitch and yaw are left to ICP, which observes them to
    ~0.01°. A prediction is returned unchanged where gravity lies within ~6° of the axis.
    """
    R = pred[:3, :3]
    axis = R.T @ axis_world
    predicted = R.T @ down_world
    across_pred = predicted - axis * (axis @ predicted)
    across_meas = gravity_sensor - axis * (axis @ gravity_sensor)
    if min(np.linalg.norm(across_pred), np.linalg.norm(across_meas)) < _MIN_GRAVITY_ACROSS_AXIS:
        return pred
    # R_new = R @ Rot(axis, θ) reads down as Rot(axis, -θ) @ predicted: θ turns the measured
    # direction onto the predicted one.
    theta = np.arctan2(axis @ np.cross(across_meas, across_pred), across_meas @ across_pred)
    corrected = pred.copy()
    corrected[:3, :3] = R @ Rotation.from_rotvec(theta * axis).as_matrix()
    return corrected


class AxialFilter:
    """The along-axis prior's uncertainty, frame by frame, and the chainage uncertainty.

    ``P`` is the standard deviation of the predicted along-axis position relative to the
    local map. An odometer step ``Δ`` adds ``scale · |Δ|`` to it (its scale error is
    systematic: it adds up linearly, not in quadrature) and its reading noise in quadrature;
    it never exceeds what the odometer can be off over the map's own length. ICP's
    information ``I`` then weighs in: ``w = P² / (P² + 1/I)``, after which ``P² ← (1 - w) P²``.

    The chainage uncertainty ``u`` is a bound on the frame's along-axis position from the
    first frame. A step adds the odometer's bound ``scale · |Δ|`` (times ``1 - w``), and ICP's
    share of the correction its error ``w/√I`` (in quadrature, at 2σ), unless ICP anchors the
    frame: its own error ``1/√I`` within what the odometer may be off over the map's length.
    Then the frame is placed against the map's features, whose place does not drift with the
    odometer, and only ICP's own error adds up, in quadrature, once per keyframe (the map moves
    on by keyframes). A slide adds the size of the disagreement (:meth:`widen`).
    """

    def __init__(
        self, scale_error_ratio: float, noise_m: float, keyframe_distance_m: float = 0.15
    ) -> None:
        self.scale = scale_error_ratio
        self.noise_m = noise_m
        self.keyframe_distance_m = keyframe_distance_m
        self.P = 0.0
        self._cap = 0.0
        self._step = 0.0
        self._odometer = True
        self.last_icp_var = 0.0
        self.last_innovation_sigmas = 0.0
        """The last update's disagreement of ICP with the odometer along the axis, in σ of both
        errors together (``|correction| / √(P² + 1/I)``); 0 without information or odometer."""
        self.last_gate_sigma_m = float("inf")
        """The σ of both errors together that the last update's innovation gate measured the
        disagreement against (``√(P² + 1/I)``, m); infinite without information."""
        self.last_overrode = False
        """Whether the last update's ICP overrode the odometer through the innovation gate."""
        self._held_m = 0.0
        self._icp_var = 0.0
        self._widened_m = 0.0

    @property
    def chainage_uncertainty_m(self) -> float:
        """The bound ``u`` of the current frame's along-axis position (m)."""
        return self._held_m + 2.0 * float(np.sqrt(self._icp_var)) + self._widened_m

    def predict(self, step_m: float, *, map_extent_m: float, odometer: bool) -> float:
        """Grow ``P`` by one step of ``step_m`` (odometer, or a constant-velocity guess);
        returns the step's own bound on the along-axis error."""
        if odometer:
            bound = self.scale * abs(step_m)
            cap = self.scale * max(map_extent_m, abs(step_m))
            noise = np.sqrt(2.0) * self.noise_m
        else:
            bound = _CONSTANT_VELOCITY_STEP_RATIO * abs(step_m)
            cap = float("inf")
            noise = 0.0
        self.P = float(np.hypot(min(self.P + bound, cap), noise))
        self._cap, self._step, self._odometer = cap, abs(step_m), odometer
        self.last_innovation_sigmas = 0.0  # until update() weighs this frame's ICP
        self.last_gate_sigma_m = float("inf")
        self.last_overrode = False
        return bound

    def update(
        self, information: float, step_bound_m: float, correction_m: float = 0.0
    ) -> tuple[float, bool]:
        """Weigh ICP's information (1/m²) against ``P``; returns ICP's weight ``w`` and
        whether ICP overrode the odometer.

        ``correction_m`` is ICP's along-axis correction of the prior (the innovation). When it
        exceeds 3σ of both errors together (``P² + 1/I``), the two cannot both be right; ICP,
        whose own error is then below a third of the disagreement, is believed (``w = 1``):
        the odometer slipped (the crawler stuck on debris while the count ran on, or sliding
        while it stood). Should ICP have jumped to a wrong minimum instead, the slide window
        catches it against the odometer (:class:`SlideDetector`). (A gate on the size of the
        jump was tried: once a real slip had run past it, ICP was never believed again.)
        """
        overrode = False
        self.last_gate_sigma_m = (
            float(np.sqrt(self.P**2 + 1.0 / information)) if information > 0 else float("inf")
        )
        self.last_innovation_sigmas = (
            abs(correction_m) / self.last_gate_sigma_m
            if self._odometer and information > 0
            else 0.0
        )
        # Without an odometer the prior is only a guess: there is nothing to slip.
        gated = (
            self._odometer
            and information > 0
            and correction_m**2 > _INNOVATION_SIGMAS**2 * (self.P**2 + 1.0 / information)
        )
        if information <= 0:
            w = 0.0
        elif gated:
            w, overrode = 1.0, True
        elif self.P == 0:
            w = 1.0
        else:
            w = self.P**2 / (self.P**2 + 1.0 / information)
        self.last_icp_var = w**2 / information if w > 0 and information > 0 else 0.0
        anchored = w > 0 and 1.0 / np.sqrt(information) <= self._cap
        if anchored:
            share = min(self._step / self.keyframe_distance_m, 1.0)
            self._icp_var += share / information
        else:
            # Held to the odometer, but for ICP's share w of a correction that carries ICP's
            # own error: that adds up, in quadrature, too.
            self._held_m += (1.0 - w) * step_bound_m
            self._icp_var += self.last_icp_var
        self.P = float(np.sqrt(1.0 - w)) * self.P
        self.last_overrode = overrode
        return w, overrode

    def widen(self, by_m: float) -> None:
        """Add ``by_m`` to the chainage uncertainty (a disagreement nobody could resolve)."""
        self._widened_m += abs(by_m)


class SlipLog:
    """The odometer's slips caught against features, one size per slip.

    A slip is caught as soon as its slide window disagrees beyond the odometer's error
    (:class:`SlideDetector`), usually before it ends: a crawler stuck for two seconds is
    caught a third of the way in, and caught again once the window has refilled if it is
    still stuck. A slip's size is how far the registered and the odometer's travel drift
    apart from the start of the window that first caught it, at most, until two windows of
    odometer travel pass without a catch. A slide (ICP's fault, put back on the odometer)
    ends the slip being followed.
    """

    def __init__(self, window_m: float) -> None:
        self.window_m = window_m
        self._closed: list[float] = []
        self._open: tuple[float, float, float] | None = None  # (start gap, size, last catch)

    def add(self, odometer_m: float, along_m: float, caught_m: float | None, slide: bool) -> None:
        """One frame: its odometer reading and registered position along the axis (m);
        ``caught_m`` the window's disagreement when the frame caught a slip, ``slide`` when
        it caught a slide instead."""
        gap = along_m - odometer_m
        if slide:
            self._close()
            return
        if caught_m is not None:
            if self._open is None:
                self._open = (gap - caught_m, 0.0, odometer_m)
            else:
                self._open = (self._open[0], self._open[1], odometer_m)
        if self._open is not None:
            start, size, last = self._open
            self._open = (start, max(size, abs(gap - start)), last)
            if abs(odometer_m - last) > 2.0 * self.window_m:
                self._close()

    def _close(self) -> None:
        if self._open is not None:
            self._closed.append(self._open[1])
            self._open = None

    @property
    def sizes_m(self) -> tuple[float, ...]:
        """The slips so far (the one being followed included), m."""
        return (*self._closed, *(() if self._open is None else (self._open[1],)))


def slip_could_hide(
    degenerate: np.ndarray, gate_sigma_m: np.ndarray, steps_m: np.ndarray
) -> np.ndarray:
    """Frames where an odometer slip leaves no trace, (F,) bool: held to the odometer
    (``degenerate``, ICP's weight below one half) and with the innovation gate's σ (ICP's own
    error along the axis and the prior's together, ``√(P² + 1/I)``) not below
    ``1/_INNOVATION_SIGMAS`` of the frame's step. Where it is below, the gate
    (:meth:`AxialFilter.update`) passes a slip of one step frame by frame, whatever ICP
    weighed elsewhere: a slip there could have been caught. The test is the gate's own. With
    ICP's error alone, frames counted as able to catch a slip where the prior's error kept the
    gate shut; that error grows with the odometer's steps between the frames registered."""
    steps = np.asarray(steps_m, dtype=float)
    sigma = np.asarray(gate_sigma_m, dtype=float)
    return np.asarray(degenerate, dtype=bool) & ~(_INNOVATION_SIGMAS * sigma < steps)


def slips_out_of_view(
    caught: np.ndarray,
    overrode: np.ndarray,
    held: np.ndarray,
    steps_m: np.ndarray,
    window_m: float,
) -> np.ndarray:
    """Frames where a slip caught against features went out of view while still going on,
    (F,) bool.

    A slip is caught while it happens (:class:`SlipLog`): a crawler stuck for two seconds is
    caught a third of the way in. While it goes on in view, ICP overrides the odometer frame
    by frame through the innovation gate (``overrode``), and the slip's size follows it. If
    the frames turn ``held`` straight after such an override, the slip was still going on as
    the view was lost, and the rest of it leaves no trace: the frames follow the odometer
    again, and the caught size is only what was seen. A run of held frames that starts
    within two slide windows of odometer travel after a catch (``caught``, the frames whose
    fault is ``"odometer_slip"``; how long :class:`SlipLog` follows a slip) is marked at its
    first frame when the frame before it overrode the odometer, unless the frame after it
    overrides again (seen again at once: that override puts the frame where ICP sees it, so
    the slip's size takes in what happened while held). From a marked frame on, the slip may
    have gone on for as long again as the largest caught (:func:`unseen_slip_allowance`).

    Found on a slipping-odometer draw read every fourth frame (``docs/registration.md``,
    *A slip that goes out of view*): a crawler stuck for 1.2 s was caught after 0.5 s, ICP
    overrode the odometer for two frames, and the frames turned held while it stood for
    0.7 s more: caught as 13 cm, 20 cm in truth.

    >>> caught = np.array([False, True, False, False, False, False])
    >>> overrode = np.array([False, True, True, False, False, False])
    >>> held = np.array([False, False, False, True, True, False])
    >>> slips_out_of_view(caught, overrode, held, np.full(6, 0.1), 0.5).tolist()
    [False, False, False, True, False, False]

    Not when the features stayed in view for two windows (1.2 m here) after the catch, nor
    when ICP no longer disagreed with the odometer as the view was lost (the slip had ended):

    >>> bool(slips_out_of_view(caught, overrode, held, np.full(6, 0.6), 0.5).any())
    False
    >>> ended = np.array([False, True, False, False, False, False])
    >>> bool(slips_out_of_view(caught, ended, held, np.full(6, 0.1), 0.5).any())
    False
    """
    caught = np.asarray(caught, dtype=bool)
    overrode = np.asarray(overrode, dtype=bool)
    held = np.asarray(held, dtype=bool)
    travel = np.cumsum(np.asarray(steps_m, dtype=float))
    marked = np.zeros(len(held), dtype=bool)
    # The last frame up to each frame that caught a slip (-1: none yet).
    last_catch = np.maximum.accumulate(np.where(caught, np.arange(len(caught)), -1))
    for h, e in zip(*_runs(held), strict=True):
        c = int(last_catch[h - 1]) if h > 0 else -1
        if c < 0 or not overrode[h - 1] or (e < len(held) and overrode[e]):
            continue
        if travel[h] - travel[c] <= 2.0 * window_m:
            marked[h] = True
    return marked


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each run of True in ``mask`` starts, and the index just past its end."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return edges[::2], edges[1::2]


def unseen_slip_allowance(
    steps_m: np.ndarray,
    held: np.ndarray,
    slips_m: Sequence[float],
    window_m: float,
    out_of_view: np.ndarray | None = None,
    stated_m: float = 0.0,
) -> np.ndarray:
    """What the odometer may have slipped unseen by each frame, (F,) m, for the chainage
    uncertainty.

    (Over 80 lines for this reference docstring: why the allowance is what it is, from the
    slips the run caught; the body is 37 lines.)

    An odometer slips wherever the crawler does (stuck on debris while the count runs on,
    sliding on a slimy invert while it stands), by more than its stated scale error covers.
    Registration catches a slip only where features carry its slide window
    (:class:`SlideDetector`). Where the frames were held to the odometer (``held``: ICP's
    along-axis weight below one half, and its own error along the axis not below a third of
    the crawler's step, so that the innovation gate could not pass a slip frame by frame
    either; :func:`~pipescan.core.registration.trajectory.chain_trajectories`) a slip
    leaves no trace: over stretches held for at
    least a slide window, counting a stretch of features shorter than a window as held (a
    window over it is mostly held, and a disagreement there is taken for a slide).

    The run's own caught slips tell how this odometer slips in this pipe: how often (``rate``,
    the slips caught per metre of travel where they could be caught, i.e. outside the held
    stretches) and by how much (``largest``, the largest caught). Slips come one at a time
    and either way: the crawler stuck while the count runs on reads long, sliding while it
    stands reads short. After ``L`` metres held in all, the odometer's net unseen slip is
    taken as the difference of two independent Poisson counts of ``rate · L / 2`` each (a
    Skellam count), each slip as large as ``largest``: the allowance is ``largest`` times the
    count that this difference stays within with 95 % probability (``SLIP_CONFIDENCE``), and
    at least one slip from the first held frame on.

    Why the rate counts only where slips could be caught: counted over the whole run, it
    takes the held stretches for slip-free, and frames lay beyond their ± where the odometer
    slipped unseen (docs/history/code-comments.md, *The unseen-slip rate*).

    A caught slip may go on where the frames turn held before it is seen to end
    (``out_of_view``, :func:`slips_out_of_view`): from each such frame on, the allowance
    holds one more slip as large as ``largest``, for the rest of it.

    A run whose odometer was never caught slipping (or that saw no feature at all) gets
    nothing: nothing in it says the odometer slips, and its stated scale error stands alone.
    Unless the crawler's operator states the largest slip it may make (``stated_m``,
    ``inspection.toml``'s ``odometer_slip_m``): then ``largest`` is at least that, and a run
    that caught none (no rate to go by) allows for one such slip from its first held
    stretch on.

    Parameters
    ----------
    steps_m : (F,) float
        Each frame's travel from the previous one (0 for the first).
    held : (F,) bool
        Frames held to the odometer.
    slips_m : sequence of float
        Sizes of the slips caught, one per slip.
    window_m : float
        The slide window's travel.
    out_of_view : (F,) bool, optional
        Frames where a caught slip went out of view (:func:`slips_out_of_view`).
    stated_m : float
        The largest unseen slip the crawler's operator states (0: none stated).
    """
    steps = np.asarray(steps_m, dtype=float)
    held = np.asarray(held, dtype=bool)
    allowance = np.zeros(len(steps))
    if not len(slips_m) and not stated_m > 0:
        return allowance
    largest = max(float(max(slips_m, default=0.0)), float(stated_m))
    if out_of_view is not None:
        allowance += largest * np.cumsum(np.asarray(out_of_view, dtype=bool))
    runs: list[list[int]] = []
    for a, b in zip(*_runs(held), strict=True):
        if runs and steps[runs[-1][1] : a].sum() < window_m:
            runs[-1][1] = b  # features for less than a window between: one stretch
        else:
            runs.append([a, b])
    stretches = [(a, b) for a, b in runs if steps[a:b].sum() >= window_m]
    if not stretches or (held.all() and not stated_m > 0):
        return allowance
    from scipy.stats import skellam  # scipy.stats takes a while to import: only when needed

    held_m = sum(float(steps[a:b].sum()) for a, b in stretches)
    seen_m = max(float(steps.sum()) - held_m, window_m)
    rate = len(slips_m) / seen_m

    def slips(held_by_m: np.ndarray) -> np.ndarray:
        mean = rate * np.asarray(held_by_m, dtype=float) / 2.0
        # |stuck - sliding| <= k with SLIP_CONFIDENCE: the Skellam's two-sided quantile.
        k = skellam.ppf(0.5 + SLIP_CONFIDENCE / 2.0, mean, mean)
        return np.where(held_by_m > 0, np.maximum(1.0, np.nan_to_num(k)), 0.0)

    before_m, done = 0.0, 0
    for a, b in stretches:
        allowance[done:a] += largest * slips(np.array([before_m]))[0]
        held_by_m = before_m + np.cumsum(steps[a:b])
        allowance[a:b] += largest * np.maximum(1.0, slips(held_by_m))
        before_m, done = float(held_by_m[-1]), b
    allowance[done:] += largest * max(1.0, float(slips(np.array([before_m]))[0]))
    return allowance


STOOD_SHARE = 0.5
"""A held frame's odometer count stood when it advanced less than this share of the run's
usual travel a frame (:func:`standstill_allowance`): stopped for at least half the frame's
interval. Halfway between standing (0) and the usual travel (1), it leaves the same margin
each side: a moving count departs from 1 by the crawler's speed changes and the odometer's
noise (±10 % and 1-2 mm on a 15 mm step a frame: under a fifth), a standing one from 0 by
its noise alone. A crawler slowed below half its speed where nothing is in view gets a wider
±, the safe side (measured: docs/registration.md, *When the count stood*)."""


def standstill_allowance(
    steps_m: np.ndarray, frame_gaps: np.ndarray, held: np.ndarray
) -> tuple[np.ndarray, int]:
    """What the crawler may have moved unseen while the odometer's count stood, (F,) m
    (cumulative: by each frame), and how many frames that was.

    A slip the other way from a count that runs on: the crawler slides (on a slimy invert,
    down a gradient) while its wheels and the count stand. Where frames rest on the odometer
    (``held``, :func:`slip_could_hide`), nothing shows it. But the count shows the stand:
    a held frame whose step is under :data:`STOOD_SHARE` of the run's usual travel a frame.
    The crawler may then have gone on at its usual speed, so the allowance grows by the
    usual travel over the frame's interval, less what was counted. A crawler that truly
    stopped there gets the same allowance: in a featureless stretch nothing can tell the
    two apart. The usual travel a frame is the median of the registered steps over the
    archive frames they span (``frame_gaps``: a strided run reads every k-th).

    The odometer then reads short, where a count running on reads long: the chainage
    uncertainty takes the larger of this and :func:`unseen_slip_allowance` frame by frame,
    not their sum (:func:`~pipescan.core.registration.trajectory.chain_trajectories`).

    Found on random layout 2 and slip draw 4, which caught no slip and whose ok sections lay
    up to 27 and 13 cm beyond their ±: their odometers stood while the crawler slid
    (``docs/registration.md``, *When the count stood*).

    Parameters
    ----------
    steps_m : (F,) float
        Each frame's travel from the previous one along the run, signed (0 for the first).
        Signed, so that over a stand the count's reading noise cancels; the steps' lengths
        would add it up as travel counted, and allow that much less.
    frame_gaps : (F,) int
        Archive frames from the previous registered frame (0 for the first).
    held : (F,) bool
        Frames held to the odometer.

    Examples
    --------
    >>> steps = np.array([0, .04, .04, .0, .002, .04, .04])
    >>> allowance, stood = standstill_allowance(steps, np.array([0, 1, 1, 1, 1, 1, 1]),
    ...                                         np.array([0, 1, 1, 1, 1, 1, 0], bool))
    >>> allowance.round(3).tolist(), stood
    ([0.0, 0.0, 0.0, 0.04, 0.078, 0.078, 0.078], 2)
    """
    steps = np.asarray(steps_m, dtype=float)
    gaps = np.asarray(frame_gaps, dtype=float)
    moved = gaps > 0
    if not moved.any():
        return np.zeros(len(steps)), 0
    usual = float(np.median(steps[moved] / gaps[moved]))
    stood = np.asarray(held, dtype=bool) & moved & (steps < STOOD_SHARE * usual * gaps)
    return np.cumsum(np.where(stood, usual * gaps - steps, 0.0)), int(stood.sum())


@dataclass
class _WindowFrame:
    odometer_m: float
    along_m: float
    weight: float
    icp_var: float
    moved_m: float = 0.0
    override_sigma_m: float = float("inf")


class SlideDetector:
    """Registered travel against the odometer's over a window of travel.

    Feed every frame with :meth:`add`. Over the frames since the window started (at least
    ``window_m`` of odometer travel), a disagreement beyond the odometer's error
    (``scale · travel`` plus 3σ of the reading noise and of ICP's own noise) is a fault:
    ``slide`` when ICP carried little weight in the window, ``odometer_slip`` when it carried
    it (features in view: the odometer is the one that is wrong). ICP carried the window when
    its mean weight is at least ½, or when its overrides through the innovation gate, each
    with an error below one step of the crawler, made at least half of its moves towards the
    disagreement (:meth:`_overrides_carried`). After a fault the window is empty: add the
    frame again where the fault left it.
    """

    def __init__(self, window_m: float, scale_error_ratio: float, noise_m: float) -> None:
        self.window_m = window_m
        self.scale = scale_error_ratio
        self.noise_m = noise_m
        self.window_frames = 0
        """Frames in the window of the last fault, this one included."""
        self._frames: deque[_WindowFrame] = deque()

    def restart(self) -> None:
        self._frames.clear()

    def add(
        self,
        odometer_m: float,
        along_m: float,
        weight: float,
        icp_var: float,
        moved_m: float = 0.0,
        override_sigma_m: float = float("inf"),
    ) -> tuple[Fault | None, float]:
        """Add a frame (odometer reading, registered position along the axis, ICP's weight
        and its variance share; how far ICP's share moved it from the prior along the axis,
        and ICP's own error where it overrode the odometer through the innovation gate);
        returns the fault found (or None) and the disagreement (m, registered minus odometer
        travel over the window)."""
        self._frames.append(
            _WindowFrame(odometer_m, along_m, weight, icp_var, moved_m, override_sigma_m)
        )
        while (
            len(self._frames) > 2 and abs(odometer_m - self._frames[1].odometer_m) >= self.window_m
        ):
            self._frames.popleft()
        first = self._frames[0]
        odometer_travel = odometer_m - first.odometer_m
        if abs(odometer_travel) < self.window_m:
            return None, 0.0
        disagreement = (along_m - first.along_m) - odometer_travel
        frames = list(self._frames)[1:]
        icp_sigma = float(np.sqrt(sum(f.icp_var for f in frames)))
        allowed = self.scale * abs(odometer_travel) + _SLIDE_SIGMAS * float(
            np.hypot(np.sqrt(2.0) * self.noise_m, icp_sigma)
        )
        if abs(disagreement) <= allowed:
            return None, disagreement
        carried = float(np.mean([f.weight for f in frames])) >= _ICP_CARRIED_WEIGHT
        if not carried:
            carried = self._overrides_carried(frames, disagreement)
        self.window_frames = len(self._frames)
        self._frames.clear()  # the caller adds the frame again, where it leaves it
        return ("odometer_slip" if carried else "slide"), disagreement

    def _overrides_carried(self, frames: list[_WindowFrame], disagreement: float) -> bool:
        """Whether ICP's resolved overrides made at least half of its moves towards the
        disagreement.

        A slip builds up one frame's step at a time, and ICP follows it through the
        innovation gate (``w = 1``) even where it weighs little elsewhere. Such an override is
        evidence of the slip only where ICP's own error is below one step of the crawler
        (the odometer's median step in the window, over the frames where it moved beyond its
        reading noise): then ICP can tell a crawler that moved from one that stood. An
        override with a larger error is a jump ICP could not have followed, a frame at a
        time, and says nothing about a slip.
        """
        readings = np.array([f.odometer_m for f in self._frames])
        steps = np.abs(np.diff(readings))
        moving = steps[steps > _SLIDE_SIGMAS * np.sqrt(2.0) * self.noise_m]
        if not len(moving):
            return False
        drive_step = float(np.median(moving))
        towards = np.array([f.moved_m for f in frames]) * np.sign(disagreement)
        resolved = np.array([f.override_sigma_m < drive_step for f in frames])
        total = float(towards.clip(min=0).sum())
        return total > 0 and float(towards[resolved].clip(min=0).sum()) >= 0.5 * total
