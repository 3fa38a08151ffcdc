"""ROS message definitions shipped with sonarmap (``marine_acoustic_msgs``), see :mod:`sonarmap.io.rosbag`.

``std_msgs/Header`` and ``geometry_msgs/Vector3`` come from the typestores built into ``rosbags``.
The definitions follow ``apl-ocean-engineering/marine_msgs`` (BSD-3-Clause).
"""
