"""Reading one real DIDSON ping (PNG + sidecar JSON), after imports.

Baseline: the straightforward path (``PIL.Image.open`` + ``json.load`` + building the geometry
from scratch on every ping, as lab scripts do), timed in the same process.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from run import DATA, timeit

from sonarmap.geometry import geometry_from_dict
from sonarmap.io.pngjson import read_png_ping


def _baseline(png: Any, side: Any) -> Any:
    from PIL import Image

    img = np.asarray(Image.open(png), dtype=np.float32) / 255.0
    with open(side) as fh:
        d = json.load(fh)
    return img, geometry_from_dict(d, source=str(side))


def run(quick: bool = False) -> list[dict[str, Any]]:
    pngs = sorted((DATA / "didson" / "test").glob("*_raw.png"))
    png = pngs[0]
    side = png.with_name(png.name.replace("_raw.png", ".json"))
    rep = 20 if quick else 200
    t = timeit(lambda: read_png_ping(png), repeat=rep)
    state = {"i": 0}

    def cycle() -> None:  # different files each call (page cache warm, no object reuse)
        read_png_ping(pngs[state["i"] % len(pngs)])
        state["i"] += 1

    t_cycle = timeit(cycle, repeat=rep)
    b = timeit(lambda: _baseline(png, side), repeat=rep)
    return [
        {"benchmark": "io", "case": "read 512x96 PNG+JSON (same file)", "median_ms": t,
         "target_ms": 1.0, "baseline": "PIL+json.load", "baseline_ms": b},
        {"benchmark": "io", "case": "read 512x96 PNG+JSON (10 files cycled)", "median_ms": t_cycle,
         "target_ms": 1.0, "baseline": "PIL+json.load", "baseline_ms": b},
    ]
