"""PDF condition reports: per inspection and per network run. Context, charts, Jinja2
templates, WeasyPrint.

Imports only the pure core (and Jinja2, WeasyPrint, matplotlib, shapely); the caller gathers
a :class:`ReportInput` (or a :class:`NetworkInput`) from the database.
"""

from pipescan.reports.context import EarlierInspection, ReportInput, TableCitation, build_context
from pipescan.reports.network import NetworkInput, PipeInspection, build_network_context
from pipescan.reports.render import (
    render_html,
    render_network_html,
    render_network_pdf,
    render_pdf,
)

__all__ = [
    "EarlierInspection",
    "NetworkInput",
    "PipeInspection",
    "ReportInput",
    "TableCitation",
    "build_context",
    "build_network_context",
    "render_html",
    "render_network_html",
    "render_network_pdf",
    "render_pdf",
]
