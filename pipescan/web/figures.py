"""The web view's own figures, as inline SVG built from the stored figures: the network map,
the pipe's overlaid blockage profiles and the trend at one chainage.

The numbers come from the storage layer (``asset_trend``, ``network_pipes``) and the core's
rules (the noise threshold of :func:`pipescan.core.trends.change_thresholds`); this module only
draws them. Every text is escaped here (:func:`markupsafe.escape`), since the templates
insert the SVG as it is. The inspection page reuses the report's own matplotlib charts.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from urllib.parse import quote

import numpy as np
from markupsafe import Markup, escape

from pipescan.core.trends import years
from pipescan.storage.database.trends import AssetTrend
from pipescan.storage.database.web_queries import PipeRow

__all__ = [
    "GRADE_COLOURS",
    "NO_GRADE_COLOUR",
    "grade_colour",
    "network_map_svg",
    "profiles_svg",
    "trend_point_svg",
]

GRADE_COLOURS = {0: "#b2182b", 1: "#e66101", 2: "#d8a200", 3: "#7fbf7b", 4: "#1b7837"}
"""Condition class (0 worst ... 4 best) to its colour, the same in map, table and legend."""

NO_GRADE_COLOUR = "#8c8c8c"

SURVEY_COLOURS = ("#3b6ea5", "#e08a2c", "#8a6bb8", "#6a9a58", "#c0392b", "#5b5b5b")
"""The colours of the inspections on a pipe's charts, newest first (the report's blue first)."""


def grade_colour(grade: int | None) -> str:
    return GRADE_COLOURS.get(grade, NO_GRADE_COLOUR) if grade is not None else NO_GRADE_COLOUR


def pipe_href(asset_id: str) -> str:
    return "/pipes/" + quote(asset_id, safe="")


def _num(value: float) -> str:
    return f"{value:.2f}".rstrip("0").rstrip(".") if math.isfinite(value) else "0"


@dataclass(frozen=True)
class MapResult:
    svg: Markup
    drawn: int
    crs: str | None
    left_out: tuple[str, ...]
    """Assets with a line in another CRS than the map's (not drawn: one CRS at a time)."""
    basemap: bool = False
    """Drawn in Web Mercator over the tile server's tiles."""


_EARTH_RADIUS_M = 6378137.0
"""WGS 84's semi-major axis: the sphere of Web Mercator (EPSG:3857)."""


def _utm_to_lonlat(
    easting_m: np.ndarray, northing_m: np.ndarray, zone: int, south: bool
) -> tuple[np.ndarray, np.ndarray]:
    """UTM (WGS 84 or ETRS89/GRS 80, the same to a millimetre here) to longitude and latitude
    in degrees: the inverse transverse Mercator by Krüger's series to n³ (millimetres within
    the zone)."""
    f = 1 / 298.257223563
    n = f / (2 - f)
    a_rect = _EARTH_RADIUS_M / (1 + n) * (1 + n**2 / 4 + n**4 / 64)
    k0 = 0.9996
    beta = (n / 2 - 2 * n**2 / 3 + 37 * n**3 / 96, n**2 / 48 + n**3 / 15, 17 * n**3 / 480)
    delta = (2 * n - 2 * n**2 / 3 - 2 * n**3, 7 * n**2 / 3 - 8 * n**3 / 5, 56 * n**3 / 15)
    xi = (northing_m - (10_000_000.0 if south else 0.0)) / (k0 * a_rect)
    eta = (easting_m - 500_000.0) / (k0 * a_rect)
    xi_p, eta_p = xi.copy(), eta.copy()
    for j, b in enumerate(beta, start=1):
        xi_p -= b * np.sin(2 * j * xi) * np.cosh(2 * j * eta)
        eta_p -= b * np.cos(2 * j * xi) * np.sinh(2 * j * eta)
    chi = np.arcsin(np.sin(xi_p) / np.cosh(eta_p))
    lat = chi + sum(d * np.sin(2 * j * chi) for j, d in enumerate(delta, start=1))
    lon = np.radians(zone * 6 - 183) + np.arctan2(np.sinh(eta_p), np.cos(xi_p))
    return np.degrees(lon), np.degrees(lat)


