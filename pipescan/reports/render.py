"""Render reports: Jinja2 to HTML, WeasyPrint to PDF (per inspection, and network summary)."""

from __future__ import annotations

import contextlib
import os
import secrets
from functools import cache
from pathlib import Path
from urllib.parse import urlsplit
from urllib.request import url2pathname

from jinja2 import Environment, PackageLoader, StrictUndefined

from pipescan.core.errors import OutputError
from pipescan.reports.context import ReportInput, build_context
from pipescan.reports.network import NetworkInput, build_network_context

__all__ = [
    "NETWORK_TEMPLATE",
    "TEMPLATE",
    "render_html",
    "render_network_html",
    "render_network_pdf",
    "render_pdf",
]

TEMPLATE = "inspection.html.j2"
NETWORK_TEMPLATE = "network.html.j2"
ASSETS_DIR = (Path(__file__).parent / "templates").resolve()
"""The package's own report assets: the only files a report may load."""


@cache
def _url_fetcher():
    """WeasyPrint's fetcher, restricted to ``data:`` URLs and files in :data:`ASSETS_DIR`.

    Reports embed their charts as data URIs and need nothing else. Text from an archive is
    escaped by Jinja2, but should a URL still reach the HTML, it cannot make the renderer
    read a local file (``file:///etc/...``) into a PDF that is e-mailed out, nor reach the
    network (``http:``, ``ftp:``). A refused resource is left out, with WeasyPrint's warning.
    """
    from weasyprint.urls import URLFetcher

    class PackageAssetsFetcher(URLFetcher):
        def __init__(self) -> None:
            super().__init__(allowed_protocols={"data", "file"}, allow_redirects=False)

        def fetch(self, url, headers=None):
            if url.lower().startswith("file:"):
                path = Path(url2pathname(urlsplit(url).path)).resolve()
                if not path.is_relative_to(ASSETS_DIR):
                    raise ValueError(f"reports load no file outside their own assets: {url}")
            return super().fetch(url, headers)

    return PackageAssetsFetcher()


@cache
def _environment() -> Environment:
    # Autoescape everything: asset ids and node names come from files users hand us.
    # StrictUndefined turns a misspelt template variable into an error, not a blank cell.
    return Environment(
        loader=PackageLoader("pipescan.reports", "templates"),
        autoescape=True,
        undefined=StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )


def render_html(inp: ReportInput) -> str:
    """The report as one self-contained HTML document (CSS inline, chart as an SVG data URI).

    Parameters
    ----------
    inp
        The report's inputs.

    Returns
    -------
    str
        HTML5 text, viewable in a browser and the input of :func:`render_pdf`.
    """
    return _environment().get_template(TEMPLATE).render(**build_context(inp))


def render_network_html(inp: NetworkInput) -> str:
    """The network summary as one self-contained HTML document."""
    return _environment().get_template(NETWORK_TEMPLATE).render(**build_network_context(inp))


def render_pdf(inp: ReportInput, out_path: Path | str) -> Path:
    """Render the report to an A4 PDF at ``out_path``.

    The PDF is written to a temporary file next to ``out_path`` and renamed into place, so a
    crash or an interrupted run never leaves a truncated PDF under the final name.

    Parameters
    ----------
    inp
        The report's inputs.
    out_path
        Where to write the PDF; its folder is created if needed. An existing file is replaced.

    Returns
    -------
    Path
        ``out_path``.
    """
    return _write_pdf(render_html(inp), Path(out_path))


def render_network_pdf(inp: NetworkInput, out_path: Path | str) -> Path:
    """Render the network summary to an A4 landscape PDF at ``out_path`` (written atomically,
    as :func:`render_pdf`)."""
    return _write_pdf(render_network_html(inp), Path(out_path))


def check_report_path(out_path: Path | str) -> None:
    """:func:`check_output_path` for a PDF report."""
    check_output_path(out_path, "report", "PDF")


