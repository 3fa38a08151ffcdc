"""Growing product stores (``sonarmap live``): :func:`create_product_store` and :class:`ProductAppender`."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.datamodel import COORD_RANGE
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.ping import Ping
from sonarmap.store.chunks import ChunkWriter, put_file
from sonarmap.store.metadata import int_attr, node_docs, read_metadata_doc, with_consolidated
from sonarmap.store.products import (
    DEFAULT_CHUNK_SIZE,
    create_products,
    finish_store,
    flagged_mask,
    inspect_products,
    store_geometry,
    write_marker,
)
from sonarmap.store.records import stack_product_records

__all__ = ["ProductAppender", "create_product_store"]


def create_product_store(path: str | os.PathLike[str], ping: Ping, products: Any, *, config: Any,
                         chunk_size: int = DEFAULT_CHUNK_SIZE, keep_labels: bool = False,
                         inputs: Sequence[str] = (), fingerprint: str = "") -> None:
    """Create an empty product store (0 pings) for :class:`ProductAppender`, atomically.

    The layout, attributes and codecs are those of :func:`process_survey`'s stores; the schema
    and static coordinates come from the first ping and its products.  The root attribute
    ``live_status`` is ``"writing"`` until the appender is closed.

    Raises
    ------
    InputError
        If ``chunk_size`` is not a positive integer.
    """
    if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
        raise InputError(f"chunk_size: must be a positive integer (got {chunk_size!r})")
    create_products(path, ping.geometry, products, config=config, keep_labels=keep_labels, chunk_size=int(chunk_size),
                    n_pings=0, n_chunks=0, inputs=list(inputs)[:20], n_input_files=len(inputs), poses=None,
                    fingerprint=fingerprint, extra_attrs={"live_status": "writing"})


class ProductAppender:
    """Append pings' products to a store made by :func:`create_product_store`; readers see prefixes.

    Each :meth:`append` is one flush, published so that readers always see a consistent prefix
    of the pings: (1) the chunk files of the new rows are written, each atomically (a partly
    filled last chunk is rewritten with its earlier rows unchanged); (2) every per-ping array's
    ``zarr.json`` gets the new length; (3) the root ``zarr.json`` - the ``n_pings`` / ``n_chunks``
    attributes and the consolidated metadata - is replaced in one rename.  Readers of the
    consolidated metadata (``xarray.open_zarr``) switch from one prefix to the next at (3);
    :func:`open_products` retries for up to :data:`LIVE_SETTLE_S` while (2)-(3) are under way.
    Full chunks get their completion marker; :meth:`close` marks the store complete.

    Parameters
    ----------
    path : path-like
        The store.
    range_m : ndarray, shape (n_bins,), optional
        Ranges of the sonar's bins (the ``echo_range`` row of every ping): pass the first ping's
        ``geometry.range_m``; default: from the store's ``source_geometry`` attribute.

    Raises
    ------
    DataFormatError
        If ``path`` is not a product store this version writes.
    """

    def __init__(self, path: str | os.PathLike[str], *, range_m: Any = None) -> None:
        self.path = Path(path)
        st, schema = inspect_products(self.path)
        self.schema = schema
        self.chunk_size = int_attr(st.attrs, "chunk_size", self.path, low=1)
        self.n_pings = int_attr(st.attrs, "n_pings", self.path)
        if self.n_pings:
            raise DataFormatError("ProductAppender needs a new, empty store", self.path)
        self._range_m = np.asarray(store_geometry(st).range_m if range_m is None else range_m, np.float64)
        if self._range_m.shape != (int(st.arrays[COORD_RANGE].shape[-1]),):
            raise InputError(f"range_m: shape {self._range_m.shape}, the store has "
                             f"{int(st.arrays[COORD_RANGE].shape[-1])} range bins")
        self._names = [*schema, COORD_RANGE]
        writer = ChunkWriter.open(self.path, self._names)
        if writer is None:
            raise DataFormatError("the store's arrays use codecs this version does not write", self.path)
        self._writer = writer
        self._root_doc = read_metadata_doc(self.path / "zarr.json")
        self._nodes = node_docs(self.path)
        self._tail: list[dict[str, Any]] = []
        self.n_flagged = 0
        self.closed = False

    def append(self, records: Sequence[dict[str, Any]]) -> None:
        """Write and publish the rows ``records`` (:func:`product_record`) after the stored pings."""
        if self.closed:
            raise SonarmapError(f"{self.path}: the store was closed")
        if not records:
            return
        k = self.chunk_size
        n0, n1 = self.n_pings, self.n_pings + len(records)
        c0 = n0 // k
        rows = [*self._tail, *records]
        for c in range(c0, -(-n1 // k)):
            part = rows[(c - c0) * k : (c - c0 + 1) * k]
            data = stack_product_records(part, self.schema)
            data[COORD_RANGE] = np.broadcast_to(self._range_m, (len(part), self._range_m.size))
            self._writer.write(c, data)
        self._tail = rows[(n1 // k - c0) * k :]
        self.n_flagged += int(flagged_mask([r["flags"] for r in records]).sum())
        for name in self._names:
            doc = self._nodes[name]
            doc["shape"] = [n1, *doc["shape"][1:]]
            self._replace(self.path / name / "zarr.json", doc)
        self._publish(n1)
        for c in range(c0, n1 // k):
            write_marker(self.path, c, c * k, (c + 1) * k)
        self.n_pings = n1

    def close(self) -> None:
        """Mark the store complete (last chunk's marker, ``live_status`` "complete", summary)."""
        if self.closed:
            return
        k, n = self.chunk_size, self.n_pings
        if n % k:
            write_marker(self.path, n // k, (n // k) * k, n)
        self._publish(n, status="complete")
        finish_store(self.path, n, self.n_flagged)
        self.closed = True

    def _publish(self, n: int, status: str = "writing") -> None:
        doc = self._root_doc
        attrs = doc.setdefault("attributes", {})
        attrs.update(n_pings=n, n_chunks=-(-n // self.chunk_size), live_status=status)
        self._replace(self.path / "zarr.json", with_consolidated(doc, self._nodes))

    def _replace(self, target: Path, doc: dict[str, Any]) -> None:
        """Replace one metadata document atomically (temporary file in the store, then rename)."""
        payload = json.dumps(doc).encode("utf-8")  # compact: the C encoder, ~10x faster
        put_file(self.path, target, payload, str(target.relative_to(self.path)))
