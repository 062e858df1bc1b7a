"""Small rules for how figures and counts read, shared by the CLI and the reports."""

from __future__ import annotations

import math

__all__ = ["plural", "signed"]


def plural(count: int, noun: str, plural_form: str | None = None) -> str:
    """A count with its noun in the right number.

    >>> plural(1, "defect"), plural(2, "defect"), plural(0, "inspection")
    ('1 defect', '2 defects', '0 inspections')
    >>> plural(3, "archive was", "archives were")
    '3 archives were'
    """
    return f"{count} {noun if count == 1 else (plural_form or noun + 's')}"


def signed(value: float, digits: int = 1) -> str:
    """A signed figure (``+1.2``, ``-0.4``) that never reads ``-0.0`` or ``+0.0``: a value that
    rounds to zero is ``0.0``.

    >>> signed(0.123, 2), signed(-0.0004, 2), signed(-1.0)
    ('+0.12', '0.00', '-1.0')
    """
    if not math.isfinite(value):
        return "-"
    text = f"{value:+.{digits}f}"
    return text[1:] if float(text) == 0.0 else text
