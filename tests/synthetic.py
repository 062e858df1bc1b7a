"""Small synthetic pipes with known geometry, for unit tests of the geometry core.

The full ray-cast simulator lives in ``pipescan.simulator.scan``; these are cheaper stand-ins for
tests that need exact control of one property at a time.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def segment_area_ratio(height_m: float, radius_m: float) -> float:
    """Share of a circle's area below a chord at ``height_m`` above the invert."""
    if height_m <= 0:
        return 0.0
    theta = 2.0 * math.acos(1.0 - height_m / radius_m)
    return (theta - math.sin(theta)) / (2.0 * math.pi)


def ring_section(
    n: int,
    *,
    radius_m: float = 0.25,
    noise_m: float = 0.005,
    deposit_m: float = 0.0,
    rng: np.random.Generator,
    gap_deg: tuple[float, float] | None = None,
) -> np.ndarray:
    """Projected section points (n, 2): a noisy circle with an optional flat deposit at the
    invert and an optional unseen arc ``gap_deg = (start, end)`` (degrees, ccw from +x)."""
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    if gap_deg is not None:
        lo, hi = np.radians(gap_deg)
        theta = theta[~((theta >= lo) & (theta <= hi))]
    r = radius_m + rng.normal(0.0, noise_m, len(theta))
    pts = np.column_stack((r * np.cos(theta), r * np.sin(theta)))
    if deposit_m > 0:
        y_top = -radius_m + deposit_m
        below = pts[:, 1] < y_top
        half = math.sqrt(radius_m**2 - y_top**2)
        m = int(below.sum())
        pts[below] = np.column_stack(
            (rng.uniform(-half, half, m), y_top + rng.normal(0.0, noise_m, m))
        )
    return pts


def pipe_cloud(
    *,
    length_m: float = 4.0,
    radius_m: float = 0.25,
    points_per_m: int = 40_000,
    noise_m: float = 0.003,
    deposit: tuple[float, float, float] | None = None,
    rng: np.random.Generator,
) -> np.ndarray:
    """A straight pipe along +x from 0 to ``length_m`` (N, 3), z up, axis through the origin.

    ``deposit = (start_m, end_m, height_m)`` fills the invert flat over that span.
    """
    n = int(length_m * points_per_m)
    x = rng.uniform(0.0, length_m, n)
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    r = radius_m + rng.normal(0.0, noise_m, n)
    y, z = r * np.cos(theta), r * np.sin(theta)
    if deposit is not None:
        start, end, h = deposit
        z_top = -radius_m + h
        inside = (x >= start) & (x < end) & (z < z_top)
        half = math.sqrt(radius_m**2 - z_top**2)
        m = int(inside.sum())
        y[inside] = rng.uniform(-half, half, m)
        z[inside] = z_top + rng.normal(0.0, noise_m, m)
    return np.column_stack((x, y, z))


def random_rigid(rng: np.random.Generator, *, max_tilt_deg: float = 20.0) -> np.ndarray:
    """A 4×4 rigid transform: any yaw, a tilt of up to ``max_tilt_deg``, and an offset.

    The tilt is bounded so that "up" stays recognisably up (as in a real, tilted scan).
    """
    yaw = rng.uniform(-180.0, 180.0)
    pitch, roll = rng.uniform(-max_tilt_deg, max_tilt_deg, 2)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [yaw, pitch, roll], degrees=True).as_matrix()
    T[:3, 3] = rng.uniform(-100.0, 100.0, 3)
    return T


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def curved_pipe_cloud(
    *,
    length_m: float = 6.0,
    bend_radius_m: float = 12.0,
    sag_m: float = 0.03,
    radius_m: float = 0.25,
    points_per_m: int = 30_000,
    noise_m: float = 0.002,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """A pipe whose centreline bends horizontally (radius ``bend_radius_m``) and sags
    vertically (a half sine of depth ``sag_m``), z up.

    Returns the points (N, 3) and each point's true distance along the centreline (N,).
    """
    u = np.linspace(0.0, length_m, 4001)

    def centre(t):
        return np.column_stack(
            (
                bend_radius_m * np.sin(t / bend_radius_m),
                bend_radius_m * (1.0 - np.cos(t / bend_radius_m)),
                -sag_m * np.sin(np.pi * t / length_m),
            )
        )

    c = centre(u)
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))))
    n = int(length_m * points_per_m)
    t = rng.uniform(0.0, length_m, n)
    p = centre(t)
    tangent = (centre(t + 1e-4) - centre(t - 1e-4)) / 2e-4
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0]) - tangent[:, 2:3] * tangent
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    right = np.cross(up, tangent)
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    r = radius_m + rng.normal(0.0, noise_m, n)
    pts = p + (r * np.cos(theta))[:, None] * right + (r * np.sin(theta))[:, None] * up
    return pts, np.interp(t, u, arc)
