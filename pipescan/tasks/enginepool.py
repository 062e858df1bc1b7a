"""Lean worker processes for the native engines that hold the GIL.

small_gicp holds the GIL for the whole of each call, and so does LAZ decoding: on the flow's
thread pool two chunks never register at the same time, whatever the number of threads. The
register-chunk task therefore hands its chunk to one of these processes and waits for the
result, while the rest of the flow stays on threads (and in one process's memory). The
measure-window task does the same with its window: measuring is NumPy in many small steps,
holding the GIL between them.

The workers import only what registering needs (NumPy, SciPy, Open3D, small_gicp and the
archive readers; not Prefect nor the database): about 2 s and 160 MB each, paid once per
process, since the pool is kept for every later flow run of the process (a network run
inspects many archives). :func:`prestart` starts them while the archive is staged, or
earlier: ``pipescan inspect`` starts them before Prefect's API, whose start-up they overlap.

A worker that dies (killed, out of memory) breaks the pool; the next call starts a new one,
and a chunk whose worker died is tried once more there. A worker whose parent is gone exits
within a second: it never outlives a killed run.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context, resource_tracker
from typing import Any, TypeVar

T = TypeVar("T")

_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_size = 0
_unused = False
"""Whether the pool was started ahead of knowing it is needed, and has run nothing yet."""


def _exit_with_parent(parent: int) -> None:
    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(0)


@contextlib.contextmanager
def _spawning_without_sigint() -> Iterator[None]:
    """Processes started in this block (``submit`` starts them, in the calling thread) begin
    with SIGINT blocked, which they inherit from this thread: a Ctrl-C while one is still
    starting (importing) would otherwise print its traceback. The parent handles Ctrl-C."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _submit(pool: ProcessPoolExecutor, fn: Callable[..., T], *args: Any) -> Future[T]:
    with _spawning_without_sigint():
        return pool.submit(fn, *args)


def _start_worker(parent: int) -> None:
    # Ctrl-C is the parent's to handle: it stops the flow, and the pool with it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    import open3d  # noqa: F401  (imported here, once, instead of in the first chunk)
    import scipy.stats  # noqa: F401  (a section's ± reads Student's t: the first window)
    import small_gicp  # noqa: F401

    import pipescan.tasks.staged  # noqa: F401


def _import_for_registration() -> None:
    try:
        import open3d  # noqa: F401
        import scipy.stats  # noqa: F401
        import small_gicp  # noqa: F401
    except Exception:  # the first real use raises it, where it is understood
        pass


def import_here_ahead() -> threading.Thread:
    """Import, in this process too and in a background thread, what registering needs here:
    the engines, and SciPy's statistics. Choosing the frame stride, the first step after
    staging, voxelises a few frames here, and importing Open3D for it took 0.43 s between
    staging and the first chunk; chaining the chunks' trajectories sizes the unseen slips
    with ``scipy.stats``, whose import took 0.35 s of the 0.38 s between the last chunk and
    the axis fit. Started as staging opens an archive of frames, the imports overlap the
    hashing of its content instead (hashing releases the GIL). A second import of a module
    waits for this one, so nothing can see it half done."""
    thread = threading.Thread(
        target=_import_for_registration, name="pipescan-registration-imports", daemon=True
    )
    thread.start()
    return thread


def _ready() -> int:
    return os.getpid()


def _call_in(cwd: str, fn: Callable[..., T], *args: Any) -> T:
    # Relative paths (an archive given as ``inputs/scan``, a relative work directory) mean
    # what they mean in the caller's process.
    if os.getcwd() != cwd:
        os.chdir(cwd)
    return fn(*args)


def _start_quiet_tracker() -> None:
    # The pool's queues and locks are named semaphores that multiprocessing's resource
    # tracker (a helper process) removes if this process dies without doing so. When it
    # does (a second Ctrl-C stops pipescan at once), the tracker cleans up and then warns
    # about "leaked semaphore objects" on the user's terminal: keep it to the cleaning.
    saved = os.environ.get("PYTHONWARNINGS")
    quiet = "ignore::UserWarning:multiprocessing.resource_tracker"
    os.environ["PYTHONWARNINGS"] = f"{saved},{quiet}" if saved else quiet
    try:
        resource_tracker.ensure_running()
    finally:
        if saved is None:
            del os.environ["PYTHONWARNINGS"]
        else:
            os.environ["PYTHONWARNINGS"] = saved


def _get(workers: int) -> ProcessPoolExecutor:
    global _pool, _size
    with _lock:
        if _pool is None:
            _start_quiet_tracker()
            _pool = ProcessPoolExecutor(
                max_workers=workers,
                mp_context=get_context("spawn"),
                initializer=_start_worker,
                initargs=(os.getpid(),),
            )
            _size = workers
        return _pool


def _discard(broken: ProcessPoolExecutor) -> None:
    global _pool
    with _lock:
        if _pool is broken:
            _pool = None
    broken.shutdown(wait=False, cancel_futures=True)


def prestart(workers: int, *, ahead: bool = False) -> list[Future]:
    """Start the pool's ``workers`` processes now (they import the engines in the
    background); a pool already running is left as it is.

    ``ahead``: started before it is known whether anything will run on it (the command line
    starts it before Prefect's API, whose start-up the workers' imports then overlap);
    :func:`release_unused` stops it again if nothing did.
    """
    global _unused
    running = _pool is not None
    pool = _get(workers)
    if ahead and not running:
        _unused = True
    # Processes start on demand, one per job no idle worker can take.
    return [_submit(pool, _ready) for _ in range(workers)]


def run(workers: int, fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` in one of the pool's processes (``fn`` and its arguments must pickle);
    its exceptions are raised here. A pool broken by a dying worker is replaced, and the call
    tried once more."""
    global _unused
    _unused = False
    for attempt in (1, 2):
        pool = _get(workers)
        try:
            return _submit(pool, _call_in, os.getcwd(), fn, *args).result()
        except BrokenProcessPool:
            _discard(pool)
            if attempt == 2:
                raise RuntimeError(
                    "an engine worker process died twice on the same chunk (killed, or out "
                    "of memory); run with PIPESCAN_ENGINE_PROCESSES=0 to register in the "
                    "flow's own process"
                ) from None
    raise AssertionError("unreachable")


def pool_size() -> int:
    """The running pool's number of workers (0 when none runs)."""
    return _size if _pool is not None else 0


def release_unused() -> None:
    """Stop a pool started ahead (:func:`prestart`) on which nothing has run: the archive
    turned out to need none (a registered cloud), and its idle workers would hold their
    memory for the rest of the run."""
    if _unused:
        shutdown()


def shutdown() -> None:
    """Stop the pool's workers (the next call starts a new pool)."""
    global _pool, _unused
    with _lock:
        pool, _pool, _unused = _pool, None, False
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)
