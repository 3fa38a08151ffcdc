"""One compilation per kernel across processes that share a numba cache.

numba compiles a kernel the first time a process calls it with new argument types and, with
``cache=True`` (every sonarmap kernel), writes the result to its cache; a process that finds it
there loads it in milliseconds instead of compiling for ~0.5 s.  Processes started together on an
empty cache (the workers of a parallel test run, of a batch run) all miss it and each compile the
same kernels at the same time: the CPU time of the compilation is multiplied by the number of
processes, and none of them finishes sooner.

:func:`install` makes the processes take turns per kernel and signature: a process about to
compile takes an exclusive lock on a file named after the kernel and signature (in ``lock_dir``),
and under it looks at the cache again - when another process compiled the kernel meanwhile, it
loads it.  Kernels that are not cached (numba's own overloads) compile as before.  Locks are
``fcntl.flock`` locks, released by the operating system when a process dies.  The call graph of
the kernels has no cycles, so processes that hold one lock and wait for another cannot deadlock;
a wait longer than ``max_wait_s`` compiles anyway (never slower than numba alone, only wasteful).

Set ``SONARMAP_JIT_LOCK_DIR`` to a directory to install it when :mod:`sonarmap` is imported (the
test suite does, for its workers and the command-line processes they start).
"""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path
from typing import Any

_installed: list[Path] = []


def install(lock_dir: str | os.PathLike[str], max_wait_s: float = 600.0) -> bool:
    """Make numba's cached compilations take turns across processes (idempotent).

    Parameters
    ----------
    lock_dir : path-like
        Directory for the lock files (created); the same for every cooperating process.
    max_wait_s : float
        Longest wait for another process's compilation before compiling anyway.

    Returns
    -------
    bool
        Whether the hook is installed (``False`` where ``fcntl`` is missing, e.g. Windows).
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        return False
    if _installed:
        return True
    from numba.core.caching import NullCache
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.dispatcher import Dispatcher
    from numba.core import sigutils

    path = Path(lock_dir)
    path.mkdir(parents=True, exist_ok=True)
    original = Dispatcher.compile

    def compile(self: Any, sig: Any) -> Any:
        if isinstance(getattr(self, "_cache", None), NullCache):
            return original(self, sig)
        # under numba's own (process-wide, re-entrant) compiler lock: a thread of this process
        # never waits for a file lock while another of its threads holds the compiler lock
        with global_compiler_lock:
            args, return_type = sigutils.normalize_signature(sig)
            if tuple(args) in self.overloads:
                return original(self, sig)
            with open(lock_file(path, self.py_func, args, return_type), "a+b") as fh:
                deadline = time.monotonic() + max_wait_s
                locked = False
                while True:
                    try:
                        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        locked = True
                        break
                    except BlockingIOError:
                        if time.monotonic() > deadline:
                            break
                        time.sleep(0.02)
                try:
                    # looks at the disk cache first: loads what another process just compiled
                    return original(self, sig)
                finally:
                    if locked:
                        fcntl.flock(fh, fcntl.LOCK_UN)

    Dispatcher.compile = compile  # type: ignore[method-assign]
    _installed.append(path)
    return True


def lock_file(lock_dir: Path, py_func: Any, args: Any, return_type: Any) -> Path:
    """The lock file of a kernel (its Python function) compiled for ``args`` (numba types)."""
    key = f"{py_func.__module__}.{py_func.__qualname__}:{py_func.__code__.co_firstlineno}:{tuple(args)}->{return_type}"
    return Path(lock_dir) / (hashlib.sha1(key.encode()).hexdigest()[:20] + ".lock")


def install_from_environment() -> None:
    """:func:`install` into ``$SONARMAP_JIT_LOCK_DIR`` when it is set."""
    lock_dir = os.environ.get("SONARMAP_JIT_LOCK_DIR")
    if lock_dir:
        install(lock_dir)
