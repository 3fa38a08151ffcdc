"""The data model of sonarmap's zarr stores, in one place: names, dimensions, coordinates, CF
attributes, fill values and documented value ranges of both kinds of store.

Both kinds of store share one coordinate layout - the raw-ping store that ``sonarmap convert``
writes (:mod:`sonarmap.store.pings`) and the product store that ``sonarmap process`` writes
(:mod:`sonarmap.store.products`)::

    dimensions    ping_time, range_sample, beam
    ping_time     (ping_time)                int64 ns since 1970, decoded as datetime64[ns]
    range_sample  (range_sample)             int32 0 .. n_bins - 1 (0 = nearest)
    beam          (beam)                     int32 0 .. n_beams - 1 (azimuth increases with beam)
    echo_range    (ping_time, range_sample)  float64, m: the range of each bin of each ping's
                                             geometry (the range window can change between pings)
    beam_azimuth  (beam)                     float64, rad, positive to starboard: the store's
                                             azimuth table; (ping_time, beam) only in a raw-ping
                                             store whose pings' tables differ (beam-steered
                                             multibeams), see :func:`azimuth_dims`

``echo_range`` and ``beam_azimuth`` are coordinates (``xarray.open_zarr`` lists them under
``Coordinates``) in both stores.  Stores written before this layout still read: raw-ping stores
with ``beam_azimuth (ping_time, beam)`` always, product stores with ``echo_range (range_sample)``
and no ``range_sample`` / ``beam`` index arrays.

The variables of each store are tabled here too: :data:`PING_ATTRS` / :data:`PING_ARRAYS` (the
raw-ping store's CF attributes and required arrays) and :data:`PRODUCT_VARIABLES` /
:data:`PRODUCT_FILL` / :data:`PRODUCT_RANGES` (the product store's dimensions and attributes, fill
values and documented value ranges).  Reading and writing the stores is :mod:`sonarmap.store`.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

__all__ = [
    "DIM_PING",
    "DIM_RANGE",
    "DIM_BEAM",
    "DIM_XYZ",
    "DIM_QUAT",
    "COORD_RANGE",
    "COORD_AZIMUTH",
    "VAR_INTENSITY",
    "COORD_ATTRS",
    "COORDINATES",
    "azimuth_dims",
    # times
    "TIME_MAX_NS",
    "TIME_UNITS_RE",
    "TIME_UNITS",
    "PING_TIME_UNITS",
    # the raw-ping store
    "VAR_GEOMETRY",
    "VAR_SOURCE",
    "VAR_POSITION",
    "VAR_ORIENTATION",
    "META_PREFIX",
    "DATA_MODEL_VERSION",
    "INT_MISSING",
    "ATTR_GEOMETRIES",
    "ATTR_SOURCES",
    "ATTR_POSE_FRAME",
    "ATTR_MODEL",
    "PING_ATTRS",
    "PING_ARRAYS",
    # the product store
    "SURVEY_FORMAT",
    "DIM_OTHER",
    "N_OTHER_RETURNS",
    "PRODUCT_VARIABLES",
    "PRODUCT_FILL",
    "PRODUCT_RANGES",
    "INFORMATIONAL_FLAGS",
]

DIM_PING = "ping_time"
DIM_RANGE = "range_sample"
DIM_BEAM = "beam"
DIM_XYZ = "xyz"
DIM_QUAT = "quaternion"
VAR_INTENSITY = "intensity"
COORD_RANGE = "echo_range"
COORD_AZIMUTH = "beam_azimuth"

#: CF attributes of the dimensions and coordinates (the single definition both stores use).
COORD_ATTRS: dict[str, dict[str, str]] = {
    DIM_PING: {"long_name": "Ping transmit time (UTC)", "axis": "T", "standard_name": "time"},
    DIM_RANGE: {"long_name": "Range sample number (0 = nearest)", "units": "1"},
    DIM_BEAM: {"long_name": "Beam number (azimuth increases with beam)", "units": "1"},
    COORD_RANGE: {"long_name": "Range from the transducer to the range bin", "units": "m"},
    COORD_AZIMUTH: {
        "long_name": "Beam centre azimuth in the sonar frame, positive to starboard",
        "units": "rad",
    },
}

#: The coordinates of both stores: name -> dimensions (``beam_azimuth``: see :func:`azimuth_dims`).
COORDINATES: dict[str, tuple[str, ...]] = {
    DIM_PING: (DIM_PING,),
    DIM_RANGE: (DIM_RANGE,),
    DIM_BEAM: (DIM_BEAM,),
    COORD_RANGE: (DIM_PING, DIM_RANGE),
    COORD_AZIMUTH: (DIM_BEAM,),
}


def azimuth_dims(per_ping: bool) -> tuple[str, ...]:
    """Dimensions of ``beam_azimuth``: ``(beam,)``, or ``(ping_time, beam)`` if the tables differ.

    Parameters
    ----------
    per_ping : bool
        Whether the pings of the store have different azimuth tables.

    Returns
    -------
    tuple of str
    """
    return (DIM_PING, DIM_BEAM) if per_ping else (DIM_BEAM,)


# ---------------------------------------------------------------------- times
#: Latest ping time a store holds (int64 nanoseconds since 1970: 2262-04-11).
TIME_MAX_NS = int(np.iinfo(np.int64).max)

#: The CF units of stored times this version reads (int64 nanoseconds since 1970).
TIME_UNITS_RE = re.compile(r"nanoseconds since 1970-01-01(?:[ T]00:00(?::00(?:\.0+)?)?)?Z?")
#: The CF units of ``ping_time`` in a product store (and of ``point_time``).
TIME_UNITS = "nanoseconds since 1970-01-01T00:00:00"
#: The CF units of ``ping_time`` in a raw-ping store (as xarray writes them).
PING_TIME_UNITS = "nanoseconds since 1970-01-01"


# ---------------------------------------------------------------------- the raw-ping store
VAR_GEOMETRY = "geometry_index"
VAR_SOURCE = "source_index"
VAR_POSITION = "pose_position_m"
VAR_ORIENTATION = "pose_orientation_xyzw"
META_PREFIX = "meta_"
DATA_MODEL_VERSION = 1
#: Stored in int64 ``meta_*`` variables for pings that lack the key.
INT_MISSING = np.iinfo(np.int64).min
ATTR_GEOMETRIES = "sonarmap_geometries"
ATTR_SOURCES = "sonarmap_sources"
ATTR_POSE_FRAME = "sonarmap_pose_frame"
ATTR_MODEL = "sonarmap_data_model"

#: CF attributes of the raw-ping store's variables and coordinates.
PING_ATTRS: dict[str, dict[str, str]] = {
    **COORD_ATTRS,
    VAR_INTENSITY: {
        "long_name": "Received echo intensity, sensor counts scaled to [0, 1]",
        "units": "1",
        "valid_min": "0",
        "valid_max": "1",
    },
    VAR_GEOMETRY: {"long_name": f"Index into the {ATTR_GEOMETRIES} attribute", "units": "1"},
    VAR_SOURCE: {"long_name": f"Index into the {ATTR_SOURCES} attribute", "units": "1"},
    VAR_POSITION: {"long_name": "Vehicle position in the world frame (NaN if unknown)", "units": "m"},
    VAR_ORIENTATION: {
        "long_name": "Vehicle orientation quaternion x, y, z, w (NaN if unknown)",
        "units": "1",
    },
}


#: The arrays every raw-ping store holds: name -> (rank, dtype kinds, trailing dims).
PING_ARRAYS: dict[str, tuple[int, str, tuple[str, ...]]] = {
    VAR_INTENSITY: (3, "f", (DIM_RANGE, DIM_BEAM)),
    DIM_PING: (1, "i", ()),
    VAR_GEOMETRY: (1, "iu", ()),
    VAR_SOURCE: (1, "iu", ()),
    VAR_POSITION: (2, "f", (DIM_XYZ,)),
    VAR_ORIENTATION: (2, "f", (DIM_QUAT,)),
}


# ---------------------------------------------------------------------- the product store
#: The ``sonarmap_format`` root attribute of a product store.
SURVEY_FORMAT = "sonarmap-survey/1"
#: Dimension of ``other_range``: the surfaces behind a beam's return that are stored.
DIM_OTHER = "other_return"
#: At most this many surfaces behind each return are stored (``other_range``).
N_OTHER_RETURNS = 2

#: Product variables: name -> (dims, attrs).  Dimension names follow the survey data model
#: (echopype style: ``ping_time``, ``range_sample``, ``beam``); ``component`` and ``parameter``
#: index the mixture model.
PRODUCT_VARIABLES: dict[str, tuple[tuple[str, ...], dict[str, str]]] = {
    DIM_PING: ((DIM_PING,), dict(COORD_ATTRS[DIM_PING])),
    "source": ((DIM_PING,), {"long_name": "Source file (and frame) of the ping"}),
    "kld": ((DIM_PING,), {"long_name": "Kullback-Leibler divergence, data || mixture fit",
                          "units": "nat"}),
    "flags": ((DIM_PING,), {"long_name": "Fit quality flags, space separated (empty: none)"}),
    "background_range_db": ((DIM_PING,), {
        "long_name": "Range dependence of the estimated background level (90th / 10th percentile over "
                     "range; NaN: image not normalised, e.g. thresholded)", "units": "dB"}),
    "floor_levels": ((DIM_PING,), {
        "long_name": "Levels of the classified image merged into its zero level before the ping was modelled "
                     "(the quantisation floor; 0: none)", "units": "1"}),
    "mixture_weight": ((DIM_PING, "component"), {"long_name": "Mixture component weight",
                                                 "units": "1"}),
    "mixture_param": ((DIM_PING, "component", "parameter"),
                      {"long_name": "Mixture component parameters, scale last (NaN: unused)"}),
    "pd": ((DIM_PING,), {"long_name": "Probability of detection at the chosen threshold",
                         "units": "1"}),
    "pfa": ((DIM_PING,), {"long_name": "Probability of false alarm at the chosen threshold",
                          "units": "1"}),
    "range": ((DIM_PING, DIM_BEAM), {"long_name": "Range to the first return per beam (NaN: none)",
                                     "units": "m",
                                     "description": "Leading edge of the return's echo along the beam: the "
                                                    "first crossing of half its peak, interpolated "
                                                    "between range bins, on the edge-aligned mean profile "
                                                    "of up to 7 neighbouring beams of the same surface "
                                                    "(the echo's peak in strongest mode)"}),
    "range_bin": ((DIM_PING, DIM_BEAM), {"long_name": "Range-bin index of the return (-1: none)",
                                         "units": "1"}),
    "range_intensity": ((DIM_PING, DIM_BEAM), {"long_name": "Intensity at the return", "units": "1"}),
    "range_confidence": ((DIM_PING, DIM_BEAM), {"long_name": "Confidence of the return",
                                                "units": "1"}),
    "range_sigma": ((DIM_PING, DIM_BEAM), {
        "long_name": "One-sigma uncertainty of the return's range (NaN: no return or no estimate)",
        "units": "m",
        "description": "Standard deviation of the error of range, estimated per echo by the ranges "
                       "stage (sonarmap.ranges.echoes)"}),
    "p_detect": ((DIM_PING, DIM_BEAM), {
        "long_name": "Probability that a surface in the beam is detected and reported (NaN: unknown)",
        "units": "1",
        "description": "The occupancy map's per-beam pD: P(the beam reports a return | a surface in "
                       "the beam), for the hit and the free-space updates of that beam"}),
    "other_range": ((DIM_PING, DIM_OTHER, DIM_BEAM), {
        "long_name": "Ranges of further surfaces behind the return, nearest first (NaN: none)",
        "units": "m",
        "description": "Leading edges of the echoes of further surfaces on the beam behind the "
                       f"reported return; at most {N_OTHER_RETURNS}, NaN-padded"}),
    "labels": ((DIM_PING, DIM_RANGE, DIM_BEAM),
               {"long_name": "Segmentation labels (1: object, 0: free space)", "units": "1"}),
}


#: Fill value of each product variable (its value in pings not written yet).
PRODUCT_FILL: dict[str, Any] = {
    "background_range_db": np.nan, "floor_levels": 0, "kld": np.nan, "pd": np.nan, "pfa": np.nan,
    "mixture_weight": np.nan, "mixture_param": np.nan,
    "range": np.nan, "range_bin": -1, "range_intensity": np.nan, "range_confidence": np.nan,
    "range_sigma": np.nan, "p_detect": np.nan, "other_range": np.nan,
    "labels": 0, "ping_time": 0, "source": "", "flags": "",
}


#: Flags that describe the scene rather than a doubtful fit (not counted as "flagged fits").
INFORMATIONAL_FLAGS = frozenset({"no_returns", "no_object", "collapsed"})


#: Documented value range of each product variable, checked by :func:`sonarmap.store.load_products`
#: (keyword arguments of :func:`sonarmap.store.check.check_values`).  NaN is "none" / "unknown" /
#: "not yet written" wherever a float variable has it as fill value.  ``range_bin`` is checked
#: against the number of range bins, ``point_beam`` against the number of beams, the times by
#: :func:`sonarmap.store.check.check_times`; ``labels`` (uint8) and the strings are not checked.
PRODUCT_RANGES: dict[str, dict[str, Any]] = {
    "kld": {"low": 0.0, "high": math.inf, "nan": True, "inf": True},  # inf: zero_mass fits
    "background_range_db": {"nan": True},
    "floor_levels": {"low": 0},
    "mixture_weight": {"low": 0.0, "high": 1.0, "nan": True},
    "mixture_param": {"nan": True},
    "pd": {"low": 0.0, "high": 1.0, "nan": True},
    "pfa": {"low": 0.0, "high": 1.0, "nan": True},
    "range": {"low": 0.0, "nan": True},
    "range_intensity": {"nan": True},
    "range_confidence": {"low": 0.0, "high": 1.0, "nan": True},
    "range_sigma": {"low": 0.0, "nan": True},
    "p_detect": {"low": 0.0, "high": 1.0, "nan": True},
    "other_range": {"low": 0.0, "nan": True},
    "point_xyz": {"nan": True, "item": "point"},
    "point_intensity": {"nan": True, "item": "point"},
    "point_range_sigma": {"low": 0.0, "nan": True, "item": "point"},
    COORD_AZIMUTH: {"low": -math.pi, "high": math.pi, "item": "beam"},
    COORD_RANGE: {"low": 0.0, "item": "range bin"},
}
