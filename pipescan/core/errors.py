"""One exception hierarchy for everything pipescan raises on purpose."""

from __future__ import annotations


class PipescanError(Exception):
    """Base class of every error pipescan raises on purpose.

    Parameters
    ----------
    message
        What is wrong, in words a user can act on.
    archive, file, field
        Where the problem is, when known: the archive, the file inside it and the
        field (metadata key or data column). They are prefixed to the message.
    hint
        What would fix it.
    """

    def __init__(
        self,
        message: str,
        *,
        archive: str | None = None,
        file: str | None = None,
        field: str | None = None,
        hint: str | None = None,
    ) -> None:
        self.reason = message
        self.archive = archive
        self.file = file
        self.field = field
        self.hint = hint
        super().__init__(self._format())

    def _format(self) -> str:
        where = []
        if self.archive:
            where.append(f"archive {self.archive}")
        if self.file:
            where.append(f"file {self.file}")
        if self.field:
            where.append(f"field {self.field!r}")
        text = (", ".join(where) + ": " if where else "") + self.reason
        if self.hint:
            text += f" ({self.hint})"
        return text


class ArchiveError(PipescanError):
    """The scan archive is unreadable, incomplete or unsafe."""


class MetadataError(ArchiveError):
    """``inspection.toml`` is missing, malformed or has an invalid field."""


class PointFileError(ArchiveError):
    """A point file is corrupt, truncated, empty or holds non-finite values."""


class RegistrationError(PipescanError):
    """The frames could not be registered into one cloud."""


class GeometryError(PipescanError):
    """The cloud does not support the geometric step asked of it (axis, sections)."""


class GradingError(PipescanError):
    """A threshold table is malformed or unknown."""


class OptionError(PipescanError):
    """A processing option names something pipescan does not know (e.g. a contour method)."""
