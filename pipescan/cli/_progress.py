"""A run's long stages as progress bars on a terminal: frames registered out of the total,
windows measured out of the total.

The flow and its tasks say where they are in their log lines (``registering 89 of 265 frames in
2 chunks``, ``registered frames 0-132 of 265``, ``axis fitted; ... in 3 windows``, ``measured
0.4-2.4 m``); on a terminal these become two bars and the other lines print above them. Piped
or redirected, the lines stay lines (a log file wants them). Tasks that run in other processes
(``PIPESCAN_TASK_RUNNER=processes``) log there, and the bars then stand still: the lines Prefect
forwards are shown with ``--verbose``.
"""

from __future__ import annotations

import contextlib
import logging
import re
import sys
from collections.abc import Iterator

_REGISTERING = re.compile(r"registering (\d+) of (\d+) frames in \d+ chunks?")
_REGISTERED_CHUNK = re.compile(r"registered frames (\d+)-(\d+) of (\d+)")
_REGISTERED = re.compile(r"registered \d+ of (\d+) frames")
_WINDOWS = re.compile(r"axis fitted; .* in (\d+) windows?")
_MEASURED = re.compile(r"measured -?\d+(\.\d+)?--?\d+(\.\d+)? m \(")
_MEASURED_AGAIN = re.compile(r"window at .* measured again")


class ProgressHandler(logging.Handler):
    """Turns the stage lines of a run into rich progress bars; prints every other line."""

    def __init__(self, console, formatter: logging.Formatter) -> None:
        super().__init__()
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self.setFormatter(formatter)
        self.progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
        )
        self._frames = None
        self._frames_done = 0
        self._windows = None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if not self._stage(record.getMessage()):
                self.progress.console.print(self.format(record), markup=False, highlight=False)
        except Exception:  # a progress bar never stops a run
            self.handleError(record)

    def _stage(self, message: str) -> bool:
        """Update the bars from a stage line; True when the line is shown by a bar."""
        p = self.progress
        if m := _REGISTERING.fullmatch(message):
            total = int(m.group(2))
            self._frames = p.add_task("frames registered", total=total)
            return False  # says the stride: worth its line
        if (m := _REGISTERED_CHUNK.match(message)) and self._frames is not None:
            first, last = int(m.group(1)), int(m.group(2))
            # Chunks share their end frames: the first frame counts once, with whichever comes.
            self._frames_done += last - first + (1 if self._frames_done == 0 else 0)
            p.update(self._frames, completed=self._frames_done)
            return True
        if (m := _REGISTERED.match(message)) and self._frames is not None:
            p.update(self._frames, completed=int(m.group(1)))
            return False
        if m := _WINDOWS.match(message):
            self._windows = p.add_task("windows measured", total=int(m.group(1)))
            return False
        if _MEASURED.match(message) and self._windows is not None:
            p.advance(self._windows)
            return True
        if _MEASURED_AGAIN.match(message) and self._windows is not None:
            task = p.tasks[self._windows]
            p.update(self._windows, total=(task.total or 0) + 1)
            return False
        return False


def on_a_terminal() -> bool:
    """Bars only where a person watches: stderr is a terminal and not a dumb one."""
    import os

    return sys.stderr.isatty() and os.environ.get("TERM", "") != "dumb"


@contextlib.contextmanager
def run_progress(logger: logging.Logger) -> Iterator[None]:
    """Show the run's stages as progress bars while the block runs, on a terminal; elsewhere
    do nothing. The logger's own stderr handler is set aside meanwhile (so that a line is
    printed once) and put back after."""
    if not on_a_terminal():
        yield
        return
    from rich.console import Console

    from pipescan.cli._app import _StderrHandler

    mine = [h for h in logger.handlers if isinstance(h, _StderrHandler)]
    formatter = mine[0].formatter if mine else logging.Formatter("%(message)s")
    handler = ProgressHandler(Console(stderr=True), formatter or logging.Formatter())
    for h in mine:
        logger.removeHandler(h)
    logger.addHandler(handler)
    try:
        with handler.progress:
            yield
    finally:
        logger.removeHandler(handler)
        for h in mine:
            logger.addHandler(h)
