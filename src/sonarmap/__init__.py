"""sonarmap: multibeam imaging-sonar processing.

Raw pings -> clean intensity images -> object/free-space labels -> per-beam ranges -> 3-D maps,
after Teixeira, Kaess, Hover and Leonard, "Multibeam Data Processing for Underwater Mapping",
IROS 2018.  Heavy sub-modules are imported lazily so ``import sonarmap`` stays fast.
"""

from __future__ import annotations

__version__ = "0.1.0"

from sonarmap.errors import (
    DataFormatError,
    FitError,
    GeometryError,
    InputError,
    SonarmapError,
    SonarmapWarning,
)
from sonarmap.geometry import SonarGeometry, load_geometry, preset, preset_names, save_geometry
from sonarmap.ping import Ping

#: Re-exported, by origin: the exception hierarchy of :mod:`sonarmap.errors` (not its warning
#: display helper), the geometry of :mod:`sonarmap.geometry` and the :class:`Ping`.
__all__ = [
    "__version__",
    "SonarmapError", "InputError", "GeometryError", "DataFormatError", "FitError", "SonarmapWarning",
    "SonarGeometry", "load_geometry", "save_geometry", "preset", "preset_names",
    "Ping",
]
