"""Mapping: poses and frames, registration, point clouds, occupancy maps, georeferenced outputs,
simulated surveys.

Frames: world NED, body and sensor FRD (see :mod:`sonarmap.mapping.frames`); ROS ENU/FLU data is
converted at the boundary.  :class:`GeoReference` ties the local frame to a projected CRS.
"""

from __future__ import annotations

from sonarmap.mapping.build import MapConfig, MapResult, map_from_pings
from sonarmap.mapping.georef import GeoReference, utm_epsg
from sonarmap.mapping.occupancy import (
    OccupancyArray,
    OccupancyConfig,
    OccupancyMap,
    SensorModel,
    voxel_iou,
    voxelize,
)
from sonarmap.mapping.octomap import OcTreeFile, OcTreeLeaves, read_octomap_bt, write_octomap_bt
from sonarmap.mapping.pointcloud import read_point_cloud, read_point_cloud_crs, write_point_cloud
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
from sonarmap.mapping.footprint import footprint_azimuths
from sonarmap.mapping.raster import GeoRaster, height_raster, occupancy_raster, read_geotiff, write_geotiff
from sonarmap.mapping.register import PointCloud, RegistrationConfig, register_ranges, register_returns

__all__ = [
    "Extrinsics",
    "GeoRaster",
    "GeoReference",
    "MapConfig",
    "MapResult",
    "OcTreeFile",
    "OcTreeLeaves",
    "OccupancyArray",
    "OccupancyConfig",
    "OccupancyMap",
    "PointCloud",
    "RegistrationConfig",
    "SensorModel",
    "SensorPoses",
    "Trajectory",
    "footprint_azimuths",
    "height_raster",
    "load_extrinsics",
    "map_from_pings",
    "occupancy_raster",
    "read_geotiff",
    "read_octomap_bt",
    "read_point_cloud",
    "read_point_cloud_crs",
    "read_trajectory_csv",
    "register_ranges",
    "register_returns",
    "save_extrinsics",
    "sensor_poses",
    "utm_epsg",
    "voxel_iou",
    "voxelize",
    "write_geotiff",
    "write_octomap_bt",
    "write_point_cloud",
    "write_trajectory_csv",
]