def check_output_path(out_path: Path | str, what: str, kind: str) -> None:
    """Refuse, before any work, an output path that cannot be written: one that names a
    folder, or whose nearest existing folder is not a folder or not writable (the folders
    below it would be created). Nothing is created here. ``what`` and ``kind`` name the
    output in the message ("report", "PDF").

    Raises
    ------
    OutputError
        Naming the path and what is wrong.
    """
    path = Path(out_path)
    reason = None
    if path.is_dir():
        reason = "it is a folder"
    else:
        existing = path.parent.absolute()
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        if not existing.is_dir():
            reason = f"{existing} is not a folder"
        elif not os.access(existing, os.W_OK | os.X_OK):
            reason = f"no permission to write in {existing}"
    if reason:
        raise OutputError(
            f"cannot write the {what}: {reason}",
            file=str(path),
            hint=f"give the path of a {kind} file in a folder you can write to",
        )


def _write_pdf(html: str, out_path: Path) -> Path:
    check_report_path(out_path)  # a folder, or a file on the way: said as before a run
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = _create_part_file(out_path)
    except OSError as exc:
        raise OutputError(
            f"cannot write the report: {exc.strerror or exc}",
            file=str(out_path),
            hint="give the path of a PDF file in a folder you can write to",
        ) from exc
    try:
        with os.fdopen(fd, "wb") as tmp:
            _layout(html).write_pdf(tmp)
            tmp.flush()
            os.fsync(tmp.fileno())
        os.replace(tmp_name, out_path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        if isinstance(exc, OSError):  # a full disk, a folder removed meanwhile
            raise OutputError(
                f"cannot write the report: {exc.strerror or exc}",
                file=str(out_path),
                hint="nothing was written under that name",
            ) from exc
        raise
    return out_path


MIN_TAIL_ROWS = 10
"""A long table (rows marked ``data-row``) leaves at least this many rows for its last page:
a page holding only a table's last few rows reads as a mistake."""


def _layout(html: str):
    """The laid-out document; a long table whose last page would hold fewer than
    :data:`MIN_TAIL_ROWS` rows is laid out again, with a page break before the row that
    leaves that many for the last page (the page before ends a little early instead)."""
    from weasyprint import HTML

    def lay_out(text: str):
        return HTML(
            string=text, base_url=ASSETS_DIR.as_uri() + "/", url_fetcher=_url_fetcher()
        ).render()

    document = lay_out(html)
    move = _row_to_break_before(document)
    if move is None:
        return document
    return lay_out(
        html.replace(f'data-row="{move}"', f'data-row="{move}" style="break-before: page"', 1)
    )


def _row_to_break_before(document) -> int | None:
    """The row to start a page with so that the long table's last page holds
    :data:`MIN_TAIL_ROWS` rows; None when it already does, or the table is too short to
    move rows without leaving the page before with fewer."""
    pages: list[list[int]] = []
    for page in document.pages:
        rows = [
            int(box.element.get("data-row"))
            for box in page._page_box.descendants()
            if type(box).__name__ == "TableRowBox"
            and getattr(box, "element", None) is not None
            and box.element.get("data-row") is not None
        ]
        pages.append(rows)
    with_rows = [rows for rows in pages if rows]
    if len(with_rows) < 2 or pages[-1] != with_rows[-1]:
        return None  # the table is on one page, or something follows it
    last, before = with_rows[-1], with_rows[-2]
    if len(last) >= MIN_TAIL_ROWS:
        return None
    first = max(last) - MIN_TAIL_ROWS + 1
    if first not in before or first - min(before) < MIN_TAIL_ROWS:
        return None
    return first


def _create_part_file(out_path: Path) -> tuple[int, str]:
    """A new, uniquely named file beside ``out_path`` with the mode any file the user writes
    gets (0666 less the umask), not ``mkstemp``'s 0600: a report is shared like a CSV."""
    for _ in range(100):
        name = str(out_path.parent / f".{out_path.name}.{secrets.token_hex(4)}.part")
        try:
            return os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), name
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {out_path}")  # pragma: no cover
