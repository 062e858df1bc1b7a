"""Surveys of one pipe over time: the same scene, with its deposits grown between them.

A trend (``pipescan trend``, ``worst --by growth``, the reports' growth figures) needs several
inspections of one asset at different dates. :func:`grow_deposits` gives the scenario of a
later (or earlier) survey: every deposit's peak height moves by a fixed share of the pipe's
diameter per year, from the scenario's own inspection date. Everything else (the pipe, the
other defects, the sensor) stays as it was; give each survey its own seed for its own noise.
"""

from __future__ import annotations

import dataclasses
from datetime import UTC, datetime

from pipescan.core.trends import SECONDS_PER_YEAR
from pipescan.simulator.scan import Scenario


def grow_deposits(
    scenario: Scenario, height_ratio_per_year: float, inspected_at: datetime
) -> Scenario:
    """The scenario as inspected at another date, its deposits grown linearly in time.

    Parameters
    ----------
    scenario
        The scene at its own ``inspected_at``: its deposits' heights hold at that date.
    height_ratio_per_year
        How fast each deposit's peak height changes, as a share of the nominal diameter per
        year (0.02: two percent of the diameter a year). Negative for a pipe being cleaned;
        a height never goes below zero.
    inspected_at
        The date of the survey to simulate (a naive datetime is taken as UTC).

    Returns
    -------
    Scenario
        With ``inspected_at`` set and every deposit's ``peak_height_ratio`` moved by
        ``height_ratio_per_year`` times the years between the two dates.

    Raises
    ------
    ValueError
        If the scenario has no deposit to grow while the rate is not zero, or if a grown
        deposit would reach the sensor's path (see :class:`Scenario`).

    Examples
    --------
    >>> from pipescan.simulator.scan import get_scenario
    >>> paper = get_scenario("paper")
    >>> later = grow_deposits(paper, 0.01, datetime(2026, 5, 14, 9, 30, tzinfo=UTC))
    >>> round(later.deposits[0].peak_height_ratio - paper.deposits[0].peak_height_ratio, 4)
    0.02
    """
    when = inspected_at if inspected_at.tzinfo is not None else inspected_at.replace(tzinfo=UTC)
    if height_ratio_per_year and not scenario.deposits:
        raise ValueError(
            f"scenario {scenario.name!r} has no deposit to grow: use one with deposits "
            "(paper, long)"
        )
    start = scenario.inspected_at
    start = start if start.tzinfo is not None else start.replace(tzinfo=UTC)
    years = (when - start).total_seconds() / SECONDS_PER_YEAR
    deposits = tuple(
        dataclasses.replace(
            d, peak_height_ratio=max(0.0, d.peak_height_ratio + height_ratio_per_year * years)
        )
        for d in scenario.deposits
    )
    return dataclasses.replace(scenario, inspected_at=when, deposits=deposits)
