"""Delivering reports: writing them to the reports location and e-mailing them.

Users receive reports; they do not go looking for them. A rendered PDF is copied to the
*reports location* (a local directory or any fsspec URL, e.g. ``s3://utility-reports/pipes``)
and, when SMTP is configured, e-mailed to the addresses the *recipients file* gives for the
asset (or for a network run).

The recipients file is TOML::

    # Every network summary goes to these addresses.
    network = ["asset-team@utility.example"]

    # Inspection reports: asset id or glob pattern -> addresses. Every matching entry adds
    # its addresses (so a pattern can copy a district's office on all its pipes).
    [assets]
    "MH1042-MH1043" = ["north-crew@utility.example"]
    "MH10*" = ["north-office@utility.example"]
    "*" = ["archive@utility.example"]

Only the CLI and the flows read settings; everything here takes explicit arguments.
"""

from __future__ import annotations

import email.policy
import fnmatch
import re
import secrets
import smtplib
import ssl
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from email.message import EmailMessage
from email.utils import make_msgid
from pathlib import Path
from typing import Any, Literal

from prefect import task

from pipescan.core.errors import PipescanError
from pipescan.tasks.retries import IO_RETRY_OPTIONS

__all__ = [
    "Delivery",
    "DeliveryError",
    "Recipients",
    "SmtpConfig",
    "deliver_report",
    "deliver_report_task",
    "load_recipients",
    "report_file_name",
    "safe_name",
    "send_email",
    "send_report_email",
    "text_message",
    "write_to_location",
]

# A practical check, not RFC 5322: one @, no spaces, a dot in the domain.
_ADDRESS = re.compile(r"^[^@\s<>,;]+@[^@\s<>,;]+\.[^@\s<>,;]+$")
_UNSAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


class DeliveryError(PipescanError):
    """A report could not be written to the reports location or e-mailed."""


@dataclass(frozen=True)
class SmtpConfig:
    """How to reach the SMTP server.

    ``security`` is ``"none"`` (plain SMTP, e.g. a relay on the local network),
    ``"starttls"`` (upgrade the connection, usually port 587) or ``"ssl"`` (TLS from the
    start, usually port 465). ``username`` and ``password`` are used when both are set; over
    ``"none"`` only with ``allow_plaintext_login``, since the password would cross the network
    in clear. The password is left out of the repr, so it never reaches a log.
    """

    host: str
    port: int = 25
    sender: str = "pipescan@localhost"
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    security: Literal["none", "starttls", "ssl"] = "none"
    timeout_s: float = 30.0
    allow_plaintext_login: bool = False

    @property
    def logs_in(self) -> bool:
        return bool(self.username and self.password)

    @classmethod
    def from_settings(cls, settings) -> SmtpConfig | None:
        """The SMTP server of pipescan's settings (``PIPESCAN_SMTP_*``), or None when
        ``PIPESCAN_SMTP_HOST`` is unset."""
        if not settings.smtp_host:
            return None
        return cls(
            host=settings.smtp_host,
            port=settings.smtp_port,
            sender=settings.smtp_sender,
            username=settings.smtp_username,
            password=settings.smtp_password.get_secret_value() if settings.smtp_password else None,
            security=settings.smtp_security,
            allow_plaintext_login=settings.smtp_allow_plaintext_login,
        )


@dataclass(frozen=True)
class Recipients:
    """Who receives which report (see the module docstring for the file format)."""

    assets: tuple[tuple[str, tuple[str, ...]], ...] = ()
    network: tuple[str, ...] = ()
    path: str = ""

    def for_asset(self, asset_id: str) -> list[str]:
        """Addresses for an inspection report of ``asset_id``: the union, in file order, of
        every entry whose key is the asset id or a glob pattern matching it (case-sensitive)."""
        addresses: list[str] = []
        for pattern, entry in self.assets:
            if pattern == asset_id or fnmatch.fnmatchcase(asset_id, pattern):
                addresses += [a for a in entry if a not in addresses]
        return addresses


@dataclass(frozen=True)
class Delivery:
    """Where one report went: the URL it was written to (None if no location) and the
    addresses it was e-mailed to (empty if none)."""

    written_to: str | None
    emailed_to: tuple[str, ...]


def checked_addresses(value: Any, *, field: str, file: str | None = None) -> tuple[str, ...]:
    """The e-mail addresses in ``value`` (a string or a list of them), stripped.

    Raises
    ------
    DeliveryError
        It is not a list of strings, or one is not an address (``name@domain.example``),
        naming the field (and the file).
    """
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(a, str) for a in value):
        raise DeliveryError(
            "must be a list of e-mail addresses", file=file, field=field,
            hint='e.g. ["ops@utility.example"]',
        )  # fmt: skip
    for address in value:
        if not _ADDRESS.match(address.strip()):
            raise DeliveryError(
                f"{address!r} is not an e-mail address", file=file, field=field,
                hint="write it as name@domain.example",
            )  # fmt: skip
    return tuple(a.strip() for a in value)


