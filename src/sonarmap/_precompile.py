"""Compile the per-ping pipeline's numba kernels in several processes at once.

On an empty numba cache every process that runs the pipeline compiles the same kernels (about
three minutes of one core at numba's default optimisation level): the workers of ``sonarmap
process -j N`` (and of ``sonarmap demo``) did so side by side, each on its own core, so the first
run took as long with two workers as with one.  The kernels the pipeline's warm-up compiles are
listed, with their signatures, in ``_kernel_signatures.json`` beside this module, longest
compilation first.  Workers that find the cache cold share that list as a queue
(:func:`compile_queue`): each takes the next kernel not yet taken, compiles it (numba saves it in
the cache) and takes another, until the list is done; the warm-up that follows then loads from
the cache what the other workers compiled.  A single-process command (``sonarmap ranges``,
``segment``) shares the list the same way with helper processes it starts for the purpose
(:func:`compile_with_helpers`).  The results do not change: the same kernels at the same
signatures, compiled by numba as the pipeline would have compiled them.

The list is written by ``python -m sonarmap._precompile_record`` (what the warm-ups and a few
simulated pings compile in a fresh process; ``tests/test_precompile.py`` checks that it is
current).
"""

from __future__ import annotations

import functools
import importlib
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["SIGNATURES_FILE", "UnsupportedType", "encode_type", "decode_type", "load_signatures",
           "cache_is_cold", "compile_entry", "compile_queue", "take_next", "compile_shared", "compile_with_helpers",
           "entry_key",
           "resolve_kernel"]

#: The checked-in list of ``{"kernel": "module:qualname", "args": [...]}`` entries.
SIGNATURES_FILE = Path(__file__).with_name("_kernel_signatures.json")


class UnsupportedType(ValueError):
    """A numba type this module does not encode (its signature is left out of the list)."""


@functools.cache
def _scalars() -> dict[str, Any]:
    """The scalar numba types by name (``"float32"``, ``"int64"``, ``"bool"``, ``"none"``, ...)."""
    from numba.core import types

    return {str(t): t for t in (*types.number_domain, types.boolean, types.none)}


def encode_type(t: Any) -> Any:
    """A JSON-able description of the numba type ``t`` (:func:`decode_type` rebuilds it).

    Raises
    ------
    UnsupportedType
        For a type outside arrays, scalars, literals, omitted arguments, tuples and strings.
    """
    from numba.core import types

    if isinstance(t, types.Array):
        if type(t) is not types.Array:
            raise UnsupportedType(f"array subtype {type(t).__name__}")
        return ["array", encode_type(t.dtype), int(t.ndim), str(t.layout), bool(not t.mutable)]
    if isinstance(t, types.Literal):
        v = t.literal_value
        if isinstance(v, bool | int | float | str) or v is None:
            return ["literal", v]
        raise UnsupportedType(f"literal of {type(v).__name__}")
    if isinstance(t, types.Omitted):
        v = t.value
        if isinstance(v, bool | int | float | str) or v is None:
            return ["omitted", v]
        raise UnsupportedType(f"omitted {type(v).__name__}")
    if isinstance(t, types.UniTuple):
        return ["unituple", encode_type(t.dtype), int(t.count)]
    if isinstance(t, types.Tuple):
        return ["tuple", [encode_type(x) for x in t.types]]
    if t == types.unicode_type:
        return ["unicode"]
    name = str(t)
    if _scalars().get(name) == t:
        return ["scalar", name]
    raise UnsupportedType(f"type {t!r}")


def decode_type(d: Any) -> Any:
    """The numba type :func:`encode_type` described."""
    from numba.core import types

    kind = d[0]
    if kind == "array":
        return types.Array(decode_type(d[1]), int(d[2]), d[3], readonly=bool(d[4]))
    if kind == "literal":
        return types.literal(d[1])
    if kind == "omitted":
        return types.Omitted(d[1])
    if kind == "unituple":
        return types.UniTuple(decode_type(d[1]), int(d[2]))
    if kind == "tuple":
        return types.Tuple([decode_type(x) for x in d[1]])
    if kind == "unicode":
        return types.unicode_type
    if kind == "scalar":
        return _scalars()[d[1]]
    raise UnsupportedType(f"unknown kind {kind!r}")


