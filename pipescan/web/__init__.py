"""The network in a browser: ``pipescan serve``'s web app (FastAPI, Jinja2 templates, inline
SVG), read-only on the pipescan database. See docs/web.md."""

from pipescan.web.app import WebConfig, create_app

__all__ = ["WebConfig", "create_app"]
