"""A seeded sweep of simulated scans over sensor and crawler effects × scenes.

Accuracy claims must hold on scans the code was not tuned on. A :class:`Draw` is one scan of
the sweep: a scene (pipe diameter, length, defects, whether the end wall is in view) and the
:class:`~pipescan.simulator.scan.Effects` that spoil it. :func:`sweep_draws` lists them:

- one draw per effect at the harsh end of its range, the others off (``effect:<name>``);
- the defaults, every effect at its harsh end together, and seeded random combinations of
  effects drawn from their ranges, over 0.3, 0.5 and 0.6 m pipes and a 30 m run
  (``combined:<name>``).

Every draw of :func:`sweep_draws` has the same defects in the same places (the paper's
deformation, box and deposit, scaled to the pipe), and the code was tuned on them over many
rounds. :func:`layout_draws` draws layouts it never saw: 2-4 defects of random kinds, sizes and
places, in pipes of 0.3-0.8 m.

The ranges are those of issue 12 (what real sewers do to a LiDAR on a crawler): spurious
returns 0.1-2 % of a frame, range noise 2-20 mm 1σ, vibration up to 1.5° 1σ per frame, mount
jitter up to 1 cm, odometer scale error up to ±3 % with slip, IMU noise 0.05-0.3° and frames
without IMU. ``benchmarks/bench_registration.py sweep`` runs them; the slow tests run a few.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipescan.simulator.scan import (
    BoxObstacle,
    DepositFill,
    Effects,
    EllipticalDeformation,
    Scenario,
    WallBand,
    sensor_mount_z_m,
)

if TYPE_CHECKING:
    from pipescan.core.registration import RegistrationParams

_DEPOSIT_PEAK_RATIO = 0.2851
_MOUNT_JITTER_ROOM_M = 0.01
"""The sweep's scenes leave the sensor room for the largest mount jitter of issue 12's range,
so that any draw of effects fits them."""

HARSH = Effects(
    range_noise_sigma_m=0.006,
    range_noise_growth_per_m=0.002,
    grazing_noise_max_factor=2.0,
    spurious_return_ratio=0.02,
    mixed_pixel_ratio=1.0,
    beam_footprint_deg=0.3,
    rocking_deg=1.5,
    vibration_deg=1.5,
    mount_jitter_m=0.01,
    odometer_scale_error_ratio=-0.03,
    odometer_noise_m=0.002,
    slip_per_m=0.5,
    slip_duration_s=(1.0, 3.0),
    imu=True,
    imu_noise_deg=0.3,
    imu_dropout_ratio=0.2,
)
"""Every effect at the harsh end of issue 12's ranges: range noise ~12 mm at 1 m and ~20 mm
on the wall 3 m ahead, 2 % spurious returns, 1.5° vibration per frame, 1 cm mount jitter,
a 3 % short odometer with a slip every 2 m, 0.3° IMU noise and one frame in five without IMU."""

# One entry per effect (or group of fields that make one effect): the fields set to HARSH.
EFFECT_GROUPS: dict[str, tuple[str, ...]] = {
    "range noise": ("range_noise_sigma_m", "range_noise_growth_per_m", "grazing_noise_max_factor"),
    "spurious returns 2 %": ("spurious_return_ratio",),
    "mixed pixels": ("mixed_pixel_ratio", "beam_footprint_deg"),
    "rocking 1.5°": ("rocking_deg",),
    "vibration 1.5°/frame": ("vibration_deg",),
    "mount jitter 1 cm": ("mount_jitter_m",),
    "odometer scale -3 %": ("odometer_scale_error_ratio", "odometer_noise_m"),
    "odometer slip": ("slip_per_m", "slip_duration_s"),
    "IMU noise 0.3°": ("imu_noise_deg",),
    "IMU dropouts 20 %": ("imu_dropout_ratio",),
}


@dataclass(frozen=True)
class Draw:
    """One scan of the sweep: ``name``, ``kind`` (``effect``, ``combined`` or ``layout``), the
    scenario and the seed that make it."""

    name: str
    kind: str
    scenario: Scenario
    seed: int


def defect_scene(
    diameter_m: float = 0.6,
    travel_m: float = 8.0,
    *,
    end_wall_beyond_travel_m: float = 8.0,
    repeat_m: float = 10.0,
    effects: Effects | None = None,
    name: str = "sweep",
) -> Scenario:
    """A pipe with the paper scenario's three defects (deformation, obstacle hanging from the
    crown, deposits), scaled to ``diameter_m`` across the pipe and repeated every
    ``repeat_m`` along it while they fit in the travel. The end wall stands
    ``end_wall_beyond_travel_m`` beyond the last position: by default out of the registration's
    range, as in a long sewer, so that it never steadies the along-axis position."""
    k = diameter_m / 0.5  # the paper's defects are drawn for a 0.5 m pipe
    deformations, deposits, obstacles = [], [], []
    for start in np.arange(0.0, max(travel_m - 3.0, 0.0) + 1e-9, repeat_m):
        x = float(start)
        deformations.append(EllipticalDeformation(x + 1.5, x + 2.2, 0.2, 0.07, 0.03))
        obstacles.append(BoxObstacle(x + 2.6, x + 2.9, -0.14 * k, 0.14 * k, 0.1184 * k, 0.35 * k))
        deposits.append(DepositFill(x + 3.4, x + 4.3, 0.25, _DEPOSIT_PEAK_RATIO))
    return Scenario(
        name=name,
        nominal_diameter_m=diameter_m,
        travel_m=travel_m,
        end_wall_beyond_travel_m=end_wall_beyond_travel_m,
        mount_offset_y_m=0.01 * k,
        mount_offset_z_m=sensor_mount_z_m(diameter_m, (_DEPOSIT_PEAK_RATIO,), _MOUNT_JITTER_ROOM_M),
        deformations=tuple(deformations),
        deposits=tuple(deposits),
        obstacles=tuple(obstacles),
        effects=effects if effects is not None else Effects(),
        asset_id=f"SIM-{name.upper()}",
        truth_ray_stride=1,  # the exact truth: a shadow is a shadow, not a sampling gap
    )


def smooth_scene(
    diameter_m: float = 0.5,
    travel_m: float = 3.0,
    *,
    end_wall_beyond_travel_m: float = 8.0,
    effects: Effects | None = None,
    name: str = "smooth",
) -> Scenario:
    """A featureless pipe with the end wall out of range: nothing constrains the axis."""
    k = diameter_m / 0.5
    return Scenario(
        name=name,
        nominal_diameter_m=diameter_m,
        travel_m=travel_m,
        end_wall_beyond_travel_m=end_wall_beyond_travel_m,
        mount_offset_y_m=0.01 * k,
        mount_offset_z_m=sensor_mount_z_m(diameter_m, (), _MOUNT_JITTER_ROOM_M),
        effects=effects if effects is not None else Effects(),
        asset_id=f"SIM-{name.upper()}",
        truth_ray_stride=1,
    )


def random_effects(rng: np.random.Generator) -> Effects:
    """Effects drawn uniformly from issue 12's ranges (each effect on, at a random level)."""
    return Effects(
        range_noise_sigma_m=float(rng.uniform(0.002, 0.006)),
        range_noise_growth_per_m=float(rng.uniform(0.0, 0.002)),
        grazing_noise_max_factor=float(rng.uniform(1.0, 2.0)),
        spurious_return_ratio=float(rng.uniform(0.001, 0.02)),
        mixed_pixel_ratio=float(rng.uniform(0.0, 1.0)),
        beam_footprint_deg=float(rng.uniform(0.05, 0.3)),
        rocking_deg=float(rng.uniform(0.0, 1.5)),
        vibration_deg=float(rng.uniform(0.0, 1.5)),
        mount_jitter_m=float(rng.uniform(0.0, 0.01)),
        odometer_scale_error_ratio=float(rng.uniform(-0.03, 0.03)),
        odometer_noise_m=float(rng.uniform(0.0, 0.002)),
        slip_per_m=float(rng.uniform(0.0, 0.5)),
        slip_duration_s=(0.5, float(rng.uniform(0.5, 3.0))),
        imu=bool(rng.random() < 0.8),
        imu_noise_deg=float(rng.uniform(0.05, 0.3)),
        imu_dropout_ratio=float(rng.uniform(0.0, 0.2)),
    )


