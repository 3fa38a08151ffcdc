"""Survey throughput: the paper's 42 000-ping hull survey through the default pipeline.

The survey is made of symbolic links to the 126 real DIDSON pings in ``../shared/data/didson``
(test + background) under new, distinct time stamps (:func:`sonarmap.survey.replicate_pings`), so
every ping is read from its own PNG+JSON file by the worker that processes it, as in a real run.

Rows:

* ``N pings, 2 workers``: wall time of ``process_survey`` (local worker processes, default
  chunk size) against the real-time target of 45 s for 42 000 pings (it was 2 minutes).  ``--quick`` processes
  2 000 and 1 000 pings and extrapolates to 42 000 from their difference, so that the fixed
  start-up of the workers is not scaled with the pings (the note gives both runs).
* ``scaling``: a smaller survey with 2 workers, against 1 worker as the baseline - the
  speed-up column is the scaling factor (target >= 1.7x); runs alternate 1, 2, 1, 2, ... workers
  (four pairs, up to eight until each side has two runs that did not overlap other work) and
  the best undisturbed run of each side is compared; every run's wall time (``*``: disturbed)
  and the median of the pairs' ratios are in the note.
* Peak memory: the resident set of the parent plus all worker processes, sampled every 0.25 s
  (psutil), is given in the notes.
* CPU accounting: the CPU time of the run (parent and workers) and the mean number of
  CPUs that *other* work used meanwhile (other processes, hypervisor steal) - the machine is
  shared, and a run overlapping someone else's job is visible as "other load" > 0.

Run with ``python benchmarks/run.py survey [--quick]`` or ``python benchmarks/bench_survey.py``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("SONARMAP_DATA", HERE.parent.parent / "shared" / "data"))

FULL_PINGS = 42_000
BUDGET_S = 45.0


class _PeakRSS:
    """Peak of the summed RSS of this process and all its descendants (sampled in a thread).

    Also accounts CPU time: ``own_cpu_s`` is the CPU used by this process and its descendants
    during the block (user + system, including reaped children - the pool's spawned workers are
    children of this process), ``other_cpu_s`` the CPU the rest of the machine
    used meanwhile (system-wide busy time minus ours) and ``steal_s`` the time the hypervisor gave
    to other guests.  On a shared machine, ``other_cpu_s`` tells whether a timing was disturbed.
    """

    def __init__(self, interval_s: float = 0.25) -> None:
        import psutil

        self._psutil = psutil
        self.interval_s = interval_s
        self.peak_bytes = 0
        self.peak_workers = 0
        self.own_cpu_s = 0.0
        self.other_cpu_s = 0.0
        self.steal_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        me = self._psutil.Process()
        total = me.memory_info().rss
        kids = 0
        for child in me.children(recursive=True):
            try:
                rss = child.memory_info().rss
            except self._psutil.Error:
                continue
            total += rss
            kids += 1
        if total > self.peak_bytes:
            self.peak_bytes = total
            self.peak_workers = kids

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.interval_s)

    def _tree_cpu(self) -> dict[int, float]:
        """CPU seconds of this process and each live descendant, reaped children included."""
        out: dict[int, float] = {}
        me = self._psutil.Process()
        for p in [me, *me.children(recursive=True)]:
            try:
                t = p.cpu_times()
            except self._psutil.Error:
                continue
            out[p.pid] = t.user + t.system + t.children_user + t.children_system
        return out

    def _machine(self) -> tuple[float, float]:
        t = self._psutil.cpu_times()
        busy = t.user + t.nice + t.system + t.irq + t.softirq
        return busy, t.steal

    def __enter__(self) -> _PeakRSS:
        self._cpu0 = self._tree_cpu()
        self._busy0, self._steal0 = self._machine()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        time.sleep(0.05)  # let the last workers be reaped (their time joins our children's)
        cpu1 = self._tree_cpu()
        busy1, steal1 = self._machine()
        self.own_cpu_s = sum(v - self._cpu0.get(pid, 0.0) for pid, v in cpu1.items())
        self.other_cpu_s = max(0.0, busy1 - self._busy0 - self.own_cpu_s)
        self.steal_s = steal1 - self._steal0


def _sources() -> list[Path]:
    d = DATA / "didson"
    srcs = sorted((d / "test").glob("*_raw.png")) + sorted((d / "background").glob("*.png"))
    if not srcs:
        raise SystemExit(f"bench_survey: no DIDSON pings under {d}")
    return srcs


def _timed_run(pings: Path, out: Path, workers: int, chunk_size: int = 256) -> dict[str, Any]:
    from sonarmap.survey import process_survey

    if out.exists():
        shutil.rmtree(out)
    with _PeakRSS() as mem:
        t0 = time.perf_counter()
        res = process_survey([pings], out, workers=workers, chunk_size=chunk_size)
        wall = time.perf_counter() - t0
    return {"wall_s": wall, "n": res.n_pings, "flagged": res.n_flagged, "peak_mb": mem.peak_bytes / 2**20,
            "procs": mem.peak_workers + 1, "own_cpu_s": mem.own_cpu_s, "other_cpu_s": mem.other_cpu_s,
            "steal_s": mem.steal_s}


def _other_load(r: dict[str, Any]) -> float:
    """Mean number of CPUs busy with other work (other processes, other guests) during a run."""
    return (r["other_cpu_s"] + r["steal_s"]) / r["wall_s"]


def run(quick: bool) -> list[dict[str, Any]]:
    from sonarmap.survey import replicate_pings

    n_main = 2_000 if quick else FULL_PINGS
    n_scale = 1_000 if quick else 4_000
    rows: list[dict[str, Any]] = []
    tmp = Path(tempfile.mkdtemp(prefix="sonarmap-bench-survey-"))
    try:
        srcs = _sources()
        t0 = time.perf_counter()
        main_dir = replicate_pings(srcs, n_main, tmp / "main")
        link_s = time.perf_counter() - t0
        scale_dir = replicate_pings(srcs, n_scale, tmp / "scale")
        # Warm the page cache and the imports once (not timed).
        _timed_run(scale_dir, tmp / "warm.zarr", workers=2)

        r2 = _timed_run(main_dir, tmp / "main.zarr", workers=2)
        per_ping_ms = 1e3 * r2["wall_s"] / r2["n"]
        est_s = r2["wall_s"]  # the full survey; from two sizes below when fewer pings were run
        note = (f"{r2['n'] / r2['wall_s']:.0f} pings/s, {per_ping_ms:.2f} ms/ping, {r2['flagged']} flagged; "
                f"peak RSS {r2['peak_mb']:.0f} MB over {r2['procs']} processes; {r2['own_cpu_s']:.0f} CPU s; "
                f"other load {_other_load(r2):.2f} CPUs")
        if r2["n"] != FULL_PINGS:
            # The wall time includes a fixed part (spawning the workers, their imports and numba
            # loads: ~1.3 s), so scaling the whole time linearly overstates a full survey (2 000
            # pings: 3.3 s -> "70 s", against 42 s measured).  The per-ping rate comes from the
            # difference of two sizes instead.
            r1 = _timed_run(scale_dir, tmp / "half.zarr", workers=2)
            slope_s = (r2["wall_s"] - r1["wall_s"]) / (r2["n"] - r1["n"])
            est_s = r2["wall_s"] + slope_s * (FULL_PINGS - r2["n"])
            note += (f"; extrapolated to {FULL_PINGS} pings: {est_s:.0f} s (from the {r1['n']} -> {r2['n']}-ping "
                     f"difference, {1e3 * slope_s:.2f} ms/ping: {r1['wall_s']:.2f} -> {r2['wall_s']:.2f} s; "
                     f"fixed start-up {r1['wall_s'] - slope_s * r1['n']:.1f} s)")
        rows.append({
            "benchmark": "survey",
            "case": (f"{r2['n']} DIDSON pings, 2 workers (links made in {link_s:.1f} s)" if r2["n"] == FULL_PINGS
                     else f"{FULL_PINGS} DIDSON pings, 2 workers, from {r2['n']} (links made in {link_s:.1f} s)"),
            "median_ms": 1e3 * est_s,
            "target_ms": 1e3 * BUDGET_S,
            "note": note,
        })
        k = max(16, n_scale // 32)  # enough chunks that 2 workers stay balanced
        # Alternate 1, 2, 1, 2, ... workers and compare each side's best run: other processes on
        # a shared machine (and other guests on its host) disturb both sides alike instead of
        # biasing the ratio, and the best run is the least disturbed one.  Runs that overlapped
        # other work (> 0.1 CPU on average) only count if a side has no undisturbed run: four
        # pairs, then more (up to eight) until each side has two undisturbed runs.
        runs: dict[int, list[dict[str, Any]]] = {1: [], 2: []}

        def best(w: int) -> dict[str, Any]:
            clean = [r for r in runs[w] if _other_load(r) <= 0.1]
            return min(clean or runs[w], key=lambda r: r["wall_s"])

        for pair in range(8):
            for w in (1, 2):
                runs[w].append(_timed_run(scale_dir, tmp / f"s{w}.zarr", workers=w, chunk_size=k))
            n_clean = min(sum(_other_load(r) <= 0.1 for r in runs[w]) for w in (1, 2))
            if pair >= 3 and n_clean >= 2:
                break
        s1, s2 = best(1), best(2)
        speedup = s1["wall_s"] / s2["wall_s"]
        pair_ratios = sorted(r1["wall_s"] / r2["wall_s"] for r1, r2 in zip(runs[1], runs[2], strict=True))
        median_pair = float(np.median(pair_ratios))
        all_s = ", ".join(f"{r1['wall_s']:.2f}{'*' * (_other_load(r1) > 0.1)}/{r2['wall_s']:.2f}"
                          f"{'*' * (_other_load(r2) > 0.1)}" for r1, r2 in zip(runs[1], runs[2], strict=True))
        rows.append({
            "benchmark": "survey",
            "case": f"scaling, {n_scale} pings (chunks of {k}): 2 workers vs 1",
            "median_ms": 1e3 * s2["wall_s"],
            "baseline": "1 worker",
            "baseline_ms": 1e3 * s1["wall_s"],
            "note": (f"speed-up {speedup:.2f}x (target >= 1.7x) {'ok' if speedup >= 1.7 else 'BELOW TARGET'}; "
                     f"best undisturbed of {len(runs[1])} alternating runs, 1/2 workers s: {all_s} "
                     f"(* other load > 0.1 CPU) "
                     f"(median ratio of the pairs {median_pair:.2f}x); "
                     f"CPU s of the best runs 1 worker {s1['own_cpu_s']:.1f}, 2 workers {s2['own_cpu_s']:.1f}; "
                     f"other load during them {_other_load(s1):.2f} / {_other_load(s2):.2f} CPUs "
                     f"(of {os.cpu_count()}); peak RSS 1 worker {s1['peak_mb']:.0f} MB, 2 workers {s2['peak_mb']:.0f} MB"),
        })
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


if __name__ == "__main__":
    import argparse
    import sys

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    sys.path.insert(0, str(HERE))
    from run import main as run_main

    raise SystemExit(run_main(["survey", *(["--quick"] if args.quick else [])]))
