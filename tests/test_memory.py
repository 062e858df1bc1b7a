"""Tasks give the memory they freed back to the operating system (pipescan.tasks.memory)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from pipescan.tasks.memory import release_free_memory, releases_memory

# Holes in glibc's heap: after a 30 MB array is freed the mmap threshold rises to 30 MB, so
# the 8 MB arrays that follow come from the heap; each is followed by a small array that is
# kept, so that freeing the large ones leaves holes that free() cannot hand back.
_FRAGMENT = textwrap.dedent(
    """
    import os

    import numpy as np
    from pipescan.tasks.memory import release_free_memory

    def rss_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    big = np.ones(30 * 2**20 // 8)
    del big
    large, kept = [], []
    for k in range(40):
        large.append(np.ones((8 * 2**20 + 4096 * k) // 8))
        kept.append(np.ones(1000))
    del large
    before = rss_mb()
    trimmed = release_free_memory()
    print(trimmed, before, rss_mb())
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_freed_heap_memory_goes_back_to_the_system() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _FRAGMENT], capture_output=True, text=True, check=True
    ).stdout.split()
    trimmed, before, after = out[0] == "True", float(out[1]), float(out[2])
    assert trimmed
    # 40 arrays of 8 MB were freed into holes of the heap: without the trim they stay resident.
    assert before - after > 200, (before, after)


def test_a_task_wrapped_returns_its_value_and_raises_its_error() -> None:
    calls = []

    @releases_memory
    def task(x: int) -> int:
        calls.append(x)
        if x < 0:
            raise ValueError("negative")
        return 2 * x

    assert task(21) == 42
    with pytest.raises(ValueError, match="negative"):
        task(-1)
    assert calls == [21, -1]
    assert isinstance(release_free_memory(), bool)
