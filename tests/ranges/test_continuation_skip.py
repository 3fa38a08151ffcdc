"""``measure._continuation`` returns None without calling ``continuation_extra`` when the
continuation mask holds no pixel: that kernel keeps none of an empty mask."""

from __future__ import annotations

import numpy as np

from sonarmap.ranges._kernels import continuation_extra


def test_an_empty_continuation_mask_keeps_nothing() -> None:
    rng = np.random.default_rng(8)
    for _ in range(200):
        n, m = int(rng.integers(1, 80)), int(rng.integers(1, 40))
        extra = np.zeros((n, m), dtype=bool)
        cand = rng.random((n, m)) < rng.random()
        edge_bin = rng.random(5) * n
        first = rng.integers(-1, 5, m)
        r0, r1 = sorted(int(v) for v in rng.integers(-2, n + 3, 2))
        out, hit, cols, e0, e1 = continuation_extra(extra, cand, first, edge_bin, r0, r1)
        assert not hit and cols.size == 0 and (e0, e1) == (n, 0) and not out.any()
