"""Cleaning up after runs that were killed: stale scratch directories and the Prefect API
server a killed run had started.

A run killed with ``kill -9`` leaves its scratch directory, and, when it ran on Prefect's
ephemeral API, the API server process that Prefect started for it (a child of the run's
process, which outlives it). The next run sweeps both, safely: only directories that carry
pipescan's run marker, and only server processes that the marker recorded, checked again by
id, start time and command line before they are stopped.

A run killed before its scratch directory exists (the first 10-20 s, while the server starts)
has no marker. So :func:`guard_ephemeral_server`, run when ``pipescan.flows`` is imported,
also makes the server stop with the process that started it (``PR_SET_PDEATHSIG``, set in the
server's process between fork and exec) and tags it with its owner
(:data:`OWNER_ENV` in its environment), so that the next run finds and stops a server whose
owner is gone even when no marker recorded it.
"""

from __future__ import annotations

import ctypes
import importlib.abc
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import psutil

from pipescan.storage.scratch import ProcessRef, create_run_dir, sweep_stale_runs

log = logging.getLogger("pipescan")

PREFECT_SERVER_APP = "prefect.server.api.server:create_app"
"""What the command line of the API server Prefect starts for an ephemeral run holds."""

_STOP_TIMEOUT_S = 5.0
OWNER_ENV = "PIPESCAN_PREFECT_SERVER_OWNER"
"""Environment variable naming, in a Prefect API server's environment, the process that
started it: ``"<pid> <start time>"``."""
_SERVER_MODULE = "prefect.server.api.server"
_PR_SET_PDEATHSIG = 1
_guarded = False
_guard_lock = threading.Lock()


def _is_prefect_server(proc: psutil.Process) -> bool:
    try:
        return PREFECT_SERVER_APP in proc.cmdline()
    except psutil.Error:
        return False


def prefect_servers_started_here() -> list[ProcessRef]:
    """The Prefect API servers this process started (its children running one)."""
    try:
        children = psutil.Process(os.getpid()).children()
    except psutil.Error:
        return []
    refs = []
    for child in children:
        if _is_prefect_server(child):
            try:
                refs.append(ProcessRef(child.pid, child.create_time()))
            except psutil.Error:
                continue
    return refs


def stop_orphaned_server(ref: ProcessRef) -> bool:
    """Stop a Prefect API server that a killed run had started; True if one was stopped.

    The process must still be that very process (id and start time) and still run a Prefect
    server; anything else is left alone.
    """
    if not ref.is_running():
        return False
    try:
        proc = psutil.Process(ref.pid)
        if not _is_prefect_server(proc):
            return False
        proc.terminate()
        try:
            proc.wait(_STOP_TIMEOUT_S)
        except psutil.TimeoutExpired:
            proc.kill()
            proc.wait(_STOP_TIMEOUT_S)
    except psutil.Error:
        return False
    log.info("stopped the Prefect API server (process %d) of a run that was killed", ref.pid)
    return True


def start_run_dir(work_dir: Path) -> Path:
    """Sweep what killed runs left in ``work_dir``, then create this run's scratch
    directory, recording the Prefect API server this process started (if any)."""
    swept = sweep_stale_runs(work_dir)
    for orphan in swept.orphans:
        stop_orphaned_server(orphan)
    return create_run_dir(work_dir, helpers=prefect_servers_started_here())


def _owner_of(proc: psutil.Process) -> ProcessRef | None:
    try:
        pid, started = proc.environ()[OWNER_ENV].split()
        return ProcessRef(int(pid), float(started))
    except (psutil.Error, KeyError, ValueError):
        return None  # not tagged by pipescan, or another user's


def stop_untracked_servers() -> int:
    """Stop the Prefect API servers tagged with an owner that no longer runs (a run killed
    before its marker recorded its server); return how many were stopped."""
    stopped = 0
    for proc in psutil.process_iter():
        if not _is_prefect_server(proc):
            continue
        owner = _owner_of(proc)
        if owner is None or owner.is_running():
            continue
        try:
            ref = ProcessRef(proc.pid, proc.create_time())
        except psutil.Error:
            continue
        stopped += stop_orphaned_server(ref)
    return stopped


def _die_with_parent(parent: int) -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGTERM when the thread that forked it ends (here the
    main thread: when the process ends, by a kill too); it ends at once if the parent already
    has."""

    def preexec() -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        if os.getppid() != parent:
            os._exit(1)

    return preexec


class _ServerPopen:
    """What Prefect's server module uses of ``subprocess``, with the API server started to die
    with its parent (when started from the main thread: PR_SET_PDEATHSIG follows the thread)."""

    def __init__(self, subprocess_module) -> None:
        self._subprocess = subprocess_module

    def __getattr__(self, name: str):
        return getattr(self._subprocess, name)

    def Popen(self, args, *rest, **kwargs):
        server = any(PREFECT_SERVER_APP in str(a) for a in args)
        if (
            server
            and sys.platform == "linux"
            and threading.current_thread() is threading.main_thread()
        ):
            kwargs.setdefault("preexec_fn", _die_with_parent(os.getpid()))
        return self._subprocess.Popen(args, *rest, **kwargs)


def _patch_server_module(module) -> None:
    if not isinstance(module.subprocess, _ServerPopen):
        module.subprocess = _ServerPopen(module.subprocess)


class _AfterImport(importlib.abc.MetaPathFinder):
    """Patches Prefect's server module when it is first imported (it takes seconds to import,
    and a run on a real API server never needs it)."""

    def find_spec(self, fullname, path, target=None):
        if fullname != _SERVER_MODULE:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None and spec.loader is not None:
                exec_module = spec.loader.exec_module

                def exec_and_patch(module, exec_module=exec_module) -> None:
                    exec_module(module)
                    _patch_server_module(module)

                spec.loader.exec_module = exec_and_patch  # type: ignore[method-assign]
                return spec
        return None


def guard_ephemeral_server() -> None:
    """Once per process: tag the Prefect API server this process may start with its owner,
    make it stop when this process ends, and stop the tagged servers whose owner is gone."""
    global _guarded
    with _guard_lock:
        if _guarded:
            return
        _guarded = True
    me = ProcessRef.of(os.getpid())
    os.environ[OWNER_ENV] = f"{me.pid} {me.started!r}"
    if _SERVER_MODULE in sys.modules:
        _patch_server_module(sys.modules[_SERVER_MODULE])
    else:
        sys.meta_path.insert(0, _AfterImport())
    stop_untracked_servers()
