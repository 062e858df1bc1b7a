"""The URLs pipescan is given, read by fsspec's own grammar: opening one
(:func:`url_filesystem`, :func:`is_local`) and the secrets it may hold.

fsspec splits a URL into links at ``::`` (``simplecache::s3://bucket/x.zip``), and each link
into its protocol and the rest at the first ``://`` (:func:`fsspec.core.split_protocol`); a
backend then reads user, password or token from the rest's authority, the part before the
first ``/``, ``?`` or ``#`` (``ftp://user:pass@host``, ``https://TOKEN@host``), or from the
query (``?X-Amz-Signature=...``). :func:`url_secret` looks at each link the same way, so a
secret is found wherever fsspec would find it. It does not need ``urllib``'s reading of the
host, which fails on an unbalanced ``[`` and would let the secret through.
"""

from __future__ import annotations

from typing import Any

from pipescan.core.errors import ArchiveError, PipescanError

__all__ = ["is_local", "unopened_url_error", "url_filesystem", "url_secret", "without_secrets"]

BACKEND_HINT = "check the protocol, and install its fsspec backend (e.g. s3fs for s3://)"

_AUTHORITY_ENDS = "/?#"
LOGIN_PROTOCOLS = frozenset({"ftp", "sftp", "ssh", "smb"})
"""Protocols whose fsspec backends read a login name from a user-only authority
(``ftp://user@host``): a user name without a password passes for these. For every other
protocol a user-only authority is a token (``https://TOKEN@host``) and is refused."""


def unopened_url_error(
    exc: BaseException,
    archive: str,
    *,
    error: type[PipescanError] = ArchiveError,
    what: str = "the URL",
) -> PipescanError:
    """The error for a URL fsspec cannot open (an unknown protocol, a backend not installed):
    ``error`` naming ``archive``, with the hint to install the backend."""
    return error(f"cannot open {what}: {exc}", archive=archive, hint=BACKEND_HINT)


def url_filesystem(
    location: str,
    archive: str,
    *,
    error: type[PipescanError] = ArchiveError,
    what: str = "the URL",
) -> tuple[Any, str]:
    """fsspec's file system and path for ``location``, a local path or a URL.

    Raises
    ------
    PipescanError
        ``error`` (:func:`unopened_url_error`) when the protocol is unknown or its backend is
        not installed. Whatever a backend raises when it connects on creation (``ftp://``,
        ``sftp://``) is the caller's to type.
    """
    import fsspec

    try:
        return fsspec.core.url_to_fs(location)
    except (ValueError, ImportError) as exc:
        raise unopened_url_error(exc, archive, error=error, what=what) from exc


def is_local(fs: Any) -> bool:
    """Whether an fsspec file system is the local disk."""
    from fsspec.implementations.local import LocalFileSystem

    return isinstance(fs, LocalFileSystem)


def _links(location: str) -> list[str]:
    """The links of an fsspec chain, as ``fsspec.core._un_chain`` splits them."""
    return location.split("::")


def _authority_end(rest: str) -> int:
    ends = [i for i in (rest.find(c) for c in _AUTHORITY_ENDS) if i >= 0]
    return min(ends, default=len(rest))


def without_secrets(location: str) -> str:
    """``location`` without the user info of any link (as fsspec splits it) and with secret
    query values redacted: what may be shown, logged or stored.

    >>> without_secrets("simplecache::arrow_hdfs://KEY:SECRET@[host/x.zip")
    'simplecache::arrow_hdfs://[host/x.zip'
    """
    from fsspec.core import split_protocol

    from pipescan.core.sanitize import strip_credentials

    links = []
    for link in _links(str(location)):
        protocol, rest = split_protocol(link)
        if protocol is not None and "://" in link:
            end = _authority_end(rest)
            rest = rest[:end].rpartition("@")[2] + rest[end:]
            link = strip_credentials(f"{protocol}://{rest}")
        links.append(link)
    return "::".join(links)


def url_secret(location: str) -> str | None:
    """What kind of secret ``location`` holds (``"user info"``, ``"a secret query value"``),
    or None. Local paths and plain URLs without user info or secret query values hold none.

    Examples
    --------
    >>> url_secret("simplecache::s3://KEY:SECRET@bucket/x.zip")
    'user info'
    >>> url_secret("https://TOKEN@host/x.zip")
    'user info'
    >>> url_secret("s3://bucket/runs/x.zip") is None
    True
    """
    from fsspec.core import split_protocol

    from pipescan.core.sanitize import REDACTED, strip_credentials

    for link in _links(str(location)):
        protocol, rest = split_protocol(link)
        if protocol is None:
            continue  # a local path, a bare protocol name in a chain ("simplecache")
        end = _authority_end(rest)
        authority = rest[:end]
        if "@" in authority:
            user = authority.rpartition("@")[0]
            if ":" in user or protocol.lower() not in LOGIN_PROTOCOLS:
                return "user info"
        query = rest[end:]
        marker = f"={REDACTED}"
        if "?" in query and marker in strip_credentials(link) and marker not in link:
            return "a secret query value"
    return None
