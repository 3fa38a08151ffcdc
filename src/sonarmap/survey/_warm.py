"""Imported by the fork server of ``sonarmap process``'s worker pool: warm the per-ping pipeline once.

The local workers of :func:`sonarmap.survey.process_survey` are forked from a fork server that
preloads this module.  Importing it runs the default pipeline once on a synthetic ping, so the
numba kernels are loaded, the lazily imported modules (scipy, readers, codecs) are in memory and
the fork server's children start warm: a worker is ready to take chunks in milliseconds instead
of ~0.6 s, and a process that runs several surveys (notebooks, tests, benchmarks) pays the
warm-up once.  Any failure is swallowed: warming is an optimisation, never a requirement (the
fork server would die on an exception raised while preloading).
"""

from __future__ import annotations

import os

WARMED = False
#: The process that imported (and so warmed) this module: in a worker forked from the fork
#: server it is the fork server's pid, i.e. the worker inherited a warm pipeline.
IMPORTED_IN_PID = os.getpid()


def status() -> tuple[bool, bool]:
    """``(warmed, inherited)``: the pipeline ran here, and it ran before this process was forked."""
    return WARMED, IMPORTED_IN_PID != os.getpid()


def warm() -> bool:
    """Run the default pipeline once on a synthetic DIDSON ping; ``True`` if it worked."""
    global WARMED
    try:
        import numpy as np
        from numcodecs.vlen import VLenUTF8  # noqa: F401 - used by the chunk writer
        from numcodecs.zstd import Zstd  # noqa: F401

        from sonarmap.geometry import preset
        from sonarmap.io.pngjson import read_png_ping  # noqa: F401 - the reader of the workers
        from sonarmap.ping import Ping
        from sonarmap.pipeline import PipelineConfig, process_ping

        g = preset("didson-hf")
        img = np.random.default_rng(0).random(g.shape, dtype=np.float32) * 0.3
        img[g.n_bins // 2 : g.n_bins // 2 + 8] = 0.9
        process_ping(Ping(img, g), PipelineConfig())
        WARMED = True
    except Exception:  # noqa: BLE001 - warming must never fail a run
        WARMED = False
    return WARMED


warm()
