"""Scenes for scoring the defect coder: each family alone, pairs side by side, a deposit under
an obstacle, ramps of several lengths, and pipes of 0.3 to 0.9 m.

:func:`coding_draws` lists them as :class:`~pipescan.simulator.sweep.Draw` s, each scene at
every diameter, every sensor and crawler effect on at its default (or at ``effects``). A scene's
defects are drawn for a 0.5 m pipe and scaled across the pipe with its diameter; along the pipe
they start where a forward-looking sensor sees the whole wall of a section from several of its
positions (6 radii and the blind zone from the start), and the crawler stops just past the last
one. ``benchmarks/bench_coding.py`` scores the coder
on them against :func:`pipescan.simulator.features.true_features`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from pipescan.simulator.scan import (
    BoxObstacle,
    DepositFill,
    Effects,
    EllipticalDeformation,
    Scenario,
    WallBand,
    sensor_mount_z_m,
)
from pipescan.simulator.sweep import Draw

__all__ = ["CODING_DIAMETERS_M", "SCENES", "coding_draws", "coding_scene"]

CODING_DIAMETERS_M = (0.3, 0.5, 0.6, 0.9)
"""The pipe diameters every scene is drawn at."""

_Parts = tuple[object, ...]


def _deformation_vertical(x: float, k: float) -> _Parts:
    return (EllipticalDeformation(x, x + 0.8, 0.2, 0.07, 0.03),)


def _deformation_horizontal(x: float, k: float) -> _Parts:
    return (EllipticalDeformation(x, x + 0.8, 0.2, 0.0, -0.08),)


def _deposit_short_ramps(x: float, k: float) -> _Parts:
    return (DepositFill(x, x + 0.8, 0.1, 0.25),)


def _deposit_paper(x: float, k: float) -> _Parts:
    return (DepositFill(x, x + 0.9, 0.25, 0.2851),)


def _deposit_long_ramps(x: float, k: float) -> _Parts:
    return (DepositFill(x, x + 1.4, 0.5, 0.2),)


def _crown_obstacle(x: float, k: float) -> _Parts:
    return (BoxObstacle(x, x + 0.3, -0.14 * k, 0.14 * k, 0.1184 * k, 0.35 * k),)


def _side_obstacle(x: float, k: float) -> _Parts:
    # On the right looking downstream (pipe-frame -y): about 3 o'clock.
    return (BoxObstacle(x, x + 0.3, -0.35 * k, -0.12 * k, -0.08 * k, 0.08 * k),)


def _invert_body(x: float, k: float) -> _Parts:
    # A narrow body standing on the invert, 0.13 m off the wall in a 0.5 m pipe.
    return (BoxObstacle(x, x + 0.2, -0.05 * k, 0.05 * k, -0.3 * k, -0.12 * k),)


def _band_right(x: float, k: float) -> _Parts:
    return (WallBand(x, x + 0.8, 1.5, 4.5, 0.02 * k),)


def _band_crown(x: float, k: float) -> _Parts:
    return (WallBand(x, x + 0.8, 10.5, 1.5, 0.025 * k),)


def _deposit_under_crown_obstacle(x: float, k: float) -> _Parts:
    return (
        DepositFill(x, x + 1.2, 0.25, 0.2),
        BoxObstacle(x + 0.4, x + 0.7, -0.14 * k, 0.14 * k, 0.1184 * k, 0.35 * k),
    )


def _body_standing_on_deposit(x: float, k: float) -> _Parts:
    return (
        DepositFill(x, x + 1.2, 0.25, 0.15),
        BoxObstacle(x + 0.5, x + 0.7, -0.12 * k, -0.02 * k, -0.3 * k, -0.11 * k),
    )


def _band_beside_deposit(x: float, k: float) -> _Parts:
    return (DepositFill(x, x + 1.0, 0.2, 0.15), WallBand(x + 0.1, x + 0.9, 8.0, 10.0, 0.02 * k))


def _side_obstacle_and_band(x: float, k: float) -> _Parts:
    return (
        BoxObstacle(x + 0.2, x + 0.5, 0.12 * k, 0.35 * k, -0.08 * k, 0.08 * k),
        WallBand(x, x + 0.8, 2.0, 4.0, 0.02 * k),
    )


def _deformation_then_deposit(x: float, k: float) -> _Parts:
    return (
        EllipticalDeformation(x, x + 0.7, 0.2, 0.07, 0.03),
        DepositFill(x + 0.7, x + 1.5, 0.2, 0.2),
    )


def _crown_and_invert_obstacles(x: float, k: float) -> _Parts:
    return (
        BoxObstacle(x, x + 0.3, -0.14 * k, 0.14 * k, 0.1184 * k, 0.35 * k),
        BoxObstacle(x + 0.05, x + 0.25, -0.05 * k, 0.05 * k, -0.3 * k, -0.12 * k),
    )


SCENES: dict[str, Callable[[float, float], _Parts]] = {
    "deformation, vertical": _deformation_vertical,
    "deformation, horizontal": _deformation_horizontal,
    "deposit, 0.1 m ramps": _deposit_short_ramps,
    "deposit, 0.25 m ramps": _deposit_paper,
    "deposit, 0.5 m ramps": _deposit_long_ramps,
    "obstacle from the crown": _crown_obstacle,
    "obstacle from the side": _side_obstacle,
    "body on the invert": _invert_body,
    "band on the right": _band_right,
    "band at the crown": _band_crown,
    "deposit under an obstacle": _deposit_under_crown_obstacle,
    "body standing on a deposit": _body_standing_on_deposit,
    "band beside a deposit": _band_beside_deposit,
    "obstacle and band side by side": _side_obstacle_and_band,
    "deformation, then a deposit": _deformation_then_deposit,
    "obstacles at the crown and the invert": _crown_and_invert_obstacles,
}
"""Every scene by name: a function of where it starts (m) and the scale across the pipe."""


def coding_scene(
    name: str, diameter_m: float = 0.5, *, effects: Effects | None = None, **overrides: object
) -> Scenario:
    """One scene of :data:`SCENES` in a pipe of ``diameter_m``.

    Parameters
    ----------
    name
        A key of :data:`SCENES`.
    diameter_m
        The pipe's nominal diameter.
    effects
        The sensor and crawler effects (default: every one on at its default).
    **overrides
        Other :class:`Scenario` fields.

    Raises
    ------
    KeyError
        For an unknown scene.
    """
    k = diameter_m / 0.5
    # A forward-looking sensor first reaches the crown and invert about 3.6 radii ahead, and
    # sees a section whole only from some way further back: 6 radii, plus 0.5 m of blind zone.
    start_m = round(6.0 * diameter_m / 2.0 + 0.5, 1)
    parts = SCENES[name](start_m, k)
    fields: dict[str, list[object]] = {
        "deformations": [],
        "deposits": [],
        "obstacles": [],
        "bands": [],
    }
    kinds = {
        EllipticalDeformation: "deformations",
        DepositFill: "deposits",
        BoxObstacle: "obstacles",
        WallBand: "bands",
    }
    for part in parts:
        fields[kinds[type(part)]].append(part)
    end_m = max(p.end_m for p in parts)  # type: ignore[attr-defined]
    effects = effects if effects is not None else Effects()
    # The sensor rides above any deposit's top, with room for its mount jitter (4σ).
    ratios = [f.peak_height_ratio for f in fields["deposits"] if isinstance(f, DepositFill)]
    mount_z_m = sensor_mount_z_m(diameter_m, ratios, effects.mount_jitter_m)
    slug = "".join(c if c.isalnum() else "-" for c in name).strip("-")
    values: dict[str, object] = {
        "name": f"coding: {name}",
        "nominal_diameter_m": diameter_m,
        "travel_m": round(end_m + 0.3, 2),
        "mount_offset_y_m": 0.01 * k,
        "mount_offset_z_m": mount_z_m,
        "effects": effects,
        "asset_id": f"SIM-{slug.upper()[:40]}-{round(1000 * diameter_m)}",
        **{key: tuple(v) for key, v in fields.items()},
    }
    values.update(overrides)
    return Scenario(**values)  # type: ignore[arg-type]


def coding_draws(
    names: Sequence[str] | None = None,
    diameters_m: Sequence[float] = CODING_DIAMETERS_M,
    *,
    effects: Effects | None = None,
    seed: int = 13,
    skipped: list[str] | None = None,
) -> list[Draw]:
    """Every scene (or ``names``) at every diameter, in a fixed order; each draw's scan seed
    is ``seed`` plus its index in that order.

    Raises
    ------
    ValueError
        When a scene cannot be simulated with ``effects`` (the sensor's clearance, which grows
        with the mount jitter, would take it through a feature), unless ``skipped`` is given:
        such scenes are then left out and named there with the reason.
    """
    draws = []
    index = 0
    for name in names or list(SCENES):
        for d in diameters_m:
            try:
                scene = coding_scene(name, d, effects=effects)
            except ValueError as error:
                if skipped is None:
                    raise
                skipped.append(f"{name}, {d} m: {error}")
            else:
                draws.append(Draw(f"{name}, {d} m", "coding", scene, seed + index))
            index += 1
    return draws
