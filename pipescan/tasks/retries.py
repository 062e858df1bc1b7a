"""When a Prefect task is retried: on transient I/O errors only, with exponential backoff.

Reading a store or scratch files and writing the database can fail once and work the next
time; a bad archive or a geometry error fails the same way every time, so retrying it only
delays the failure. Every task that does I/O is declared with ``IO_RETRY_OPTIONS``.
"""

from __future__ import annotations

from collections.abc import Iterator

import sqlalchemy as sa
from prefect.tasks import exponential_backoff

from pipescan.core.errors import (
    ArchiveError,
    GeometryError,
    GradingError,
    RegistrationError,
    ScratchSpaceError,
)

IO_RETRY_COUNT = 3
"""How many times an I/O failure (store read, database write) is retried."""

IO_RETRY_BACKOFF_S = 2.0
"""The first retry's delay; each next one doubles (2, 4, 8 s), with ±50 % jitter."""

# Errors that come from the archive's content or the geometry: the same input fails the same
# way every time, so a retry only delays the failure.
_DETERMINISTIC: tuple[type[BaseException], ...] = (
    GeometryError,
    RegistrationError,
    GradingError,
    ArchiveError,  # with MetadataError and PointFileError: whatever it wraps
    ScratchSpaceError,
    FileNotFoundError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
)
# Database driver errors that a second attempt can get past: a lock, a dropped connection.
_TRANSIENT_DB: tuple[type[BaseException], ...] = (
    sa.exc.OperationalError,
    sa.exc.InterfaceError,
    sa.exc.DisconnectionError,
    sa.exc.TimeoutError,
)


def _causes(exc: BaseException) -> Iterator[BaseException]:
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        yield current
        current = current.__cause__ or current.__context__


def is_transient_io_error(exc: BaseException) -> bool:
    """True when ``exc`` is an I/O failure that a retry may get past.

    Walks the exception and its causes: a connection, timeout or other ``OSError`` (reading
    from a store, a network file system), or a database lock or lost connection, is
    transient, also when wrapped in a :class:`~pipescan.core.errors.FetchError` or a
    ``StorageError``. Archive errors (metadata, point files, limits, unsafe or clashing
    names), a full work directory, geometry, registration and grading errors, and missing
    files or permissions, are deterministic: never transient, whatever they wrap.

    Examples
    --------
    >>> is_transient_io_error(ConnectionResetError("peer reset"))
    True
    >>> is_transient_io_error(GeometryError("no points in the window"))
    False
    """
    for link in _causes(exc):
        if isinstance(link, _DETERMINISTIC) or _refused_login(link):
            return False
        if isinstance(link, (*_TRANSIENT_DB, OSError)):
            return True
    return False


# SQLSTATE classes of a database's answer that a second attempt gets the same way: the login
# or the database itself is wrong (28: invalid authorization, 3D: no such database).
_REFUSED_SQLSTATE_CLASSES = ("28", "3D")


def _refused_login(link: BaseException) -> bool:
    orig = getattr(link, "orig", None)
    sqlstate = getattr(orig, "sqlstate", None) or getattr(link, "sqlstate", None)
    return isinstance(sqlstate, str) and sqlstate[:2] in _REFUSED_SQLSTATE_CLASSES


def _prefect_unreachable(link: BaseException) -> bool:
    """Prefect's API did not answer, answered with a server error, or could not give a
    concurrency slot, Prefect took the run for crashed, or it lost a finished sub-flow's
    result (``MissingResult``: its state read back from the API without its data, seen under
    load on the test machine): all of it outside the archive. A second attempt finds what the
    first stored (``reuse_stored``)."""
    import httpx
    from prefect.exceptions import Abort, CrashedRun, MissingResult

    try:
        from prefect.concurrency._asyncio import ConcurrencySlotAcquisitionError
    except ImportError:  # pragma: no cover - another Prefect layout
        ConcurrencySlotAcquisitionError = ()  # type: ignore[assignment]
    if isinstance(link, httpx.HTTPStatusError):
        return link.response.status_code >= 500 or link.response.status_code in (408, 429)
    return isinstance(link, (httpx.TransportError, Abort, CrashedRun, MissingResult)) or (
        bool(ConcurrencySlotAcquisitionError) and isinstance(link, ConcurrencySlotAcquisitionError)
    )


TRANSIENT = "transient"
CONTENT = "content"
OTHER = "error"


def failure_cause(exc: BaseException) -> str:
    """Why an archive failed, as a network run decides whether to try it again.

    Returns
    -------
    str
        ``"transient"``: outside the archive and likely to pass (the database or Prefect's API
        unreachable, a concurrency slot not granted, the run taken for crashed, another
        transient I/O error): worth another attempt later in the run.
        ``"content"``: the archive's own content or figures (a bad file, metadata, geometry,
        registration, a value the database refuses) or a refused database login: the same
        input fails the same way, so it is not tried again.
        ``"error"``: anything else (a defect of pipescan): not tried again either.

    Examples
    --------
    >>> failure_cause(ConnectionRefusedError("connection refused"))
    'transient'
    >>> failure_cause(GeometryError("no points in the window"))
    'content'
    >>> from prefect.exceptions import MissingResult
    >>> failure_cause(MissingResult("State data is missing."))
    'transient'
    """
    from pipescan.core.errors import PipescanError

    links = list(_causes(exc))
    if any(isinstance(link, _DETERMINISTIC) or _refused_login(link) for link in links):
        return CONTENT
    if is_transient_io_error(exc) or any(_prefect_unreachable(link) for link in links):
        return TRANSIENT
    if any(isinstance(link, PipescanError) for link in links):
        return CONTENT
    return OTHER


def retry_on_io_error(task, task_run, state) -> bool:
    """Prefect ``retry_condition_fn``: retry a failed task run only on a transient I/O error."""
    exc = state.data if isinstance(state.data, BaseException) else None
    if exc is None:
        try:
            exc = state.result(raise_on_failure=False)
        except Exception as raised:  # the result itself could not be read back
            exc = raised
    return isinstance(exc, BaseException) and is_transient_io_error(exc)


IO_RETRY_OPTIONS = {
    "retries": IO_RETRY_COUNT,
    "retry_delay_seconds": exponential_backoff(IO_RETRY_BACKOFF_S),
    "retry_jitter_factor": 0.5,
    "retry_condition_fn": retry_on_io_error,
}
"""Task options (``@task(..., **IO_RETRY_OPTIONS)``) for tasks that read the store or
write the database: retried with exponential backoff, on transient I/O errors only."""
