"""Survey-scale processing: chunked, resumable batch runs on local processes or dask.distributed.

A survey is a list of pings (one PNG+JSON file each, or frames of multi-ping files) cut into
chunks of ``chunk_size`` consecutive pings.  Each chunk is one task: a worker reads its own pings
from disk (tasks carry file names, never images), runs the fused per-ping pipeline
(:func:`sonarmap.pipeline.process_ping`: pre-process -> mixture fit -> segment -> ranges) and stores
chunk ``k`` in zarr chunk ``k`` of every product variable.  Who writes the chunk files depends on
the executor: local worker processes (same file system) write their own chunk through zarr's API
(:class:`sonarmap.survey.store.ChunkRows`; distinct chunks are distinct files, so concurrent
writers are safe) and report success; dask workers, possibly on other machines, send back the
products (a few kB per ping) and the calling process writes them the same way.  Either way the
calling process alone writes a chunk's completion marker, atomically, and only *after* the chunk's
data is in place (a chunk without its marker is recomputed by a resumed run).  Because the
per-ping path is a pure function of (ping, configuration), every chunk has a fixed place in the
store and the chunk files are the same bytes whoever writes them, the output is identical whether
chunks ran serially, in local worker processes or on a dask cluster, in any
order, with retries, or across an interruption and a resumed run.

Layout of the output store (zarr v3, readable with :func:`open_products` / ``xarray.open_zarr``;
dimensions and coordinates those of every sonarmap store, :mod:`sonarmap.datamodel`)::

    survey.zarr/
      zarr.json                 root attributes: provenance (sonarmap version, configuration,
                                inputs, fingerprint), written once when the store is created;
                                consolidated metadata (re-written whenever arrays change)
      range_sample, beam, echo_range (ping_time, range_sample), beam_azimuth (beam)  coordinates
      ping_time, source, kld, flags, mixture_weight, mixture_param, range, range_bin, ... arrays
      point_xyz, point_ping ... when poses were given (written after the last chunk)
      .sonarmap/chunks/<k>.done completion markers (data first, marker second)
      .sonarmap/tmp/            chunk files being written (moved into place; cleared on resume)
      .sonarmap/complete        the run finished (summary in JSON)

The store is created in a temporary directory and renamed into place, so it either exists with
complete metadata or not at all.  Every chunk carries a CRC32C checksum (``crc32c`` codec after
``zstd``); :func:`load_products` (what ``sonarmap report`` reads) checks the metadata, the chunks
and every value against the documented ranges of the variables (:data:`PRODUCT_RANGES`).  A run
holds an exclusive lock on its output (:class:`sonarmap._atomic.WriterLock`), so a second run on
the same output fails at once instead of interleaving with the first; the lock of a killed run
is taken over by the next.  Re-running the same command (same inputs, configuration and
options: compared through a fingerprint) resumes; anything else needs ``overwrite=True``.


Modules: :mod:`~sonarmap.survey.plan` (chunks, fingerprint), :mod:`~sonarmap.survey.records`
(products as rows), :mod:`~sonarmap.survey.store` (the product store), :mod:`~sonarmap.survey.executors`
(serial, local processes, dask) and :mod:`~sonarmap.survey.run` (:func:`process_survey`).
"""

from __future__ import annotations

from sonarmap.io.products import (
    INFORMATIONAL_FLAGS,
    N_OTHER_RETURNS,
    PRODUCT_VARIABLES,
    flagged_mask,
    is_product_store,
    product_summary,
    survey_status,
)
from sonarmap.survey.plan import (
    ChunkSpec,
    DEFAULT_CHUNK_SIZE,
    PingFunction,
    SurveyExistsError,
    SurveyPlan,
    plan_survey,
)
from sonarmap.survey.records import product_record, product_schema, stack_product_records
from sonarmap.survey.store import (
    LIVE_SETTLE_S,
    PRODUCT_RANGES,
    ProductAppender,
    create_product_store,
    load_products,
    open_products,
    product_ping,
    remove_store,
)
from sonarmap.survey.executors import warm_pipeline_once
from sonarmap.survey.run import SurveyResult, process_survey, replicate_pings, run_chunk

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "PingFunction",
    "N_OTHER_RETURNS",
    "PRODUCT_RANGES",
    "LIVE_SETTLE_S",
    "remove_store",
    "ChunkSpec",
    "SurveyPlan",
    "SurveyResult",
    "SurveyExistsError",
    "plan_survey",
    "process_survey",
    "run_chunk",
    "open_products",
    "load_products",
    "survey_status",
    "is_product_store",
    "product_summary",
    "product_ping",
    "replicate_pings",
    "PRODUCT_VARIABLES",
    "INFORMATIONAL_FLAGS",
    "flagged_mask",
    "product_record",
    "product_schema",
    "stack_product_records",
    "create_product_store",
    "ProductAppender",
    "warm_pipeline_once",
]
