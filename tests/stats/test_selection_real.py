"""select_model on the real DIDSON test pings chooses what it chose before the K distribution
and the kernel refactor (recorded with the 21 default candidates, BIC, EM), but for images 0 and 6
since SQUAREM: there plain EM's choice came from candidates that had not converged in 2000
iterations (and so were refitted from the other starts); plain EM with max_iter=20000 chooses as
SQUAREM does on all 10 images (exponential + gamma; on image 6 exponential + rayleigh + weibull
since the Newton M-step no longer stalls at Weibull shape 1, before exponential + rice + rice)."""

from __future__ import annotations

import pytest

from sonarmap.io import read_ping
from sonarmap.stats.selection import select_model

CHOSEN = [
    ("exponential", "gamma"),
    ("exponential", "gamma"),
    ("exponential", "rayleigh"),
    ("exponential", "gamma"),
    ("exponential", "rayleigh", "rice"),
    ("exponential", "weibull"),
    ("exponential", "rayleigh", "weibull"),
    ("exponential", "exponential", "weibull"),
    ("exponential", "rayleigh", "weibull"),
    ("exponential", "rayleigh", "rayleigh"),
]


@pytest.mark.slow
def test_default_selection_unchanged_on_didson(test_ping_paths):
    chosen = [select_model(read_ping(p).image) for p in test_ping_paths]
    assert [s.candidates[s.best_index] for s in chosen] == CHOSEN
