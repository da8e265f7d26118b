"""The one stamp helper and the one TransformStamped <-> 4x4 matrix converter of genreg_ros.

Frames, units and transform names follow `genreg_core.geometry` (T_target_source, x' = R x + t, metres).
Messages are duck-typed: rclpy messages and rosbags' deserialised messages have the same field names, so
both go through these functions (the rosbags side passes its own message classes as `types`).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

NS_PER_S = 1_000_000_000


def stamp_ns(header: Any) -> int:
    """A header's stamp (builtin_interfaces/Time: sec, nanosec) in integer nanoseconds."""
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def stamp_error(header: Any) -> str:
    """Why a header's stamp is not a valid time ("" if it is): a negative sec (a uint32-sized sec above
    2**31 arrives as negative) or a nanosec of 1e9 or more."""
    sec, nanosec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec < 0:
        return f"stamp sec {sec} is negative"
    if not 0 <= nanosec < NS_PER_S:
        return f"stamp nanosec {nanosec} is not in [0, 1e9)"
    return ""


def split_ns(ns: int) -> tuple[int, int]:
    """(sec, nanosec) of a stamp in integer nanoseconds."""
    return divmod(int(ns), NS_PER_S)


def pose_matrix(translation: Any, quaternion_xyzw: Any) -> np.ndarray:
    """4x4 rigid transform of a translation (3,) and a quaternion (qx, qy, qz, qw), normalised here.

    ValueError for a zero or non-finite quaternion or translation."""
    t = np.asarray(translation, dtype=np.float64).reshape(3)
    q = np.asarray(quaternion_xyzw, dtype=np.float64).reshape(4)
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or np.linalg.norm(q) < 1e-6:
        raise ValueError("transform has a zero or non-finite quaternion or translation")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    T[:3, 3] = t
    return T


def msg_to_matrix(msg: Any) -> np.ndarray:
    """4x4 T_parent_child of a geometry_msgs TransformStamped (or a PoseStamped / PoseWithCovariance:
    T_frame_pose)."""
    if hasattr(msg, "transform"):
        tr, r = msg.transform.translation, msg.transform.rotation
    else:
        tr, r = msg.pose.position, msg.pose.orientation
    return pose_matrix([tr.x, tr.y, tr.z], [r.x, r.y, r.z, r.w])


def rclpy_types() -> SimpleNamespace:
    """The rclpy geometry_msgs classes `matrix_to_msg` builds with (imported on first use)."""
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3

    return SimpleNamespace(TransformStamped=TransformStamped, Transform=Transform, Vector3=Vector3,
                           Quaternion=Quaternion)


def _xyz_quat(T: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    T = np.asarray(T, dtype=np.float64)
    x, y, z = (float(v) for v in T[:3, 3])
    qx, qy, qz, qw = (float(v) for v in Rotation.from_matrix(T[:3, :3]).as_quat())
    return (x, y, z), (qx, qy, qz, qw)


def matrix_to_pose_msg(T: np.ndarray, header: Any, covariance: np.ndarray | None) -> Any:
    """rclpy PoseWithCovarianceStamped of T_frame_pose (frame = header.frame_id) with a (6, 6) covariance in
    ROS order (x, y, z, rotation about x, y, z), row-major; None (unknown) is all zeros but -1 first, the
    sensor_msgs convention for "no estimate"."""
    from geometry_msgs.msg import Point, Pose, PoseWithCovariance, PoseWithCovarianceStamped, Quaternion

    (x, y, z), (qx, qy, qz, qw) = _xyz_quat(T)
    cov = np.zeros(36)
    if covariance is None:
        cov[0] = -1.0
    else:
        cov[:] = np.asarray(covariance, dtype=np.float64).reshape(36)
    pose = Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
    return PoseWithCovarianceStamped(header=header, pose=PoseWithCovariance(pose=pose, covariance=cov.tolist()))


def matrix_to_msg(T: np.ndarray, header: Any, child_frame: str, types: SimpleNamespace | None = None) -> Any:
    """TransformStamped of T_parent_child: parent = header.frame_id, child = child_frame.

    `types` holds the message classes TransformStamped, Transform, Vector3 and Quaternion (default:
    rclpy's, `rclpy_types()`); the header must be of the same family."""
    types = types or rclpy_types()
    (x, y, z), (qx, qy, qz, qw) = _xyz_quat(T)
    transform = types.Transform(translation=types.Vector3(x=x, y=y, z=z),
                                rotation=types.Quaternion(x=qx, y=qy, z=qz, w=qw))
    return types.TransformStamped(header=header, child_frame_id=child_frame, transform=transform)
