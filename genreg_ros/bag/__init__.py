"""rosbag2 bags of RGB-D frames, written and read with the `rosbags` package (no ROS graph, no rclpy).

A bag holds one `sensor_msgs/PointCloud2` per frame (x, y, z float32 metres in the camera optical frame,
plus a packed `rgb` float32 where colour exists) and the ground-truth camera pose per frame as a
`geometry_msgs/TransformStamped` (parent = world frame, child = the optical frame: T_world_camera,
x_world = R x_camera + t). Stamps are `start + (frame - first_frame) / rate`.
"""

from genreg_ros.bag.reader import BagData, CloudRecord, PoseRecord, decode_cloud, read_bag
from genreg_ros.bag.writer import (
    DEFAULT_CLOUD_TOPIC,
    DEFAULT_FRAME_ID,
    DEFAULT_POSE_TOPIC,
    DEFAULT_RATE,
    DEFAULT_START_NS,
    DEFAULT_WORLD_FRAME,
    BagWriter,
    Frame,
    cloud_message,
    sequence_frames,
    write_sequence_bag,
)

__all__ = [
    "DEFAULT_CLOUD_TOPIC",
    "DEFAULT_FRAME_ID",
    "DEFAULT_POSE_TOPIC",
    "DEFAULT_RATE",
    "DEFAULT_START_NS",
    "DEFAULT_WORLD_FRAME",
    "BagData",
    "BagWriter",
    "CloudRecord",
    "Frame",
    "PoseRecord",
    "cloud_message",
    "decode_cloud",
    "read_bag",
    "sequence_frames",
    "write_sequence_bag",
]