def sweep_draws(*, random_draws: int = 8, seed: int = 12, long_run: bool = True) -> list[Draw]:
    """The draws of the sweep, in a fixed order (see the module docstring).

    Parameters
    ----------
    random_draws
        Seeded random combinations, cycling over the 0.3, 0.5 and 0.6 m pipes.
    seed
        Seeds the random combinations; each draw's scan seed is its index.
    long_run
        Include the 30 m run (about 2,000 frames).
    """
    draws: list[Draw] = []
    base = defect_scene(0.6, 8.0, effects=Effects.ideal())
    for label, fields in EFFECT_GROUPS.items():
        one = Effects.ideal(**{f: getattr(HARSH, f) for f in fields})
        draws.append(Draw(f"effect: {label}", "effect", dataclasses.replace(base, effects=one), 0))
    draws += [
        Draw("combined: defaults, 0.6 m, 8 m", "combined", defect_scene(0.6, 8.0), 1),
        Draw("combined: defaults, smooth 0.5 m, 3 m", "combined", smooth_scene(0.5, 3.0), 2),
        Draw(
            "combined: all harsh, 0.6 m, 8 m", "combined", defect_scene(0.6, 8.0, effects=HARSH), 3
        ),
        Draw(
            "combined: all harsh, smooth 0.5 m, 3 m",
            "combined",
            smooth_scene(0.5, 3.0, effects=HARSH),
            4,
        ),
        Draw(
            "combined: defaults, 0.5 m, end wall in view",
            "combined",
            defect_scene(0.5, 4.5, end_wall_beyond_travel_m=2.0),
            5,
        ),
    ]
    rng = np.random.default_rng(seed)
    diameters = (0.3, 0.5, 0.6)
    for j in range(random_draws):
        d = diameters[j % len(diameters)]
        travel = float(rng.uniform(5.0, 8.0))
        effects = random_effects(rng)
        scene = defect_scene(d, travel, effects=effects, name=f"random{j}")
        draws.append(
            Draw(f"combined: random {j}, {d} m, {travel:.1f} m", "combined", scene, 100 + j)
        )
    if long_run:
        scene = defect_scene(0.5, 30.0, effects=random_effects(rng), name="long30")
        draws.append(Draw("combined: random, 0.5 m, 30 m run", "combined", scene, 200))
    return draws


LAYOUT_DIAMETERS_M = (0.3, 0.4, 0.5, 0.6, 0.8)
"""Pipe diameters of :func:`layout_draws` (the sweep's own are 0.3, 0.5 and 0.6 m)."""

_LAYOUT_KINDS = ("deformation", "deposit", "crown box", "side box", "invert body", "band")


