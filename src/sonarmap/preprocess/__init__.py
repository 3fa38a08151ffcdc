"""Pre-processing: beam-pattern deconvolution, taper, radial gain / absorption (paper eq. 2-7).

See ``docs/preprocessing.md``.  Sub-modules are imported on first attribute access.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "deconvolve",
    "wiener_filter",
    "correct_taper",
    "estimate_taper",
    "TaperEstimate",
    "RadialGain",
    "radial_gain_db",
    "apply_radial_gain",
    "estimate_radial_gain",
    "background_intensity",
    "intensity_from_nonzero_mean",
    "absorption_db_per_m",
    "PreprocessConfig",
    "preprocess",
    "preprocess_image",
]

_WHERE = {
    "deconvolve": "deconvolution",
    "wiener_filter": "deconvolution",
    "correct_taper": "gain",
    "estimate_taper": "gain",
    "TaperEstimate": "gain",
    "RadialGain": "gain",
    "radial_gain_db": "gain",
    "apply_radial_gain": "gain",
    "estimate_radial_gain": "gain",
    "background_intensity": "gain",
    "intensity_from_nonzero_mean": "gain",
    "absorption_db_per_m": "absorption",
    "PreprocessConfig": "pipeline",
    "preprocess": "pipeline",
    "preprocess_image": "pipeline",
}


def __getattr__(name: str) -> Any:
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module 'sonarmap.preprocess' has no attribute {name!r}")
    return getattr(importlib.import_module(f"sonarmap.preprocess.{mod}"), name)
