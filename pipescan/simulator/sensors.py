"""Other sensors than the forward-looking one, and water, for the scan simulator.

:class:`~pipescan.simulator.scan.Scenario` takes one of these as ``sensor`` (None keeps the
Livox HAP-like pattern its own fields describe) and a :class:`WaterLevel` as ``water``.

- :class:`RingProfiler`: a 2D LiDAR spinning in the section plane, as profiling crawlers
  carry. One frame is one revolution, on a fixed angular grid; the ring can be tilted from the
  section plane (the sensor mounted askew, or the crawler pitched).
- :class:`StaticScanner`: a terrestrial laser scanner (FARO-like) set up at stations along
  the pipe, each station one frame: a full turn in azimuth about the pipe frame's vertical,
  on a grid of elevations. The wall it sees grows sparse and grazing with the distance
  along the pipe.
- :class:`WaterLevel`: water standing in the invert to a depth. Rays that reach its surface
  mostly give no return (specular, or absorbed below); a small share returns from the surface.
  The wall below it is never seen. Water is not blockage: the true open area keeps it.

Directions are unit vectors in the sensor frame (x forward along the pipe, y left, z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RingProfiler:
    """A 2D LiDAR spinning in the plane across the pipe.

    Attributes
    ----------
    points_per_revolution : int
        Rays per turn, on a fixed grid (a 2D LiDAR's angular step is ``360 / this``).
    tilt_deg : float
        Angle between the ring's plane and the section plane (a turn about the sensor's y).
    """

    points_per_revolution: int = 120
    tilt_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.points_per_revolution < 8:
            raise ValueError("RingProfiler.points_per_revolution must be >= 8.")
        if not 0 <= abs(self.tilt_deg) < 45:
            raise ValueError("RingProfiler.tilt_deg must be within (-45, 45) degrees.")

    @property
    def rays_per_frame(self) -> int:
        return self.points_per_revolution

    def directions(self, frame_index: int, stride: int = 1) -> np.ndarray:
        """Unit ray directions (N, 3) of one revolution (every ``stride``-th ray)."""
        n = self.points_per_revolution
        a = 2.0 * np.pi * np.arange(0, n, stride) / n
        ring = np.column_stack((np.zeros_like(a), np.cos(a), np.sin(a)))
        t = math.radians(self.tilt_deg)
        # Turn about y: the ring's top leans forward by tilt_deg.
        rot = np.array(
            [[math.cos(t), 0.0, math.sin(t)], [0.0, 1.0, 0.0], [-math.sin(t), 0.0, math.cos(t)]]
        )
        return ring @ rot.T


@dataclass(frozen=True)
class StaticScanner:
    """A terrestrial laser scanner at a station: a full turn in azimuth about the vertical.

    Attributes
    ----------
    step_deg : float
        Angular step in azimuth and in elevation.
    elevation_min_deg, elevation_max_deg : float
        Elevations scanned (the tripod hides what lies below the lower one).
    """

    step_deg: float = 0.5
    elevation_min_deg: float = -60.0
    elevation_max_deg: float = 90.0

    def __post_init__(self) -> None:
        if not 0.01 <= self.step_deg <= 10:
            raise ValueError("StaticScanner.step_deg must be within [0.01, 10] degrees.")
        if not -90 <= self.elevation_min_deg < self.elevation_max_deg <= 90:
            raise ValueError("StaticScanner elevations must satisfy -90 <= min < max <= 90.")

    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        az = np.radians(np.arange(0.0, 360.0, self.step_deg))
        el = np.radians(
            np.arange(self.elevation_min_deg, self.elevation_max_deg + 1e-9, self.step_deg)
        )
        return az, el

    @property
    def rays_per_frame(self) -> int:
        az, el = self._grid()
        return len(az) * len(el)

    def directions(self, frame_index: int, stride: int = 1) -> np.ndarray:
        """Unit ray directions (N, 3) of one station's scan (every ``stride``-th ray)."""
        az, el = self._grid()
        a, e = np.meshgrid(az, el, indexing="ij")
        a, e = a.ravel()[::stride], e.ravel()[::stride]
        return np.column_stack((np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)))


@dataclass(frozen=True)
class WaterLevel:
    """Water in the invert, ``depth_ratio`` of the nominal diameter deep, over
    ``[start_m, end_m]`` along the axis (default: everywhere).

    ``surface_return_ratio`` of the rays that reach the surface straight down return from it
    (with the sensor's range noise), fewer by the cosine of their incidence (turbid water
    scatters diffusely; a ray at grazing incidence glances off); the others give no return.
    """

    depth_ratio: float
    surface_return_ratio: float = 0.1
    start_m: float = -math.inf
    end_m: float = math.inf

    def __post_init__(self) -> None:
        if not 0 < self.depth_ratio < 0.6:
            raise ValueError("WaterLevel.depth_ratio must be in (0, 0.6).")
        if not 0 <= self.surface_return_ratio <= 1:
            raise ValueError("WaterLevel.surface_return_ratio must be in [0, 1].")
        if not self.start_m < self.end_m:
            raise ValueError("WaterLevel needs start_m < end_m.")

    def surface_z_m(self, radius_m: float) -> float:
        """Pipe-frame z of the water surface for a pipe of ``radius_m``."""
        return -radius_m + self.depth_ratio * 2.0 * radius_m