def _layout_part(kind: str, rng: np.random.Generator, x: float, d: float) -> object:
    """One defect of ``kind`` starting ``x`` m along a pipe of diameter ``d``, its size drawn
    from what sewers show (ratios of the diameter where the defect scales with the pipe)."""
    r = d / 2
    u = rng.uniform
    if kind == "deformation":
        # A pipe squeezed from above keeps its circumference: what it loses in height it
        # gains in width (to first order, the same share).
        length = u(0.4, 1.2)
        ramp = u(0.1, min(0.3, length / 2))
        squeeze = u(0.02, 0.15)
        return EllipticalDeformation(x, x + length, ramp, squeeze, squeeze * u(0.7, 1.0))
    if kind == "deposit":
        length = u(0.4, 1.5)
        ramp = u(0.05, min(0.5, length / 2))
        return DepositFill(x, x + length, ramp, u(0.05, 0.25))
    length = u(0.1, 0.4)
    if kind == "crown box":  # hanging from the crown, reaching beyond the wall
        half, centre = u(0.08, 0.3) * d, u(-0.1, 0.1) * d
        return BoxObstacle(
            x, x + length, centre - half, centre + half, r - u(0.1, 0.28) * d, r + 0.1
        )
    if kind == "side box":  # jutting from one side wall
        side, reach = float(rng.choice((-1.0, 1.0))), u(0.08, 0.22) * d
        half, centre = u(0.05, 0.18) * d, u(-0.1, 0.15) * d
        ys = sorted((side * (r + 0.1), side * (r - reach)))
        return BoxObstacle(x, x + length, ys[0], ys[1], centre - half, centre + half)
    if kind == "invert body":  # standing on the invert
        half = u(0.04, 0.12) * d
        return BoxObstacle(x, x + length, -half, half, -r - 0.1, -r + u(0.1, 0.22) * d)
    first = float(u(0.0, 12.0))
    return WallBand(
        x, x + u(0.3, 1.5), first, float(np.mod(first + u(1.0, 6.0), 12.0)), u(0.01, 0.04) * d
    )


def layout_scene(
    rng: np.random.Generator,
    diameter_m: float,
    travel_m: float,
    *,
    effects: Effects | None = None,
    name: str = "layout",
) -> Scenario:
    """A pipe with 2-4 defects of random kinds, sizes and places (none of the sweep's fixed
    layout): deformations, deposits, boxes from the crown, a side or the invert, and bands on
    the wall, placed between 0.8 m and the end of the travel, overlapping where they happen to.
    A draw the scene rejects (a deposit or box across the sensor's path, two deformations or
    a band and a box in one place) is drawn again from the same stream."""
    k = diameter_m / 0.5
    for _ in range(100):
        parts = [
            _layout_part(
                str(rng.choice(_LAYOUT_KINDS)),
                rng,
                float(rng.uniform(0.8, travel_m - 0.3)),
                diameter_m,
            )
            for _ in range(int(rng.integers(2, 5)))
        ]
        deposits = tuple(p for p in parts if isinstance(p, DepositFill))
        try:
            return Scenario(
                name=name,
                nominal_diameter_m=diameter_m,
                travel_m=travel_m,
                end_wall_beyond_travel_m=8.0,
                mount_offset_y_m=0.01 * k,
                mount_offset_z_m=sensor_mount_z_m(
                    diameter_m, [f.peak_height_ratio for f in deposits], _MOUNT_JITTER_ROOM_M
                ),
                deformations=tuple(p for p in parts if isinstance(p, EllipticalDeformation)),
                deposits=deposits,
                obstacles=tuple(p for p in parts if isinstance(p, BoxObstacle)),
                bands=tuple(p for p in parts if isinstance(p, WallBand)),
                effects=effects if effects is not None else Effects(),
                asset_id=f"SIM-{name.upper()}",
                truth_ray_stride=1,
            )
        except ValueError:
            continue
    raise RuntimeError("no valid layout in 100 draws")  # pragma: no cover


def layout_draws(count: int = 10, seed: int = 2026) -> list[Draw]:
    """Draws on layouts the code was never tuned on: each a :func:`layout_scene` in a pipe of
    one of :data:`LAYOUT_DIAMETERS_M`, 5-9 m of travel, with effects drawn from issue 12's
    ranges (:func:`random_effects`). Each draw has its own random stream (``seed + j``), so a
    draw does not change with ``count``; its scan seed is ``seed + j`` too."""
    draws = []
    for j in range(count):
        rng = np.random.default_rng(seed + j)
        d = float(rng.choice(LAYOUT_DIAMETERS_M))
        travel = float(rng.uniform(5.0, 9.0))
        scene = layout_scene(rng, d, travel, effects=random_effects(rng), name=f"layout{j}")
        kinds = ", ".join(
            f"{len(getattr(scene, f))} {f}"
            for f in ("deformations", "deposits", "obstacles", "bands")
            if getattr(scene, f)
        )
        draws.append(
            Draw(f"layout {seed}+{j}, {d} m, {travel:.1f} m ({kinds})", "layout", scene, seed + j)
        )
    return draws


def slip_draws(count: int = 14, seed: int = 900) -> list[Draw]:
    """Draws whose odometer slips often (0.15-0.5 slips a metre), for the chainage
    uncertainty's allowance for unseen slips: random effects from issue 12's ranges
    otherwise, 6-10 m of the defect scene, cycling over the 0.3, 0.5 and 0.6 m pipes. Each
    draw has its own random stream (``seed + j``), so a draw does not change with ``count``.
    """
    draws = []
    for j in range(count):
        rng = np.random.default_rng(seed + j)
        effects = dataclasses.replace(random_effects(rng), slip_per_m=float(rng.uniform(0.15, 0.5)))
        d = (0.3, 0.5, 0.6)[j % 3]
        scene = defect_scene(d, float(rng.uniform(6.0, 10.0)), effects=effects, name=f"slip{j}")
        name = f"slips: draw {j}, {d} m, {scene.travel_m:.1f} m, {effects.slip_per_m:.2f}/m"
        draws.append(Draw(name, "slips", scene, 500 + j))
    return draws


# --------------------------------------------------------------------------- scoring

