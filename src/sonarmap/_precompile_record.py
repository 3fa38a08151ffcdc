"""Write the list of kernels :mod:`sonarmap._precompile` compiles on a cold cache.

``python -m sonarmap._precompile_record`` runs the pipeline's warm-ups and a few simulated pings
in this (fresh) process, records the kernels they call from Python with their argument types (the
entry points: the kernels those call are compiled with them) and rewrites
``_kernel_signatures.json``, keeping the seconds of entries already listed; ``--time`` instead
compiles each listed entry on its own and records its seconds (run it with ``NUMBA_CACHE_DIR``
set to an empty directory), which orders the queue; ``--check`` exits 1, naming the
differences, when the list is not what a fresh process records (``tests/test_precompile.py``).
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from sonarmap._precompile import SIGNATURES_FILE, UnsupportedType, compile_entry, entry_key, encode_type, load_signatures

__all__ = ["RECORDED_SCENES", "recording", "recorded_signatures", "write_signatures", "main"]


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
            k = entry_key(entry)
            if k not in seen:
                seen.add(k)
                calls.append(entry)
        return out

    Dispatcher._compile_for_args = compile_for_args  # type: ignore[method-assign]
    try:
        yield calls
    finally:
        Dispatcher._compile_for_args = original  # type: ignore[method-assign]


#: Simulated pings :func:`recorded_signatures` runs besides the warm-ups: (preset, scene), seed 0
#: at the preset's noise floor - the paths of real pings that the warm-ups' synthetic ones do not
#: take (band pooling and crosstalk on a DIDSON hull, the max-flow graph under an ARIS seafloor,
#: the Oculus hull's smoothing).
RECORDED_SCENES = (("didson-hf", "hull"), ("aris3000-128", "seafloor"), ("oculus-m750d-like", "hull"))


def recorded_signatures() -> list[dict[str, Any]]:
    """The entry points the pipeline's warm-ups (:func:`sonarmap.live.loop.warm_pipeline`: a
    thresholded DIDSON ping and a speckled, normalised one) and the pings of
    :data:`RECORDED_SCENES` call, in this process, sorted by kernel and signature (the simulator's
    own kernels not among them).  Only a process that has not run them yet records them all."""
    from sonarmap.evaluate import preset_sim_configs
    from sonarmap.geometry import preset
    from sonarmap.live.loop import warm_pipeline
    from sonarmap.pipeline import process_ping
    from sonarmap.simulate import scene_from_name, simulate_ping

    pings = []
    for name, scene in RECORDED_SCENES:
        g = preset(name)
        sim = simulate_ping(scene_from_name(scene, geometry=g), g, config=preset_sim_configs(g)[0], seed=0,
                            recording_meta=True)
        pings.append(sim.ping)
    with recording() as calls:
        warm_pipeline()
        for ping in pings:
            process_ping(ping)
    return sorted(calls, key=entry_key)


def write_signatures(path: Path = SIGNATURES_FILE, *, timed: bool = False) -> int:
    """Record the warm-ups' entry points in this process (:func:`recorded_signatures`: run it in a
    fresh process, ``python -m sonarmap._precompile_record``) and write them, keeping the seconds of
    entries already listed; with ``timed``, instead compile each listed entry on its own and
    record its ``seconds`` (on an empty cache: ``NUMBA_CACHE_DIR=<empty dir> python -m
    sonarmap._precompile_record --time``).  The number of entries written."""
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
        seconds = {entry_key(e): e["seconds"] for e in listed if "seconds" in e}
        entries = recorded_signatures()
        for e in entries:
            if entry_key(e) in seconds:
                e["seconds"] = seconds[entry_key(e)]
    entries = sorted(entries, key=entry_key)
    import numba

    text = json.dumps({"about": "numba signatures the per-ping pipeline's warm-up compiles, with the seconds "
                                "each took to compile on an empty cache; rewrite with "
                                "`python -m sonarmap._precompile_record [--time]`",
                       "numba": numba.__version__, "signatures": entries}, indent=1)
    atomic_write_text(path, text + "\n")
    return len(entries)


def _compiled_here(entry: dict[str, Any]) -> bool:
    """Whether this process's dispatcher of the entry's kernel holds its signature."""
    from sonarmap._precompile import decode_type, resolve_kernel

    try:
        sig = tuple(decode_type(a) for a in entry["args"])
        return sig in [tuple(s) for s in resolve_kernel(entry["kernel"]).signatures]
    except Exception:  # noqa: BLE001 - an unknown kernel or type: not compiled here
        return False


def main(argv: Sequence[str]) -> int:  # pragma: no cover - the maintainer's command (tested by a subprocess)
    """``--check``: exit 1, naming the differences, when the list is not what a fresh process
    records; ``--time``: measure the listed entries; otherwise rewrite the list."""
    if "--check" in argv:
        want = {entry_key(e) for e in recorded_signatures()}
        listed = load_signatures()
        have = {entry_key(e) for e in listed}
        # on an empty cache a listed entry point may have been compiled inside a kernel that calls
        # it before the warm-up called it from Python (then it is not recorded): it counts when
        # its dispatcher holds the signature
        extra = {entry_key(e) for e in listed if entry_key(e) not in want and not _compiled_here(e)}
        for k in sorted(want - have):
            print(f"missing: {k}")
        for k in sorted(extra):
            print(f"not compiled by the warm-up: {k}")
        if want - have or extra:
            print("rewrite the list: python -m sonarmap._precompile_record")
            return 1
        print(f"{len(have)} signatures, as listed")
        return 0
    n = write_signatures(timed="--time" in argv)
    print(f"{n} signatures -> {SIGNATURES_FILE}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main(sys.argv[1:]))
