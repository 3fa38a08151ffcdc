"""Scoring sonarmap against simulator truth.

* :mod:`sonarmap.evaluate.segmentation` - labels and per-beam ranges of simulated pings, per
  sonar preset and scene (``python -m sonarmap.evaluate`` prints its tables);
* :mod:`sonarmap.evaluate.mapping` - registration accuracy, coverage and occupancy IoU of a
  simulated survey (:mod:`sonarmap.simulate.survey`);
* :mod:`sonarmap.evaluate.bound` - the Cramér-Rao bound of a simulated ping's ranges: what its
  samples can say, against which a detector's recall is read;
* :mod:`sonarmap.evaluate.convention` - the range convention read on a simulated ping's recorded
  echoes aligned on the truth: what the convention's half-peak crossing itself carries.
"""

from sonarmap.evaluate.bound import *  # noqa: F403
from sonarmap.evaluate.bound import __all__ as _bound_all
from sonarmap.evaluate.convention import *  # noqa: F403
from sonarmap.evaluate.convention import __all__ as _convention_all
from sonarmap.evaluate.mapping import *  # noqa: F403
from sonarmap.evaluate.mapping import __all__ as _mapping_all
from sonarmap.evaluate.segmentation import *  # noqa: F403
from sonarmap.evaluate.segmentation import __all__ as _segmentation_all

__all__ = [*_segmentation_all, *_mapping_all, *_bound_all, *_convention_all]