def web_mercator(crs: str | None, xy: np.ndarray) -> np.ndarray | None:
    """(N, 2) coordinates in ``crs`` as Web Mercator metres (EPSG:3857), for a basemap's
    tiles; None for a CRS this does not convert (it knows EPSG:3857 and the UTM zones of
    WGS 84, EPSG:326xx and 327xx, and of ETRS89, EPSG:25828-25838)."""
    match = re.fullmatch(r"EPSG:+(\d+)", (crs or "").strip().upper())
    if match is None:
        return None
    code = int(match[1])
    if code == 3857:
        return np.asarray(xy, dtype=np.float64)
    if 32601 <= code <= 32660 or 32701 <= code <= 32760:
        zone, south = code % 100, code > 32700
    elif 25828 <= code <= 25838:
        zone, south = code - 25800, False
    else:
        return None
    lon, lat = _utm_to_lonlat(xy[:, 0], xy[:, 1], zone, south)
    x = _EARTH_RADIUS_M * np.radians(lon)
    y = _EARTH_RADIUS_M * np.log(np.tan(np.pi / 4 + np.radians(lat) / 2))
    return np.column_stack([x, y])


def _tile_layer(
    x_range: tuple[float, float], y_range: tuple[float, float], scale: float
) -> tuple[list[tuple[int, int, int, float, float, float]], int]:
    """The tiles covering a Web Mercator box, at the zoom whose tiles show about 256 units
    wide at ``scale`` (units per metre): ``(z, x, y, left, top, size)`` each, at most 64."""
    world = 2 * math.pi * _EARTH_RADIUS_M
    zoom = int(min(19, max(0, round(math.log2(world * scale / 256.0)))))
    while True:
        size = world / 2**zoom
        first_x = math.floor((x_range[0] + world / 2) / size)
        last_x = math.floor((x_range[1] + world / 2) / size)
        first_y = math.floor((world / 2 - y_range[1]) / size)
        last_y = math.floor((world / 2 - y_range[0]) / size)
        if (last_x - first_x + 1) * (last_y - first_y + 1) <= 64 or zoom == 0:
            break
        zoom -= 1
    tiles = []
    for ty in range(max(0, first_y), min(2**zoom - 1, last_y) + 1):
        for tx in range(max(0, first_x), min(2**zoom - 1, last_x) + 1):
            tiles.append((zoom, tx, ty, tx * size - world / 2, world / 2 - ty * size, size))
    return tiles, zoom


def tile_href(tile_url: str, z: int, x: int, y: int) -> str:
    """A tile's address from the template (``{z}``, ``{x}``, ``{y}`` replaced; nothing else
    in the template is interpreted)."""
    return tile_url.replace("{z}", str(z)).replace("{x}", str(x)).replace("{y}", str(y))


