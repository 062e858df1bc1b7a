"""A bound on how deep a TOML document nests, checked before ``tomllib`` parses it.

``tomllib`` recurses once per nested array or inline table (200,000 levels: a
``RecursionError``), and its time grows faster than the length of a table header's or key's
dotted parts (a header of 200,000 parts took minutes; 200,000 headers nesting one more level
each, longer). ``inspection.toml`` nests three levels at most (``[[frames]]``, ``[ros]``). So
the text is scanned once with a regular expression, strings and comments skipped as TOML reads
them, and refused at the first key, header or value nested more than :data:`TOML_MAX_DEPTH`
deep: the dotted parts of its key, plus the arrays and inline tables it is in.
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["TOML_MAX_DEPTH", "TomlTooDeep", "check_toml_depth"]

TOML_MAX_DEPTH = 32
"""Dotted key parts plus enclosing arrays and inline tables allowed, at most."""

_SKIPPED = (
    r'"""(?:\\[\s\S]|[^\\])*?"{3,5}'  # multi-line basic string (up to two quotes end it)
    r"|'''[\s\S]*?'{3,5}"  # multi-line literal string
    r'|"(?:\\.|[^"\\\n])*"'  # basic string
    r"|'[^'\n]*'"  # literal string
    r"|#[^\n]*"  # comment
)
_TOKENS = re.compile(_SKIPPED + r"|[\[\]{}=.,\n]")
_STRINGS = re.compile(_SKIPPED)


class TomlTooDeep(ValueError):
    """The document nests deeper than the bound; ``line`` is where it first does."""

    def __init__(self, depth: int, line: int) -> None:
        super().__init__(
            f"nests keys, tables or arrays more than {TOML_MAX_DEPTH} deep (line {line})"
        )
        self.depth, self.line = depth, line


_BLOCK = 1 << 22


def _upper_bound(text: str) -> int:
    """At least the depth :func:`check_toml_depth` finds, vectorised a block at a time: the
    deepest running count of brackets plus the most dots on a line, strings and comments left
    out (a genuine document of 50,000 frames is checked in a few tens of milliseconds)."""
    bare = np.frombuffer(_STRINGS.sub("", text).encode("utf-8", "replace"), dtype=np.uint8)
    nesting = most_dots = 0
    depth = line_dots = 0  # carried from one block to the next
    for at in range(0, len(bare), _BLOCK):
        block = bare[at : at + _BLOCK]
        step = np.isin(block, (91, 123)).astype(np.int32) - np.isin(block, (93, 125))  # [{ ]}
        running = np.cumsum(step, dtype=np.int64) + depth
        nesting = max(nesting, int(running.max()))
        depth = int(running[-1])
        dots = np.cumsum(block == 46, dtype=np.int64)  # "."
        newlines = np.flatnonzero(block == 10)
        ends = np.concatenate((dots[newlines], dots[-1:]))
        per_line = np.diff(np.concatenate(([0], ends)))
        per_line[0] += line_dots
        most_dots = max(most_dots, int(per_line.max()))
        line_dots = int(per_line[-1]) if not len(newlines) or newlines[-1] != len(block) - 1 else 0
    return nesting + most_dots + 1


def check_toml_depth(text: str, max_depth: int = TOML_MAX_DEPTH) -> None:
    """Refuse ``text`` (raise :class:`TomlTooDeep`) when a key, header or value nests deeper
    than ``max_depth``; a document that is not valid TOML is left for ``tomllib`` to refuse.
    Linear in the text's length.

    >>> check_toml_depth('[ros]\\npoints_topic = "/a.b"\\nx = [[1.5, 2], {a.b = 1}]')
    >>> try:
    ...     check_toml_depth("x = " + "[" * 40 + "]" * 40)
    ... except TomlTooDeep as exc:
    ...     print(exc)
    nests keys, tables or arrays more than 32 deep (line 1)
    """
    if _upper_bound(text) <= max_depth:
        return
    stack: list[str] = []  # the open arrays and inline tables of the current value
    in_key = True  # reading a key (or a table header), where dots nest
    in_header = False
    parts = 1  # dotted parts of the key being read
    line = 1
    for match in _TOKENS.finditer(text):
        token = match.group()
        if token[0] in "\"'#":
            line += token.count("\n")
            continue
        if token == "\n":
            line += 1
            if not stack:  # a new line at the top: a new key or header
                in_key, in_header, parts = True, False, 1
            continue
        if token == "." and (in_key or in_header):
            parts += 1
        elif token == "[":
            if not stack and in_key:  # a table header, [ or [[
                in_header = True
                continue
            stack.append("[")
        elif token == "{":
            stack.append("{")
            in_key, parts = True, 1
        elif token in "]}":
            if in_header and not stack:
                continue
            if stack:
                stack.pop()
        elif token == "=":
            in_key = False
        elif token == "," and stack and stack[-1] == "{":
            in_key, parts = True, 1
        depth = len(stack) + (parts if in_key or in_header else 0)
        if depth > max_depth:
            raise TomlTooDeep(depth, line)
