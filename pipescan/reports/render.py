"""Render a per-inspection report: Jinja2 to HTML, WeasyPrint to PDF."""

from __future__ import annotations

import contextlib
import os
import tempfile
from functools import cache
from pathlib import Path

from jinja2 import Environment, PackageLoader, StrictUndefined

from pipescan.reports.context import ReportInput, build_context

__all__ = ["TEMPLATE", "render_html", "render_pdf"]

TEMPLATE = "inspection.html.j2"


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
    # WeasyPrint loads Pango at import; keep it out of HTML-only use.
    from weasyprint import HTML

    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    html = render_html(inp)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{out_path.name}.", suffix=".part", dir=out_path.parent
    )
    try:
        with os.fdopen(fd, "wb") as tmp:
            HTML(string=html, base_url=str(out_path.parent)).write_pdf(tmp)
            tmp.flush()
            os.fsync(tmp.fileno())
        os.replace(tmp_name, out_path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    return out_path