def load_signatures(path: Path = SIGNATURES_FILE) -> list[dict[str, Any]]:
    """The checked-in list, longest compilation first (``[]`` when the file is missing or
    unreadable: precompiling is an optimisation, never a requirement)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        entries = [e for e in data["signatures"] if isinstance(e, dict) and isinstance(e.get("kernel"), str)
                   and isinstance(e.get("args"), list)]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    return sorted(entries, key=lambda e: -_seconds(e))


def _seconds(e: dict[str, Any]) -> float:
    v = e.get("seconds")
    return float(v) if isinstance(v, int | float) else 1.0


def resolve_kernel(kernel: str) -> Any:
    """The dispatcher an entry names (``"module:name"``; the module imported)."""
    mod_name, _, attr = kernel.partition(":")
    return getattr(importlib.import_module(mod_name), attr)


def cache_is_cold() -> bool:
    """Whether numba's cache holds no valid compilation of the pipeline yet
    (``not`` :func:`sonarmap.ranges.compiled.kernels_cached`; False when that cannot be told)."""
    from sonarmap.ranges.compiled import kernels_cached

    return not kernels_cached()


def compile_entry(entry: dict[str, Any]) -> bool:
    """Compile one listed signature (numba loads it from its cache when it is there); False when
    the kernel is unknown or its types do not build under this numba (the pipeline then compiles
    what it needs as usual)."""
    try:
        resolve_kernel(entry["kernel"]).compile(tuple(decode_type(a) for a in entry["args"]))
    except Exception:  # noqa: BLE001 - precompiling is an optimisation, never a requirement
        return False
    return True


def compile_queue(entries: Sequence[dict[str, Any]], take: Callable[[], int]) -> int:
    """Compile ``entries[take()]`` until ``take()`` passes the end: ``take`` hands out the indices
    ``0, 1, ...`` across the processes sharing the list (a counter under a lock).  The number of
    entries this process compiled."""
    done = 0
    while True:
        i = take()
        if not 0 <= i < len(entries):
            return done
        done += compile_entry(entries[i])


def take_next(counter: Any) -> int:
    """The next index of the queue ``counter`` (a ``multiprocessing.Value``) hands out."""
    with counter.get_lock():
        i = int(counter.value)
        counter.value = i + 1
    return i


def compile_shared(counter: Any, entries: Sequence[dict[str, Any]]) -> int | None:
    """Take part in a queue that processes share through ``counter`` (a ``multiprocessing.Value``,
    the next index; -1: not decided yet): the first process to take it decides whether the cache
    is cold (:func:`cache_is_cold`) and otherwise marks the queue done.  The number of entries this
    process compiled, None when the queue was done or not used (a warm cache, no list)."""
    with counter.get_lock():
        if counter.value < 0:
            counter.value = 0 if entries and cache_is_cold() else len(entries)
        if counter.value >= len(entries):
            return None
    return compile_queue(entries, lambda: take_next(counter))


def _helper(counter: Any, entries: list[dict[str, Any]]) -> None:  # pragma: no cover - runs in a helper process
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops its helpers
    compile_shared(counter, entries)  # (the parent decided: counter >= 0)


def compile_with_helpers(helpers: int | None = None, *,
                         progress: Callable[[float, float], None] | None = None) -> int:
    """On a cold cache, compile the list in this process and in ``helpers`` spawned helper
    processes at once (the queue the pool's workers share), and wait for them; the number of
    helpers started (0: the cache is warm, no list, no spare CPU, or ``SONARMAP_COMPILE_HELPERS=0``
    in the environment).

    ``helpers`` defaults to the CPUs beyond this process's, at most 3 (``SONARMAP_COMPILE_HELPERS``
    sets it).  ``progress(taken, total)``, when given, is called in this process each time it
    takes an entry: the recorded compile seconds of the entries every process took before it,
    and of all of them.  The command line calls this before a single-process run's first ping,
    with a progress bar; an interrupted run stops its helpers.  Never raises but for an
    interrupt: precompiling is an optimisation.
    """
    import multiprocessing

    if helpers is None:
        env = os.environ.get("SONARMAP_COMPILE_HELPERS", "")
        helpers = int(env) if env.isdigit() else min((os.cpu_count() or 1) - 1, 3)
    try:
        entries = load_signatures()
        if helpers < 1 or not entries or not cache_is_cold():
            return 0
        ctx = multiprocessing.get_context("spawn")
        counter = ctx.Value("i", 0)
        procs = [ctx.Process(target=_helper, args=(counter, entries), daemon=True, name="sonarmap-compile")
                 for _ in range(helpers)]
        for proc in procs:
            proc.start()
    except Exception:  # noqa: BLE001 - never fail a run for it
        return 0
    # the compile seconds of the entries before each one: the progress in (recorded) time
    before = [0.0]
    for e in entries:
        before.append(before[-1] + _seconds(e))

    def take() -> int:
        i = take_next(counter)
        if progress is not None:
            progress(before[min(i, len(entries))], before[-1])
        return i

    try:
        compile_queue(entries, take)
    except BaseException:
        for proc in procs:
            proc.terminate()
        raise
    for proc in procs:
        proc.join()
    return helpers


def entry_key(e: dict[str, Any]) -> str:
    """An entry's identity: its kernel and encoded argument types."""
    return str(e["kernel"]) + json.dumps(e["args"])
