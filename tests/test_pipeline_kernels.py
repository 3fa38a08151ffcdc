"""The pipeline's kernels (:mod:`sonarmap._pipeline_kernels`) equal the numpy they replace."""

from __future__ import annotations

import numpy as np

from sonarmap._pipeline_kernels import any_columns
from sonarmap.pipeline import _labelled_columns


def test_any_columns_is_numpys_any_along_range() -> None:
    rng = np.random.default_rng(11)
    for shape in [(512, 96), (64, 16), (7, 3), (1, 1), (0, 4), (5, 0)]:
        for p in (0.0, 0.002, 0.4):
            for dtype in (np.uint8, np.uint16):
                labels = ((rng.random(shape) < p) * rng.integers(1, 300, shape)).astype(dtype)
                want = labels.any(axis=0)
                got = any_columns(labels)
                assert got.dtype == np.bool_ and np.array_equal(got, want)
                assert np.array_equal(_labelled_columns(labels), want)
                assert np.array_equal(_labelled_columns(np.asfortranarray(labels)), want)
