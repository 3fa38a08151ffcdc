"""Compile the per-ping pipeline's numba kernels in several processes at once.

On an empty numba cache every process that runs the pipeline compiles the same kernels (about
three minutes of one core at numba's default optimisation level): the workers of ``sonarmap
process -j N`` (and of ``sonarmap demo``) did so side by side, each on its own core, so the first
run took as long with two workers as with one.  The kernels the pipeline's warm-up compiles are
listed, with their signatures, in ``_kernel_signatures.json`` beside this module, longest
compilation first.  Workers that find the cache cold share that list as a queue
(:func:`compile_queue`): each takes the next kernel not yet taken, compiles it (numba saves it in
the cache) and takes another, until the list is done; the warm-up that follows then loads from
the cache what the other workers compiled.  The results do not change: the same kernels at the
same signatures, compiled by numba as the pipeline would have compiled them.

``python -m sonarmap._precompile`` rewrites the list from what the warm-ups compile in a fresh
process (``tests/test_precompile.py`` checks that it is current); ``--time`` measures each
entry's compilation on an empty cache (run it with ``NUMBA_CACHE_DIR`` set to an empty directory),
which orders the queue.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import json
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["SIGNATURES_FILE", "encode_type", "decode_type", "recorded_signatures", "load_signatures",
           "cache_is_cold", "compile_entry", "compile_queue", "write_signatures"]

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


def _kernel_key(disp: Any) -> str | None:
    """``"module:name"`` of a dispatcher bound at module level under its own name (None: a
    nested or renamed one, which cannot be found again by name)."""
    py = getattr(disp, "py_func", None)
    mod = sys.modules.get(getattr(py, "__module__", ""), None)
    name = getattr(py, "__qualname__", "")
    if mod is None or not str(mod.__name__).startswith("sonarmap") or getattr(mod, name, None) is not disp:
        return None
    return f"{mod.__name__}:{name}"


@contextlib.contextmanager
def recording() -> Iterator[list[dict[str, Any]]]:
    """Within the block, list every sonarmap kernel called from Python for the first time with
    new argument types (numba's ``Dispatcher._compile_for_args``: the entry points; the kernels
    they call are compiled with them), as encoded entries in call order, each once."""
    from numba.core import types
    from numba.core.dispatcher import Dispatcher, OmittedArg

    calls: list[dict[str, Any]] = []
    seen: set[str] = set()
    original = Dispatcher._compile_for_args

    def compile_for_args(self: Any, *args: Any, **kws: Any) -> Any:
        out = original(self, *args, **kws)
        key = _kernel_key(self)
        if key is not None:
            try:
                enc = [encode_type(types.Omitted(a.value) if isinstance(a, OmittedArg) else self.typeof_pyval(a))
                       for a in args]
            except UnsupportedType:
                return out
            entry = {"kernel": key, "args": enc}
            if _key(entry) not in seen:
                seen.add(_key(entry))
                calls.append(entry)
        return out

    Dispatcher._compile_for_args = compile_for_args  # type: ignore[method-assign]
    try:
        yield calls
    finally:
        Dispatcher._compile_for_args = original  # type: ignore[method-assign]


def recorded_signatures() -> list[dict[str, Any]]:
    """The entry points the pipeline's warm-ups (:func:`sonarmap.live.loop.warm_pipeline`: a
    thresholded DIDSON ping and a speckled, normalised one) call, in this process, sorted by
    kernel and signature.  Only a process that has not run them yet records them all."""
    from sonarmap.live.loop import warm_pipeline

    with recording() as calls:
        warm_pipeline()
    return sorted(calls, key=_key)


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


def _resolve(kernel: str) -> Any:
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
        _resolve(entry["kernel"]).compile(tuple(decode_type(a) for a in entry["args"]))
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


def write_signatures(path: Path = SIGNATURES_FILE, *, timed: bool = False) -> int:
    """Record the warm-ups' entry points in this process (:func:`recorded_signatures`: run it in a
    fresh process, ``python -m sonarmap._precompile``) and write them, keeping the seconds of
    entries already listed; with ``timed``, instead compile each listed entry on its own and
    record its ``seconds`` (on an empty cache: ``NUMBA_CACHE_DIR=<empty dir> python -m
    sonarmap._precompile --time``).  The number of entries written."""
    import time

    from sonarmap._atomic import atomic_write_text

    listed = load_signatures(path)
    if timed:
        entries = listed
        for e in entries:
            t = time.perf_counter()
            if compile_entry(e):
                e["seconds"] = round(time.perf_counter() - t, 2)
    else:
        seconds = {_key(e): e["seconds"] for e in listed if "seconds" in e}
        entries = recorded_signatures()
        for e in entries:
            if _key(e) in seconds:
                e["seconds"] = seconds[_key(e)]
    entries = sorted(entries, key=_key)
    text = json.dumps({"about": "numba signatures the per-ping pipeline's warm-up compiles, with the seconds "
                                "each took to compile on an empty cache; rewrite with "
                                "`python -m sonarmap._precompile [--time]`",
                       "signatures": entries}, indent=1)
    atomic_write_text(path, text + "\n")
    return len(entries)


def _key(e: dict[str, Any]) -> str:
    return str(e["kernel"]) + json.dumps(e["args"])


def main(argv: Sequence[str]) -> int:  # pragma: no cover - the maintainer's command (tested by a subprocess)
    """``--check``: exit 1, naming the differences, when the list is not what a fresh process
    records; ``--time``: measure the listed entries; otherwise rewrite the list."""
    if "--check" in argv:
        want = {_key(e) for e in recorded_signatures()}
        have = {_key(e) for e in load_signatures()}
        for k in sorted(want - have):
            print(f"missing: {k}")
        for k in sorted(have - want):
            print(f"not compiled by the warm-up: {k}")
        if want != have:
            print("rewrite the list: python -m sonarmap._precompile")
            return 1
        print(f"{len(want)} signatures, as listed")
        return 0
    n = write_signatures(timed="--time" in argv)
    print(f"{n} signatures -> {SIGNATURES_FILE}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main(sys.argv[1:]))
