"""Physically based multibeam-sonar simulator: scenes, the sonar-equation renderer and truth.

>>> from sonarmap import preset
>>> from sonarmap.simulate import scene_from_name, simulate_ping
>>> res = simulate_ping(scene_from_name("hull"), preset("didson-hf"), seed=0)
>>> res.ping.image.shape, int(res.class_mask.max())
((512, 96), 1)

See ``docs/simulator.md`` for the model, its order of operations and how it compares with the real
DIDSON background pings.
"""

from __future__ import annotations

from sonarmap.simulate.render import (
    SimResult,
    SimulationConfig,
    SimulationFiles,
    channel_gain,
    expected_background_image,
    expected_background_level,
    read_truth,
    seawater_absorption_db_per_m,
    simulate_ping,
    transmission_loss_db,
    write_simulation,
)
from sonarmap.simulate.scene import (
    CLUTTER,
    SCENE_NAMES,
    STRUCTURE,
    Scene,
    View,
    curved_hull,
    empty_scene,
    fish_school,
    planar_hull,
    plane_patch,
    point_target,
    propeller,
    rudder,
    scene_from_name,
    seafloor,
)

__all__ = [
    "SimulationConfig",
    "SimResult",
    "SimulationFiles",
    "Scene",
    "View",
    "STRUCTURE",
    "CLUTTER",
    "SCENE_NAMES",
    "scene_from_name",
    "simulate_ping",
    "write_simulation",
    "read_truth",
    "channel_gain",
    "transmission_loss_db",
    "expected_background_level",
    "expected_background_image",
    "seawater_absorption_db_per_m",
    "plane_patch",
    "planar_hull",
    "curved_hull",
    "seafloor",
    "propeller",
    "rudder",
    "fish_school",
    "point_target",
    "empty_scene",
]
