"""The one zarr store of sonarmap: raw pings (``sonarmap convert``) and per-ping products
(``sonarmap process`` / ``sonarmap live``), written, checked and read in one place.

Both kinds of store share the data model of :mod:`sonarmap.datamodel` (names, dimensions,
coordinates, CF attributes, fill values, value ranges), the codecs (every chunk ``zstd`` + ``crc32c``, every chunk written), consolidated
metadata kept in step with the arrays, atomic creation (built beside the target, renamed into
place) and one exclusive writer at a time (:class:`sonarmap._atomic.WriterLock`).  sonarmap's
readers never trust a store: every metadata document is parsed and checked first, every chunk file
is checked before zarr opens it, and every value against its documented range; a failure is one
:class:`~sonarmap.errors.DataFormatError` naming the store and the file, array, chunk or ping.

Modules
-------
:mod:`~sonarmap.store.metadata`
    Metadata documents, root attributes (geometries as JSON), consolidated metadata.
:mod:`~sonarmap.store.check`
    Metadata inspection (:class:`CheckedStore`), chunk files and checksums, value checks.
:mod:`~sonarmap.store.chunks`
    The codecs, chunk keys, the store's temporary files, and the two chunk writers of product
    stores (zarr's API; direct and atomic).
:mod:`~sonarmap.store.pings`
    The raw-ping store: pings <-> xarray Dataset, opening and reading it back.
:mod:`~sonarmap.store.writer`
    Writing raw-ping stores (:class:`SurveyWriter`), extra per-ping variables.
:mod:`~sonarmap.store.records`
    Per-ping products as the rows of a product store.
:mod:`~sonarmap.store.products`
    The product store: schema, creation, resume markers, progress, checked opening and loading.
:mod:`~sonarmap.store.appender`
    Growing product stores of live runs (:class:`ProductAppender`).

Examples
--------
>>> from sonarmap.store import dataset_to_pings, open_survey, write_survey  # doctest: +SKIP
>>> write_survey(pings, "survey.zarr")  # doctest: +SKIP
>>> back = list(dataset_to_pings(open_survey("survey.zarr")))  # doctest: +SKIP
"""

from __future__ import annotations

from sonarmap.store.appender import ProductAppender, create_product_store
from sonarmap.store.check import (
    CheckedStore,
    check_chunk_files,
    check_times,
    check_values,
    crc_failures,
    inspect_store,
    kind_of,
    locate_error,
    read_array,
)
from sonarmap.store.chunks import (
    STATE_DIR,
    ChunkRows,
    ChunkWriter,
    StoreReplacedError,
    array_codec_kwargs,
    checksum_codecs,
    create_array,
    open_writable,
    remove_tmp,
)
from sonarmap.store.metadata import (
    consolidate,
    consolidated_status,
    int_attr,
    invalidate_consolidated,
    is_zarr_store,
    read_root_attrs,
)
from sonarmap.store.pings import (
    PingVariable,
    dataset_to_pings,
    inspect_survey,
    open_survey,
    pings_to_dataset,
    survey_geometries,
    survey_length,
)
from sonarmap.store.products import (
    DEFAULT_CHUNK_SIZE,
    LIVE_SETTLE_S,
    complete_marker,
    create_products,
    damaged_chunks,
    done_chunks,
    finish_store,
    flagged_mask,
    inspect_products,
    is_product_store,
    load_products,
    marker_dir,
    open_products,
    product_ping,
    product_summary,
    reference_range,
    remove_marker_temporaries,
    remove_store,
    store_geometry,
    survey_status,
    unmark_chunk,
    write_marker,
)
from sonarmap.store.records import mixture_arrays, product_record, product_schema, stack_product_records
from sonarmap.store.writer import SurveyWriter, add_ping_variable, write_ping_variable, write_survey

__all__ = [
    # raw-ping stores
    "PingVariable", "SurveyWriter", "write_survey", "pings_to_dataset", "open_survey", "inspect_survey",
    "survey_length", "dataset_to_pings", "survey_geometries", "add_ping_variable", "write_ping_variable",
    # product stores
    "DEFAULT_CHUNK_SIZE", "LIVE_SETTLE_S", "flagged_mask", "product_record", "product_schema",
    "stack_product_records", "mixture_arrays", "create_products", "create_product_store", "ProductAppender",
    "marker_dir", "done_chunks", "damaged_chunks", "unmark_chunk", "write_marker", "remove_marker_temporaries", "complete_marker", "finish_store",
    "remove_store", "survey_status", "inspect_products", "is_product_store", "store_geometry", "reference_range",
    "product_summary", "open_products", "load_products", "product_ping",
    # metadata, checking and chunks
    "is_zarr_store", "read_root_attrs", "int_attr", "consolidate", "invalidate_consolidated",
    "consolidated_status", "CheckedStore", "inspect_store", "kind_of", "read_array", "check_times",
    "check_values", "check_chunk_files", "crc_failures", "locate_error", "STATE_DIR", "checksum_codecs", "array_codec_kwargs",
    "create_array", "remove_tmp", "ChunkRows", "ChunkWriter", "StoreReplacedError", "open_writable",
]
