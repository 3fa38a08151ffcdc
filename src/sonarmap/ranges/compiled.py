"""Whether numba has compiled sonarmap's kernels yet (a first run compiles them, then caches them).

numba compiles a kernel on its first call and caches the machine code (``cache=True``) beside the
sources, or in its user cache directory when that is not writable, so only the first run on a
machine pays for it: minutes on a 2-core machine for the whole per-ping pipeline.  The command
line tells an interactive user so when it starts processing with the cache empty
(:func:`sonarmap.cli._common.first_run_notice`), instead of leaving them at a bar that does not
move.
"""

from __future__ import annotations

__all__ = ["kernels_cached"]


def kernels_cached() -> bool:
    """True when numba's cache holds a valid index for the range stage's main kernel (the last of
    the per-ping pipeline to compile); False when it has none, or one for other sources.

    Reads numba's cache locator and index through attributes that are not public API; any failure
    to read them answers True (no notice rather than a wrong one).

    Examples
    --------
    >>> isinstance(kernels_cached(), bool)
    True
    """
    try:
        from numba.core.caching import FunctionCache

        import sonarmap.ranges._kernels as _kernels  # (its own package's private module)

        index = FunctionCache(_kernels.pooled_kept_edges.py_func)._cache_file._load_index()
        return bool(index)
    except Exception:  # noqa: BLE001 - a private API: never let it break a command
        return True
