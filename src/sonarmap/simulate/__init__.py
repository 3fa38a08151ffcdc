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

from sonarmap.simulate.render import (
    EdgeRise,
    SimResult,
    SimulationConfig,
    SimulationFiles,
    beam_widths_for,
    channel_gain,
    expected_background_image,
    expected_background_level,
    first_peak_crossing,
    leading_edges_m,
    measure_edge_rise,
    pulse_envelope,
    read_truth,
    render_psf,
    seawater_absorption_db_per_m,
    simulate_ping,
    simulation_config_for,
    transmission_loss_db,
    write_simulation,
)
from sonarmap.simulate.presets import SONAR_PROFILES, SonarProfile, profile_for
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
    scene_scale_for,
    seafloor,
    sloped_hull,
    sloped_hull_yaw_deg,
    view_for,
)

__all__ = [
    "SimulationConfig",
    "simulation_config_for",
    "SonarProfile",
    "SONAR_PROFILES",
    "profile_for",
    "scene_scale_for",
    "view_for",
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
    "pulse_envelope",
    "beam_widths_for",
    "render_psf",
    "first_peak_crossing",
    "leading_edges_m",
    "EdgeRise",
    "measure_edge_rise",
    "sloped_hull",
    "sloped_hull_yaw_deg",
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
