"""Survey-scale processing: chunked, resumable batch runs on local processes or dask.distributed.

A survey is a list of pings (one PNG+JSON file each, or frames of multi-ping files) cut into
chunks of ``chunk_size`` consecutive pings.  Each chunk is one task: a worker reads its own pings
from disk (tasks carry file names, never images), runs the fused per-ping pipeline
(:func:`sonarmap.pipeline.process_ping`: pre-process -> mixture fit -> segment -> ranges) and stores
chunk ``k`` in zarr chunk ``k`` of every product variable.  Who writes the chunk files depends on
the executor: local worker processes (same file system) write their own chunk through zarr's API
(:class:`sonarmap.store.ChunkRows`; distinct chunks are distinct files, so concurrent
writers are safe) and report success; dask workers, possibly on other machines, send back the
products (a few kB per ping) and the calling process writes them the same way.  Either way the
calling process alone writes a chunk's completion marker, atomically, and only *after* the chunk's
data is in place (a chunk without its marker is recomputed by a resumed run, and so is a chunk
marked done whose files are missing or fail their checksum).  Because the
per-ping path is a pure function of (ping, configuration), every chunk has a fixed place in the
store and the chunk files are the same bytes whoever writes them, the output is identical whether
chunks ran serially, in local worker processes or on a dask cluster, in any
order, with retries, or across an interruption and a resumed run.

The output is a product store (:mod:`sonarmap.store.products`: its layout, markers and checks;
:func:`open_products` / :func:`load_products` read it).  A run holds an exclusive lock on its
output (:class:`sonarmap._atomic.WriterLock`), so a second run on the same output fails at once
instead of interleaving with the first; the lock of a killed run is taken over by the next.
Re-running the same command (same inputs, configuration and options: compared through a
fingerprint) resumes; anything else needs ``overwrite=True``.

Modules: :mod:`~sonarmap.survey.plan` (chunks, fingerprint), :mod:`~sonarmap.survey.executors`
(serial, local processes, dask) and :mod:`~sonarmap.survey.run` (:func:`process_survey`); the
store itself, and the store functions re-exported here, are :mod:`sonarmap.store`.
"""

from __future__ import annotations

from sonarmap.datamodel import INFORMATIONAL_FLAGS, N_OTHER_RETURNS, PRODUCT_RANGES, PRODUCT_VARIABLES
from sonarmap.store import (
    LIVE_SETTLE_S,
    ProductAppender,
    create_product_store,
    flagged_mask,
    is_product_store,
    load_products,
    open_products,
    product_ping,
    product_record,
    product_schema,
    product_summary,
    remove_store,
    stack_product_records,
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
