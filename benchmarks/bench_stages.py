"""Where a ping's time goes: the default pipeline's per-ping time split by stage, on the cases of
``bench_realtime`` (single thread, in memory).

Each stage's time is exclusive (a stage called from inside another is counted as itself only; the
edge image's own pre-processing counts as the edge image) and averaged over the pings (mean, so
the stages add up to the total):

- ``normalise / pre-process``: input conditioning and the background normalisation
  (ARIS, Oculus, simulated) or the pre-processing recipe (DIDSON);
- ``fit``: the level histogram and the mixture fit with its restarts and gates' statistics;
- ``classify``: the classification (the graph-cut MRF of the default);
- ``edge image``: the image the echoes of a pre-processed ping are measured on (DIDSON);
- ``ranges``: candidate structure, echoes, tracking, pooled / template / smoothed edges;
- ``rest``: everything else - the fit's gates, the products, the Python between the stages.

The total is timed separately, without the split's wrappers (their cost, ~1 us a call, is in the
stage rows only); its note gives the case's ``bench_realtime`` target, which ``realtime`` checks.
"""

from __future__ import annotations

import itertools
import time
from typing import Any, Callable

from bench_realtime import cases, ping_median_ms

#: Stage name -> (module, function) whose calls are that stage's (wrapped where the pipeline
#: looks them up: the names ``sonarmap.pipeline`` imported, or the module attribute it reads).
STAGES: dict[str, tuple[tuple[str, str], ...]] = {
    "normalise / pre-process": (("sonarmap.pipeline", "condition_image"),
                                ("sonarmap.pipeline", "estimate_background_levels"),
                                ("sonarmap.pipeline", "preprocess_finite"),
                                ("sonarmap.pipeline", "preprocess_image")),
    "fit": (("sonarmap.pipeline", "fit_levels"), ("sonarmap.pipeline", "fit_counts"),
            ("sonarmap.stats.mixture", "quantize_counts")),
    "classify": (("sonarmap.pipeline", "segment"),),
    "edge image": (("sonarmap.pipeline", "measurement_image"),),
    "ranges": (("sonarmap.pipeline", "candidate_mask"), ("sonarmap.pipeline", "surface_ranges"),
               ("sonarmap.pipeline", "rule_ranges")),
}


#: Stages whose wrapped callees count as the stage itself (the edge image pre-processes the ping
#: again, without the deconvolution: that is the edge image's work, not the ping's pre-processing).
INCLUSIVE = frozenset({"edge image"})


class _Split:
    """Exclusive wall time per stage of the wrapped functions (a stack of the open calls: a call's
    time less its wrapped callees'; inside an :data:`INCLUSIVE` stage nothing is split off)."""

    def __init__(self) -> None:
        self.total: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self._inner: list[float] = []
        self._inclusive = 0  # open calls of INCLUSIVE stages

    def wrap(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        whole = stage in INCLUSIVE

        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._inclusive:
                return fn(*args, **kwargs)
            self._inclusive += whole
            self._inner.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                self._inclusive -= whole
                inner = self._inner.pop()
                self.total[stage] += dt - inner
                if self._inner:
                    self._inner[-1] += dt
        return timed


def _patched(split: _Split) -> list[tuple[Any, str, Any]]:
    """Wrap every stage function; returns ``(module, name, original)`` to restore."""
    import importlib

    saved = []
    for stage, names in STAGES.items():
        for mod_name, fn_name in names:
            mod = importlib.import_module(mod_name)
            fn = getattr(mod, fn_name)
            saved.append((mod, fn_name, fn))
            setattr(mod, fn_name, split.wrap(stage, fn))
    return saved


def split_ms(pings: list[Any], n: int) -> tuple[dict[str, float], float]:
    """``(stage -> mean ms per ping, mean total ms per ping with the wrappers)`` of ``n`` calls of
    the default ``process_ping`` cycling over ``pings`` (warmed up first)."""
    from sonarmap.pipeline import PipelineConfig, process_ping

    cfg = PipelineConfig()
    for p in pings:
        process_ping(p, cfg)
    split = _Split()
    saved = _patched(split)
    try:
        it = itertools.cycle(pings)
        t0 = time.perf_counter()
        for _ in range(n):
            process_ping(next(it), cfg)
        total = time.perf_counter() - t0
    finally:
        for mod, name, fn in saved:
            setattr(mod, name, fn)
    per = {k: 1e3 * v / n for k, v in split.total.items()}
    per["rest"] = 1e3 * total / n - sum(per.values())
    return per, 1e3 * total / n


def run(quick: bool) -> list[dict]:
    rows = []
    for name, pings, target, _ in cases(quick):
        n = max(len(pings), (20 if quick else 100) if pings[0].image.size < 1_000_000 else 6)
        per, wrapped = split_ms(pings, n)
        rows.append({"benchmark": "stages", "case": f"{name}: total (median)",
                     "median_ms": ping_median_ms(pings, quick), "note": f"target {target:g} ms (realtime)"})
        for stage, ms in per.items():
            rows.append({"benchmark": "stages", "case": f"{name}: {stage} (mean)", "median_ms": ms,
                         "note": f"{100 * ms / wrapped:.0f} %"})
    return rows
