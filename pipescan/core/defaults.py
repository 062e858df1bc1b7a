"""The defaults of an inspection's parameters, written once: the settings
(:class:`pipescan.settings.Settings`, the ``PIPESCAN_*`` variables) and the code that takes the
same parameters explicitly (``flows.inspect.InspectionParams``, ``core.sections.plan_windows``,
``core.contour.grid.GridParams``, the ISYBAU export's fallback step) all read them here.

Plain values, so that reading the settings imports no NumPy or SciPy. The grading defaults (the
threshold table, the flag rule) are in :mod:`pipescan.core.flags`; the registration's are
``RegistrationParams``'s own.
"""

from __future__ import annotations

__all__ = [
    "CHUNK_FRAMES",
    "CONTOUR_METHOD",
    "GRID_K",
    "GRID_S_THRESHOLD_RAD",
    "PIPE_CLASS",
    "SECTION_STEP_M",
    "WINDOW_M",
]

SECTION_STEP_M = 0.1
"""A section's length along the chainage."""
WINDOW_M = 2.0
"""The chainage window one task places and measures."""
CHUNK_FRAMES = 60
"""Frames one task registers."""
PIPE_CLASS = "auto"
"""The BAA deformation rule: from the archive's material (``rigid`` or ``flexible`` to set it)."""
CONTOUR_METHOD = "polar"
"""The contour method (a name in ``pipescan.core.contour.CONTOUR_METHODS``)."""
GRID_K = 12
"""The grid method's neighbours in the angle-gap test."""
GRID_S_THRESHOLD_RAD = 0.55
"""The grid method's angle-gap standard deviation S of a boundary point."""
