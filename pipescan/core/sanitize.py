"""Text that leaves pipescan: no credentials, no control characters.

Archive URLs may carry credentials (``s3://KEY:SECRET@bucket/run.zip``, a pre-signed
``https://...?X-Amz-Signature=...``). Whatever pipescan stores, logs, prints or renders goes
through :func:`strip_credentials` first. Names that come from files users hand us (member
names, asset ids) may hold control characters: :func:`escape_control` makes them visible
instead of letting an ESC sequence reach a terminal. See docs/security.md.
"""

from __future__ import annotations

import re
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

__all__ = ["escape_control", "strip_credentials", "strip_credentials_in_text"]

REDACTED = "REDACTED"
"""What a secret query-string value is replaced with."""

# Query parameters that carry secrets in pre-signed or SAS URLs (S3, GCS, Azure) and in the
# URLs of fsspec backends (token=, password=...). Matched anywhere in the name, any case.
_SECRET_PARAM = re.compile(
    r"sig|signature|token|secret|passw|pwd|credential|key|auth|session", re.IGNORECASE
)
# scheme://userinfo@ inside free text (an exception message quoting a URL).
_USERINFO_IN_TEXT = re.compile(r"\b([A-Za-z][A-Za-z0-9+.-]*://)[^\s/@?#]*@")
_SECRET_QUERY_IN_TEXT = re.compile(
    r"([?&](?:[^=&\s#]*(?:" + _SECRET_PARAM.pattern + r")[^=&\s#]*)=)[^&\s#]*", re.IGNORECASE
)


def strip_credentials(uri: str) -> str:
    """``uri`` without user name, password or secret query values.

    Local paths come back unchanged. fsspec chains (``zip::s3://...``) are handled link by
    link.

    Examples
    --------
    >>> strip_credentials("s3://AKIA123:s3cr3t@bucket/runs/site7.zip")
    's3://bucket/runs/site7.zip'
    >>> strip_credentials("https://host/x.zip?versionId=4&X-Amz-Signature=abc")
    'https://host/x.zip?versionId=4&X-Amz-Signature=REDACTED'
    >>> strip_credentials("/data/scans/site7.zip")
    '/data/scans/site7.zip'
    """
    text = str(uri)
    if "::" in text:
        return "::".join(strip_credentials(part) for part in text.split("::"))
    if "://" not in text:
        return text
    try:
        parts = urlsplit(text)
    except ValueError:  # e.g. an unbalanced '[' in the host: redact as free text
        return strip_credentials_in_text(text)
    netloc = parts.netloc.rpartition("@")[2]
    query = parts.query
    if query:
        pairs = parse_qsl(query, keep_blank_values=True)
        if any(_SECRET_PARAM.search(k) for k, _ in pairs):
            query = urlencode(
                [(k, REDACTED if _SECRET_PARAM.search(k) else v) for k, v in pairs], safe="/:"
            )
    return urlunsplit((parts.scheme, netloc, parts.path, query, parts.fragment))


def strip_credentials_in_text(text: str) -> str:
    """Strip the user info and secret query values of every URL inside free ``text``.

    >>> strip_credentials_in_text("cannot open s3://K:S@bucket/a.zip: Access Denied")
    'cannot open s3://bucket/a.zip: Access Denied'
    """
    text = _USERINFO_IN_TEXT.sub(r"\1", text)
    return _SECRET_QUERY_IN_TEXT.sub(r"\1" + REDACTED, text)


def escape_control(text: str) -> str:
    r"""``text`` with control, format and separator characters written as escapes.

    Tabs, CR, LF, ESC, NUL, bidirectional overrides (U+202E) and the like become ``\t``,
    ``\x1b``, ``\u202e``..., so one message stays one visible line and cannot drive a
    terminal.

    >>> escape_control("MH1\x1b[2J\nMH2")
    'MH1\\x1b[2J\\nMH2'
    """
    if text.isprintable():
        return text
    return "".join(
        ch if ch.isprintable() else ch.encode("unicode_escape").decode("ascii") for ch in text
    )
