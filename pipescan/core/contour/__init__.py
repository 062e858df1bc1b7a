"""Inner contours of pipe cross-sections: the registry of contour methods.

Each method is one module of this package with a function
``contour(points, profile, params) -> ContourResult`` (see :class:`ContourMethod`), listed in
:data:`CONTOUR_METHODS` by the name users choose it by (``--contour``,
``PIPESCAN_CONTOUR_METHOD``). Adding a method is one new module here and one line in that
table; the CLI's choices, the settings' check and the tests' parametrisation all read it.

A method only traces the contour. Whether a section's figures can be trusted (its coverage by
angle, its point count) is judged once, before any method runs, by
:func:`pipescan.core.measures.measure_section`; a method that cannot trace a closed contour
raises :class:`~pipescan.core.errors.GeometryError`, and the section is ``no_contour``.

This module imports nothing heavy, so that the command line can list the methods quickly; the
method's module is imported when it is first used.

Examples
--------
>>> list(CONTOUR_METHODS)
['polar', 'grid']
>>> check_contour_method("polr")
Traceback (most recent call last):
...
pipescan.core.errors.OptionError: unknown contour method 'polr' (use one of: polar, grid)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any, Protocol

from pipescan.core.defaults import CONTOUR_METHOD
from pipescan.core.errors import OptionError

if TYPE_CHECKING:
    import numpy as np

    from pipescan.core.contour.base import ContourResult
    from pipescan.core.contour.polar import PolarProfile

__all__ = [
    "CONTOUR_METHODS",
    "CONTOUR_PARAMS",
    "DEFAULT_CONTOUR_METHOD",
    "ContourMethod",
    "check_contour_method",
    "contour_method",
]

#: Contour methods by name: the module that holds each one's ``contour`` function.
CONTOUR_METHODS: dict[str, str] = {
    "polar": "pipescan.core.contour.polar",
    "grid": "pipescan.core.contour.grid",
}
DEFAULT_CONTOUR_METHOD = CONTOUR_METHOD
#: The field of ``MeasureParams`` that holds each method's own parameters (none for polar).
CONTOUR_PARAMS: dict[str, str] = {"grid": "grid"}


class ContourMethod(Protocol):
    """A contour method: the ``contour`` function of a module listed in
    :data:`CONTOUR_METHODS`.

    Parameters
    ----------
    points : (N, 2) or (N, 3) float
        The section's points after stray-point removal, metres: columns 0-1 in the section
        plane with the pipe axis at the origin (0 across, 1 up), column 2 (optional) the
        distance along the axis from the section's start.
    profile : PolarProfile
        The section's profile by angle, from which its coverage was judged; the result's
        ``radii_m`` are at ``profile.angles_rad``.
    params : object or None
        The method's own parameters, and only those (``GridParams`` for ``grid``; ``polar``
        has none): the measuring code hands each method what :data:`CONTOUR_PARAMS` names.

    Returns
    -------
    ContourResult

    Raises
    ------
    GeometryError
        When the method cannot trace a closed inner contour.
    """

    def __call__(self, points: np.ndarray, profile: PolarProfile, params: Any) -> ContourResult: ...


def check_contour_method(name: str) -> str:
    """``name`` if it is a known contour method.

    Raises
    ------
    OptionError
        Naming the known methods, when it is not.
    """
    if name not in CONTOUR_METHODS:
        raise OptionError(
            f"unknown contour method {name!r}", hint=f"use one of: {', '.join(CONTOUR_METHODS)}"
        )
    return name


def contour_method(name: str) -> ContourMethod:
    """The contour method registered as ``name``.

    Raises
    ------
    OptionError
        When no method has that name.
    """
    module = importlib.import_module(CONTOUR_METHODS[check_contour_method(name)])
    method: ContourMethod = module.contour
    return method
