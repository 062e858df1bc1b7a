"""Reading a ``.npy`` header safely from several threads at once.

NumPy parses a ``.npy`` header with :func:`ast.literal_eval`. On CPython before 3.11.8 two
threads doing that at the same moment can fail with ``SystemError: AST constructor recursion
depth mismatch`` (CPython issue gh-106905). pipescan reads frames and scratch files from
several threads of one process, so every header is parsed here, under one lock; the data
that follows is read without it.
"""

from __future__ import annotations

import threading
from typing import BinaryIO

import numpy as np

__all__ = ["read_npy_header"]

_AST_LOCK = threading.Lock()


def read_npy_header(fh: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Shape, Fortran order and dtype of the ``.npy`` file open at its start; ``fh`` is left
    at the first byte of the data.

    Raises
    ------
    ValueError
        Not a ``.npy`` file, or a version NumPy does not know.
    """
    fmt = np.lib.format
    version = fmt.read_magic(fh)
    with _AST_LOCK:
        if version == (1, 0):
            return fmt.read_array_header_1_0(fh)
        if version in ((2, 0), (3, 0)):
            return fmt.read_array_header_2_0(fh)
    raise ValueError(f"unknown .npy version {version}")