def load_recipients(path: Path | str) -> Recipients:
    """Read and check a recipients file.

    Raises
    ------
    DeliveryError
        The file is missing, not TOML, or a key or an address is invalid; the error names
        the file and the field.
    """
    file = str(path)
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise DeliveryError(
            "recipients file not found", file=file,
            hint="create it (see docs/reports.md) or unset PIPESCAN_RECIPIENTS_FILE",
        ) from exc  # fmt: skip
    except (OSError, UnicodeDecodeError) as exc:
        raise DeliveryError(f"cannot read the recipients file: {exc}", file=file) from exc
    except tomllib.TOMLDecodeError as exc:
        raise DeliveryError(f"not valid TOML: {exc}", file=file) from exc
    unknown = set(data) - {"network", "assets"}
    if unknown:
        raise DeliveryError(
            "unknown key", file=file, field=sorted(unknown)[0],
            hint='use "network" (a list of addresses) and an [assets] table',
        )  # fmt: skip
    assets = data.get("assets", {})
    if not isinstance(assets, dict):
        raise DeliveryError(
            "must be a table of asset id or pattern = [addresses]", file=file, field="assets"
        )
    return Recipients(
        assets=tuple(
            (key, checked_addresses(value, field=f"assets.{key}", file=file))
            for key, value in assets.items()
        ),
        network=checked_addresses(data.get("network", []), field="network", file=file),
        path=file,
    )


def safe_name(text: str) -> str:
    """``text`` with every run of characters other than letters, digits, ``.``, ``_`` and
    ``-`` replaced by ``_``: safe as a file or folder name anywhere (asset ids come from
    files users hand us and may hold ``/`` or ``..``).

    >>> safe_name("../MH 10/42")
    'MH_10_42'
    """
    return _UNSAFE_NAME.sub("_", text).strip("._") or "asset"


def report_file_name(asset_id: str, inspected_at: datetime, inspection_id: int | str) -> str:
    """A file name for an inspection report that is safe on any file system or bucket.

    >>> from datetime import datetime
    >>> report_file_name("MH1042/MH1043", datetime(2025, 3, 14), 7)
    'MH1042_MH1043_2025-03-14_inspection-7.pdf'
    """
    return f"{safe_name(asset_id)}_{inspected_at:%Y-%m-%d}_inspection-{inspection_id}.pdf"


def write_to_location(pdf_path: Path, location: str, name: str) -> str:
    """Copy a rendered PDF to ``location/name``.

    Parameters
    ----------
    pdf_path
        The rendered PDF.
    location
        A local directory (created if needed) or an fsspec URL (``s3://bucket/reports``,
        ``memory://reports``, ...).
    name
        File name, or a relative path (``"MH1042-MH1043/report.pdf"``) under ``location``.

    Returns
    -------
    str
        Where the report now is (a path or URL).

    Raises
    ------
    DeliveryError
        The location cannot be written (the error names it and the cause).
    """
    import fsspec

    from pipescan.storage.atomic import atomic_file
    from pipescan.storage.input.urls import is_local

    target = location.rstrip("/") + "/" + name.lstrip("/")
    try:
        fs, path = fsspec.core.url_to_fs(target)
        parent = path.rsplit("/", 1)[0]
        if parent:
            fs.makedirs(parent, exist_ok=True)
        data = Path(pdf_path).read_bytes()
        # Write beside the target and move into place, so a reader never sees half a PDF: on
        # a local folder a new file of a random name (O_EXCL, no link followed); on a store,
        # a random name no one can plant ahead.
        if is_local(fs):
            with atomic_file(path) as fh:
                fh.write(data)
        else:
            partial = f"{path}.{secrets.token_hex(8)}.part"
            fs.pipe_file(partial, data)
            fs.mv(partial, path)
    except (OSError, ValueError, ImportError) as exc:
        raise DeliveryError(
            f"could not write the report to {target}: {exc}",
            hint="check PIPESCAN_REPORTS_LOCATION and that it can be written",
        ) from exc
    return target


