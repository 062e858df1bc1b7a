"""Limits on what an archive and its point files may make pipescan write and allocate.

Every size pipescan acts on is checked against what was actually read, while streaming, before
it is written or allocated: a header's point count against the bytes the file holds, an
archive member's size against the bytes its decompressor produced. On top of that, the caps
below bound a genuine-looking input. Their defaults are generous for real scans (a 100 m reach
is ~300 M points, ~10 GB as LAS); each is a setting (``PIPESCAN_<NAME>``, see
docs/security.md) and the error that stops an input names it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from pipescan.core.errors import ArchiveError, PointFileError

KIB = 1024
MIB = 1024 * KIB
GIB = 1024 * MIB


@dataclass(frozen=True)
class InputLimits:
    """Caps on one archive and its point files (each field is the setting of that name).

    Attributes
    ----------
    archive_max_bytes
        Total bytes an archive may expand to (extracted, or copied from a store).
    member_max_bytes
        Bytes of one member (one file) of an archive.
    compression_max_ratio
        Uncompressed / compressed bytes, of one member and of the archive so far; checked
        once more than :data:`RATIO_FLOOR_BYTES` came out. Real scans compress 1-10×
        (LAZ ~1, ASCII x y z ~3-5); a zip bomb, ~1000×.
    archive_max_members
        Members (files and folders) of an archive; frames at 10 Hz for 5,000 s fit.
    line_max_bytes
        Length of one line of an ASCII point file or header.
    points_max_count
        Points in one point file (a whole 100 m reach as one cloud is ~300 M).
    metadata_max_bytes
        Size of ``inspection.toml`` (50,000 ``[[frames]]`` entries take ~7 MB).
    """

    archive_max_bytes: int = 64 * GIB
    member_max_bytes: int = 32 * GIB
    compression_max_ratio: float = 100.0
    archive_max_members: int = 50_000
    line_max_bytes: int = 64 * KIB
    points_max_count: int = 500_000_000
    metadata_max_bytes: int = 32 * MIB

    def __post_init__(self) -> None:
        for f in fields(self):
            if not getattr(self, f.name) > 0:
                raise ValueError(f"{f.name} must be positive, got {getattr(self, f.name)!r}")

    @classmethod
    def from_settings(cls, settings: Any) -> InputLimits:
        """The limits that ``settings`` (an object with these attribute names) give."""
        return cls(**{f.name: getattr(settings, f.name) for f in fields(cls)})


RATIO_FLOOR_BYTES = 4 * MIB
"""Compression ratios are checked only past this much output: a small, repetitive file (an
``inspection.toml``, an empty frame) compresses far more than a scan, harmlessly."""

DEFAULT_LIMITS = InputLimits()


def setting_name(cap: str) -> str:
    """The environment variable that sets a cap: ``member_max_bytes`` ->
    ``PIPESCAN_MEMBER_MAX_BYTES``."""
    return f"PIPESCAN_{cap.upper()}"


def _hint(cap: str) -> str:
    return (
        f"if the input is genuine, raise the limit: set {setting_name(cap)} "
        "(docs/security.md lists the limits)"
    )


def archive_limit_error(
    cap: str, limits: InputLimits, what: str, *, archive: str, file: str | None = None
) -> ArchiveError:
    """An :class:`ArchiveError` for an archive over a cap, naming the cap and its setting."""
    return ArchiveError(
        f"{what}, over the limit of {format_cap(cap, limits)} ({cap})",
        archive=archive,
        file=file,
        field="size" if cap != "archive_max_members" else "members",
        hint=_hint(cap),
    )


def point_limit_error(
    cap: str, limits: InputLimits, what: str, *, archive: str | None, file: str, field: str
) -> PointFileError:
    """A :class:`PointFileError` for a point file over a cap, naming the cap and its setting."""
    return PointFileError(
        f"{what}, over the limit of {format_cap(cap, limits)} ({cap})",
        archive=archive,
        file=file,
        field=field,
        hint=_hint(cap),
    )


def format_cap(cap: str, limits: InputLimits) -> str:
    value = getattr(limits, cap)
    if cap.endswith("_bytes"):
        return format_bytes(value)
    if cap.endswith("_ratio"):
        return f"{value:g}:1"
    return f"{value:,}"


def format_bytes(n: int) -> str:
    """``n`` bytes for a message: ``'2.0 GiB (2147483648 bytes)'``."""
    for unit, size in (("GiB", GIB), ("MiB", MIB), ("KiB", KIB)):
        if n >= size:
            return f"{n / size:.1f} {unit} ({n} bytes)"
    return f"{n} bytes"