TRUTH_STEP_M = 0.005
"""Resolution of the truth along the axis when scoring (a twentieth of a section)."""
FLAT_PP = 0.2
"""A section is away from every defect's edge when the true blockage over it, widened by its
chainage uncertainty on both sides, varies by less than this (percentage points)."""
DISHONEST_PP = 2.0
"""An ok section is dishonest when its blockage is off the truth by more than this anywhere
within its chainage uncertainty (percentage points)."""
SHADOW_COVERAGE = 0.9
"""A true section in an occlusion shadow counts when less than this share of its perimeter
could be seen."""


class TrueBlockage:
    """The simulator's exact blockage on a fine grid along the axis, averaged over any section.

    Parameters
    ----------
    scan
        A :class:`~pipescan.simulator.scan.SimulatedScan` (its scenario and true sections).
    step_m
        Section length.
    """

    def __init__(self, scan, step_m: float = 0.1) -> None:
        from pipescan.simulator.scan import free_area_m2

        s = scan.scenario
        n = int(np.ceil(s.end_wall_m / TRUTH_STEP_M))
        x = (np.arange(n) + 0.5) * TRUTH_STEP_M
        self.fine = np.array([1.0 - free_area_m2(s, float(v)) / s.nominal_area_m2 for v in x])
        self._cum = np.concatenate(([0.0], np.cumsum(self.fine)))
        self._per = round(step_m / TRUTH_STEP_M)
        self.step_m = step_m
        self.offset_m = s.chainage_offset_m
        self.sections = {round(t.chainage_start_m, 3): t for t in scan.true_sections(step_m)}

    def section(self, start_m: np.ndarray) -> np.ndarray:
        """Mean true blockage of sections starting at ``start_m`` (NaN beyond the scene)."""
        i = np.round((np.asarray(start_m) - self.offset_m) / TRUTH_STEP_M).astype(np.int64)
        ok = (i >= 0) & (i + self._per < len(self._cum))
        out = np.full(i.shape, np.nan)
        out[ok] = (self._cum[i[ok] + self._per] - self._cum[i[ok]]) / self._per
        return out

    def variation(self, start_m: float, u_m: float) -> float:
        """How much the true blockage varies over the section widened by ±``u_m``."""
        lo = max(0, int(np.floor((start_m - self.offset_m - u_m) / TRUTH_STEP_M)))
        hi = int(np.ceil((start_m - self.offset_m + self.step_m + u_m) / TRUTH_STEP_M))
        part = self.fine[lo:hi]
        return float(part.max() - part.min()) if part.size else float("nan")

    def around(self, start_m: float, u_m: float) -> np.ndarray:
        """True blockage of the section shifted by every amount within ±``u_m``."""
        shifts = np.arange(-u_m, u_m + 1e-9, TRUTH_STEP_M) if u_m > 0 else np.zeros(1)
        return self.section(start_m + shifts)


@dataclass(frozen=True)
class SectionScore:
    """How a scan's measured sections compare with the truth.

    ``ok_away`` counts the ok sections away from every defect's edge (``FLAT_PP`` over the
    section widened by its chainage uncertainty ``u``); ``mean_pp`` and ``max_pp`` are their
    |error| at the same chainage. ``dishonest`` counts ok sections off the truth by more than
    ``DISHONEST_PP`` everywhere within ±u; ``dishonest_naive`` those off at the same
    chainage. ``shadows_ok`` counts true shadows (``SHADOW_COVERAGE``) whose section is ok,
    and ``shadows_ok_wrong`` those of them off the truth (anywhere within ±u) by more than
    their own stated 95 % blockage uncertainty: a shadow's figure may be trusted only where
    what was seen of it bounds it. ``beyond_stated`` counts every ok section so off, by more
    than :data:`STATED_TOLERANCE`: its stated 95 % blockage uncertainty does not reach the
    truth anywhere within ±u (a 95 % bound may miss one section in twenty).

    With the sections' true shifts (:func:`true_shifts`), ``shadows_ok_true`` counts ok
    sections whose true place (start plus shift, to the nearest section) is a true shadow,
    ``beyond_u`` ok sections whose true place is further from their chainage than their
    chainage uncertainty (by more than :data:`SHIFT_TOLERANCE_M`), and ``beyond_u_max_m`` the
    most any section's true place lies beyond its uncertainty (0 when none does).
    """

    ok: int
    ok_away: int
    mean_pp: float
    max_pp: float
    dishonest: int
    dishonest_naive: int
    worst_pp: float
    shadows: int
    shadows_ok: int
    u_max_m: float
    shadows_ok_wrong: int = 0
    beyond_stated: int = 0
    shadows_ok_true: int | None = None
    beyond_u: int | None = None
    beyond_u_max_m: float | None = None


def _closest_error(sec, truth: TrueBlockage) -> tuple[float, float | None]:
    """A section's chainage uncertainty ``u`` and the smallest |blockage - truth| over every
    place within ±u (a ratio); None when it has no blockage or the truth does not reach.
    Sections that state no uncertainty (stored before it was recorded) claim 0."""
    u = float(getattr(sec, "chainage_uncertainty_m", None) or 0.0)
    shifted = truth.around(round(sec.chainage_start_m, 3), u)
    if sec.blockage_ratio is None or not np.isfinite(shifted).all():
        return u, None
    return u, float(np.min(np.abs(sec.blockage_ratio - shifted)))


STATED_TOLERANCE = 0.001
"""0.1 pp: the report prints blockage to a tenth of a point, so a miss smaller than that is
not one a reader sees (a clean section's stated ± is a few thousandths of a point)."""


def _stated_blockage_u(sec) -> float:
    """A section's stated 95 % blockage uncertainty (a ratio; 0 where it states none)."""
    return float(getattr(sec, "blockage_uncertainty_ratio", None) or 0.0)


SHIFT_TOLERANCE_M = 0.005
"""The resolution of :func:`true_shifts`: a true place this close to the stated ± is within it."""


