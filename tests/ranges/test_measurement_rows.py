"""The range stage's measurement image on a subset of rows (``measure._measurement_rows``: the beam
factor interpolated from its block grid on the fly, this thread's reused work image) against the
reference :func:`sonarmap.ranges.measure.measurement_image`, bit for bit."""

from __future__ import annotations

import types

import numpy as np
import pytest

from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping
from sonarmap.ranges.config import RangeConfig
from sonarmap.ranges.measure import _measurement_rows, measurement_image


def _ping(rng: np.random.Generator, n: int, m: int, log_db: float | None) -> Ping:
    geom = SonarGeometry(range_m=1.0 + 0.01 * np.arange(n), azimuth_rad=np.linspace(-0.5, 0.5, m))
    img = rng.exponential(1.0, (n, m)).astype(np.float32) * np.float32(0.2)
    if log_db is not None:
        img = np.round(img * 255) / np.float32(255)
    return Ping(image=img.astype(np.float32), geometry=geom, meta={} if log_db is None else
                {"log_dynamic_range_db": log_db})


@pytest.mark.parametrize("seed", range(12))
def test_rows_match_measurement_image(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(5, 90)), int(rng.integers(2, 40))
    ping = _ping(rng, n, m, None if seed % 2 else 37.0)
    nb = (int(rng.integers(1, 9)), int(rng.integers(1, 7)))
    factor = None if seed % 4 == 3 else rng.uniform(0.5, 2.0, nb).astype(np.float32)
    bg = types.SimpleNamespace(level_by_bin=rng.uniform(0.05, 0.3, n).astype(np.float32), beam_factor=factor)
    config = RangeConfig()
    done: list[object] = []
    # a sequence of requests on one ping (growing, shrinking), then a new ping reusing the work image
    for _ in range(4):
        r0, r1 = sorted(int(v) for v in rng.integers(-5, n + 5, 2))
        got = _measurement_rows(ping, bg, config, r0, r1, done).copy()
        a, b = done[1]  # type: ignore[misc]
        want = measurement_image(ping, bg, config, rows=(a, b))
        assert np.array_equal(got, want)
        assert (a, b) == (max(r0, 0), min(r1, n)) or (a <= max(r0, 0) and b >= min(r1, n))
    done = []
    got = _measurement_rows(ping, bg, config, 2, n - 1, done)
    assert np.array_equal(got, measurement_image(ping, bg, config, rows=(2, n - 1)))
