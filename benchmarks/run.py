"""Run every benchmark and print one table.

Usage::

    python benchmarks/run.py            # all benchmarks
    python benchmarks/run.py io mrf     # only bench_io.py, bench_mrf.py

Each ``benchmarks/bench_<name>.py`` defines ``run(quick: bool) -> list[dict]``; each row has
``benchmark``, ``case``, ``median_ms`` and optionally ``baseline``, ``baseline_ms`` (a reference
implementation timed in the same process), ``target_ms`` (the budget) and ``note``; the exit status is 1 when any target is missed.
The runner pins numerical libraries to one thread so numbers are single-threaded unless a
benchmark says otherwise.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("SONARMAP_DATA", HERE.parent.parent / "shared" / "data"))


def timeit(fn: Callable[[], Any], *, repeat: int = 50, warmup: int = 3, min_time_s: float = 0.2) -> float:
    """Median wall time of ``fn()`` in milliseconds (after warm-up)."""
    for _ in range(warmup):
        fn()
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < repeat or (time.perf_counter() - start < min_time_s and len(times) < 100 * repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return 1e3 * times[len(times) // 2]


def interleaved(fn_a: Callable[[Any], Any], fn_b: Callable[[Any], Any], items: list[Any], *,
                rounds: int = 3) -> tuple[float, float]:
    """Median wall times (ms) of ``fn_a(item)`` and ``fn_b(item)``, alternated item by item so that
    machine drift hits both alike."""
    t_a: list[float] = []
    t_b: list[float] = []
    for _ in range(max(rounds, 1)):
        for it in items:
            t0 = time.perf_counter()
            fn_a(it)
            t_a.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            fn_b(it)
            t_b.append(time.perf_counter() - t0)
    return 1e3 * sorted(t_a)[len(t_a) // 2], 1e3 * sorted(t_b)[len(t_b) // 2]


def _load(path: Path) -> Any:
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="benchmark modules to run (default: all)")
    ap.add_argument("--quick", action="store_true", help="fewer repetitions / smaller cases")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    files = sorted(HERE.glob("bench_*.py"))
    if args.names:
        files = [f for f in files if f.stem.removeprefix("bench_") in args.names]
    rows: list[dict[str, Any]] = []
    for f in files:
        mod = _load(f)
        rows.extend(mod.run(quick=args.quick))
    from rich.console import Console
    from rich.table import Table

    table = Table(title="sonarmap benchmarks (single thread, median)")
    for col in ("benchmark", "case", "median ms", "target ms", "ok", "baseline", "baseline ms", "speed-up", "note"):
        table.add_column(col, justify="right" if "ms" in col or col == "speed-up" else "left")
    failed = 0
    for r in rows:
        med = r["median_ms"]
        tgt = r.get("target_ms")
        ok = "" if tgt is None else ("yes" if med <= tgt else "NO")
        failed += ok == "NO"
        bms = r.get("baseline_ms")
        table.add_row(
            r["benchmark"], r["case"], f"{med:.4g}", "" if tgt is None else f"{tgt:g}", ok,
            r.get("baseline", ""), "" if bms is None else f"{bms:.4g}",
            "" if bms is None else f"{bms / med:.1f}x", r.get("note", ""),
        )
    Console(width=200).print(table)
    if failed:
        print(f"{failed} of {sum(r.get('target_ms') is not None for r in rows)} targets missed", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
