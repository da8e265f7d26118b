"""Write RGB-D frames into a rosbag2 bag (mcap or sqlite3) with rosbags' own typestore and CDR serialiser.

Per frame, at stamp `start + (frame - first_frame) / rate` (30 Hz as recorded in 7-Scenes):
- `cloud_topic` (sensor_msgs/PointCloud2): unorganised (height 1), dense, little-endian; fields x, y, z
  FLOAT32 metres in the camera optical frame (x right, y down, z forward; frame_id `frame_id`), plus a
  packed `rgb` FLOAT32 (PCL layout 0x00RRGGBB) where the frame has colour;
- `pose_topic` (geometry_msgs/TransformStamped): header.frame_id = `world_frame` (parent), child_frame_id =
  `frame_id`; the ground-truth T_world_camera, x_world = R x_camera + t (metres).
The bag's metadata `custom_data["genreg"]` holds a JSON description (sequence, frame numbers, rate, ...).
A bag is a folder that must not exist yet (overwrite=True removes it first).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Self

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from genreg_core.data.rgbd import RGBDSequence
from genreg_ros import conversions
from genreg_ros.pointcloud2 import CLOUD_TYPE, TYPESTORE

STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
BAG_VERSION = 9
INFO_KEY = "genreg"
TRANSFORM_TYPE = "geometry_msgs/msg/TransformStamped"
DEFAULT_CLOUD_TOPIC = "/camera/depth/points"
DEFAULT_POSE_TOPIC = "/camera/pose"
DEFAULT_FRAME_ID = "camera_depth_optical_frame"
DEFAULT_WORLD_FRAME = "world"
DEFAULT_RATE = 30.0  # Hz, the 7-Scenes and SUN3D capture rate
DEFAULT_START_NS = 1_700_000_000 * 10**9  # first stamp: a fixed time, so bags are reproducible

_T = TYPESTORE.types
_FLOAT32 = _T["sensor_msgs/msg/PointField"].FLOAT32
MESSAGE_TYPES = SimpleNamespace(**{name: _T[f"geometry_msgs/msg/{name}"]  # for conversions.matrix_to_msg
                                   for name in ("TransformStamped", "Transform", "Vector3", "Quaternion")})


@dataclass(frozen=True)
class Frame:
    """One frame: (N, 3) float32 points (metres, optical frame), optional (N, 3) uint8 RGB colours and
    4x4 T_world_camera pose, its frame number and its stamp (ns)."""

    index: int
    stamp_ns: int
    points: np.ndarray
    colors: np.ndarray | None = None
    pose: np.ndarray | None = None


def header(stamp_ns: int, frame_id: str) -> Any:
    """A rosbags std_msgs/Header."""
    sec, nanosec = conversions.split_ns(stamp_ns)
    return _T["std_msgs/msg/Header"](stamp=_T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                     frame_id=frame_id)


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB -> (N,) float32 holding the bits of uint32 0x00RRGGBB (PCL's packed rgb)."""
    c = np.asarray(colors, dtype=np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).astype("<u4").view("<f4")


