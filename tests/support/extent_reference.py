"""Test-side reference of the metric extent rule (``sonarmap.ranges.drop_small_components``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["extent_reference"]


def extent_reference(mask: NDArray[np.bool_], geometry: object, min_extent_m: float) -> NDArray[np.bool_]:
    """``mask`` without the 8-connected components whose far-edge arc length (one beam spacing
    included) and range extent both stay below ``min_extent_m`` - a per-component loop over
    scipy's labels, independent of the library's kernel."""
    from scipy import ndimage

    r = np.asarray(geometry.range_m, dtype=np.float64)  # type: ignore[attr-defined]
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)  # type: ignore[attr-defined]
    dr, daz = (r[-1] - r[0]) / (r.size - 1), (az[-1] - az[0]) / (az.size - 1)
    lab, n = ndimage.label(mask, structure=np.ones((3, 3)))
    keep = np.zeros(n + 1, bool)
    for k, sl in enumerate(ndimage.find_objects(lab), 1):
        i0, i1, j0, j1 = sl[0].start, sl[0].stop - 1, sl[1].start, sl[1].stop - 1
        keep[k] = max(max(r[i1], r[i0]) * (az[j1] - az[j0] + daz), (i1 - i0 + 1) * dr) >= min_extent_m
    return keep[lab]
