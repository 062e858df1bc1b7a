"""Per-inspection PDF condition reports: context, charts, Jinja2 templates, WeasyPrint.

Imports only the pure core (and Jinja2, WeasyPrint, matplotlib); the caller gathers a
:class:`ReportInput` from the database.
"""

from pipescan.reports.context import ReportInput, TableCitation, build_context
from pipescan.reports.render import render_html, render_pdf

__all__ = ["ReportInput", "TableCitation", "build_context", "render_html", "render_pdf"]
