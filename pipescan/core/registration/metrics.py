"""What a registration is worth: its summary, its errors against a truth, and what it says
about each stretch of chainage (uncertainty, slides) for the sections measured there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipescan.core.registration.params import RegistrationParams
from pipescan.core.registration.trajectory import Trajectory
from pipescan.core.wording import plural


def degenerate_spans(trajectory: Trajectory) -> list[tuple[int, int]]:
    """Runs of consecutive degenerate frames, as (first, last) archive frame indices."""
    return _spans(trajectory, lambda q: q.degenerate)


def slide_spans(trajectory: Trajectory) -> list[tuple[int, int]]:
    """Runs of consecutive frames put back on the odometer after a slide."""
    return _spans(trajectory, lambda q: q.fault == "slide")


def _spans(trajectory: Trajectory, flagged) -> list[tuple[int, int]]:
    spans: list[tuple[int, int]] = []
    previous = False
    for q in trajectory.quality:
        now = bool(flagged(q))
        if now and previous:
            spans[-1] = (spans[-1][0], q.index)
        elif now:
            spans.append((q.index, q.index))
        previous = now
    return spans


def registration_summary(
    trajectory: Trajectory,
    params: RegistrationParams,
    odometer_m: tuple[float | None, float | None] | None = None,
) -> dict:
    """What to store and print about a registration: engine, quality, travel, where it held.

    ``unconstrained_spans`` lists the runs of frames whose along-axis position the geometry
    hardly constrained (ICP's weight below one half), with the distance travelled (from the
    first frame, metres) at each end. With an odometer they were held to it; without one
    (``along_axis_prior`` = ``constant_velocity``) they are extrapolated, *not measured*, and
    ``warning`` says so. ``travel_m`` is the registered travel (first to last position);
    ``odometer_travel_m`` the odometer's (when ``odometer_m``, its first and last readings,
    is given). ``chainage_uncertainty_m`` bounds the last frame's along-axis position.
    ``slides`` and ``odometer_slips`` count the faults found over the slide window;
    ``odometer_slips_caught_m`` sizes each slip caught (what the chainage uncertainty allows
    for where the odometer was alone). ``frames`` counts the registered frames;
    ``frames_tracked`` the frames between them placed by tracking, ``frames_not_tracked``
    those that could not be (not placed).
    """
    q = trajectory.quality[1:] or trajectory.quality
    positions = trajectory.positions_m()
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    travel = np.concatenate(([0.0], np.cumsum(steps)))
    pos_of = {i: k for k, i in enumerate(trajectory.frame_indices)}

    def span_dict(a: int, b: int) -> dict:
        return {
            "first_frame": a,
            "last_frame": b,
            "start_travel_m": round(float(travel[pos_of[a]]), 4),
            "end_travel_m": round(float(travel[pos_of[b]]), 4),
        }

    spans = [span_dict(a, b) for a, b in degenerate_spans(trajectory)]
    degenerate = sum(x.degenerate for x in q)
    summary: dict = {
        "engine": params.label,
        "frames": len(trajectory.quality),
        "mean_fitness": float(np.mean([x.fitness for x in q])),
        "mean_rmse_m": float(np.mean([x.rmse_m for x in q])),
        "degenerate_frames": degenerate,
        "along_axis_prior": trajectory.along_axis_prior,
        "unconstrained_spans": spans,
        "travel_m": round(float(np.linalg.norm(positions[-1] - positions[0])), 4),
        "chainage_uncertainty_m": round(
            max((x.chainage_uncertainty_m for x in trajectory.quality), default=0.0), 4
        ),
        "slides": sum(x.fault == "slide" for x in q),
        "odometer_slips": sum(x.fault == "odometer_slip" for x in q),
        "odometer_slips_caught_m": [round(float(m), 4) for m in trajectory.odometer_slips_m],
        "unseen_slips_allowed_m": round(float(trajectory.unseen_slips_m), 4),
        "odometer_stood_frames": int(trajectory.standstill_frames),
        "odometer_stood_allowed_m": round(float(trajectory.standstill_m), 4),
        "slide_spans": [span_dict(a, b) for a, b in slide_spans(trajectory)],
        "odometer_uncertainty_ratio": params.odometer_scale_error_ratio,
        "odometer_slip_stated_m": params.odometer_slip_m,
        "frames_tracked": len(trajectory.tracked_indices) - trajectory.frames_not_tracked,
        "frames_not_tracked": trajectory.frames_not_tracked,
    }
    if odometer_m is not None and None not in odometer_m:
        first, last = odometer_m
        assert first is not None and last is not None
        summary["odometer_travel_m"] = round(abs(last - first), 4)
    if degenerate and trajectory.along_axis_prior != "odometer":
        summary["warning"] = (
            f"{degenerate} frame(s) in {len(spans)} span(s) had no odometer and no geometry "
            "along the pipe axis: their chainage is extrapolated, not measured"
        )
    return summary


def allows_unseen_slips(summary: dict) -> bool:
    """Whether the chainage uncertainty at the end allows for odometer slips nothing could
    see (``unseen_slips_allowed_m`` > 0). A summary stored before that was kept cannot say,
    and is taken to allow for them, as it was then reported.

    >>> allows_unseen_slips({"unseen_slips_allowed_m": 0.0}), allows_unseen_slips({})
    (False, True)
    """
    return summary.get("unseen_slips_allowed_m", 1.0) > 0


def unseen_slips_clause(summary: dict) -> str:
    """What the chainage uncertainty allows for odometer slips nothing could see, in words
    ("" where no frame rested on the odometer), for the line that reports the slips caught.
    ``summary`` is a stored :func:`registration_summary`; one stored before it kept
    ``unseen_slips_allowed_m`` gets the general clause.

    >>> unseen_slips_clause({"degenerate_frames": 40, "unseen_slips_allowed_m": 0.62})
    'the ± allows 0.62 m for unseen ones where it was alone'
    >>> unseen_slips_clause({"degenerate_frames": 7, "unseen_slips_allowed_m": 0.0})
    'no stretch rested on the odometer long enough to hide one'
    >>> unseen_slips_clause({"degenerate_frames": 40})
    'allowed for where it was alone'
    """
    if not summary.get("degenerate_frames"):
        return ""
    allowed = summary.get("unseen_slips_allowed_m")
    if allowed is None:
        return "allowed for where it was alone"
    if allowed > 0:
        return f"the ± allows {allowed:.2f} m for unseen ones where it was alone"
    return "no stretch rested on the odometer long enough to hide one"


def standstill_clause(summary: dict) -> str:
    """What the chainage uncertainty allows for the crawler moving on while the odometer's
    count stood and the frames rested on it, in words ("" where it never did, and for a
    summary stored before it was kept).

    >>> text = standstill_clause({"odometer_stood_frames": 12, "odometer_stood_allowed_m": 0.42})
    >>> for part in text.split(": "):
    ...     print(part)
    the odometer stood over 12 frames that rested on it
    the ± allows 0.42 m for the crawler moving on meanwhile
    >>> standstill_clause({"odometer_stood_frames": 0, "odometer_stood_allowed_m": 0.0})
    ''
    """
    frames = summary.get("odometer_stood_frames") or 0
    if not frames:
        return ""
    allowed = float(summary.get("odometer_stood_allowed_m") or 0.0)
    return (
        f"the odometer stood over {plural(frames, 'frame')} that rested "
        f"on it: the ± allows {allowed:.2f} m for the crawler moving on meanwhile"
    )


def unseen_slip_caveat(summary: dict) -> str | None:
    """What the chainage uncertainty cannot allow for, in words, or None.

    (Over 80 lines: the docstring says why each caveat is worded as it is, and the body is
    one sentence built clause by clause, 45 lines.)

    Where frames were held to the odometer, a slip (the count running on while the crawler
    stands, or standing while it slides) leaves no trace in the frames. The chainage
    uncertainty allows for slips there as often and as large as those caught where features
    were in view; when none was caught, it is the odometer's stated uncertainty alone, and a
    user must be told that it holds only if the odometer did not slip where it was alone.
    ``summary`` is a stored :func:`registration_summary`.

    >>> text = unseen_slip_caveat({"degenerate_frames": 40, "along_axis_prior": "odometer",
    ...     "odometer_slips_caught_m": [], "odometer_uncertainty_ratio": 0.03,
    ...     "unconstrained_spans": [{"start_travel_m": 1.0, "end_travel_m": 3.5}]})
    >>> text.split(": ")[0], "the odometer's 3 % and allows for no slip" in text
    ('2.5 m of travel rested on the odometer alone', True)
    >>> unseen_slip_caveat({"degenerate_frames": 200, "frames": 201,
    ...     "odometer_slips_caught_m": []}).split("(")[1].split(";")[0]
    'no features were in view to catch one'

    A run that caught slips has them allowed for where the odometer was alone, each as large
    as the largest caught: a larger one there is not (``docs/registration.md``, *A slip that
    goes out of view*: on a slip draw whose unseen slips were 18-22 cm and whose largest
    caught was 11 cm, frames lay up to 23 cm beyond their ±). This holds at every stride;
    registering every frame caught as many slips as the flow's stride on the slip draws
    (12 and 12), so it is not offered as the remedy.

    >>> unseen_slip_caveat({"degenerate_frames": 40, "along_axis_prior": "odometer",
    ...     "odometer_slips_caught_m": [0.2, 0.44]}).split(";")[0]
    'The ± allows for slips where the odometer was alone as large as the largest caught (0.44 m)'
    >>> unseen_slip_caveat({"degenerate_frames": 0, "odometer_slips_caught_m": [0.2]}) is None
    True

    Nor where no stretch rested on the odometer long enough to hide a slip (the summary's
    ``unseen_slips_allowed_m`` is 0; summaries stored before it was kept get the caveat):

    >>> unseen_slip_caveat({"degenerate_frames": 7, "odometer_slips_caught_m": [0.17],
    ...     "unseen_slips_allowed_m": 0.0}) is None
    True

    Where the crawler's operator stated the largest slip it may make (``inspection.toml``'s
    ``odometer_slip_m``), that is the size allowed for when it is larger than any caught,
    and a run that caught none allows for one:

    >>> unseen_slip_caveat({"degenerate_frames": 40, "odometer_slips_caught_m": [0.2],
    ...     "odometer_slip_stated_m": 0.5}).split(";")[0]
    'The ± allows for slips where the odometer was alone as large as the stated 0.50 m'
    >>> text = unseen_slip_caveat({"degenerate_frames": 40, "odometer_slips_caught_m": [],
    ...     "odometer_slip_stated_m": 0.3, "odometer_uncertainty_ratio": 0.03,
    ...     "unconstrained_spans": [{"start_travel_m": 1.0, "end_travel_m": 3.5}]})
    >>> "the odometer's 3 % and one unseen slip of the stated 0.30 m (none was caught" in text
    True
    """
    if not summary.get("degenerate_frames"):
        return None
    caught = summary.get("odometer_slips_caught_m") or []
    stated_m = float(summary.get("odometer_slip_stated_m") or 0.0)
    if caught:
        if not allows_unseen_slips(summary):
            return None  # no stretch held long enough to hide a slip: the ± allows for none
        size = (
            f"the stated {stated_m:.2f} m"
            if stated_m > max(caught)
            else f"the largest caught ({max(caught):.2f} m)"
        )
        return (
            f"The ± allows for slips where the odometer was alone as large as {size}; a "
            "larger one there is not allowed for (for a crawler known to slip further, state "
            "its largest slip as odometer_slip_m in inspection.toml)"
        )
    if summary.get("along_axis_prior", "odometer") == "constant_velocity":
        return None  # no odometer at all: the summary's warning says the chainage is not measured
    spans = summary.get("unconstrained_spans") or []
    held_m = sum(s["end_travel_m"] - s["start_travel_m"] for s in spans)
    ratio = summary.get("odometer_uncertainty_ratio")
    stated = f"the odometer's {100 * ratio:.3g} %" if ratio else "the odometer's uncertainty"
    travel = f"{held_m:.1f} m of travel" if held_m > 0 else "Travel"
    frames = summary.get("frames") or 0
    # The first frame has no step of its own: all others held means no feature was in view.
    why = (
        "no features were in view to catch one"
        if frames and summary["degenerate_frames"] >= frames - 1
        else "none was caught where features were in view"
    )
    if stated_m > 0 and allows_unseen_slips(summary):
        return (
            f"{travel} rested on the odometer alone: the ± there is {stated} and one unseen "
            f"slip of the stated {stated_m:.2f} m (none was caught; more than one, or a "
            "larger one, is not allowed for)"
        )
    stood = bool(summary.get("odometer_stood_frames"))
    besides = ", and the crawler moving on where its count stood," if stood else ""
    other = "no other slip" if stood else "no slip"
    return (
        f"{travel} rested on the odometer alone: the ± there is {stated}{besides} and allows "
        f"for {other} ({why}; one where it was alone would not be seen; state the crawler's "
        "largest slip as odometer_slip_m in inspection.toml)"
    )


@dataclass(frozen=True)
class RegistrationEvidence:
    """What registration says about each stretch of chainage, for the sections measured there.

    A section is seen by the frames within ``seen_from_m`` behind it (in the direction of
    travel: the sensor looks forward). Its chainage uncertainty is the largest of theirs. Its
    registration is weak when one of them had no odometer and no geometry along the axis
    (its place is extrapolated), or when most of them slid along the axis (a fault the
    odometer caught: such frames are left out of the sections, and the few left may not show
    the section whole), or when registration as a whole is ``untrusted``.

    Attributes
    ----------
    frame_chainage_m : (F,) float
        Chainage of each frame's sensor position on the fitted axis.
    uncertainty_m : (F,) float
        Each frame's chainage uncertainty.
    extrapolated, slid : (F,) bool
        Frames placed along the axis by a guess (no odometer, no geometry), frames that slid.
    seen_from_m : float
        How far ahead of the sensor a section can be seen (the section range).
    ahead : {1, -1}
        The direction of travel along the chainage.
    """

    frame_chainage_m: np.ndarray
    uncertainty_m: np.ndarray
    extrapolated: np.ndarray
    slid: np.ndarray
    seen_from_m: float
    ahead: int = 1
    untrusted: bool = False
    """Registration as a whole is not trusted for figures: every section is weak
    (:func:`pipescan.core.instrument.registration_trusted`)."""

    @classmethod
    def uniform(cls, uncertainty_m: float) -> RegistrationEvidence:
        """The same chainage uncertainty everywhere, nothing weak: a registered cloud, whose
        chainage is known as well as its start is (``CloudStart.uncertainty_m``).

        >>> RegistrationEvidence.uniform(0.4).for_section(12.0, 12.1)
        (0.4, False)
        """
        c = np.array([-np.inf])
        return cls(c, np.array([uncertainty_m]), np.zeros(1, bool), np.zeros(1, bool), np.inf)

    def for_section(self, start_m: float, end_m: float) -> tuple[float, bool]:
        """(chainage uncertainty, weak) of the section ``[start_m, end_m)``."""
        c = self.frame_chainage_m
        if self.untrusted:
            return float(self.uncertainty_m.max()) if len(c) else 0.0, True
        if self.ahead >= 0:
            seen = (c >= start_m - self.seen_from_m) & (c <= end_m)
        else:
            seen = (c >= start_m) & (c <= end_m + self.seen_from_m)
        if not seen.any():
            return 0.0, False
        weak = bool(self.extrapolated[seen].any()) or float(self.slid[seen].mean()) > 0.5
        return float(self.uncertainty_m[seen].max()), weak


def registration_evidence(
    trajectory: Trajectory, frame_chainage_m: np.ndarray, *, seen_from_m: float
) -> RegistrationEvidence:
    """The :class:`RegistrationEvidence` of a trajectory whose frames sit at
    ``frame_chainage_m`` (their sensor positions on the fitted axis, (F,))."""
    chainage = np.asarray(frame_chainage_m, dtype=np.float64)
    q = trajectory.quality
    guessed = trajectory.along_axis_prior != "odometer"
    extrapolated = np.array([guessed and x.degenerate for x in q], dtype=bool)
    slid = np.array([x.fault == "slide" for x in q], dtype=bool)
    uncertainty = np.array([x.chainage_uncertainty_m for x in q])
    ahead = 1 if len(chainage) < 2 or chainage[-1] >= chainage[0] else -1
    return RegistrationEvidence(chainage, uncertainty, extrapolated, slid, seen_from_m, ahead)


@dataclass(frozen=True)
class TrajectoryErrors:
    """Pose errors of an estimated trajectory against the truth (both from the first frame).

    Translation errors are split along the pipe axis (the direction from the first to the
    last true position) and across it; rotation errors into roll about that axis (which a
    round pipe cannot observe, and which moves neither chainages nor areas) and the tilt of
    the axis (pitch and yaw together).
    """

    across_rms_m: float
    along_final_m: float
    along_max_m: float
    tilt_rms_deg: float
    roll_rms_deg: float


def trajectory_errors(T_estimated: np.ndarray, T_true: np.ndarray) -> TrajectoryErrors:
    """Compare poses, (F, 4, 4) each; both are re-expressed relative to their first pose.

    Raises
    ------
    ValueError
        When the shapes differ or the truth does not move (no axis to split along).
    """
    est, true = np.asarray(T_estimated, np.float64), np.asarray(T_true, np.float64)
    if est.shape != true.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"Poses must both have shape (F, 4, 4), got {est.shape}, {true.shape}.")
    est = np.einsum("ij,fjk->fik", np.linalg.inv(est[0]), est)
    true = np.einsum("ij,fjk->fik", np.linalg.inv(true[0]), true)
    travel = true[-1, :3, 3]
    if np.linalg.norm(travel) < 1e-6:
        raise ValueError("The true trajectory does not move; there is no axis to split along.")
    axis = travel / np.linalg.norm(travel)
    err = est[:, :3, 3] - true[:, :3, 3]
    along = err @ axis
    across = np.linalg.norm(err - np.outer(along, axis), axis=1)
    rotvec = Rotation.from_matrix(est[:, :3, :3] @ true[:, :3, :3].transpose(0, 2, 1)).as_rotvec()
    roll = rotvec @ axis
    tilt = np.linalg.norm(rotvec - np.outer(roll, axis), axis=1)
    return TrajectoryErrors(
        across_rms_m=float(np.sqrt(np.mean(across**2))),
        along_final_m=float(along[-1]),
        along_max_m=float(np.abs(along).max()),
        tilt_rms_deg=float(np.degrees(np.sqrt(np.mean(tilt**2)))),
        roll_rms_deg=float(np.degrees(np.sqrt(np.mean(roll**2)))),
    )
