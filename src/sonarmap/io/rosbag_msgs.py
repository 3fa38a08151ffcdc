"""ROS message definitions beyond ``ProjectedSonarImage`` that sonarmap reads or writes.

The field lists follow the upstream ``.msg`` files (names, types and constants, which fix the
ROS 1 MD5 sums and the ROS 2 type hashes); the upstream comments are summarised here, not copied:

``marine_acoustic_msgs/RawSonarImage`` (apl-ocean-engineering/marine_msgs, read)
    One ping in the sample (time) domain: ``sample_rate`` (Hz), ``samples_per_beam``, ``sample0``
    (index of the first sample in the data), per-beam ``tx_delays``, ``tx_angles`` and ``rx_angles``
    (radians) and a ``SonarImageData``.  The package README gives the range of sample ``i`` as
    ``(i + sample0) * sound_speed / (2 * sample_rate)``.
``marine_acoustic_msgs/SonarRanges`` and ``DetectionFlag`` (marine_msgs, written)
    One ping of a profiling sonar: per-beam ``flags`` (``DetectionFlag``: 0 good, bit 0 bad by the
    sonar, bit 1 bad by a processing filter, bit 2 bad by the user), ``transmit_delays``,
    ``intensities``, ``beam_unit_vec`` and ``ranges``.
``acoustic_msgs/SonarImage`` (the older acoustic_msgs, hydrographic_msgs; read)
    ``frequency``, ``sound_speed``, ``azimuth_beamwidth``, ``elevation_beamwidth``,
    ``azimuth_angles`` (radians, zero straight ahead, positive to starboard), ``elevation_angles``,
    ``ranges`` (bin centres, m), ``is_bigendian``, ``data_size`` (bytes per sample) and
    ``intensities``.
``apl_msgs/RawData`` (apl-ocean-engineering/apl_msgs, read)
    Raw bytes exchanged with a device (``data``) and their ``direction`` (``DATA_OUT`` / ``DATA_IN``);
    the header stamp falls just after the bytes were sent or received.  When a bag carries its own
    definition (ROS 1 always, ROS 2 usually) its constants are used, not these.

``std_msgs``, ``geometry_msgs`` and ``sensor_msgs`` (``PointCloud2``, ``PointField``) come from the
typestores built into ``rosbags``.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "RAW_SONAR_IMAGE",
    "SONAR_RANGES",
    "DETECTION_FLAG",
    "LEGACY_SONAR_IMAGE",
    "RAW_DATA",
    "POINTCLOUD2",
    "DETECT_OK",
    "DETECT_BAD_SONAR",
    "DETECT_BAD_FILTER",
    "DETECT_BAD_USER",
    "DEFINITIONS",
    "REQUIRED_FIELDS",
    "register",
]

RAW_SONAR_IMAGE = "marine_acoustic_msgs/msg/RawSonarImage"
SONAR_RANGES = "marine_acoustic_msgs/msg/SonarRanges"
DETECTION_FLAG = "marine_acoustic_msgs/msg/DetectionFlag"
LEGACY_SONAR_IMAGE = "acoustic_msgs/msg/SonarImage"
RAW_DATA = "apl_msgs/msg/RawData"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"

#: ``DetectionFlag`` values (a bit mask; 0 is a good beam).
DETECT_OK = 0
DETECT_BAD_SONAR = 1
DETECT_BAD_FILTER = 2
DETECT_BAD_USER = 4

#: Message type -> definition (fields and constants of the upstream ``.msg``).
DEFINITIONS: dict[str, str] = {
    DETECTION_FLAG: """\
uint8 DETECT_OK = 0
uint8 DETECT_BAD_SONAR = 1
uint8 DETECT_BAD_FILTER = 2
uint8 DETECT_BAD_USER = 4
uint8 flag
""",
    RAW_SONAR_IMAGE: """\
std_msgs/Header header
PingInfo ping_info
float32 sample_rate
uint32 samples_per_beam
uint32 sample0
float32[] tx_delays
float32[] tx_angles
float32[] rx_angles
SonarImageData image
""",
    SONAR_RANGES: """\
std_msgs/Header header
PingInfo ping_info
DetectionFlag[] flags
float32[] transmit_delays
float32[] intensities
geometry_msgs/Vector3[] beam_unit_vec
float32[] ranges
""",
    LEGACY_SONAR_IMAGE: """\
Header header
float32 frequency
float32 sound_speed
float32 azimuth_beamwidth
float32 elevation_beamwidth
float32[] azimuth_angles
float32[] elevation_angles
float32[] ranges
bool is_bigendian
uint8 data_size
uint8[] intensities
""",
    RAW_DATA: """\
std_msgs/Header header
uint8 DATA_OUT = 0
uint8 DATA_IN = 1
uint8 direction
uint8[] data
""",
}

#: Fields a bag's definition of a read type must have for sonarmap to decode it.
REQUIRED_FIELDS: dict[str, frozenset[str]] = {
    RAW_SONAR_IMAGE: frozenset(
        {"header", "ping_info", "sample_rate", "samples_per_beam", "sample0", "rx_angles", "image"}
    ),
    "acoustic_msgs/msg/RawSonarImage": frozenset(
        {"header", "ping_info", "sample_rate", "samples_per_beam", "sample0", "rx_angles", "image"}
    ),
    LEGACY_SONAR_IMAGE: frozenset(
        {"header", "sound_speed", "azimuth_angles", "ranges", "is_bigendian", "data_size", "intensities"}
    ),
    RAW_DATA: frozenset({"header", "data"}),
}


def register(store: Any) -> None:
    """Register :data:`DEFINITIONS` in a rosbags typestore that already has ``PingInfo`` and
    ``SonarImageData`` (see :func:`sonarmap.io.rosbag.typestore`)."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for name in (DETECTION_FLAG, RAW_SONAR_IMAGE, SONAR_RANGES, LEGACY_SONAR_IMAGE, RAW_DATA):
        types.update(get_types_from_msg(DEFINITIONS[name], name))
    store.register(types)
