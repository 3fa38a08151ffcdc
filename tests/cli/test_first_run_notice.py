"""The first-run notice: printed on an interactive stderr while numba's cache lacks the kernels."""

from __future__ import annotations

import io
import sys

import pytest

from sonarmap.cli import _common


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("tty,quiet,cached,printed", [
    (True, False, False, True),
    (True, True, False, False),   # --quiet: nothing
    (False, False, False, False),  # a log or pipe: nothing it did not ask for
    (True, False, True, False),   # compiled already
])
def test_notice_only_on_a_terminal_with_the_cache_empty(monkeypatch, tty, quiet, cached, printed):
    import sonarmap.ranges.compiled as jit

    err = _Tty() if tty else io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setattr(jit, "kernels_cached", lambda: cached)
    assert _common.first_run_notice(quiet) is printed
    assert (_common.FIRST_RUN_NOTICE in err.getvalue()) is printed


def test_the_cache_is_read_for_these_sources(monkeypatch, tmp_path):
    """An empty numba cache directory has no valid index: not cached; the real check never raises."""
    from numba.core.caching import FunctionCache

    import sonarmap.ranges.compiled as jit
    import sonarmap.ranges._kernels as k

    assert isinstance(jit.kernels_cached(), bool)
    cache = FunctionCache(k.pooled_kept_edges.py_func)._cache_file
    monkeypatch.setattr(type(cache), "_load_index", lambda self: {})
    assert jit.kernels_cached() is False
    monkeypatch.setattr(type(cache), "_load_index", lambda self: 1 / 0)
    assert jit.kernels_cached() is True  # a private API that fails: no notice rather than a wrong one
