"""select_model on the real DIDSON test pings chooses what it chose before the K distribution
and the kernel refactor (recorded with the 21 default candidates, BIC, EM)."""

from __future__ import annotations

import pytest

from sonarmap.io import read_ping
from sonarmap.stats.selection import select_model

CHOSEN = [
    ("exponential", "rice", "rice"),
    ("exponential", "gamma"),
    ("exponential", "rayleigh"),
    ("exponential", "gamma"),
    ("exponential", "rayleigh", "rice"),
    ("exponential", "weibull"),
    ("exponential", "rayleigh", "rice"),
    ("exponential", "exponential", "weibull"),
    ("exponential", "rayleigh", "weibull"),
    ("exponential", "rayleigh", "rayleigh"),
]


@pytest.mark.slow
def test_default_selection_unchanged_on_didson(test_ping_paths):
    chosen = [select_model(read_ping(p).image) for p in test_ping_paths]
    assert [s.candidates[s.best_index] for s in chosen] == CHOSEN
