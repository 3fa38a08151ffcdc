"""MRF solvers on real 512x96 DIDSON pings (exact graph cut <= 2 ms median).

Unaries come from the default pipeline (paper Table-I pre-processing, EM fit) of two shared test
pings: a hull (image 4) and the propeller (image 7, the largest structure).  The baseline is the
same exact cut on the full lattice (no persistency reduction, grid helpers); the paper's simulated
annealing and ICM are listed for reference.
"""

from __future__ import annotations

from pathlib import Path

from run import DATA, timeit


def _problem(index: int):  # type: ignore[no-untyped-def]
    import numpy as np

    from sonarmap.io import read_pings
    from sonarmap.classify.segment import class_costs
    from sonarmap.pipeline import PipelineConfig
    from sonarmap.preprocess.pipeline import preprocess_image
    from sonarmap.stats.mixture import quantize
    from sonarmap.stats.model import fit_levels

    cfg = PipelineConfig()
    ping = list(read_pings(Path(DATA) / "didson" / "test"))[index]
    img = preprocess_image(ping.image, ping.geometry, cfg.preprocess_config())
    levels = np.ascontiguousarray(quantize(img, cfg.fit.n_levels))
    cost = class_costs(fit_levels(levels, cfg.fit), object_prior_min=cfg.classify.object_prior_min,
                       speckle_eps=cfg.classify.speckle_eps)
    return cfg, levels, cost, np.ascontiguousarray(cost[:, levels])


def run(quick: bool) -> list[dict]:
    from sonarmap.classify import mrf

    rows = []
    rep = 10 if quick else 50
    for index, name in ((4, "hull (test 4)"), (7, "propeller (test 7)")):
        cfg, levels, cost, unary = _problem(index)
        lv = {"beta": cfg.classify.beta, "neighbourhood": cfg.classify.neighbourhood, "range_weight": cfg.classify.range_weight}
        wt = mrf.pairwise_weights(levels.shape, beta=cfg.classify.beta, neighbourhood=cfg.classify.neighbourhood,
                                  range_weight=cfg.classify.range_weight)
        r = mrf.solve_graphcut_levels(levels, cost, **lv)
        full_ms = timeit(lambda: mrf.solve_graphcut(unary, weights=wt, reduce=False), repeat=max(3, rep // 5))
        t = timeit(lambda: mrf.solve_graphcut_levels(levels, cost, **lv), repeat=rep)
        rows.append({"benchmark": "mrf", "case": f"graph cut exact, 512x96 {name}", "median_ms": t,
                     "target_ms": 2.0, "baseline": "full-lattice cut", "baseline_ms": full_ms,
                     "note": f"{r.n_free} of {levels.size} px in graph; E={r.energy:.1f}"})
        lv8 = dict(lv, neighbourhood=8)
        t8 = timeit(lambda: mrf.solve_graphcut_levels(levels, cost, **lv8), repeat=rep)
        rows.append({"benchmark": "mrf", "case": f"graph cut exact 8-nbhd, {name}", "median_ms": t8})
        icm = mrf.solve_icm(unary, weights=wt)
        ticm = timeit(lambda: mrf.solve_icm(unary, weights=wt), repeat=max(3, rep // 5))
        rows.append({"benchmark": "mrf", "case": f"ICM, {name}", "median_ms": ticm,
                     "note": f"E={icm.energy:.1f} (cut {r.energy:.1f})"})
        sched = mrf.AnnealSchedule()
        ann = mrf.solve_anneal(unary, weights=wt, schedule=sched)
        tann = timeit(lambda: mrf.solve_anneal(unary, weights=wt, schedule=sched), repeat=3, warmup=1, min_time_s=0.0)
        rows.append({"benchmark": "mrf", "case": f"annealing (paper) {sched.n_sweeps} sweeps, {name}",
                     "median_ms": tann, "note": f"E={ann.energy:.1f} (cut {r.energy:.1f})"})
    return rows