def send_report_email(
    pdf_path: Path,
    recipients: Sequence[str],
    smtp: SmtpConfig,
    *,
    subject: str,
    body: str,
) -> None:
    """E-mail a PDF report, attached, to ``recipients`` in one message.

    Raises
    ------
    DeliveryError
        No recipients, or the server refused or could not be reached.
    """
    message = text_message(smtp, recipients, subject=subject, body=body)
    message.add_attachment(
        Path(pdf_path).read_bytes(),
        maintype="application",
        subtype="pdf",
        filename=Path(pdf_path).name,
    )
    send_email(message, recipients, smtp)


def text_message(
    smtp: SmtpConfig, recipients: Sequence[str], *, subject: str, body: str
) -> EmailMessage:
    """A plain-text message from ``smtp.sender`` to ``recipients``."""
    # The SMTP policy folds long headers (a subject with an asset id) the modern way and
    # ends lines with CRLF, as servers expect.
    message = EmailMessage(policy=email.policy.SMTP)
    message["From"] = smtp.sender
    message["To"] = ", ".join(recipients)
    message["Subject"] = subject
    message["Message-ID"] = make_msgid(domain=smtp.sender.rsplit("@", 1)[-1])
    message.set_content(body)
    return message


def send_email(message: EmailMessage, recipients: Sequence[str], smtp: SmtpConfig) -> None:
    """Send ``message`` to ``recipients`` through the SMTP server (TLS and login as
    ``smtp`` says).

    Raises
    ------
    DeliveryError
        No recipients, a password that would cross the network in clear, or the server
        refused or could not be reached.
    """
    if not recipients:
        raise DeliveryError("no recipients to e-mail")
    if smtp.logs_in and smtp.security == "none" and not smtp.allow_plaintext_login:
        raise DeliveryError(
            f"refusing to send the SMTP password to {smtp.host}:{smtp.port} without TLS",
            field="PIPESCAN_SMTP_SECURITY",
            hint="set PIPESCAN_SMTP_SECURITY=starttls (port 587) or ssl (port 465); only on a "
            "trusted network, PIPESCAN_SMTP_ALLOW_PLAINTEXT_LOGIN=true",
        )
    where = f"SMTP server {smtp.host}:{smtp.port}"
    try:
        client: smtplib.SMTP
        if smtp.security == "ssl":
            client = smtplib.SMTP_SSL(
                smtp.host, smtp.port, timeout=smtp.timeout_s, context=ssl.create_default_context()
            )
        else:
            client = smtplib.SMTP(smtp.host, smtp.port, timeout=smtp.timeout_s)
        with client:
            if smtp.security == "starttls":
                client.starttls(context=ssl.create_default_context())
            if smtp.logs_in:
                assert smtp.username is not None and smtp.password is not None
                client.login(smtp.username, smtp.password)
            refused = client.send_message(message, to_addrs=list(recipients))
    except (smtplib.SMTPException, OSError) as exc:
        raise DeliveryError(
            f"could not e-mail through the {where}: {exc}",
            hint="check PIPESCAN_SMTP_HOST, PIPESCAN_SMTP_PORT and PIPESCAN_SMTP_SECURITY",
        ) from exc
    if refused:
        raise DeliveryError(
            f"the {where} refused {', '.join(sorted(refused))}",
            hint="check those addresses in the recipients file",
        )


def deliver_report(
    pdf_path: Path,
    *,
    name: str,
    location: str | None,
    recipients: Sequence[str] = (),
    smtp: SmtpConfig | None = None,
    subject: str = "",
    body: str = "",
) -> Delivery:
    """Write a report to the reports location and e-mail it, as configured.

    Parameters
    ----------
    pdf_path
        The rendered PDF.
    name
        Its file name (or relative path) at the location and in the e-mail.
    location
        Reports location (directory or fsspec URL); None to skip writing.
    recipients
        Addresses to e-mail; empty to skip e-mail.
    smtp
        SMTP settings; required when there are recipients.
    subject, body
        The e-mail's subject and text.

    Raises
    ------
    DeliveryError
        Writing or e-mailing failed, or there are recipients but no SMTP server.
    """
    written = write_to_location(pdf_path, location, name) if location else None
    emailed: tuple[str, ...] = ()
    if recipients:
        if smtp is None:
            raise DeliveryError(
                f"the report should be e-mailed to {', '.join(recipients)} but no SMTP server "
                "is configured",
                hint="set PIPESCAN_SMTP_HOST (and PIPESCAN_SMTP_PORT), or remove the recipients",
            )
        send_report_email(pdf_path, recipients, smtp, subject=subject, body=body)
        emailed = tuple(recipients)
    return Delivery(written_to=written, emailed_to=emailed)


# Retried: both steps are network I/O.
deliver_report_task = task(name="deliver-report", **IO_RETRY_OPTIONS)(deliver_report)
"""`deliver_report` as a Prefect task."""
