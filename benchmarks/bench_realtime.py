"""Per-ping default pipeline against the real-time budgets of every sonar (single thread, in memory).

``process_ping(ping, PipelineConfig())`` on already-read pings: the real DIDSON test pings, ARIS
frames and Oculus pings, and simulated pings of larger lattices (the ``aris3000-128`` and
``oculus-m750d-like`` presets with their range window resampled to the given number of bins,
beams interpolated for 512 beams; a hull scene).  Targets are the real-time goals (a ping well
inside the sonar's ping interval, leaving room for reading, writing and mapping); ``note`` gives
the ping interval of the fastest mode of that sonar and the figure measured before the
real-time work (the same cases on the same machine class).

The "fixed cost" row is a 64 x 16 ping: almost no compute, so it measures the per-ping Python
set-up of the stages.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from run import DATA, timeit


def _resampled(name: str, n_bins: int, n_beams: int | None = None) -> Any:
    import numpy as np

    from sonarmap import preset

    g = preset(name)
    r = np.linspace(float(g.range_m[0]), float(g.range_m[-1]), n_bins)
    changes: dict[str, Any] = {"range_m": r}
    if n_beams is not None and n_beams != g.n_beams:
        az = np.linspace(float(g.azimuth_rad[0]), float(g.azimuth_rad[-1]), n_beams)
        changes.update(azimuth_rad=az, psf=None, taper=None, psf_raw=None)
    return g.replace(**changes)


def _sim_pings(geometry: Any, n: int = 3) -> list[Any]:
    from sonarmap.simulate import scene_from_name, simulate_pings

    scene = scene_from_name("hull", geometry=geometry)
    return [sim.ping for sim in simulate_pings(scene, geometry, seeds=range(n))]


def cases(quick: bool) -> list[tuple[str, list[Any], float, str]]:
    """``(name, pings, target ms, note)`` of every case (the 4096 x 512 one only without ``quick``)."""
    from sonarmap.io import read_pings

    data = Path(DATA)
    out: list[tuple[str, list[Any], float, str]] = [
        ("DIDSON 512 x 96 (10 real test pings)", list(read_pings(data / "didson" / "test")), 0.6,
         "10 Hz; before: 1.38 ms"),
        ("Oculus 703 x 256 (3 real pings)", list(read_pings(data / "oculus" / "three_pings_8bit.raw")), 2.5,
         "40 Hz; before: 20.5 ms"),
        ("ARIS 2000 x 48 (6 real frames)", list(read_pings(data / "aris" / "sample.aris")), 2.0,
         "15 Hz; before: 7.3 ms"),
        ("2000 x 128 (sim, aris3000-128)", _sim_pings(_resampled("aris3000-128", 2000)), 5.0,
         "15 Hz; before: 5.4 ms"),
        ("1024 x 512 (sim, oculus-m750d-like)", _sim_pings(_resampled("oculus-m750d-like", 1024, 512)), 25.0,
         "40 Hz; before: 16.6 ms"),
    ]
    if not quick:
        out.append(("4096 x 512 (sim, oculus-m750d-like)",
                    _sim_pings(_resampled("oculus-m750d-like", 4096, 512), 2), 25.0, "40 Hz; before: 69 ms"))
    out.append(("fixed cost: 64 x 16 (sim, oculus-m750d-like)",
                _sim_pings(_resampled("oculus-m750d-like", 64, 16)), 0.1, "before: ~0.30 ms"))
    return out


def ping_median_ms(pings: list[Any], quick: bool) -> float:
    """Median ms of the default ``process_ping`` cycling over ``pings`` (warmed up first)."""
    import itertools

    from sonarmap.pipeline import PipelineConfig, process_ping

    cfg = PipelineConfig()
    for p in pings:  # warm caches (geometry, filters, numba)
        process_ping(p, cfg)
    it = itertools.cycle(pings)
    rep = max(10, (30 if quick else 100) // max(1, len(pings) // 3))
    return timeit(lambda: process_ping(next(it), cfg), repeat=rep, warmup=1)


def run(quick: bool) -> list[dict]:
    return [{"benchmark": "realtime", "case": f"process_ping, {name}", "median_ms": ping_median_ms(pings, quick),
             "target_ms": target, "note": note} for name, pings, target, note in cases(quick)]
