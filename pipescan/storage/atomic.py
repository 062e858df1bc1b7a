"""Output files written whole or not at all, through temporary files no one else can plant.

A temporary name beside the output that anyone can predict (``.report.csv.part``) can be
planted by another user of a shared folder: a symlink there is written through (the link's
target overwritten), a FIFO blocks the writer for ever. So a temporary file is created with
:func:`tempfile.mkstemp` in the output's folder (a random name, ``O_CREAT | O_EXCL |
O_NOFOLLOW``, mode 0600: it is new, it is ours, it is not a link), written through the file
descriptor that created it, and renamed onto the output, which replaces a link or a FIFO at
the output's name instead of following it. Writers that need a name rather than a file (GDAL,
which adds its own journal files) get one inside a new private folder
(:func:`tempfile.mkdtemp`, mode 0700). The output then gets the mode a plain ``open`` would
have given it (0666 less the umask).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_file", "atomic_path"]


def _umask() -> int:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _publish(tmp: Path, target: Path) -> None:
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, target)  # replaces a link or FIFO at ``target``; never writes through it


@contextmanager
def atomic_file(target: Path | str, mode: str = "wb", **open_kwargs: Any) -> Iterator[IO]:
    """A new file, opened with ``mode`` (``"wb"`` or ``"w"``), renamed onto ``target`` when the
    block ends without an error; removed otherwise. ``target``'s folder must exist.

    >>> import tempfile, pathlib
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "a.csv"
    >>> with atomic_file(out, "w", encoding="utf-8") as fh:
    ...     _ = fh.write("x\\n")
    >>> out.read_text()
    'x\\n'
    """
    target = Path(target)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as fh:
            yield fh
        _publish(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_path(target: Path | str) -> Iterator[Path]:
    """A path to write ``target``'s content to by name (it does not exist yet), inside a new
    private folder beside ``target``; renamed onto ``target`` when the block ends without an
    error. The folder is removed either way."""
    target = Path(target)
    folder = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent))
    try:
        tmp = folder / target.name
        yield tmp
        _publish(tmp, target)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
