"""Background normalisation helpers (module sonarmap.preprocess.normalise)."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from sonarmap.preprocess.normalise import expand_grid


def _bilinear_reference(grid: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Float64 bilinear interpolation from block centres, edges held (dense weight matrices)."""

    def weights(n: int, nb: int) -> np.ndarray:
        x = np.clip((np.arange(n) + 0.5) * nb / n - 0.5, 0, nb - 1)
        i0 = np.minimum(np.floor(x).astype(int), max(nb - 2, 0))
        i1 = np.minimum(i0 + 1, nb - 1)
        w = np.zeros((n, nb))
        np.add.at(w, (np.arange(n), i0), 1 - (x - i0))
        np.add.at(w, (np.arange(n), i1), x - i0)
        return w

    return weights(shape[0], grid.shape[0]) @ grid.astype(np.float64) @ weights(shape[1], grid.shape[1]).T


@pytest.mark.parametrize(("grid_shape", "shape"), [((16, 16), (703, 256)), ((16, 3), (2000, 48)),
                                                   ((1, 1), (40, 30)), ((5, 1), (40, 30)), ((1, 7), (9, 64)),
                                                   ((2, 2), (4, 3))])
def test_expand_grid_is_bilinear_and_independent_of_blas_threads(grid_shape, shape) -> None:
    grid = np.random.default_rng(0).uniform(0.5, 2.0, grid_shape).astype(np.float32)
    out = expand_grid(grid, shape)
    assert out.dtype == np.float32 and out.shape == shape and out.flags.c_contiguous
    np.testing.assert_allclose(out, _bilinear_reference(grid, shape), rtol=0, atol=1e-6)
    # block centres are reproduced and the corners held
    assert out[0, 0] == pytest.approx(grid[0, 0], abs=1e-6)
    assert out[-1, -1] == pytest.approx(grid[-1, -1], abs=1e-6)
    with threadpool_limits(1):
        assert np.array_equal(expand_grid(grid, shape), out)
