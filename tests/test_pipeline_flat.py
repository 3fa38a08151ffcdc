"""The pipeline's constant-image tests (``_all_equal``, ``_flat``) answer as ``max == min`` and
``not np.any(image > 0) or max == min`` do, without the pass for the minimum where the first
pixel decides."""

from __future__ import annotations

import numpy as np

from sonarmap.pipeline import _all_equal, _flat


def test_all_equal_and_flat_are_numpys() -> None:
    rng = np.random.default_rng(9)
    images = [np.zeros((4, 3), np.float32), np.full((4, 3), 0.5, np.float32), -np.zeros((2, 2), np.float32),
              np.array([[-0.0, 0.0], [0.0, -0.0]], np.float32), np.array([[0.0, np.nan]], np.float32),
              np.array([[np.nan, 0.3]], np.float32), np.array([[0.2, 0.2], [0.2, 0.1]], np.float32),
              np.array([[-1.0, -1.0]], np.float32)]
    for _ in range(200):
        img = (rng.random((int(rng.integers(1, 9)), int(rng.integers(1, 9)))) * rng.integers(0, 3)).astype(np.float32)
        if rng.random() < 0.3:
            img[:] = img.flat[0]
        images.append(img)
    for img in images:
        hi, lo = float(img.max()), float(img.min())
        assert _all_equal(img, hi) == (hi == lo)
        assert _flat(img) == (not np.any(img > 0) or hi == lo)
