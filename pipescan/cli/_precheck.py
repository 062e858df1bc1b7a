"""What ``pipescan inspect`` checks and says before Prefect starts: the archive, what it holds,
and its first and last point files, read in well under a second.

A run reads every point file again; this look catches the archive that would fail anyway
(millimetres, NaN, an empty file, a diameter off in scale) before the ten seconds Prefect's
local API takes to start, and tells the user what the run is about to process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC
from pathlib import Path

from pipescan.core.errors import MetadataError
from pipescan.core.wording import plural
from pipescan.storage.input.pointfiles import width_across_m

DIAMETER_SCALE_FACTOR = 1.8
"""How far the points' width across the pipe may differ from ``nominal_diameter_m`` (a
factor, either way) before the look refuses the archive: below the nearest mistake of unit or
quantity, a radius given for the diameter (2 times off; feet 3.3, inches 39, centimetres 100),
and well above a right diameter's scatter (docs/usage.md, *Mistakes are found first*)."""


@dataclass(frozen=True)
class FirstLook:
    """What the look found: lines to print (``found``, ``checked``) and ``warnings``."""

    found: str
    checked: str | None = None
    warnings: list[str] = field(default_factory=list)


def _describe(meta, content: str) -> str:
    when = meta.inspected_at
    shown = (
        when.astimezone(UTC).strftime("%Y-%m-%d %H:%M UTC")
        if when.tzinfo is not None
        else when.strftime("%Y-%m-%d %H:%M UTC")
    )
    size = (
        f"DN {round(1000 * meta.nominal_diameter_m)}"
        if not math.isnan(meta.nominal_diameter_m)
        else meta.pipe_shape
    )
    nodes = (
        f" ({meta.upstream_node} to {meta.downstream_node})"
        if meta.upstream_node and meta.downstream_node
        else ""
    )
    material = f" {meta.material}" if meta.material else ""
    return f"asset {meta.asset_id}{nodes}, {size}{material}, inspected {shown}; {content}"


def naive_date_warning(meta) -> str | None:
    """The warning for an ``inspected_at`` without a time zone: it is stored as UTC."""
    if meta.inspected_at.tzinfo is not None:
        return None
    as_utc = meta.inspected_at.replace(tzinfo=UTC).isoformat().replace("+00:00", "Z")
    return (
        f"inspection.toml: inspected_at has no time zone; read as {as_utc} (UTC). "
        f"Write it with its offset (e.g. {meta.inspected_at.isoformat()}+02:00) if that is "
        "not UTC"
    )


def _check_scale(meta, widths: list[tuple[str, float]], archive: str) -> None:
    """Refuse a circular pipe whose every checked file is off its nominal diameter by more
    than :data:`DIAMETER_SCALE_FACTOR` in the same direction."""
    d = meta.nominal_diameter_m
    if meta.pipe_shape != "circular" or math.isnan(d) or not widths:
        return
    ratios = [w / d for _, w in widths]
    if all(r > DIAMETER_SCALE_FACTOR for r in ratios) or all(
        0 < r < 1 / DIAMETER_SCALE_FACTOR for r in ratios
    ):
        spans = " and ".join(f"{w:.3g} m ({name})" for name, w in widths)
        raise MetadataError(
            f"the points span {spans} across the pipe, {ratios[0]:.2g} times nominal_diameter_"
            f"m = {d:g}",
            archive=archive,
            file="inspection.toml",
            field="nominal_diameter_m",
            hint="give the inside diameter in metres (not the radius), and the points in metres",
        )


def first_look(archive: str, settings) -> FirstLook | None:
    """Open a local archive and read its first and last point files (a registered cloud: its
    first million points), with the checks every read makes (no points, NaN, millimetres) and
    the diameter's scale. None for a remote archive (the run copies and checks it once).

    Raises
    ------
    ArchiveError, MetadataError, PointFileError
        As :func:`pipescan.storage.input.archive.open_archive` and the point readers; a
        diameter off in scale is a MetadataError on ``nominal_diameter_m``.
    """
    if "://" in archive and not archive.startswith("file://"):
        return None
    from pipescan.storage.input.archive import open_archive
    from pipescan.storage.input.pointfiles import check_points

    with open_archive(archive, workdir=settings.work_dir, limits=settings.input_limits()) as arc:
        meta = arc.meta
        widths: list[tuple[str, float]] = []
        counts: list[int] = []
        if arc.has_frames:
            n = arc.frame_count
            kind = "bag" if arc.bag is not None else Path(meta.frames[0].file).suffix or "files"
            content = f"{plural(n, 'frame')} ({kind})"
            ends = [0, n - 1] if n > 1 else [0]
            # One frame at a time: a bag is then read at two places, not end to end.
            for i, points in (next(arc.iter_frames([end])) for end in ends):
                widths.append(
                    (
                        f"frame {i + 1}" if arc.bag is not None else meta.frames[i].file,
                        width_across_m(points),
                    )
                )
                counts.append(len(points))
            what = "first and last frames" if len(ends) > 1 else "frame"
        else:
            content = f"a registered cloud ({arc.cloud_member})"
            chunk = next(arc.iter_cloud(), None)  # an empty cloud raises at the end
            if chunk is not None:
                check_points(
                    chunk.points,
                    archive=arc.name,
                    member=str(arc.cloud_member),
                    kind="cloud",
                    limits=arc.limits,
                )
                widths.append((str(arc.cloud_member), width_across_m(chunk.points)))
                counts.append(len(chunk.points))
            what = "cloud's first points"
        _check_scale(meta, widths, arc.name)
    found = f"archive {arc.name}: {_describe(meta, content)}"
    across = " and ".join(f"{w:.2f}" for _, w in widths)
    checked = (
        f"checked the {what}: {' and '.join(f'{c:,}' for c in counts)} points, in metres, "
        f"{across} m across the pipe"
        + (
            f" (nominal {meta.nominal_diameter_m:g} m)"
            if not math.isnan(meta.nominal_diameter_m)
            else ""
        )
    )
    warning = naive_date_warning(meta)
    return FirstLook(found=found, checked=checked, warnings=[warning] if warning else [])
