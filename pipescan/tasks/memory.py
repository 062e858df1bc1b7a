"""Giving the memory a task freed back to the operating system.

glibc's allocator serves a freed block of up to 32 MB again from its heap instead of
returning it (its mmap threshold rises to the largest block freed so far). The section tasks
allocate and free arrays of every size up to that, and the holes they leave in the heap stay
resident, so the peak would grow with the pipe. Trimming after each bucketing and measuring
task keeps it flat (``docs/throughput.md``, *The design*, **Memory**; the measurements:
``docs/history/code-comments.md``). ``malloc_trim`` gives the free pages of every arena
back, in milliseconds, and changes no figure.
"""

from __future__ import annotations

import ctypes
import functools
import sys
from collections.abc import Callable
from typing import ParamSpec, TypeVar

P = ParamSpec("P")
R = TypeVar("R")


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, or None where the C library has none (macOS, musl)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    return getattr(libc, "malloc_trim", None)


def release_free_memory() -> bool:
    """Return the allocator's free pages to the operating system; True where it could."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def releases_memory(function: Callable[P, R]) -> Callable[P, R]:
    """Run ``function``, then :func:`release_free_memory` (also when it raises)."""

    @functools.wraps(function)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return function(*args, **kwargs)
        finally:
            release_free_memory()

    return wrapper
