"""Frame registration: odometer-initialised ICP, fused with the odometer and the IMU.

In a smooth straight pipe, ICP cannot tell where along the axis one frame sits relative to the
next, nor how it is rolled about the axis: the cost is flat in those directions. And what is
not surface (spurious returns from mist, spray and dust; mixed pixels at depth edges) can fake
exactly the information that is missing, and let ICP slide along the pipe. The stages:

``preprocess``
    Range crop, voxel filter and isolated-point removal of each frame; a keyframe of the
    local map keeps only what at least two of its frames saw.
``engines``
    The local map (the last few keyframes) and the ICP step: ``small_gicp`` (default),
    Open3D's legacy ``open3d`` and tensor ``open3d_tensor`` pipelines (with a Tukey robust
    kernel), and the paper's point-to-point ICP with the Kabsch step
    (``method="point_to_point"``, as printed: no fusion).
``fusion``
    Along the axis, ICP's correction is weighed against the odometer by ICP's information
    along the axis (the Hessian, less what a smooth wall fakes) and the odometer's stated
    uncertainty; a window of travel catches slides, and the odometer's slips it caught are
    allowed for where it was alone (:func:`unseen_slip_allowance`). About the axis, roll is
    held where the Hessian is degenerate, at an attitude turned to agree with the IMU's
    gravity.
``deskew``
    :func:`~pipescan.core.registration.deskew.deskew_points`: a frame whose points carry
    times, moved to the sensor's pose at its first point by the travel over the frame.
``registrar``
    :class:`FrameRegistrar` and :func:`register_frames`: the streaming loop.
``trajectory``
    :class:`Trajectory`, chunks (:func:`plan_chunks`) and :func:`chain_trajectories`.
``metrics``
    :func:`registration_summary`, :func:`trajectory_errors` and the per-chainage
    :class:`RegistrationEvidence` that section statuses depend on.

Poses are 4×4 matrices ``T_world_frame`` mapping frame (sensor) coordinates into the world
frame, which is the first frame's sensor frame. ``docs/registration.md`` has the measurements.
"""

from pipescan.core.registration.engines import LocalMap, icp_point_to_point, kabsch, transform
from pipescan.core.registration.fusion import (
    AxialFilter,
    SlideDetector,
    SlipLog,
    axial_information,
    degenerate_directions,
    gravity_corrected,
    point_to_plane_hessian,
    slips_out_of_view,
    standstill_allowance,
    unseen_slip_allowance,
)
from pipescan.core.registration.metrics import (
    RegistrationEvidence,
    TrajectoryErrors,
    degenerate_spans,
    registration_evidence,
    registration_summary,
    slide_spans,
    standstill_clause,
    trajectory_errors,
    unseen_slip_caveat,
    unseen_slips_clause,
)
from pipescan.core.registration.params import (
    REGISTRATION_ENGINES,
    REGISTRATION_METHODS,
    AlongAxisPrior,
    RegistrationEngine,
    RegistrationMethod,
    RegistrationParams,
)
from pipescan.core.registration.preprocess import (
    drop_early_returns,
    estimate_normals,
    preprocess_frame,
    remove_isolated,
    seen_twice,
    voxel_downsample,
)
from pipescan.core.registration.registrar import (
    FrameRegistrar,
    register_frames,
    register_keyframes,
)
from pipescan.core.registration.stride import (
    FrameStride,
    PlacedShare,
    choose_frame_stride,
    choose_placed_share,
    frames_to_register,
    is_stride_frame,
    sample_frame_indices,
)
from pipescan.core.registration.trajectory import (
    FramePoses,
    Trajectory,
    chain_trajectories,
    chunk_frame_indices,
    interpolate_pose,
    iter_registered_points,
    plan_chunks,
    share_of_way,
    used_frame_indices,
)

__all__ = [
    "REGISTRATION_ENGINES",
    "REGISTRATION_METHODS",
    "AlongAxisPrior",
    "AxialFilter",
    "FramePoses",
    "FrameRegistrar",
    "FrameStride",
    "LocalMap",
    "PlacedShare",
    "RegistrationEngine",
    "RegistrationEvidence",
    "RegistrationMethod",
    "RegistrationParams",
    "SlideDetector",
    "SlipLog",
    "Trajectory",
    "TrajectoryErrors",
    "axial_information",
    "chain_trajectories",
    "choose_frame_stride",
    "choose_placed_share",
    "chunk_frame_indices",
    "degenerate_directions",
    "degenerate_spans",
    "drop_early_returns",
    "estimate_normals",
    "frames_to_register",
    "gravity_corrected",
    "icp_point_to_point",
    "interpolate_pose",
    "is_stride_frame",
    "iter_registered_points",
    "kabsch",
    "plan_chunks",
    "point_to_plane_hessian",
    "preprocess_frame",
    "register_frames",
    "register_keyframes",
    "registration_evidence",
    "registration_summary",
    "remove_isolated",
    "sample_frame_indices",
    "seen_twice",
    "share_of_way",
    "slide_spans",
    "slips_out_of_view",
    "standstill_allowance",
    "standstill_clause",
    "trajectory_errors",
    "transform",
    "unseen_slip_allowance",
    "unseen_slip_caveat",
    "unseen_slips_clause",
    "used_frame_indices",
    "voxel_downsample",
]
