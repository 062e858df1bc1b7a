"""Parse and validate ``inspection.toml``, the metadata of one scan archive.

The schema is a pydantic v2 model; :func:`parse_inspection_toml` turns its result into the
core :class:`~pipescan.core.model.InspectionMeta` and every problem (TOML syntax, a missing
or misspelt key, a bad value, inconsistent ``[[frames]]``) into a :class:`MetadataError`
that names the archive, ``inspection.toml`` and the exact field (a dotted path such as
``frames[3].odometer_m``, or ``line 7`` for a syntax error), with a hint on the fix.

Unknown keys are ignored, so that newer archives still open; but a misspelt required key
is reported as missing, with a "did you mean" for the key that was found instead.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import math
import re
import tomllib
import unicodedata
from collections.abc import Sequence
from datetime import UTC, date, datetime, time, timedelta
from pathlib import Path, PurePosixPath
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
    field_validator,
)
from pydantic_core import PydanticCustomError

from pipescan.core.errors import MetadataError
from pipescan.core.instrument import SensorProfile
from pipescan.core.model import FrameRef, InspectionMeta, RosTopics
from pipescan.storage.input.tomlguard import TomlTooDeep, check_toml_depth
from pipescan.storage.lookalike import fold, lookalike_letters

INSPECTION_FILE = "inspection.toml"
EARLIEST_INSPECTION = datetime(1900, 1, 1)
"""The earliest ``inspected_at`` accepted (UTC); the latest is tomorrow."""

MIN_DIAMETER_M = 0.05
"""Nominal diameters must be greater than this (50 mm: smaller is not a pipe you crawl)."""

MAX_DIAMETER_M = 6.0
"""Nominal diameters must be at most this (6 m: larger is a tunnel, or millimetres)."""

MAX_NAME_CHARS = 64
"""Longest asset id, node name, material or pipe shape. Asset registers use far less (ISYBAU
allows 30 characters for an object's name); report file names are built from the asset id,
and must stay within the 255 bytes a file system allows."""

MAX_FILE_CHARS = 1024
"""Longest ``[[frames]]`` file path (as long as an archive member path may be)."""

MAX_COORDINATE = 1.0e8
"""Largest node coordinate accepted, in the CRS's units. Projected coordinates in metres stay
below 1e7 (a UTM northing, with a zone prefix); anything larger is a unit or a typing error."""

MIN_NODE_DISTANCE_M = 0.1
"""Node positions closer together than this cannot be the two ends of a pipe."""

_CRS_PATTERN = r"^[A-Za-z][A-Za-z0-9_-]{0,15}:[A-Za-z0-9_.-]{1,32}$"

ODOMETER_TOLERANCE_M = 0.05
"""How far the cable counter may step back between frames (slack, jitter) before the
``[[frames]]`` order is taken to be wrong."""

_EXAMPLES = {
    "asset_id": 'asset_id = "MH1042-MH1043"',
    "inspected_at": "inspected_at = 2024-05-17 (or a datetime, e.g. 2024-05-17T09:30:00Z)",
    "nominal_diameter_m": "nominal_diameter_m = 0.5 (metres)",
    "file": 'file = "frames/000001.npy" in each [[frames]] table',
}


def _printable(value: str) -> str:
    """Refuse control and invisible characters (CR, LF, ESC, NUL, bidirectional overrides,
    zero-width spaces...): ids end up in terminals, file names, CSV cells and reports."""
    if value.isprintable():
        return value
    bad = sorted({ch for ch in value if not ch.isprintable()})
    raise PydanticCustomError(
        "control_characters",
        "holds control or invisible characters ({chars}), got {value}",
        {
            "chars": ", ".join(ch.encode("unicode_escape").decode("ascii") for ch in bad),
            "value": _short_repr(value),
            "hint": "use printable text only: letters, digits, spaces and punctuation",
        },
    )


def _folded(value: str) -> str:
    """NFKC: full-width and other compatibility forms as plain letters and digits, so that
    ``ＭＨ１`` and ``MH1`` are one asset (pipescan.storage.lookalike)."""
    folded = fold(value)
    if len(folded) > MAX_NAME_CHARS:
        raise PydanticCustomError(
            "string_too_long",
            "is at most {max_length} characters (NFKC-folded), got {value}",
            {"max_length": MAX_NAME_CHARS, "value": _short_repr(value)},
        )
    return folded


NameText = Annotated[
    str,
    StringConstraints(min_length=1, max_length=MAX_NAME_CHARS),
    AfterValidator(_printable),
    AfterValidator(_folded),
]
"""An asset id, node name, material or shape: 1-64 printable characters."""


def _authority_code(value: str) -> str:
    if re.fullmatch(_CRS_PATTERN, value):
        return value
    raise PydanticCustomError(
        "crs_not_a_code",
        "{value} is not an authority code such as EPSG:25832",
        {"value": _short_repr(value), "hint": _HINTS["crs"]},
    )


CrsText = Annotated[
    str, StringConstraints(max_length=MAX_NAME_CHARS), AfterValidator(_authority_code)
]
"""A coordinate reference system as an authority code, e.g. ``EPSG:25832``."""

FileText = Annotated[
    str, StringConstraints(min_length=1, max_length=MAX_FILE_CHARS), AfterValidator(_printable)
]


class _FrameEntry(BaseModel):
    """One ``[[frames]]`` table."""

    model_config = ConfigDict(extra="ignore", allow_inf_nan=False, str_strip_whitespace=True)

    file: FileText
    time_s: float | None = None
    odometer_m: float | None = None
    gravity: list[float] | None = None

    @field_validator("gravity")
    @classmethod
    def _unit_gravity(cls, value: list[float] | None) -> tuple[float, float, float] | None:
        """Normalise the IMU's gravity direction; a zero vector has no direction."""
        if value is None:
            return None
        if len(value) != 3:
            raise PydanticCustomError(
                "gravity_length",
                "gravity must have 3 components [gx, gy, gz], got {value}",
                {"value": list(value), "hint": _HINTS["gravity"]},
            )
        norm = math.hypot(*value)
        if not norm > 0 or not math.isfinite(norm):
            raise PydanticCustomError(
                "zero_gravity",
                "gravity must be a non-zero direction, got {value}",
                {"value": list(value), "hint": _HINTS["gravity"]},
            )
        return (value[0] / norm, value[1] / norm, value[2] / norm)


class _RosTable(BaseModel):
    """The ``[ros]`` table: a bag's topics."""

    model_config = ConfigDict(extra="ignore", str_strip_whitespace=True)

    points_topic: FileText | None = None
    odometry_topic: FileText | None = None
    imu_topic: FileText | None = None


class _SensorTable(BaseModel):
    """The ``[sensor]`` table: a model from ``pipescan.core.instrument.SENSOR_MODELS``, the
    sensor's own figures, or both (its figures override the model's)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, str_strip_whitespace=True)

    model: str | None = Field(default=None, max_length=MAX_NAME_CHARS)
    min_range_m: float | None = Field(default=None, ge=0.0, le=100.0)
    max_range_m: float | None = Field(default=None, gt=0.0, le=10_000.0)
    fov_horizontal_deg: float | None = Field(default=None, gt=0.0, le=360.0)
    fov_vertical_deg: float | None = Field(default=None, gt=0.0, le=360.0)
    pattern: Literal["repetitive", "non_repetitive", "profiler", "static"] | None = None
    points_per_s: float | None = Field(default=None, gt=0.0, le=1e9)
    range_noise_m: float | None = Field(default=None, ge=0.0, le=1.0)

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str | None) -> str | None:
        from pipescan.core.instrument import SENSOR_MODELS

        if value is None:
            return None
        name = value.lower()
        if name not in SENSOR_MODELS:
            close = difflib.get_close_matches(name, SENSOR_MODELS, n=1)
            known = ", ".join(SENSOR_MODELS)
            raise PydanticCustomError(
                "sensor_model",
                "unknown sensor model",
                {
                    "value": value,
                    "hint": (f"did you mean {close[0]!r}? " if close else "")
                    + f"known models: {known}; or leave out model and give the figures",
                },
            )
        return name


class InspectionDocument(BaseModel):
    """The schema of ``inspection.toml`` (the archive contract: docs/archive.md).

    ``nominal_diameter_m`` is optional here because it is required only for circular
    pipes; :func:`parse_inspection_toml` enforces that, and the ``[[frames]]`` consistency,
    where it can name the exact field.
    """

    model_config = ConfigDict(
        extra="ignore",
        allow_inf_nan=False,
        str_strip_whitespace=True,
        coerce_numbers_to_str=True,  # asset_id = 1042 is an id, not an error
    )

    asset_id: NameText
    inspected_at: datetime
    nominal_diameter_m: float | None = None
    upstream_node: NameText | None = None
    downstream_node: NameText | None = None
    direction: Literal["downstream", "upstream"] = "downstream"
    chainage_offset_m: float = Field(default=0.0, ge=0.0)
    material: NameText | None = None
    pipe_shape: NameText = "circular"
    frames: list[_FrameEntry] = Field(default_factory=list)
    upstream_node_xyz: list[float] | None = None
    downstream_node_xyz: list[float] | None = None
    crs: CrsText | None = None

    @field_validator("upstream_node_xyz", "downstream_node_xyz")
    @classmethod
    def _node_position(cls, value: list[float] | None) -> tuple[float, ...] | None:
        if value is None:
            return None
        if len(value) not in (2, 3):
            raise PydanticCustomError(
                "node_xyz_length",
                "a node position has 2 or 3 coordinates [x, y] or [x, y, z], got {value}",
                {"value": list(value), "hint": _HINTS["node_xyz"]},
            )
        if any(abs(v) > MAX_COORDINATE for v in value):
            raise PydanticCustomError(
                "node_xyz_range",
                "a coordinate is larger than {limit} in magnitude, got {value}",
                {"value": list(value), "limit": f"{MAX_COORDINATE:g}", "hint": _HINTS["node_xyz"]},
            )
        return tuple(float(v) for v in value)

    start_xyz: list[float] | None = None
    ros: _RosTable | None = None
    sensor: _SensorTable | None = None
    odometer_uncertainty_ratio: float | None = Field(default=None, gt=0.0, le=0.5)
    odometer_slip_m: float | None = Field(default=None, ge=0.0, le=10.0, allow_inf_nan=False)

    @field_validator("start_xyz")
    @classmethod
    def _three(cls, value: list[float] | None) -> list[float] | None:
        if value is not None and len(value) != 3:
            raise PydanticCustomError(
                "start_xyz_length",
                "start_xyz must have 3 components [x, y, z], got {value}",
                {"value": list(value), "hint": _HINTS["start_xyz"]},
            )
        return value

    @field_validator("inspected_at", mode="before")
    @classmethod
    def _parse_inspected_at(cls, value: Any) -> datetime:
        # TOML gives native dates and datetimes; strings are parsed as ISO 8601.
        if isinstance(value, datetime):
            return value
        if isinstance(value, date):
            return datetime(value.year, value.month, value.day)
        if isinstance(value, time):
            raise PydanticCustomError(
                "time_without_date", "a time of day {value} without a date", {"value": value}
            )
        if isinstance(value, str):
            try:
                return datetime.fromisoformat(value.strip())
            except ValueError:
                pass
        raise PydanticCustomError(
            "not_iso_date", "{value} is not an ISO 8601 date or datetime", {"value": repr(value)}
        )

    @field_validator("inspected_at", mode="after")
    @classmethod
    def _plausible_date(cls, value: datetime) -> datetime:
        # A year-9999 inspection would be every asset's latest, and year 1 with an offset
        # overflowed when stored: only dates from 1900 to tomorrow are inspections.
        now = datetime.now(UTC)
        latest = now + timedelta(days=1)
        if EARLIEST_INSPECTION.year <= value.year <= latest.year:
            utc = value if value.tzinfo is None else value.astimezone(UTC).replace(tzinfo=None)
            if EARLIEST_INSPECTION <= utc <= latest.replace(tzinfo=None):
                return value
        raise PydanticCustomError(
            "implausible_date",
            "{value} is not a plausible inspection date (from {low} to tomorrow, {high})",
            {
                "value": value.isoformat(),
                "low": EARLIEST_INSPECTION.date().isoformat(),
                "high": latest.date().isoformat(),
                "hint": "give the date the pipe was scanned (ISO 8601, e.g. 2024-05-17)",
            },
        )

    @field_validator("nominal_diameter_m")
    @classmethod
    def _plausible_diameter(cls, value: float | None) -> float | None:
        if value is None or MIN_DIAMETER_M < value <= MAX_DIAMETER_M:
            return value
        if MIN_DIAMETER_M * 1000 < value <= MAX_DIAMETER_M * 1000:
            raise PydanticCustomError(
                "diameter_in_mm",
                "{value} looks like millimetres: write {metres}",
                {"value": f"{value:g}", "metres": f"{value / 1000:g}"},
            )
        raise PydanticCustomError(
            "implausible_diameter",
            "{value} m is not a plausible pipe diameter (expected {low} < d <= {high} m)",
            {"value": f"{value:g}", "low": f"{MIN_DIAMETER_M:g}", "high": f"{MAX_DIAMETER_M:g}"},
        )

    @field_validator("pipe_shape")
    @classmethod
    def _lower_shape(cls, value: str) -> str:
        return value.lower()


def read_inspection_toml(
    path: Path, *, archive: str, max_bytes: int | None = None
) -> InspectionMeta:
    """Read and validate an ``inspection.toml`` file.

    Parameters
    ----------
    path
        The file on disk.
    archive
        The archive's name, for error messages.
    max_bytes
        The largest file accepted (the ``metadata_max_bytes`` limit); None: any.

    Returns
    -------
    InspectionMeta
        As :func:`parse_inspection_toml`.

    Raises
    ------
    MetadataError
        The file is missing, larger than ``max_bytes``, not UTF-8, or invalid (see
        :func:`parse_inspection_toml`).
    """
    if not path.is_file():
        raise MetadataError(
            "the archive has no inspection.toml at its root",
            archive=archive,
            file=INSPECTION_FILE,
            hint="add inspection.toml with at least asset_id, inspected_at and "
            "nominal_diameter_m next to frames/ (or the cloud)",
        )
    try:
        with path.open("rb") as fh:
            data = fh.read(max_bytes + 1 if max_bytes is not None else -1)
    except OSError as exc:
        raise MetadataError(
            f"cannot read the file: {exc.strerror}", archive=archive, file=INSPECTION_FILE
        ) from exc
    if max_bytes is not None and len(data) > max_bytes:
        raise MetadataError(
            f"the file is larger than {max_bytes:,} bytes, the limit (metadata_max_bytes)",
            archive=archive,
            file=INSPECTION_FILE,
            field="size",
            hint="if it is genuine, raise PIPESCAN_METADATA_MAX_BYTES (docs/security.md)",
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MetadataError(
            f"the file is not UTF-8 text (byte {exc.start})",
            archive=archive,
            file=INSPECTION_FILE,
            hint="save inspection.toml as UTF-8",
        ) from exc
    return parse_inspection_toml(text, archive=archive)


def parse_inspection_toml(text: str, *, archive: str) -> InspectionMeta:
    """Parse and validate the text of ``inspection.toml``.

    Parameters
    ----------
    text
        The TOML document.
    archive
        The archive's name, for error messages.

    Returns
    -------
    InspectionMeta
        The validated metadata. ``frames`` holds the ``[[frames]]`` entries in the order
        given (file paths relative to the archive root, ``/``-separated), or is empty when
        the document has none. ``inspected_at`` is a datetime (midnight for a bare date;
        timezone-aware only when the document gives an offset). ``pipe_shape`` is lower
        case. For a non-circular pipe without ``nominal_diameter_m`` the diameter is NaN.

    Raises
    ------
    MetadataError
        With ``file="inspection.toml"`` and ``field`` the dotted path of the first problem
        (``"line N"`` for a TOML syntax error); the message counts any further problems.

    Examples
    --------
    >>> meta = parse_inspection_toml(
    ...     'asset_id = "MH1-MH2"\\ninspected_at = 2024-05-17\\nnominal_diameter_m = 0.5',
    ...     archive="run.zip",
    ... )
    >>> meta.asset_id, meta.nominal_diameter_m, meta.frames
    ('MH1-MH2', 0.5, ())
    """

    def fail(reason: str, field: str | None, hint: str | None = None) -> MetadataError:
        return MetadataError(reason, archive=archive, file=INSPECTION_FILE, field=field, hint=hint)

    try:
        check_toml_depth(text)  # before tomllib, which recurses and slows with depth
    except TomlTooDeep as exc:
        raise fail(
            f"the document {exc}",
            f"line {exc.line}",
            hint="inspection.toml nests three levels at most ([[frames]], [ros])",
        ) from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        match = re.search(r"line (\d+)", str(exc))
        raise fail(
            f"TOML syntax error: {exc}",
            f"line {match.group(1)}" if match else None,
            hint="check quotes, '=' and brackets on that line; strings need double quotes",
        ) from exc

    try:
        doc = InspectionDocument.model_validate(raw)
    except ValidationError as exc:
        raise _metadata_error(exc, raw, fail) from exc
    _warn_lookalike(doc.asset_id, archive)

    if doc.nominal_diameter_m is None and doc.pipe_shape == "circular":
        raise fail(
            "required field is missing: circular pipes need it",
            "nominal_diameter_m",
            hint=_missing_hint("nominal_diameter_m", raw),
        )
    frames = _check_frames(doc.frames, fail)
    _check_node_positions(doc, fail)
    return InspectionMeta(
        asset_id=doc.asset_id,
        inspected_at=doc.inspected_at,
        nominal_diameter_m=(
            doc.nominal_diameter_m if doc.nominal_diameter_m is not None else math.nan
        ),
        upstream_node=doc.upstream_node,
        downstream_node=doc.downstream_node,
        direction=doc.direction,
        chainage_offset_m=doc.chainage_offset_m,
        material=doc.material,
        pipe_shape=doc.pipe_shape,
        frames=frames,
        upstream_node_xyz=_as_position(doc.upstream_node_xyz),
        downstream_node_xyz=_as_position(doc.downstream_node_xyz),
        crs=doc.crs,
        start_xyz=None
        if doc.start_xyz is None
        else (doc.start_xyz[0], doc.start_xyz[1], doc.start_xyz[2]),
        ros=None
        if doc.ros is None
        else RosTopics(doc.ros.points_topic, doc.ros.odometry_topic, doc.ros.imu_topic),
        odometer_uncertainty_ratio=doc.odometer_uncertainty_ratio,
        odometer_slip_m=doc.odometer_slip_m,
        sensor=_sensor_profile(doc.sensor, fail),
    )


def _sensor_profile(table: _SensorTable | None, fail: Any) -> SensorProfile | None:
    """The ``[sensor]`` table as a profile: the named model's figures, overridden by any
    the table gives itself."""
    from pipescan.core.instrument import SENSOR_MODELS

    if table is None:
        return None
    own = table.model_dump(exclude_none=True, exclude={"model"})
    base = SENSOR_MODELS[table.model] if table.model else SensorProfile()
    source = base.source if not own else f"{base.source}; inspection.toml's [sensor]"
    try:
        return dataclasses.replace(base, **own, source=source)
    except ValueError as exc:
        raise fail(str(exc), "sensor") from exc


def _as_position(value: Sequence[float] | None) -> tuple[float, ...] | None:
    return None if value is None else tuple(value)


def _check_node_positions(doc: InspectionDocument, fail: Any) -> None:
    """Node positions come as a pair with their CRS, in the same dimension, apart."""
    up, down = doc.upstream_node_xyz, doc.downstream_node_xyz
    if up is None and down is None:
        if doc.crs is not None:
            raise fail(
                "crs is given without node positions",
                "crs",
                hint="add upstream_node_xyz and downstream_node_xyz, or leave crs out",
            )
        return
    if up is None or down is None:
        missing = "upstream_node_xyz" if up is None else "downstream_node_xyz"
        raise fail(
            "required field is missing: node positions are given as a pair",
            missing,
            hint="give both upstream_node_xyz and downstream_node_xyz, or neither",
        )
    if len(up) != len(down):
        raise fail(
            f"has {len(down)} coordinates but upstream_node_xyz has {len(up)}",
            "downstream_node_xyz",
            hint="give both nodes as [x, y] or both as [x, y, z]",
        )
    if doc.crs is None:
        raise fail(
            "required field is missing: node positions need their coordinate reference system",
            "crs",
            hint='add crs = "EPSG:25832" (the code of the network\'s CRS)',
        )
    if math.dist(up, down) < MIN_NODE_DISTANCE_M:
        raise fail(
            f"is {math.dist(up, down):.3g} from upstream_node_xyz: the two ends of a pipe "
            f"must be at least {MIN_NODE_DISTANCE_M:g} apart",
            "downstream_node_xyz",
            hint="check the two positions (and that they are in the CRS's units, metres)",
        )


def _check_frames(entries: Sequence[_FrameEntry], fail: Any) -> tuple[FrameRef, ...]:
    """Normalise ``[[frames]]`` file paths and check the entries agree with each other."""
    frames: list[FrameRef] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(entries):
        file = entry.file.replace("\\", "/")
        parts = PurePosixPath(file).parts
        if file.startswith("/") or re.match(r"^[A-Za-z]:", file) or ".." in parts:
            raise fail(
                f"{entry.file!r} is not a path inside the archive",
                f"frames[{i}].file",
                hint='give the path relative to the archive root, e.g. "frames/000001.npy"',
            )
        file = str(PurePosixPath(*[p for p in parts if p != "."]))
        if file in seen:
            raise fail(
                f"{file!r} is listed twice (first as frames[{seen[file]}])",
                f"frames[{i}].file",
                hint="list each frame once",
            )
        seen[file] = i
        frames.append(
            FrameRef(
                file=file, time_s=entry.time_s, odometer_m=entry.odometer_m, gravity=entry.gravity
            )
        )

    # gravity may be missing on some frames: an IMU drops readings, and registration then
    # holds those frames' roll to the previous attitude.
    for key in ("time_s", "odometer_m"):
        given = [getattr(f, key) is not None for f in frames]
        if any(given) and not all(given):
            i = given.index(False)
            raise fail(
                f"{key} is given for some frames but not for this one",
                f"frames[{i}].{key}",
                hint=f"give {key} for every [[frames]] entry or for none",
            )
    for i in range(1, len(frames)):
        before, now = frames[i - 1], frames[i]
        if before.time_s is not None and now.time_s is not None and now.time_s < before.time_s:
            raise fail(
                f"time goes backwards: {now.time_s:g} s after {before.time_s:g} s "
                f"at frames[{i - 1}]",
                f"frames[{i}].time_s",
                hint="list [[frames]] in capture order",
            )
        if (
            before.odometer_m is not None
            and now.odometer_m is not None
            and now.odometer_m < before.odometer_m - ODOMETER_TOLERANCE_M
        ):
            raise fail(
                f"the odometer goes back {before.odometer_m - now.odometer_m:.3g} m: "
                f"{now.odometer_m:g} m after {before.odometer_m:g} m at frames[{i - 1}] "
                f"(more than the {ODOMETER_TOLERANCE_M:g} m tolerance)",
                f"frames[{i}].odometer_m",
                hint="list [[frames]] in capture order, and check the odometer values",
            )
    return tuple(frames)


_WARNED: set[str] = set()


def _warn_lookalike(asset_id: str, archive: str) -> None:
    """Warn (once per id and process) of an asset id with letters of another script drawn like
    Latin ones: it names another asset than the Latin id it looks like."""
    letters = lookalike_letters(asset_id)
    if not letters or asset_id in _WARNED:
        return
    _WARNED.add(asset_id)
    names = (f"{ch} ({unicodedata.name(ch, '?').title()})" for ch in dict.fromkeys(letters))
    shown = ", ".join(names)
    logging.getLogger("pipescan").warning(
        f"warning: {archive}: asset_id {asset_id!r} holds letters of another script drawn like "
        f"Latin ones ({shown}); it is another asset than the Latin id it looks like"
    )


def _metadata_error(exc: ValidationError, raw: dict[str, Any], fail: Any) -> MetadataError:
    """Turn the first pydantic error into a MetadataError naming its dotted field path."""
    errors = exc.errors(include_url=False)
    first = errors[0]
    loc = first["loc"]
    field = _dotted(loc)
    more = f" ({len(errors) - 1} more problem(s) in inspection.toml)" if len(errors) > 1 else ""
    ctx = first.get("ctx") or {}
    if first["type"] == "missing":
        return fail("required field is missing" + more, field, hint=_missing_hint(loc, raw))
    reason = first["msg"].removeprefix("Value error, ")
    if first["type"] not in _CUSTOM_ERROR_TYPES:  # their messages already quote the value
        reason += f", got {_short_repr(first['input'])}"
    # The innermost named field: frames[0].gravity[1] takes the hint of gravity.
    name = next((str(part) for part in reversed(loc) if isinstance(part, str)), "")
    hint = ctx.get("hint") or _HINTS.get(name)
    if loc and loc[0] == "frames" and len(loc) == 1:
        hint = "write each frame as a [[frames]] table with file = ..."
    return fail(reason + more, field, hint=hint)


_CUSTOM_ERROR_TYPES = {
    "control_characters",
    "implausible_date",
    "diameter_in_mm",
    "implausible_diameter",
    "not_iso_date",
    "time_without_date",
    "zero_gravity",
    "gravity_length",
    "node_xyz_length",
    "node_xyz_range",
    "crs_not_a_code",
    "start_xyz_length",
}

_HINTS = {
    "nominal_diameter_m": "nominal_diameter_m is the design inner diameter in metres",
    "inspected_at": "write an ISO 8601 date or datetime, e.g. inspected_at = 2024-05-17",
    "direction": 'write direction = "downstream" or "upstream"',
    "chainage_offset_m": "give the distance in metres from the upstream node to the scan start",
    "asset_id": 'write the pipe asset id, e.g. asset_id = "MH1042-MH1043"',
    "file": 'give the frame file relative to the archive root, e.g. "frames/000001.npy"',
    "node_xyz": (
        "give the node's position in the network's CRS, e.g. "
        'upstream_node_xyz = [512345.2, 5803210.7, 41.3], with crs = "EPSG:25832"'
    ),
    "crs": 'write the CRS as an authority code, e.g. crs = "EPSG:25832"',
    "start_xyz": (
        "start_xyz = [x, y, z] is the sensor's first position in the cloud's frame, metres"
    ),
    "gravity": (
        "gravity = [gx, gy, gz] is the IMU's gravity direction in the sensor frame "
        "(any length but zero), e.g. gravity = [0.05, 0.0, -1.0]"
    ),
}

_HINTS["upstream_node_xyz"] = _HINTS["downstream_node_xyz"] = _HINTS["node_xyz"]


def _dotted(loc: Sequence[int | str]) -> str:
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else ("." if text else "") + str(part)
    return text


def _short_repr(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _missing_hint(loc: Sequence[int | str] | str, raw: dict[str, Any]) -> str:
    """Suggest the fix for a missing key, spotting a misspelling of it among the keys given."""
    loc = (loc,) if isinstance(loc, str) else tuple(loc)
    table: Any = raw
    for part in loc[:-1]:
        try:
            table = table[part]
        except (KeyError, IndexError, TypeError):
            table = {}
            break
    name = str(loc[-1])
    known = InspectionDocument.model_fields if len(loc) == 1 else _FrameEntry.model_fields
    given = [k for k in table if k not in known] if isinstance(table, dict) else []
    normal = {re.sub(r"[^a-z0-9]", "", k.lower()): k for k in given}
    close = normal.get(re.sub(r"[^a-z0-9]", "", name)) or next(
        iter(difflib.get_close_matches(name, given, n=1, cutoff=0.6)), None
    )
    if close is not None:
        return f"found {close!r}: did you mean {name!r}?"
    return f"add {_EXAMPLES.get(name, name + ' = ...')}"