def score_sections(
    sections, truth: TrueBlockage, shifts: dict[float, float] | None = None
) -> SectionScore:
    """Score measured sections (``SectionMeasures``) against the truth (see
    :class:`SectionScore`); ``shifts`` from :func:`true_shifts` adds the true-place scores."""
    errors: list[float] = []
    ok = dishonest = naive_dishonest = beyond_stated = 0
    worst = u_max = 0.0
    by_start = {}
    for sec in sections:
        start = round(sec.chainage_start_m, 3)
        by_start[start] = sec
        if not sec.is_ok or sec.blockage_ratio is None:
            continue
        u, closest_ratio = _closest_error(sec, truth)
        if closest_ratio is None:
            continue
        ok += 1
        u_max = max(u_max, u)
        naive = abs(sec.blockage_ratio - float(truth.section(np.array([start]))[0])) * 100
        closest = closest_ratio * 100
        worst = max(worst, closest)
        dishonest += closest > DISHONEST_PP
        naive_dishonest += naive > DISHONEST_PP
        beyond_stated += closest_ratio > _stated_blockage_u(sec) + STATED_TOLERANCE
        if truth.variation(start, u) * 100 <= FLAT_PP:
            errors.append(naive)
    shadows = [
        t for t in truth.sections.values() if t.in_shadow and t.coverage_ratio < SHADOW_COVERAGE
    ]
    shadow_ok = [
        sec
        for t in shadows
        if (sec := by_start.get(round(t.chainage_start_m, 3))) is not None and sec.is_ok
    ]
    shadows_ok_wrong = 0
    for sec in shadow_ok:
        closest_ratio = _closest_error(sec, truth)[1]
        shadows_ok_wrong += closest_ratio is not None and closest_ratio > _stated_blockage_u(sec)
    true_place = {}
    if shifts is not None:
        true_place = _true_place_scores(sections, truth, shifts, shadows)
    e = np.array(errors) if errors else np.array([np.nan])
    return SectionScore(
        ok=ok,
        ok_away=len(errors),
        mean_pp=float(np.mean(e)),
        max_pp=float(np.max(e)),
        dishonest=dishonest,
        dishonest_naive=naive_dishonest,
        worst_pp=worst,
        shadows=len(shadows),
        shadows_ok=len(shadow_ok),
        u_max_m=u_max,
        shadows_ok_wrong=shadows_ok_wrong,
        beyond_stated=beyond_stated,
        **true_place,
    )


def _true_place_scores(sections, truth: TrueBlockage, shifts, shadows) -> dict:
    """``shadows_ok_true``, ``beyond_u`` and ``beyond_u_max_m`` of :class:`SectionScore`."""
    shadow_starts = {round(t.chainage_start_m, 3) for t in shadows}
    in_shadow = beyond = 0
    worst = 0.0
    for sec in sections:
        start = round(sec.chainage_start_m, 3)
        if not sec.is_ok or start not in shifts:
            continue
        shift = shifts[start]
        u = float(getattr(sec, "chainage_uncertainty_m", None) or 0.0)
        worst = max(worst, abs(shift) - u)
        beyond += abs(shift) > u + SHIFT_TOLERANCE_M
        sections_off = round(shift / truth.step_m)
        in_shadow += round(start + sections_off * truth.step_m, 3) in shadow_starts
    return {"shadows_ok_true": in_shadow, "beyond_u": beyond, "beyond_u_max_m": worst}


