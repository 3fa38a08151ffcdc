"""``preprocess_finite`` (the pipeline's pre-processing of an image it has checked) equals
``preprocess_image`` bit for bit, and hands anything it cannot take to it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import preset
from sonarmap.preprocess.pipeline import PreprocessConfig, preprocess_finite, preprocess_image, recipe


@pytest.mark.parametrize("normalise", ["rescale-max", "min-max", "none"])
def test_the_same_image_as_preprocess_image(normalise: str) -> None:
    g = preset("didson-hf")
    rng = np.random.default_rng(7)
    cfg = PreprocessConfig(**{**dataclasses.asdict(recipe("paper-table1")), "normalise": normalise})
    for _ in range(3):
        img = (rng.integers(0, 256, g.shape) * (rng.random(g.shape) < 0.4) / 255.0).astype(np.float32)
        want = preprocess_image(img, g, cfg)
        got = preprocess_finite(img, g, cfg, float(img.max()))
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_other_arrays_go_through_the_checks() -> None:
    g = preset("didson-hf")
    img = np.zeros(g.shape)  # float64: not the pipeline's float32 image
    img[3, 4] = np.nan
    with pytest.raises(InputError):
        preprocess_finite(img, g, PreprocessConfig(), 0.0)
    with pytest.raises(InputError):
        preprocess_finite(np.zeros((0, 4), dtype=np.float32), g, PreprocessConfig(), 0.0)
    f64 = np.full(g.shape, 0.5)
    assert np.array_equal(preprocess_finite(f64, g, PreprocessConfig(), 0.5), preprocess_image(f64, g, PreprocessConfig()))