def network_map_svg(
    pipes: Sequence[PipeRow],
    highlighted: set[str] | None = None,
    *,
    tile_url: str | None = None,
) -> MapResult:
    """The pipes as lines coloured by their latest worst condition class, each a link to its
    pipe page. Lines are in the network's CRS (the most common one), north up, to scale; pipes
    outside ``highlighted`` (when given) are drawn faint.

    With ``tile_url`` (``https://host/{z}/{x}/{y}.png``) and a CRS that
    :func:`web_mercator` converts, the map is drawn in Web Mercator over that server's tiles;
    otherwise the lines are drawn on their own."""
    with_line = [p for p in pipes if p.line_xy is not None]
    if not with_line:
        return MapResult(Markup(""), 0, None, ())
    crs_counts: dict[str, int] = {}
    for p in with_line:
        crs_counts[p.crs or ""] = crs_counts.get(p.crs or "", 0) + 1
    crs = max(crs_counts, key=lambda c: (crs_counts[c], c))
    drawn = [p for p in with_line if (p.crs or "") == crs]
    left_out = tuple(p.asset_id for p in with_line if (p.crs or "") != crs)
    lines = {p.asset_id: np.asarray(p.line_xy, dtype=np.float64) for p in drawn}
    # Ground metres per map unit: 1 in a projected CRS, cos(latitude) in Web Mercator.
    ground_per_unit = 1.0
    basemap = False
    if tile_url:
        everything = np.vstack(list(lines.values()))
        mercator = web_mercator(crs, everything)
        if mercator is not None:
            basemap = True
            k = 0
            for asset_id, line in lines.items():
                lines[asset_id] = mercator[k : k + len(line)]
                k += len(line)
            mid_y = float(mercator[:, 1].mean())
            ground_per_unit = math.cos(
                2 * math.atan(math.exp(mid_y / _EARTH_RADIUS_M)) - math.pi / 2
            )
    xy = np.vstack(list(lines.values()))
    x0, y0 = xy.min(axis=0)
    x1, y1 = xy.max(axis=0)
    span = max(x1 - x0, y1 - y0, 1.0)
    width = 1000.0
    scale = width / span
    height = max(200.0, (y1 - y0) * scale)
    pad = 24.0
    # Centre the network in the box, north up (SVG's y runs down).
    ox = pad + (width - (x1 - x0) * scale) / 2.0
    oy = pad + (height - (y1 - y0) * scale) / 2.0

    def point(x: float, y: float) -> str:
        return f"{_num(ox + (x - x0) * scale)},{_num(oy + (y1 - y) * scale)}"

    view_w, view_h = width + 2 * pad, height + 2 * pad

    # A large network is drawn with thinner lines and without its nodes, so it stays legible
    # (and the page small: a few hundred bytes a pipe).
    dense = len(drawn) > 400
    parts = [
        f'<svg class="network-map{" dense" if dense else ""}" '
        f'viewBox="0 0 {_num(width + 2 * pad)} {_num(height + 2 * pad)}"'
        ' xmlns="http://www.w3.org/2000/svg" role="img" aria-label="Network map: pipes coloured '
        'by the worst condition class of their latest inspection">'
    ]
    if basemap and tile_url:
        # The tiles behind the lines: the box the view shows, in Web Mercator metres.
        x_range = (x0 - ox / scale, x0 + (view_w - ox) / scale)
        y_range = (y1 - (view_h - oy) / scale, y1 + oy / scale)
        tiles, _ = _tile_layer(x_range, y_range, scale)
        parts.append('<g class="basemap">')
        # Each tile 0.6 units larger than its place: no hairline seams between them.
        for z, tx, ty, left, top, size in tiles:
            href = escape(tile_href(tile_url, z, tx, ty))
            parts.append(
                f'<image href="{href}" x="{_num(ox + (left - x0) * scale)}" '
                f'y="{_num(oy + (y1 - top) * scale)}" width="{_num(size * scale + 0.6)}" '
                f'height="{_num(size * scale + 0.6)}" preserveAspectRatio="none"/>'
            )
        parts.append("</g>")
    # Worst last, so that it is drawn on top where lines meet.
    order = sorted(drawn, key=lambda p: -(p.worst_grade if p.worst_grade is not None else 5))
    for p in order:
        colour = grade_colour(p.worst_grade)
        faint = highlighted is not None and p.asset_id not in highlighted
        points = " ".join(point(x, y) for x, y in lines[p.asset_id])
        grade = "none" if p.worst_grade is None else str(p.worst_grade)
        label = p.gis_id or p.asset_id
        title = f"{label}: class {grade}" + (
            "" if p.peak_blockage_ratio is None else f", peak {100 * p.peak_blockage_ratio:.1f} %"
        )
        parts.append(
            f'<a href="{escape(pipe_href(p.asset_id))}">'
            f'<polyline class="pipe{" faint" if faint else ""}" points="{points}" '
            f'stroke="{colour}" data-asset="{escape(p.asset_id)}" data-grade="{grade}">'
            f"<title>{escape(title)}</title></polyline></a>"
        )
    for p in [] if dense else drawn:
        coords = lines[p.asset_id]
        for x, y in (coords[0], coords[-1]):
            cx, cy = point(x, y).split(",")
            parts.append(f'<circle class="node" cx="{cx}" cy="{cy}" r="3"/>')
    # A scale bar: a round length near a fifth of the map's width.
    span_m = span * ground_per_unit
    bar_m = 10 ** math.floor(math.log10(span_m / 5.0))
    for factor in (5, 2):
        if bar_m * factor <= span_m / 4.0:
            bar_m *= factor
            break
    bar_px = bar_m / ground_per_unit * scale
    by = height + 2 * pad - 8
    parts.append(
        f'<g class="scale"><line x1="{pad}" y1="{_num(by)}" x2="{_num(pad + bar_px)}" '
        f'y2="{_num(by)}"/><text x="{pad}" y="{_num(by - 4)}">{_num(bar_m)} m</text></g>'
    )
    parts.append("</svg>")
    return MapResult(Markup("".join(parts)), len(drawn), crs or None, left_out, basemap)


