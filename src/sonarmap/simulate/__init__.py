"""Physically based multibeam-sonar simulator: scenes, the sonar-equation renderer and truth.

>>> from sonarmap import preset
>>> from sonarmap.simulate import scene_from_name, simulate_ping
>>> res = simulate_ping(scene_from_name("hull"), preset("didson-hf"), seed=0)
>>> res.ping.image.shape, int(res.class_mask.max())
((512, 96), 1)

Every sonar renders with its own profile of gain, floor, receiver, transmit pulse and main lobe
(:mod:`sonarmap.simulate.presets`) for the :class:`SimulationConfig` fields the caller leaves unset.
Besides the class mask, every ping carries the sub-bin physical surface range per beam
(:attr:`SimResult.surface_range_m`).  See ``docs/simulator.md`` for the
model, its order of operations and how it compares with the real DIDSON, ARIS and Oculus recordings.
"""

from __future__ import annotations

from sonarmap.simulate.presets import *  # noqa: F403
from sonarmap.simulate.presets import __all__ as _presets_all
from sonarmap.simulate.render import *  # noqa: F403
from sonarmap.simulate.render import __all__ as _render_all
from sonarmap.simulate.scene import *  # noqa: F403
from sonarmap.simulate.scene import __all__ as _scene_all

#: The public names of the renderer, the sonar profiles and the scenes.
__all__ = [*_render_all, *_presets_all, *_scene_all]
