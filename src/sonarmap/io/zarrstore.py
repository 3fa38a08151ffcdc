"""Registry hooks for zarr stores (:mod:`sonarmap.store`).

The store itself (data model, writing, checking and reading) lives in :mod:`sonarmap.store`;
this module only lets :func:`sonarmap.io.read_pings` and ``sonarmap info`` recognise a store.
A product store of ``sonarmap process`` (:mod:`sonarmap.survey`) is recognised too: ``info``
summarises it (:func:`sonarmap.store.product_summary`); it holds products, not pings, so reading
pings from it is a clean error.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.errors import DataFormatError
from sonarmap.geometry import as_geometry
from sonarmap.io._binary import make_summary
from sonarmap._files import MAX_SIDECAR_BYTES, read_bytes_bounded
from sonarmap.io.reader import GeometrySpec
from sonarmap.ping import Ping
from sonarmap.datamodel import ATTR_MODEL, DIM_PING, VAR_GEOMETRY, VAR_INTENSITY
from sonarmap.store import (
    dataset_to_pings,
    inspect_survey,
    is_product_store,
    is_zarr_store,
    open_survey,
    product_summary,
    read_array,
    survey_geometries,
    survey_length,
    survey_status,
)

__all__ = ["FORMAT", "sniff", "iter_pings", "count_pings", "summary"]

FORMAT = "zarr"


def sniff(path: Path, head: bytes) -> bool:
    """A zarr store directory (v2 ``.zgroup`` or v3 ``zarr.json``) holding an intensity array, or
    whose root metadata names the sonarmap data model (so a store that lost its intensity array
    is reported as a damaged survey, not as an unknown format)."""
    if not is_zarr_store(path):
        return False
    if (path / VAR_INTENSITY).is_dir():
        return True
    for name in ("zarr.json", ".zattrs"):
        try:
            head = read_bytes_bounded(path / name, MAX_SIDECAR_BYTES, "group metadata")
            if ATTR_MODEL.encode() in head or b"sonarmap_format" in head:
                return True
        except DataFormatError:
            continue
    return False


def iter_pings(path: str | os.PathLike[str], *, geometry: GeometrySpec = None, start: int = 0,
               stop: int | None = None, **_: Any) -> Iterator[Ping]:
    """:meth:`Reader.iter_pings <sonarmap.io.reader.Reader.iter_pings>` of survey stores: pings
    ``start:stop``, one ``ping_time`` chunk in memory; the chunks before ``start`` are not read.

    Messages about a bad value or chunk give the store's ping and chunk numbers, whatever
    ``start`` is.  A product store (``sonarmap process``) holds no ping images and is refused
    with a ``DataFormatError``.
    """
    from sonarmap.io.reader import check_ping_range

    start, stop = check_ping_range(start, stop)
    if is_product_store(path):
        raise DataFormatError("is a product store (sonarmap process): it holds products, not pings; read its "
                              "inputs, or use sonarmap info / sonarmap show on it", path)
    ds = open_survey(path)
    g = None if geometry is None else as_geometry(geometry)
    yield from dataset_to_pings(ds, geometry=g, start=start, stop=stop)


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of pings (array metadata only; a product store's ``n_pings``)."""
    if is_product_store(path):
        return int(survey_status(path)["n_pings"])
    return survey_length(Path(path))


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry, ping count, time span and store fields (metadata and the time coordinate only).

    Raises
    ------
    DataFormatError
        If the store's metadata, times or first geometry index are corrupt (naming the store).
    """
    from sonarmap.store import consolidated_status

    if is_product_store(path):
        return product_summary(path)
    ds = open_survey(path)
    n = int(ds.sizes.get(DIM_PING, 0))
    geoms = survey_geometries(ds)
    t = ds[DIM_PING].values.astype("datetime64[ns]").astype(np.int64) if n else np.zeros(0, np.int64)
    st = inspect_survey(Path(path))
    g = st.group
    first = None
    if n and geoms:
        gi = int(read_array(st, VAR_GEOMETRY, slice(0, 1))[0])
        if not 0 <= gi < len(geoms):
            raise DataFormatError(f"{VAR_GEOMETRY}: ping 0: value {gi} outside the {len(geoms)} stored geometries",
                                  path)
        first = geoms[gi]
    return make_summary(
        FORMAT,
        path,
        n_pings=n,
        geometry=first,
        time_start_ns=int(t.min()) if n else None,
        time_end_ns=int(t.max()) if n else None,
        data_model=ds.attrs.get(ATTR_MODEL),
        image_shape=tuple(int(s) for s in ds[VAR_INTENSITY].shape[1:]),
        n_geometries=len(geoms),
        variables=sorted(str(v) for v in ds.data_vars),
        chunk_pings=int(st.arrays[VAR_INTENSITY].chunks[0]),
        zarr_format=int(g.metadata.zarr_format),
        consolidated=consolidated_status(path),
    )
