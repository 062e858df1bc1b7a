"""Moved to :mod:`pipescan.storage.input.readers.bags`. This name stays only while
``pipescan/tasks/staged.py`` (being rewritten) still imports ``BagIndex`` from here; remove it
once that import reads ``from pipescan.storage.input.readers.bags import BagIndex``."""

from pipescan.storage.input.readers.bags import BagIndex

__all__ = ["BagIndex"]
