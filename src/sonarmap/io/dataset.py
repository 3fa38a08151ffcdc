"""The raw-ping survey store's public names at their earlier import path.

The store lives in :mod:`sonarmap.store` (pings and products, one package); import from there.
"""

from __future__ import annotations

from sonarmap.datamodel import (
    COORD_AZIMUTH,
    COORD_RANGE,
    DATA_MODEL_VERSION,
    DIM_BEAM,
    DIM_PING,
    DIM_RANGE,
    INT_MISSING,
    TIME_UNITS_RE,
    VAR_INTENSITY,
)
from sonarmap.store import (
    CheckedStore,
    PingVariable,
    SurveyWriter,
    add_ping_variable,
    check_chunk_files,
    check_times,
    dataset_to_pings,
    inspect_store,
    kind_of,
    locate_error,
    open_survey,
    pings_to_dataset,
    read_array,
    survey_geometries,
    write_ping_variable,
    write_survey,
)

__all__ = [
    "DIM_PING",
    "DIM_RANGE",
    "DIM_BEAM",
    "VAR_INTENSITY",
    "COORD_RANGE",
    "COORD_AZIMUTH",
    "DATA_MODEL_VERSION",
    "INT_MISSING",
    "PingVariable",
    "SurveyWriter",
    "pings_to_dataset",
    "dataset_to_pings",
    "write_survey",
    "open_survey",
    "add_ping_variable",
    "write_ping_variable",
    "survey_geometries",
    "CheckedStore",
    "TIME_UNITS_RE",
    "inspect_store",
    "kind_of",
    "read_array",
    "check_times",
    "check_chunk_files",
    "locate_error",
]