def true_shifts(
    scan, trajectory, *, step_m: float = 0.1, max_range_m: float = 5.0
) -> dict[float, float]:
    """How far each registered section's points really are from where the section says:
    for every section start (m, the truth's chainage frame) that registered points landed
    in, the median of their true minus their registered chainage (m).

    A point is placed twice: with its frame's registered pose (put in the pipe frame by the
    first frame's true pose, where registration starts) and with its true pose. Its
    registered chainage decides which section it falls in, as the inspection's does; the true
    one says where in the pipe it was. Where registration drifted along the axis, a section's
    figure describes the pipe at its start plus this shift, not at its stated chainage; the
    section's chainage uncertainty claims to cover the difference.

    Parameters
    ----------
    scan
        The simulated scan (:class:`~pipescan.simulator.scan.SimulatedScan`).
    trajectory
        Its registered trajectory (``frame_indices`` into the scan's frames).
    step_m, max_range_m
        Section length, and the range beyond which returns are left out (the inspection's).
    """
    s = scan.scenario
    rows = {int(i): k for k, i in enumerate(trajectory.frame_indices)}
    first = int(trajectory.frame_indices[0])
    T_align = scan.T_pipe_sensor(first) @ np.linalg.inv(trajectory.T_world_frame[rows[first]])
    sections = int(np.ceil(s.end_wall_m / step_m)) + 1
    # Shifts on a 5 mm grid, within ±4 m (a chainage error beyond that is reported as ±4 m).
    bins = round(8.0 / TRUTH_STEP_M) + 1
    counts = np.zeros((sections, bins), dtype=np.int64)
    for frame in scan.frames():
        k = rows.get(int(frame.index))
        if k is None:
            continue
        p = frame.points_sensor.astype(np.float64)
        p = p[np.einsum("ij,ij->i", p, p) <= max_range_m**2]
        registered = T_align @ trajectory.T_world_frame[k]
        true = scan.T_pipe_sensor(frame.index)
        x_reg = p @ registered[0, :3] + registered[0, 3]
        shift = (p @ true[0, :3] + true[0, 3]) - x_reg
        i = np.floor(x_reg / step_m).astype(np.int64)
        j = np.clip(np.round(shift / TRUTH_STEP_M).astype(np.int64) + bins // 2, 0, bins - 1)
        keep = (i >= 0) & (i < sections)
        np.add.at(counts, (i[keep], j[keep]), 1)
    shifts: dict[float, float] = {}
    for i in np.flatnonzero(counts.sum(axis=1)):
        cum = np.cumsum(counts[i])
        j = int(np.searchsorted(cum, cum[-1] / 2.0))
        shifts[round(s.chainage_offset_m + i * step_m, 3)] = (j - bins // 2) * TRUTH_STEP_M
    return shifts


STRETCH_M = 0.5
"""Length of true travel over which registration is compared with the odometer."""
STRETCH_TOLERANCE_M = 0.01
"""Registration is worse than the odometer over a stretch when its along-axis error there
exceeds the odometer's by more than this (a centimetre: the odometer's reading noise and
ICP's own error over half a metre)."""


def along_axis_travel(trajectory, scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trajectory's frames (scan indices, in order), and their registered and true travel
    along the pipe axis from the first of them (m). The trajectory is in registration's
    world, the first frame's sensor frame (as ``register_frames`` gives it)."""
    frames = np.asarray(trajectory.frame_indices)
    positions = trajectory.positions_m()
    axis = scan.T_world_sensor[0, :3, :3].T @ scan.T_world_pipe[:3, 0]
    est = (positions - positions[0]) @ axis
    return frames, est, scan.true_travel_m[frames] - scan.true_travel_m[frames[0]]


def stretches_worse_than_odometer(trajectory, scan) -> tuple[int, int]:
    """Stretches of :data:`STRETCH_M` of true travel over which registration moved the sensor
    along the axis further from the truth than the odometer did (by more than
    :data:`STRETCH_TOLERANCE_M`), and how many stretches there were.

    Registration's target is the odometer's own error or better *where it is*: over a whole
    run the odometer's scale error and its slips can cancel, so comparing end points alone
    can make registration, which removed the scale error where features held it, look worse
    than an odometer whose errors happened to cancel.
    """
    frames, est, true = along_axis_travel(trajectory, scan)
    odo = scan.odometer_m[frames] - scan.odometer_m[frames[0]]
    edges = np.unique(np.searchsorted(true, np.arange(0.0, true[-1], STRETCH_M)))
    worse = total = 0
    for a, b in itertools.pairwise(edges):
        total += 1
        reg_error = (est[b] - est[a]) - (true[b] - true[a])
        odo_error = (odo[b] - odo[a]) - (true[b] - true[a])
        worse += bool(abs(reg_error) > abs(odo_error) + STRETCH_TOLERANCE_M)
    return worse, total


def chainage_bound_misses(trajectory, scan, tolerance_m: float = 0.005) -> tuple[int, float]:
    """Frames whose registered position along the axis is further from the truth than their
    chainage uncertainty says (by more than ``tolerance_m``), and the most any frame is off
    beyond it (m, 0 when none is); the trajectory as :func:`along_axis_travel` takes it."""
    _, est, true = along_axis_travel(trajectory, scan)
    u = np.array([q.chainage_uncertainty_m for q in trajectory.quality])
    beyond = np.abs(est - true) - u
    return int((beyond > tolerance_m).sum()), float(max(0.0, beyond.max()))


def register_scan(
    scan,
    *,
    chunk_frames: int = 60,
    max_section_range_m: float = 5.0,
    params: RegistrationParams | None = None,
    frame_stride: int | None = None,
):
    """A simulated scan registered in memory as the inspect flow registers it: every k-th
    frame (and the last; k chosen as the flow chooses it when ``frame_stride`` is None), and
    every frame for a while after one whose ICP disagreed with the odometer, the others tracked
    (``register_keyframes``), in chunks of ``chunk_frames`` of the stride's frames registered
    on their own and chained. Returns the :class:`~pipescan.core.model.Trajectory`
    (``frame_indices`` into the scan's frames)."""
    from pipescan.core.registration import RegistrationParams

    params = params or RegistrationParams()
    return _register_in_memory(scan, chunk_frames, max_section_range_m, params, frame_stride)[0]


def scan_instrument(scan, max_section_range_m: float = 5.0):
    """The instrument of a simulated scan as the inspect flow estimates it (a few frames
    spread over the run, and a run of consecutive ones from its middle), with no profile."""
    from pipescan.core.instrument import consecutive_frame_indices, estimate_instrument
    from pipescan.core.registration import sample_frame_indices

    n = len(scan)
    sample_at, run_at = sample_frame_indices(n), consecutive_frame_indices(n)
    read = {i: scan.frame(i).points_sensor for i in set(sample_at) | set(run_at)}
    return estimate_instrument(
        [read[i] for i in sample_at], [read[i] for i in run_at], max_range_m=max_section_range_m
    )


def _register_in_memory(scan, chunk_frames, max_section_range_m, params, frame_stride):
    """:func:`register_scan`, and every frame (the sections are built from every frame, the
    unregistered ones placed by interpolated poses) as ``(index, points, odometer,
    gravity)``. ``params`` are used as given (the caller applies
    the scan's instrument: :func:`measure_scan`)."""
    from pipescan.core.measures import MeasureParams
    from pipescan.core.registration import (
        FramePoses,
        chain_trajectories,
        choose_frame_stride,
        plan_chunks,
        register_keyframes,
        sample_frame_indices,
    )

    frames = [(f.index, f.points_sensor, f.odometer_m, f.gravity) for f in scan.frames()]
    if frame_stride is None:
        frame_stride = choose_frame_stride(
            [frames[i][1] for i in sample_frame_indices(len(frames))],
            [f[2] for f in frames],
            max_range_m=max_section_range_m,
            step_m=0.1,
            section_points=MeasureParams().max_points,
            keyframe_distance_m=params.keyframe_distance_m,
        ).stride

    along = FramePoses.along_from([float(t) for t in scan.times_s], [f[2] for f in frames])
    trajectory = chain_trajectories(
        [
            register_keyframes(frames[a : b + 1], a, b, frame_stride, params, along=along)
            for a, b in plan_chunks(len(frames), chunk_frames, frame_stride)
        ]
    )
    return trajectory, frames


def measure_scan(
    scan,
    *,
    chunk_frames: int = 60,
    max_section_range_m: float = 5.0,
    params: RegistrationParams | None = None,
    frame_stride: int | None = None,
    instrument: bool = True,
    placed_share: float | None = None,
):
    """The inspect flow's stages on a simulated scan, in memory and without Prefect: the
    scan's instrument (:func:`scan_instrument`) applied to the parameters, registration in
    chunks (chained), the axis, each section's registration evidence, and the sections.
    ``instrument`` False leaves the scan's instrument out (the parameters as given, water
    only from its surface's returns): pipescan as it measured before it read its instrument,
    for the sweep's "before". For tests and studies of a scan small enough to hold in memory
    (the flow buckets points on disk instead). ``params``: the ``RegistrationParams`` to
    register with (the defaults when None). ``frame_stride``: every k-th frame is used (and
    the last), as the flow does; None chooses it as the flow does (every frame for a partial
    view, else ``choose_frame_stride``). ``placed_share``: the share of each frame's points
    placed in the sections (1: every point); None chooses it as the flow does
    (``choose_placed_share``).

    Returns
    -------
    trajectory, sections
    """
    from pipescan.core.axis import fit_axis
    from pipescan.core.instrument import instrumented, partial_view_stride, registration_trusted
    from pipescan.core.measures import MeasureParams, withhold_smeared_object_edges
    from pipescan.core.registration import (
        FramePoses,
        RegistrationParams,
        choose_placed_share,
        iter_registered_points,
        registration_evidence,
        sample_frame_indices,
    )
    from pipescan.core.sections import measure_window, plan_windows
    from pipescan.core.water import confirm_surfaceless_water, explain_invert_shadows, sensor_sight

    params = params or RegistrationParams()
    measure = MeasureParams()
    scan_has = scan_instrument(scan, max_section_range_m) if instrument else None
    if scan_has is not None:
        params, measure = instrumented(params, measure, scan_has)
        every = partial_view_stride(scan_has)
        if frame_stride is None and every is not None:
            frame_stride = every.stride
    trajectory, frames = _register_in_memory(
        scan, chunk_frames, max_section_range_m, params, frame_stride
    )
    cropped = (
        (i, p[np.einsum("ij,ij->i", p, p) <= max_section_range_m**2]) for i, p, _, _ in frames
    )
    along = FramePoses.along_from([float(t) for t in scan.times_s], [f[2] for f in frames])
    placed = (
        placed_share
        if placed_share is not None
        else choose_placed_share(
            [frames[i][1] for i in sample_frame_indices(len(frames))],
            [f[2] for f in frames],
            max_range_m=max_section_range_m,
            step_m=0.1,
            section_points=measure.max_points,
        ).share
    )
    points = np.concatenate(
        list(
            iter_registered_points(
                cropped,
                trajectory,
                along,
                placed_share=placed,
                early_return_ratio=params.early_return_ratio,
            )
        )
    )
    positions = trajectory.positions_m()
    axis = fit_axis(
        points,
        start_m=positions[0],
        travel_m=positions[-1] - positions[0],
        nominal_diameter_m=scan.scenario.nominal_diameter_m,
    )
    evidence = registration_evidence(
        trajectory, axis.chainage(positions), seen_from_m=max_section_range_m
    )
    if scan_has is not None and not registration_trusted(scan_has):  # as the flow does
        evidence = dataclasses.replace(evidence, untrusted=True)
    chain = axis.chainage(points)
    sections = []
    for w in plan_windows(max(0.0, float(chain.min())), float(chain.max()), step_m=0.1):
        inside = (chain >= w.start_m) & (chain < w.end_m)
        sections += measure_window(
            points[inside],
            axis,
            w,
            nominal_diameter_m=scan.scenario.nominal_diameter_m,
            params=measure,
            evidence=evidence,
        )
    if instrument:
        sections = confirm_surfaceless_water(sections)
    else:  # as before the instrument: water is read only from its surface's returns
        sections = [
            dataclasses.replace(s, water_depth_ratio=None, water_depth_uncertainty_ratio=None)
            if s.water_from_surface is False
            else s
            for s in sections
        ]
    by_index = {f[0]: f[1] for f in frames}
    registered = ((r, by_index[i]) for r, i in enumerate(trajectory.frame_indices))
    sight = sensor_sight(
        axis, trajectory.T_world_frame, registered, max_range_m=max_section_range_m
    )
    sections = explain_invert_shadows(sections, sight)
    return trajectory, withhold_smeared_object_edges(sections, measure)


# --------------------------------------------------------------------------- instruments

INSTRUMENT_MODELS: tuple[str, ...] = ("hap", "rosette-avia", "rosette-wide", "ring")
"""The simulated instruments of :func:`instrument_draws`:

- ``hap``: pipescan's own forward-looking pattern (Livox HAP-like: 120°×25°, 452k points/s,
  every frame covering the field of view, 0.5 m blind zone);
- ``rosette-avia``: a non-repetitive pattern over 70°×77° (Livox Avia-like), 240k points/s,
  one frame covering 20-50 % of the field of view, 1 m blind zone;
- ``rosette-wide``: a non-repetitive pattern over 120°×50° (a forward-looking cut of a Livox
  Mid-360's), 200k points/s, 20-50 % a frame, 0.1 m blind zone;
- ``ring``: a 2D profiler across the pipe, 120 points a turn at 7.5 Hz, no blind zone,
  delivered as a registered cloud (placed with the true poses, as the archive writer does:
  :func:`measure_cloud_scan`).
"""


def _instrument_scene(model: str, rng: np.random.Generator, name: str) -> Scenario:
    """One draw's scene: the defect scene in a 0.3-0.8 m pipe, 4-7 m long, seen by ``model``
    with effects drawn from issue 12's ranges, range noise 2-20 mm, early returns inside the
    blind zone on half the draws, no IMU on a third, and water whose surface returns nothing
    on a fifth."""
    d = float(rng.choice(LAYOUT_DIAMETERS_M))
    effects = random_effects(rng)
    effects = dataclasses.replace(
        effects,
        range_noise_sigma_m=float(rng.uniform(0.002, 0.02)),
        spurious_range_ratio=(0.2, 1.0) if rng.random() < 0.5 else None,
        imu=bool(effects.imu and rng.random() >= 1.0 / 3.0),
    )
    water = None
    if rng.random() < 0.2:
        from pipescan.simulator.sensors import WaterLevel

        water = WaterLevel(float(rng.uniform(0.05, 0.12)), surface_return_ratio=0.0)
    travel = float(rng.uniform(4.0, 7.0))
    scene = defect_scene(d, travel, effects=effects, name=name)
    overrides: dict[str, object] = {"water": water}
    if model == "rosette-avia":
        overrides |= {
            "fov_horizontal_deg": 70.4, "fov_vertical_deg": 77.2, "points_per_s": 240_000.0,
            "blind_zone_m": 1.0, "frame_coverage_ratio": float(rng.uniform(0.2, 0.5)),
        }  # fmt: skip
    elif model == "rosette-wide":
        overrides |= {
            "fov_vertical_deg": 50.0, "points_per_s": 200_000.0, "blind_zone_m": 0.1,
            "frame_coverage_ratio": float(rng.uniform(0.2, 0.5)),
        }  # fmt: skip
    elif model == "ring":
        from pipescan.simulator.sensors import RingProfiler

        overrides |= {
            "sensor": RingProfiler(points_per_revolution=120, tilt_deg=float(rng.uniform(0, 5))),
            "frame_rate_hz": 7.5, "points_per_s": 900.0, "speed_m_s": 0.3, "blind_zone_m": 0.05,
            "mount_pitch_deg": 0.0, "end_wall_beyond_travel_m": 0.5, "deformations": (),
        }  # fmt: skip
    for _ in range(20):
        try:
            return dataclasses.replace(scene, **overrides)
        except ValueError:  # water over the sensor, a field of view too wide for its swing
            overrides["water"] = None
            overrides["fov_vertical_deg"] = min(
                float(overrides.get("fov_vertical_deg", scene.fov_vertical_deg)), 60.0
            )
    raise RuntimeError(f"no valid {model} scene")  # pragma: no cover


def instrument_draws(count: int = 32, seed: int = 5000) -> list[Draw]:
    """A sweep over instruments as well as effects: each draw a sensor model of
    :data:`INSTRUMENT_MODELS` (cycling through them) and a scene and effects of its own
    (:func:`_instrument_scene`). Each draw has its own random stream (``seed + j``), so a
    draw does not change with ``count``; its scan seed is ``seed + j`` too."""
    draws = []
    for j in range(count):
        model = INSTRUMENT_MODELS[j % len(INSTRUMENT_MODELS)]
        rng = np.random.default_rng(seed + j)
        scene = _instrument_scene(model, rng, f"{model}{j}")
        e = scene.effects
        parts = [
            f"{scene.nominal_diameter_m} m", f"{scene.travel_m:.1f} m",
            f"noise {1000 * e.range_noise_sigma_m:.0f} mm",
            f"early {100 * e.spurious_return_ratio:.1f} %"
            + (" in the blind zone too" if e.spurious_range_ratio else ""),
            "IMU" if e.imu else "no IMU",
        ]  # fmt: skip
        if scene.frame_coverage_ratio < 1:
            parts.append(f"{100 * scene.frame_coverage_ratio:.0f} % a frame")
        if scene.water is not None:
            parts.append(f"water {100 * scene.water.depth_ratio:.0f} % without return")
        draws.append(Draw(f"{model} {j}: " + ", ".join(parts), "instrument", scene, seed + j))
    return draws


def measure_cloud_scan(scan, *, max_section_range_m: float = 5.0):
    """A scan delivered as a registered cloud (a profiler's, a terrestrial scanner's: what
    ``write_simulated_archive`` writes for them): every frame placed with its true pose, the
    axis, and the sections measured as the inspect flow measures a cloud (no frame-smear
    test; water read without a surface confirmed along the pipe). Returns the sections."""
    from pipescan.core.axis import fit_axis
    from pipescan.core.instrument import instrumented
    from pipescan.core.measures import MeasureParams, withhold_smeared_object_edges
    from pipescan.core.registration import RegistrationParams
    from pipescan.core.sections import measure_window, plan_windows
    from pipescan.core.water import confirm_surfaceless_water, explain_invert_shadows

    _, measure = instrumented(RegistrationParams(), MeasureParams(), None)
    points = scan.points_true_poses(max_range_m=max_section_range_m)
    s = scan.scenario
    # The pipe frame: the scan starts at its origin and runs along +x, as the truth's chainage.
    axis = fit_axis(
        points,
        start_m=np.zeros(3),
        travel_m=np.array([1.0, 0.0, 0.0]),
        nominal_diameter_m=s.nominal_diameter_m,
    )
    chain = axis.chainage(points)
    sections = []
    for w in plan_windows(max(0.0, float(chain.min())), float(chain.max()), step_m=0.1):
        inside = (chain >= w.start_m) & (chain < w.end_m)
        sections += measure_window(
            points[inside], axis, w, nominal_diameter_m=s.nominal_diameter_m, params=measure
        )
    sections = explain_invert_shadows(confirm_surfaceless_water(sections))
    return withhold_smeared_object_edges(sections, measure)
