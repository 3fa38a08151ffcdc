"""Processes sharing a numba cache compile a kernel once between them (sonarmap._jitlock)."""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

from numba import types

from sonarmap import _jitlock

KERNEL = textwrap.dedent("""
    from numba import njit

    @njit(cache=True)
    def plus_one(x):
        return x + 1
""")

CHILD = textwrap.dedent("""
    import time
    t = time.monotonic()
    import sonarmap  # installs the hook from SONARMAP_JIT_LOCK_DIR
    import kernel_mod
    assert kernel_mod.plus_one(41) == 42
    s = kernel_mod.plus_one.stats
    print(sum(s.cache_hits.values()), sum(s.cache_misses.values()), round(time.monotonic() - t, 3))
""")


def test_a_process_waits_for_the_kernel_another_compiles_and_loads_it(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    (src / "kernel_mod.py").write_text(KERNEL)
    locks = tmp_path / "locks"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), SONARMAP_JIT_LOCK_DIR=str(locks),
               PYTHONPATH=os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")]))
    sys.path.insert(0, str(src))
    try:
        import kernel_mod  # noqa: PLC0415 - the module written above
    finally:
        sys.path.remove(str(src))
    locks.mkdir()
    lock = _jitlock.lock_file(locks, kernel_mod.plus_one.py_func, (types.int64,), None)
    # this process holds the kernel's lock, as a process compiling it would
    with open(lock, "a+b") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        child = subprocess.Popen([sys.executable, "-c", CHILD], env=env, stdout=subprocess.PIPE, text=True)
        time.sleep(3.0)
        assert child.poll() is None  # waiting for the lock, not compiling
        # compile into the shared cache (numba reads NUMBA_CACHE_DIR once: write it from a process)
        subprocess.run([sys.executable, "-c", "import kernel_mod; kernel_mod.plus_one(1)"], env=dict(
            env, SONARMAP_JIT_LOCK_DIR=""), check=True)
        fcntl.flock(fh, fcntl.LOCK_UN)
    out, _ = child.communicate(timeout=120)
    hits, misses, seconds = out.split()
    assert (int(hits), int(misses)) == (1, 0)  # loaded what the other process compiled
    assert float(seconds) >= 3.0


def test_without_the_lock_directory_nothing_is_installed(tmp_path: Path) -> None:
    code = "import sonarmap, numba.core.dispatcher as d; print(d.Dispatcher.compile.__module__)"
    env = dict(os.environ, SONARMAP_JIT_LOCK_DIR="")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "numba.core.dispatcher"