def _index_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index runs where ``mask`` is true, in order.

    >>> _index_runs(np.array([True, True, False, True]))
    [(0, 2), (3, 4)]
    """
    edges = np.flatnonzero(np.diff(np.concatenate(([0], np.asarray(mask, np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def profiles_svg(trend: AssetTrend, *, selected_cell: int | None, href_at: str) -> Markup:
    """Each inspection's blockage profile along the aligned chainage, overlaid (newest on
    top), with a lane per inspection beneath: solid where measured, hatched where a section
    was not measured, empty where it has no section. Each chainage cell is a link to the
    trend at that chainage (``href_at`` + metres)."""
    n, k = trend.blockage_ratio.shape
    if k == 0:
        return Markup("")
    w, left, right, top = 1000.0, 84.0, 12.0, 12.0
    plot_h = 240.0
    lane_h, lane_gap = 9.0, 3.0
    lanes_top = top + plot_h + 34.0
    h = lanes_top + n * (lane_h + lane_gap) + 6.0
    start = float(trend.chainage_start_m[0])
    end = float(trend.chainage_start_m[-1]) + trend.step_m
    finite = trend.blockage_ratio[np.isfinite(trend.blockage_ratio)]
    top_pct = max(10.0, float(finite.max()) * 100.0 * 1.1) if finite.size else 10.0
    low_pct = min(0.0, float(finite.min()) * 100.0) if finite.size else 0.0

    def x(m: float) -> float:
        return left + (m - start) / (end - start) * (w - left - right)

    def y(pct: float) -> float:
        return top + (top_pct - pct) / (top_pct - low_pct) * plot_h

    parts = [
        f'<svg class="profiles" viewBox="0 0 {_num(w)} {_num(h)}" '
        'xmlns="http://www.w3.org/2000/svg" role="img" aria-label="Blockage along the pipe, '
        'each inspection overlaid">',
        '<defs><pattern id="hatch" width="6" height="6" patternUnits="userSpaceOnUse" '
        'patternTransform="rotate(45)"><rect width="6" height="6" fill="#f2f2f2"/>'
        '<line x1="0" y1="0" x2="0" y2="6" stroke="#8c8c8c" stroke-width="2"/></pattern></defs>',
    ]
    # Axes and ticks.
    step = _nice_step(top_pct - low_pct, 5)
    tick = math.ceil(low_pct / step) * step
    while tick <= top_pct + 1e-9:
        parts.append(
            f'<line class="grid" x1="{left}" x2="{_num(w - right)}" y1="{_num(y(tick))}" '
            f'y2="{_num(y(tick))}"/><text class="tick" x="{left - 6}" y="{_num(y(tick) + 4)}" '
            f'text-anchor="end">{_num(tick)} %</text>'
        )
        tick += step
    xstep = _nice_step(end - start, 8)
    xt = math.ceil(start / xstep) * xstep
    while xt <= end + 1e-9:
        parts.append(
            f'<text class="tick" x="{_num(x(xt))}" y="{_num(top + plot_h + 16)}" '
            f'text-anchor="middle">{_num(xt)}</text>'
        )
        xt += xstep
    parts.append(
        f'<text class="axis" x="{_num(w - right)}" y="{_num(top + plot_h + 30)}" '
        'text-anchor="end">chainage from the upstream node, m (the reference survey\'s)</text>'
    )
    if selected_cell is not None:
        sx = x(float(trend.chainage_start_m[selected_cell]))
        parts.append(
            f'<rect class="selected" x="{_num(sx)}" y="{top}" '
            f'width="{_num(max(2.0, x(start + trend.step_m) - x(start)))}" height="{plot_h}"/>'
        )
    # Oldest first, so that the newest is drawn on top.
    for i in range(n):
        colour = SURVEY_COLOURS[(n - 1 - i) % len(SURVEY_COLOURS)]
        values = trend.blockage_ratio[i]
        for a, b in _index_runs(np.isfinite(values)):
            pts = " ".join(
                f"{_num(x(float(trend.chainage_start_m[c]) + trend.step_m / 2))},"
                f"{_num(y(100.0 * float(values[c])))}"
                for c in range(a, b)
            )
            if b - a == 1:
                cx, cy = pts.split(",")
                parts.append(f'<circle cx="{cx}" cy="{cy}" r="2" fill="{colour}"/>')
            else:
                parts.append(
                    f'<polyline class="profile" data-inspection='
                    f'"{trend.surveys[i].inspection_id}" points="{pts}" stroke="{colour}"/>'
                )
        # The lane: measured, not measured (hatched), or no section.
        ly = lanes_top + i * (lane_h + lane_gap)
        status = trend.section_status[i]
        has_section = np.array([s is not None for s in status])
        measured = np.isfinite(values)
        for a, b in _index_runs(measured):
            parts.append(
                f'<rect x="{_num(x(start + a * trend.step_m))}" y="{_num(ly)}" '
                f'width="{_num(x(start + b * trend.step_m) - x(start + a * trend.step_m))}" '
                f'height="{lane_h}" fill="{colour}"/>'
            )
        for a, b in _index_runs(has_section & ~measured):
            x_a, x_b = x(start + a * trend.step_m), x(start + b * trend.step_m)
            parts.append(
                f'<rect class="unmeasured" x="{_num(x_a)}" y="{_num(ly)}" '
                f'width="{_num(max(1.0, x_b - x_a))}" height="{lane_h}" fill="url(#hatch)">'
                f"<title>{escape(_lane_title(trend, i, a, b))}</title></rect>"
            )
        parts.append(
            f'<text class="tick" x="{left - 6}" y="{_num(ly + lane_h - 1)}" text-anchor="end">'
            f"{trend.surveys[i].inspected_at.date().isoformat()}</text>"
        )
    # Stretches that no inspection measured, hatched across the plot.
    none_measured = np.isfinite(trend.blockage_ratio).sum(axis=0) == 0
    for a, b in _index_runs(none_measured):
        x_a, x_b = x(start + a * trend.step_m), x(start + b * trend.step_m)
        parts.append(
            f'<rect class="unmeasured" x="{_num(x_a)}" y="{top}" '
            f'width="{_num(max(1.0, x_b - x_a))}" height="{plot_h}" fill="url(#hatch)" '
            'opacity="0.7"><title>not measured by any '
            f"inspection: {_num(start + a * trend.step_m)}-{_num(start + b * trend.step_m)} m"
            "</title></rect>"
        )
    parts.append(
        f'<line class="axisline" x1="{left}" x2="{_num(w - right)}" y1="{_num(y(0))}" '
        f'y2="{_num(y(0))}"/>'
    )
    # Invisible cells over the plot: a click picks that chainage.
    cell_w = max(1.0, x(start + trend.step_m) - x(start))
    for c in range(k):
        m = float(trend.chainage_start_m[c])
        parts.append(
            f'<a href="{escape(href_at)}{m:.2f}"><rect class="cell" x="{_num(x(m))}" '
            f'y="{top}" width="{_num(cell_w)}" height="{plot_h}"><title>'
            f"{m:.2f}-{m + trend.step_m:.2f} m: show the trend here</title></rect></a>"
        )
    parts.append("</svg>")
    return Markup("".join(parts))


def _lane_title(trend: AssetTrend, i: int, a: int, b: int) -> str:
    statuses = sorted({str(s) for s in trend.section_status[i, a:b] if s is not None})
    start = float(trend.chainage_start_m[a])
    end = float(trend.chainage_start_m[b - 1]) + trend.step_m
    return (
        f"{trend.surveys[i].inspected_at.date().isoformat()}: not measured "
        f"{start:.2f}-{end:.2f} m ({', '.join(statuses)})"
    )


def _nice_step(span: float, count: int) -> float:
    raw = max(span, 1e-9) / count
    base = 10 ** math.floor(math.log10(raw))
    for factor in (1, 2, 5, 10):
        if base * factor >= raw:
            return base * factor
    return base * 10


def trend_point_svg(
    dates: Sequence[datetime],
    values_ratio: Sequence[float],
    *,
    inspection_ids: Sequence[int],
    noise_ratio: float,
    slope_per_year: float | None,
    label: str = "Blockage at this chainage over time",
) -> Markup:
    """Blockage at one chainage over time: a point per inspection that measured it, a band
    of the change that noise alone can give (``noise_ratio`` either side of the first
    measured reading) and the Theil–Sen growth line through the readings' median."""
    w, left, right, top, plot_h = 640.0, 56.0, 16.0, 12.0, 220.0
    h = top + plot_h + 40.0
    measured = [
        (d, v, i)
        for d, v, i in zip(dates, values_ratio, inspection_ids, strict=True)
        if math.isfinite(v)
    ]
    parts = [
        f'<svg class="trend-point" viewBox="0 0 {_num(w)} {_num(h)}" '
        f'xmlns="http://www.w3.org/2000/svg" role="img" aria-label="{escape(label)}">'
    ]
    if not measured:
        parts.append(
            f'<text x="{w / 2}" y="{h / 2}" text-anchor="middle">not measured by any '
            "inspection</text></svg>"
        )
        return Markup("".join(parts))
    t = np.array([years(d) for d, _, _ in measured])
    v = np.array([100.0 * val for _, val, _ in measured])
    t0, t1 = float(min(years(d) for d in dates)), float(max(years(d) for d in dates))
    if t1 - t0 < 0.5:
        t0, t1 = t0 - 0.5, t1 + 0.5
    pad_t = 0.08 * (t1 - t0)
    t0, t1 = t0 - pad_t, t1 + pad_t
    first = float(v[0])
    band = 100.0 * noise_ratio
    hi = max(float(v.max()), first + band) + 2.0
    lo = min(0.0, float(v.min()), first - band)

    def x(tt: float) -> float:
        return left + (tt - t0) / (t1 - t0) * (w - left - right)

    def y(pct: float) -> float:
        return top + (hi - pct) / (hi - lo) * plot_h

    parts.append(
        f'<rect class="noise" x="{_num(x(t0))}" y="{_num(y(first + band))}" '
        f'width="{_num(x(t1) - x(t0))}" height="{_num(y(first - band) - y(first + band))}">'
        f"<title>the change that noise alone can give: ±{band:.1f} pp around the first "
        "reading</title></rect>"
    )
    step = _nice_step(hi - lo, 5)
    tick = math.ceil(lo / step) * step
    while tick <= hi + 1e-9:
        parts.append(
            f'<line class="grid" x1="{left}" x2="{_num(w - right)}" y1="{_num(y(tick))}" '
            f'y2="{_num(y(tick))}"/><text class="tick" x="{left - 6}" y="{_num(y(tick) + 4)}" '
            f'text-anchor="end">{_num(tick)} %</text>'
        )
        tick += step
    for year in range(math.ceil(1970 + t0), math.floor(1970 + t1) + 1):
        xx = x(year - 1970)
        parts.append(
            f'<text class="tick" x="{_num(xx)}" y="{_num(top + plot_h + 16)}" '
            f'text-anchor="middle">{year}</text>'
        )
    if slope_per_year is not None and math.isfinite(slope_per_year) and len(t) >= 2:
        # Theil–Sen's line passes through the median of the residual intercepts.
        intercept = float(np.median(v - 100.0 * slope_per_year * t))
        ya = intercept + 100.0 * slope_per_year * float(t[0])
        yb = intercept + 100.0 * slope_per_year * float(t[-1])
        parts.append(
            f'<line class="fit" x1="{_num(x(float(t[0])))}" y1="{_num(y(ya))}" '
            f'x2="{_num(x(float(t[-1])))}" y2="{_num(y(yb))}"/>'
        )
    for (d, val, inspection_id), tt in zip(measured, t, strict=True):
        parts.append(
            f'<circle class="reading" data-inspection="{inspection_id}" cx="{_num(x(float(tt)))}"'
            f' cy="{_num(y(100.0 * val))}" r="5"><title>{d.date().isoformat()}: '
            f"{100.0 * val:.1f} % (inspection {inspection_id})</title></circle>"
        )
    parts.append("</svg>")
    return Markup("".join(parts))
