"""Mapping: poses and frames, registration, point clouds, occupancy maps, simulated surveys.

Frames: world NED, body and sensor FRD (see :mod:`sonarmap.mapping.frames`); ROS ENU/FLU data is
converted at the boundary.
"""

from __future__ import annotations

from sonarmap.mapping.occupancy import (
    OccupancyArray,
    OccupancyConfig,
    OccupancyMap,
    SensorModel,
    voxel_iou,
    voxelize,
)
from sonarmap.mapping.pointcloud import read_point_cloud, write_point_cloud
from sonarmap.mapping.poses import (
    Extrinsics,
    SensorPoses,
    Trajectory,
    load_extrinsics,
    read_trajectory_csv,
    save_extrinsics,
    sensor_poses,
    write_trajectory_csv,
)
from sonarmap.mapping.register import PointCloud, RegistrationConfig, register_ranges, register_returns

__all__ = [
    "Extrinsics",
    "OccupancyArray",
    "OccupancyConfig",
    "OccupancyMap",
    "PointCloud",
    "RegistrationConfig",
    "SensorModel",
    "SensorPoses",
    "Trajectory",
    "load_extrinsics",
    "read_point_cloud",
    "read_trajectory_csv",
    "register_ranges",
    "register_returns",
    "save_extrinsics",
    "sensor_poses",
    "voxel_iou",
    "voxelize",
    "write_point_cloud",
    "write_trajectory_csv",
]