def cloud_message(stamp_ns: int, frame_id: str, points: np.ndarray, colors: np.ndarray | None = None) -> Any:
    """A rosbags PointCloud2: x, y, z (and rgb if colours are given) FLOAT32, little-endian, height 1."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    names = ["x", "y", "z"] + ([] if colors is None else ["rgb"])
    records = np.empty(len(points), dtype=np.dtype({"names": names, "formats": ["<f4"] * len(names)}))
    records["x"], records["y"], records["z"] = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        if len(colors) != len(points):
            raise ValueError(f"{len(colors)} colours for {len(points)} points")
        records["rgb"] = pack_rgb(colors)
    step = records.dtype.itemsize
    fields = [_T["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=_FLOAT32, count=1)
              for k, n in enumerate(names)]
    return _T[CLOUD_TYPE](
        header=header(stamp_ns, frame_id), height=1, width=len(points), fields=fields, is_bigendian=False,
        point_step=step, row_step=step * len(points), data=records.view(np.uint8).reshape(-1), is_dense=True,
    )


def transform_message(stamp_ns: int, parent: str, child: str, T: np.ndarray) -> Any:
    """A rosbags TransformStamped of the 4x4 T_parent_child (`genreg_ros.conversions.matrix_to_msg`)."""
    return conversions.matrix_to_msg(T, header(stamp_ns, parent), child, MESSAGE_TYPES)


class BagWriter:
    """Context manager writing clouds and poses into a new bag folder (see the module docstring)."""

    def __init__(
        self,
        path: str | Path,
        storage: str = "mcap",
        cloud_topic: str = DEFAULT_CLOUD_TOPIC,
        pose_topic: str = DEFAULT_POSE_TOPIC,
        frame_id: str = DEFAULT_FRAME_ID,
        world_frame: str = DEFAULT_WORLD_FRAME,
        overwrite: bool = False,
    ) -> None:
        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {sorted(STORAGES)}, got {storage!r}")
        self.path = Path(path)
        if self.path.exists():
            if not overwrite:
                raise FileExistsError(f"bag {self.path} exists (use overwrite)")
            shutil.rmtree(self.path) if self.path.is_dir() else self.path.unlink()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.frame_id, self.world_frame = frame_id, world_frame
        self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=STORAGES[storage])
        self._writer.open()
        self._clouds = self._writer.add_connection(cloud_topic, CLOUD_TYPE, typestore=TYPESTORE)
        self._poses = self._writer.add_connection(pose_topic, TRANSFORM_TYPE, typestore=TYPESTORE)
        self.num_clouds = 0
        self.num_poses = 0

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        self.close()

    def set_info(self, info: dict[str, Any]) -> None:
        """Store a JSON-serialisable description in the bag metadata (custom_data['genreg'])."""
        self._writer.set_custom_data(INFO_KEY, json.dumps(info))

    def write_cloud(self, msg: Any) -> None:
        """Write any rosbags PointCloud2 (also a deliberately malformed one) at its header stamp."""
        self._writer.write(self._clouds, conversions.stamp_ns(msg.header), TYPESTORE.serialize_cdr(msg, CLOUD_TYPE))
        self.num_clouds += 1

    def write_pose(self, stamp_ns: int, T_world_camera: np.ndarray) -> None:
        msg = transform_message(stamp_ns, self.world_frame, self.frame_id, T_world_camera)
        self._writer.write(self._poses, int(stamp_ns), TYPESTORE.serialize_cdr(msg, TRANSFORM_TYPE))
        self.num_poses += 1

    def write_frame(self, frame: Frame) -> None:
        """The frame's cloud and, if it has one, its ground-truth pose, both at `frame.stamp_ns`."""
        self.write_cloud(cloud_message(frame.stamp_ns, self.frame_id, frame.points, frame.colors))
        if frame.pose is not None:
            self.write_pose(frame.stamp_ns, frame.pose)

    def close(self) -> None:
        self._writer.close()


def sequence_frames(
    sequence: RGBDSequence,
    frames: Iterable[int],
    pixel_stride: int = 4,
    rate: float = DEFAULT_RATE,
    start_ns: int = DEFAULT_START_NS,
    color: bool = True,
) -> Iterator[Frame]:
    """Frames of `sequence` (frame numbers in `frames`, increasing), back-projected every `pixel_stride`-th
    pixel; stamp = start_ns + (frame - first frame) / rate, so a frame stride keeps the original timing."""
    if rate <= 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    frames = list(frames)
    for index in frames:
        points = sequence.points(index, pixel_stride)
        colors = sequence.colors(index, pixel_stride) if color and sequence.has_color(index) else None
        stamp = int(start_ns) + round((index - frames[0]) * 1e9 / rate)
        yield Frame(index, stamp, points, colors, sequence.pose(index))


def write_sequence_bag(
    sequence: RGBDSequence,
    path: str | Path,
    frames: Iterable[int] | None = None,
    pixel_stride: int = 4,
    rate: float = DEFAULT_RATE,
    storage: str = "mcap",
    start_ns: int = DEFAULT_START_NS,
    color: bool = True,
    overwrite: bool = False,
    **topics: str,
) -> dict[str, Any]:
    """Write frames of an RGB-D sequence (all by default) into a bag; returns the info stored in it.

    `topics` may set cloud_topic, pose_topic, frame_id and world_frame (see BagWriter).
    """
    wanted = sorted(set(sequence.frame_indices if frames is None else frames))
    missing = [i for i in wanted if i not in sequence]
    if missing or not wanted:
        raise ValueError(f"frames not in {sequence.folder}: {missing[:5] or 'none selected'}")
    with BagWriter(path, storage, overwrite=overwrite, **topics) as writer:
        num_points, colored = [], 0
        for frame in sequence_frames(sequence, wanted, pixel_stride, rate, start_ns, color):
            writer.write_frame(frame)
            num_points.append(len(frame.points))
            colored += frame.colors is not None
        info = {
            "sequence": sequence.name, "folder": str(sequence.folder), "frames": wanted, "rate_hz": rate,
            "pixel_stride": pixel_stride, "start_ns": int(start_ns), "storage": storage,
            "frame_id": writer.frame_id, "world_frame": writer.world_frame, "colored_frames": colored,
            "mean_points": float(np.mean(num_points)), "intrinsics": sequence.K.tolist(),
        }
        writer.set_info(info)
    return info
