"""Range stage: echo finding + surface tracking per ping, the default against the rules, and the
default with and without the surface significance test (normalised pings: ARIS, Oculus)."""

from __future__ import annotations

import itertools
from pathlib import Path

from run import DATA, interleaved, timeit


def run(quick: bool) -> list[dict]:
    import numpy as np

    from sonarmap.io import read_pings
    from sonarmap.pipeline import PipelineConfig, process_ping
    from sonarmap.ranges import component_rule
    from sonarmap.ranges.echoes import find_echoes, level_llr
    from sonarmap.ranges.tracking import track_surfaces
    from sonarmap.stats.mixture import quantize

    rep = 30 if quick else 200
    rows = []
    for name, paths in (("DIDSON 512 x 96 (10 test pings)", sorted((Path(DATA) / "didson" / "test").glob("*_raw.png"))),
                        ("ARIS 2000 x 48 (sample.aris)", [Path(DATA) / "aris" / "sample.aris"]),
                        ("Oculus 703 x 256 (three_pings_8bit.raw)", [Path(DATA) / "oculus" / "three_pings_8bit.raw"])):
        pings = list(read_pings([str(p) for p in paths]))
        c = PipelineConfig()
        cases = []
        for p in pings:
            pr = process_ping(p, keep_labels=True)
            if pr.fit is None or pr.gates:
                continue
            mask = component_rule(pr.labels >= 1, c.candidates.min_component_beams, c.candidates.min_component_bins, c.candidates.link_beams,
                                  c.candidates.min_component_pixels)
            cases.append((mask, pr.image, p.geometry, quantize(pr.image, c.fit.n_levels), np.maximum(level_llr(pr.fit), 0.0)))
        it = itertools.cycle(cases)

        def stage() -> None:
            mask, img, geom, levels, lut = next(it)
            track_surfaces(find_echoes(mask, img, geom, levels=levels, level_evidence=lut), c.ranges.track)

        rows.append({"benchmark": "ranges", "case": f"find_echoes + track_surfaces, {name}",
                     "median_ms": timeit(stage, repeat=rep), "target_ms": 0.3 if name.startswith("DIDSON") else None})
        # the whole default against the previous per-beam rules, interleaved ping by ping
        rules = PipelineConfig().replace(tracker="rules")
        cfg = PipelineConfig()
        t_new, t_old = interleaved(lambda p: process_ping(p, cfg), lambda p: process_ping(p, rules), pings,
                                   rounds=max(rep // len(pings), 3))
        rows.append({"benchmark": "ranges", "case": f"process_ping default, {name}",
                     "median_ms": t_new, "baseline": "tracker='rules'", "baseline_ms": t_old,
                     "note": "target: no slower"})
        if not name.startswith("DIDSON"):  # (pre-processed pings are not tested)
            untested = PipelineConfig().replace(surface_min_z=0.0)
            t_on, t_off = interleaved(lambda p: process_ping(p, cfg), lambda p: process_ping(p, untested), pings,
                                      rounds=max(rep // len(pings), 3))
            rows.append({"benchmark": "ranges", "case": f"process_ping default (surface significance), {name}",
                         "median_ms": t_on, "baseline": "surface_min_z=0", "baseline_ms": t_off,
                         "note": "the test's cost"})
    return rows
