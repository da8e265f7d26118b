"""Read a rosbag2 bag (mcap or sqlite3) of clouds and poses back into numpy, with rosbags (no rclpy).

`read_bag` returns every PointCloud2 of the cloud topic in bag order as a `CloudRecord`: stamp (ns),
frame_id, x/y/z as (N, 3) float32 (metres, the cloud's frame), colours if it has a packed rgb field, and the
raw CDR bytes (ready to publish with rclpy). A message that cannot be decoded (truncated data, missing or
non-float x/y/z, bad layout) is kept with `error` set to a short reason code instead of raising. Poses come
from a TransformStamped (T_parent_child) or PoseStamped (T_frame_pose) topic.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.rosbag2 import Reader

from genreg_ros.conversions import msg_to_matrix, stamp_ns
from genreg_ros.pointcloud2 import CLOUD_TYPE, TYPESTORE, PointCloud2Error, read_points, unpack_rgb

POSE_TYPES = ("geometry_msgs/msg/TransformStamped", "geometry_msgs/msg/PoseStamped")


@dataclass
class CloudRecord:
    """One PointCloud2 of the bag. points: (N, 3) float32 metres in `frame_id`, None if undecodable."""

    topic: str
    stamp_ns: int  # header stamp
    log_time_ns: int  # bag receive time
    frame_id: str
    raw: bytes  # the serialised message (CDR), publishable as is
    points: np.ndarray | None = None
    colors: np.ndarray | None = None  # (N, 3) uint8 RGB
    fields: tuple[str, ...] = ()
    error: str | None = None  # reason code when the message is malformed
    error_text: str = ""


@dataclass
class PoseRecord:
    """A ground-truth pose: 4x4 T_parent_child (x_parent = R x_child + t, metres) at `stamp_ns`."""

    stamp_ns: int
    parent: str
    child: str
    matrix: np.ndarray


@dataclass
class BagData:
    """The clouds and poses of a bag, in bag order, and the writer's description (`info`)."""

    path: Path
    cloud_topic: str
    pose_topic: str | None
    clouds: list[CloudRecord]
    poses: list[PoseRecord]
    info: dict[str, Any] = field(default_factory=dict)

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        """T_world_camera at exactly this stamp, or None."""
        if not hasattr(self, "_pose_index"):
            self._pose_index = {p.stamp_ns: p.matrix for p in self.poses}
        return self._pose_index.get(int(stamp_ns))

    @property
    def frame_numbers(self) -> list[int]:
        """The source frame number of each cloud (from the writer's info), else 0, 1, 2, ..."""
        frames = self.info.get("frames")
        if isinstance(frames, list) and len(frames) == len(self.clouds):
            return [int(f) for f in frames]
        return list(range(len(self.clouds)))


def decode_cloud(msg: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float32 x, y, z (all points, row-major, NaNs kept) and (N, 3) uint8 colours or None, decoded
    by the node's codec (`genreg_ros.pointcloud2`). Raises PointCloud2Error (reason 'empty_cloud',
    'missing_xyz', 'bad_xyz_type', 'bad_layout' or 'truncated_data')."""
    cloud = read_points(msg, finite_only=False)
    return cloud.points.astype(np.float32, copy=False), unpack_rgb(cloud)


def _pose(msg: Any) -> PoseRecord:
    return PoseRecord(stamp_ns(msg.header), msg.header.frame_id, getattr(msg, "child_frame_id", ""),
                      msg_to_matrix(msg))


def _pick(topics: dict[str, str], wanted: str | None, types: tuple[str, ...], what: str) -> str | None:
    if wanted is not None:
        if topics.get(wanted) not in types:
            raise ValueError(f"bag has no {what} topic {wanted!r} (topics: {topics})")
        return wanted
    found = sorted(t for t, ty in topics.items() if ty in types)
    return found[0] if found else None


def read_bag(
    path: str | Path, cloud_topic: str | None = None, pose_topic: str | None = None, decode: bool = True
) -> BagData:
    """Read clouds (and poses, if any) from a bag folder; topics default to the first of each type.

    decode=False keeps only stamps, frames, raw bytes and errors (points stay None) to save memory.
    """
    path = Path(path)
    with Reader(path) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        cloud_topic = _pick(topics, cloud_topic, (CLOUD_TYPE,), "PointCloud2")
        if cloud_topic is None:
            raise ValueError(f"bag {path} has no PointCloud2 topic (topics: {topics})")
        pose_topic = _pick(topics, pose_topic, POSE_TYPES, "pose")
        conns = [c for c in reader.connections if c.topic in (cloud_topic, pose_topic)]
        clouds, poses = [], []
        for conn, log_time, raw in reader.messages(connections=conns):
            msg = TYPESTORE.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == pose_topic:
                poses.append(_pose(msg))
                continue
            rec = CloudRecord(conn.topic, stamp_ns(msg.header), log_time, msg.header.frame_id, bytes(raw),
                              fields=tuple(f.name for f in msg.fields))
            try:
                points, colors = decode_cloud(msg)
                if decode:
                    rec.points, rec.colors = points, colors
            except PointCloud2Error as exc:
                rec.error, rec.error_text = exc.reason, str(exc)
            clouds.append(rec)
    return BagData(path, cloud_topic, pose_topic, clouds, poses, read_info(path))


def read_info(path: str | Path) -> dict[str, Any]:
    """The writer's description (custom_data['genreg'] in metadata.yaml), {} if there is none."""
    meta_file = Path(path) / "metadata.yaml"
    if not meta_file.is_file():
        return {}
    meta = yaml.safe_load(meta_file.read_text()) or {}
    custom = (meta.get("rosbag2_bagfile_information") or {}).get("custom_data") or {}
    return json.loads(custom["genreg"]) if "genreg" in custom else {}
