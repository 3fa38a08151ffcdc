"""Per-ping products as the rows of a product store (one record per ping) and their stacking into chunks."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError, SonarmapError
from sonarmap.datamodel import N_OTHER_RETURNS, PRODUCT_FILL

__all__ = ["mixture_arrays", "product_record", "product_schema", "stack_product_records"]


def mixture_arrays(fit: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], tuple[str, ...]]:
    """``(weights (K,), params (K, P), component names)`` of a mixture fit.

    Accepts :class:`sonarmap.stats.mixture.MixtureFit` or a mapping with ``weights`` and
    ``params``; ragged parameter lists (the zero spike has none) are padded with NaN.
    """
    if fit is None:
        return np.zeros(0), np.zeros((0, 0)), ()
    get = fit.get if isinstance(fit, Mapping) else (lambda k, d=None: getattr(fit, k, d))
    weights = np.asarray(get("weights"), dtype=np.float64).reshape(-1)
    params = get("params", None)
    rows = [np.asarray(r, dtype=np.float64).reshape(-1) for r in (params if params is not None else ())]
    width = max((r.size for r in rows), default=0)
    arr = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        arr[i, : r.size] = r
    names = tuple(str(n) for n in (get("component_names", None) or ()))
    return weights, arr, names


def product_record(products: Any, *, keep_labels: bool = False) -> dict[str, Any]:
    """One ping's products as the row of every product variable (what a store holds per ping).

    Parameters
    ----------
    products : PingProducts
        The output of :func:`sonarmap.pipeline.process_ping`.
    keep_labels : bool
        Include the ``labels`` image.

    Returns
    -------
    dict of str to ndarray or str
    """
    if products.fit is None:  # no fit (e.g. a constant image): the mixture rows stay NaN
        weights, params = np.zeros(0), np.zeros((0, 0))
    else:
        weights, params, _ = mixture_arrays(products.fit)
    r = products.ranges
    rec: dict[str, Any] = {
        "ping_time": np.int64(products.time_ns),
        "source": str(products.source),
        "kld": np.float64(np.nan if products.kld is None else products.kld),
        "flags": " ".join(str(f) for f in (products.flags or ())),
        "background_range_db": np.float64(_background_db(products)),
        "floor_levels": np.int16(getattr(products, "floor_levels", 0)),
        "mixture_weight": weights,
        "mixture_param": params,
        "pd": np.float64(np.nan if getattr(products, "pd", None) is None else products.pd),
        "pfa": np.float64(np.nan if getattr(products, "pfa", None) is None else products.pfa),
        "range": np.asarray(r.range_m, dtype=np.float32),
        "range_bin": np.asarray(r.bin, dtype=np.int32),
        "range_intensity": np.asarray(r.intensity, dtype=np.float32),
        "range_confidence": np.asarray(r.confidence, dtype=np.float32),
        "range_sigma": _beam_row(r, "sigma_m"),
        "p_detect": _beam_row(r, "p_detect"),
        "other_range": _other_rows(r),
    }
    if keep_labels:
        labels = getattr(products, "labels", None)
        if labels is None:
            raise SonarmapError(f"{products.source}: pipeline returned no labels with keep_labels")
        rec["labels"] = np.asarray(labels).astype(np.uint8)
    return rec


def _beam_row(ranges: Any, name: str) -> NDArray[np.float32]:
    """``ranges.<name>`` as a float32 row (NaN when the ranges do not carry it)."""
    v = getattr(ranges, name, None)
    n = np.asarray(ranges.range_m).shape[0]
    return np.full(n, np.nan, np.float32) if v is None else np.asarray(v, dtype=np.float32)


def _other_rows(ranges: Any) -> NDArray[np.float32]:
    """``ranges.other_range_m`` as float32 ``(N_OTHER_RETURNS, n_beams)``: the nearest surfaces,
    NaN-padded (further ones are not stored)."""
    n = np.asarray(ranges.range_m).shape[0]
    out = np.full((N_OTHER_RETURNS, n), np.nan, np.float32)
    v = getattr(ranges, "other_range_m", None)
    if v is not None and np.ndim(v) == 2:
        v = np.asarray(v, dtype=np.float32)[:N_OTHER_RETURNS]
        out[: v.shape[0]] = v
    return out


def _background_db(products: Any) -> float:
    bg = getattr(products, "background", None)
    return float(bg.range_dependence_db) if bg is not None and bg.applied else math.nan


def stack_product_records(records: Sequence[dict[str, Any]], schema: Mapping[str, tuple[tuple[int, ...], str]],
                          sources: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Stack :func:`product_record` rows into one array per variable (leading dimension: pings).

    ``sources`` names the pings in messages (default: the records' ``source``).

    Raises
    ------
    InputError
        If a ping's products do not fit the schema (another sonar geometry).
    """
    if sources is None:
        sources = [str(r.get("source", "")) for r in records]
    out: dict[str, np.ndarray] = {}
    n = len(records)
    for name, (shape, dtype) in schema.items():
        if dtype == "str":
            out[name] = np.array([rec[name] for rec in records], dtype=object)
            continue
        arr = np.full((n, *shape), PRODUCT_FILL[name], dtype=dtype)
        for i, rec in enumerate(records):
            val = np.asarray(rec[name])
            if val.shape != shape:
                # Mixture fits with fewer components than the survey's keep their fill value.
                if name.startswith("mixture") and val.ndim == len(shape) and all(
                    a <= b for a, b in zip(val.shape, shape, strict=True)
                ):
                    arr[(i, *(slice(0, s) for s in val.shape))] = val
                    continue
                raise InputError(
                    f"{sources[i]}: product {name} has shape {val.shape}, the survey's is {shape} "
                    "(are all pings from the same sonar geometry?)"
                )
            arr[i] = val
        out[name] = arr
    return out


def product_schema(record: Mapping[str, Any]) -> dict[str, tuple[tuple[int, ...], str]]:
    """Shapes (without the ping dimension) and dtypes of a :func:`product_record`."""
    schema: dict[str, tuple[tuple[int, ...], str]] = {}
    for name, val in record.items():
        if isinstance(val, str):
            schema[name] = ((), "str")
        else:
            a = np.asarray(val)
            schema[name] = (tuple(a.shape), a.dtype.str)
    return schema
