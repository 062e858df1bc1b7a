"""One exception hierarchy for everything pipescan raises on purpose."""

from __future__ import annotations

from pipescan.core.sanitize import escape_control, strip_credentials, strip_credentials_in_text


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
        # The message is printed, logged and stored: it carries no credentials (an archive
        # URL, a backend's error quoting one) and stays one line whatever names the input
        # holds (a member name with an ESC sequence cannot drive the terminal).
        where = []
        if self.archive:
            where.append(f"archive {strip_credentials(self.archive)}")
        if self.file:
            where.append(f"file {self.file}")
        if self.field:
            where.append(f"field {self.field!r}")
        text = (", ".join(where) + ": " if where else "") + self.reason
        if self.hint:
            text += f" ({self.hint})"
        return escape_control(strip_credentials_in_text(text))


class ArchiveError(PipescanError):
    """The scan archive is unreadable, incomplete, unsafe or over a limit.

    Always the input's fault, so the same archive fails the same way every time: never
    retried. A failure to *reach* the archive (network, store) is a :class:`FetchError`.
    """


class MetadataError(ArchiveError):
    """``inspection.toml`` is missing, malformed or has an invalid field."""


class PointFileError(ArchiveError):
    """A point file is corrupt, truncated, empty or holds non-finite values."""


class FetchError(PipescanError):
    """The archive could not be copied from where it lives (a network store, a backend).

    Retried when what caused it is transient I/O (a reset connection, a timeout); a missing
    object or refused credentials fail at once.
    """


class ScratchSpaceError(PipescanError):
    """The work directory cannot hold what the run must write there (disk full, quota,
    read-only). Not the archive's fault and not transient: never retried."""


class RegistrationError(PipescanError):
    """The frames could not be registered into one cloud."""


class GeometryError(PipescanError):
    """The cloud does not support the geometric step asked of it (axis, sections)."""


class GradingError(PipescanError):
    """A threshold table is malformed or unknown."""


class LayerError(PipescanError):
    """A GIS layer cannot be imported: unreadable, a field missing, ids missing or repeated,
    geometry that is not one line per pipe, or no usable CRS."""


class OutputError(PipescanError):
    """An output file cannot be written: its folder cannot be made, it names a folder, or
    the user may not write there. Nothing is left under its name."""


class OptionError(PipescanError):
    """A processing option names something pipescan does not know (e.g. a contour method)."""
