"""sensor_msgs/PointCloud2 <-> numpy, vectorised, written for genreg (sensor_msgs_py is not used).

Conventions:
- x, y, z are metres (REP-103) in the cloud's `header.frame_id`; they must be FLOAT32 or FLOAT64.
- Any other fields (rgb, intensity, ring, ...) and `point_step` padding are carried byte for byte.
- Both endiannesses are read and written; organised clouds (height > 1) and `row_step` padding are
  read row by row and flattened in row-major order (index = row * width + column).
- Points with a NaN/Inf coordinate are dropped (unless `finite_only=False`); `DecodedCloud.mask` says
  which ones were kept.
- rclpy messages and rosbags' deserialised messages (same field names, `data` a uint8 array) are both
  read here: the node decodes live messages and `genreg_ros.bag.reader` bag messages with `read_points`.
  The node subscribes to clouds serialised (`raw=True`) and deserialises them with `from_cdr` (rosbags'
  CDR reader, handed a memoryview so that `data` is a view of the received bytes, not a copy: 0.02 ms
  for a 4.4 MB cloud, where rclpy's own deserialisation takes about 16 ms).

Speed: nothing here loops over points. `msg.data` is read with `np.frombuffer` (no copy) and written
as one `array.array('B')` built with `frombytes` (one memcpy) and handed to the message without a
further copy (see `_new_cloud`); the generated `data` setter is slow on anything else.
"""

from __future__ import annotations

import array
import sys
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from genreg_core import kernels

TYPESTORE = get_typestore(Stores.ROS2_KILTED)  # rosbags' message types: the bag tools and `from_cdr`
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"

# PointField.datatype -> numpy scalar type (byte order applied separately).
_DATATYPES: dict[int, np.dtype] = {
    PointField.INT8: np.dtype("i1"),
    PointField.UINT8: np.dtype("u1"),
    PointField.INT16: np.dtype("i2"),
    PointField.UINT16: np.dtype("u2"),
    PointField.INT32: np.dtype("i4"),
    PointField.UINT32: np.dtype("u4"),
    PointField.FLOAT32: np.dtype("f4"),
    PointField.FLOAT64: np.dtype("f8"),
}
_NUMPY_TO_DATATYPE = {(dt.kind, dt.itemsize): code for code, dt in _DATATYPES.items()}
_XYZ = ("x", "y", "z")
_PADDING = "_"  # PCL's name for padding fields: it may repeat


class PointCloud2Error(ValueError):
    """A PointCloud2 message that cannot be decoded. `reason` is a short machine-readable code."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class CloudLayout:
    """Where x, y, z live inside one point record of `point_step` bytes."""

    fields: tuple[tuple[str, int, int, int], ...]  # (name, offset, datatype, count) as in the message
    point_step: int
    is_bigendian: bool
    xyz_offsets: tuple[int, int, int]
    xyz_dtypes: tuple[np.dtype, np.dtype, np.dtype]  # with the message's byte order

    @property
    def packed_xyz(self) -> bool:
        """x, y, z share one type and sit back to back (x at o, y at o+s, z at o+2s): one strided view."""
        o, s = self.xyz_offsets[0], self.xyz_dtypes[0].itemsize
        return len(set(self.xyz_dtypes)) == 1 and self.xyz_offsets == (o, o + s, o + 2 * s)

    @property
    def point_dtype(self) -> np.dtype:
        """float64 if any coordinate is FLOAT64, else float32 (native byte order)."""
        return np.dtype("f8") if any(d.itemsize == 8 for d in self.xyz_dtypes) else np.dtype("f4")


@dataclass
class DecodedCloud:
    """A decoded cloud. `points` are the finite points (K, 3), native byte order, in input order."""

    points: np.ndarray  # (K, 3) float32 or float64
    mask: np.ndarray | None  # (height * width,) bool of kept points, or None when all were finite
    records: np.ndarray  # (height * width, point_step) uint8: every input point's raw bytes
    layout: CloudLayout
    num_input: int  # height * width

    @property
    def num_dropped(self) -> int:
        return self.num_input - len(self.points)


def from_cdr(raw: bytes) -> Any:
    """A serialised (CDR) PointCloud2 as rosbags' message: `data` a read-only numpy uint8 view of `raw`
    (no copy: rosbags slices a memoryview where it would copy bytes), the header a rosbags Header
    (stamp.sec, stamp.nanosec, frame_id). Raises PointCloud2Error ("undecodable_message") on bytes that
    are not a PointCloud2."""
    try:
        return TYPESTORE.deserialize_cdr(memoryview(raw), CLOUD_TYPE)
    except Exception as exc:  # rosbags raises several types on malformed bytes
        raise PointCloud2Error("undecodable_message",
                               f"not a serialised PointCloud2 ({len(raw)} bytes): {exc}") from exc


def parse_layout(msg: PointCloud2) -> CloudLayout:
    """Validate the message's fields and sizes (no point data is touched). Raises PointCloud2Error."""
    num = int(msg.width) * int(msg.height)
    if num == 0:
        raise PointCloud2Error("empty_cloud", f"cloud is empty (width={msg.width}, height={msg.height})")
    step = int(msg.point_step)
    fields = tuple((f.name, int(f.offset), int(f.datatype), max(int(f.count), 1)) for f in msg.fields)
    names = [f[0] for f in fields]
    repeated = sorted({n for n in names if names.count(n) > 1 and n != _PADDING})
    if repeated:
        raise PointCloud2Error("bad_layout", f"field name(s) {', '.join(map(repr, repeated))} appear more than once")
    by_name = {f[0]: f for f in fields}
    missing = [n for n in _XYZ if n not in by_name]
    if missing:
        raise PointCloud2Error("missing_xyz", f"cloud has no {'/'.join(missing)} field (fields: {names})")
    order = ">" if msg.is_bigendian else "<"
    for name, offset, datatype, count in fields:
        if datatype not in _DATATYPES:
            raise PointCloud2Error("bad_layout", f"field '{name}' has unknown datatype {datatype}")
        if offset < 0 or offset + _DATATYPES[datatype].itemsize * count > step:
            raise PointCloud2Error(
                "bad_layout", f"field '{name}' (offset {offset}) does not fit in point_step {step}"
            )
    xyz_dtypes = []
    for name in _XYZ:
        datatype = by_name[name][2]
        if datatype not in (PointField.FLOAT32, PointField.FLOAT64):
            raise PointCloud2Error(
                "bad_xyz_type", f"field '{name}' must be FLOAT32 or FLOAT64, got datatype {datatype}"
            )
        xyz_dtypes.append(_DATATYPES[datatype].newbyteorder(order))
    spans = sorted((by_name[n][1], by_name[n][1] + _DATATYPES[by_name[n][2]].itemsize * by_name[n][3], n) for n in _XYZ)
    for (_, end, first), (start, _, second) in pairwise(spans):
        if start < end:
            raise PointCloud2Error("bad_layout", f"fields '{first}' and '{second}' overlap in the point record "
                                   f"(offsets {by_name[first][1]} and {by_name[second][1]})")
    if int(msg.row_step) < int(msg.width) * step:
        raise PointCloud2Error(
            "bad_layout", f"row_step {msg.row_step} < width {msg.width} * point_step {step}"
        )
    needed = int(msg.row_step) * int(msg.height)
    if len(msg.data) < needed:
        raise PointCloud2Error(
            "truncated_data", f"data has {len(msg.data)} bytes, row_step * height needs {needed}"
        )
    return CloudLayout(
        fields=fields,
        point_step=step,
        is_bigendian=bool(msg.is_bigendian),
        xyz_offsets=tuple(by_name[n][1] for n in _XYZ),
        xyz_dtypes=tuple(xyz_dtypes),
    )


def _raw_records(msg: PointCloud2, step: int) -> np.ndarray:
    """(height * width, point_step) uint8 over msg.data; a view unless rows are padded."""
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    h, w, row = int(msg.height), int(msg.width), int(msg.row_step)
    if row == w * step:
        return buf[: h * row].reshape(h * w, step)
    rows = np.lib.stride_tricks.as_strided(buf, shape=(h, w * step), strides=(row, 1), writeable=False)
    return np.ascontiguousarray(rows).reshape(h * w, step)


def _xyz_view(records: np.ndarray, layout: CloudLayout) -> list[np.ndarray]:
    """Strided views of the coordinates inside `records` (contiguous (n, point_step) uint8)."""
    n, step = records.shape
    if layout.packed_xyz:
        dt = layout.xyz_dtypes[0]
        return [np.ndarray((n, 3), dt, records, layout.xyz_offsets[0], (step, dt.itemsize))]
    return [np.ndarray((n,), dt, records, off, (step,)) for off, dt in zip(layout.xyz_offsets, layout.xyz_dtypes)]


def read_points(msg: PointCloud2, max_points: int | None = None, finite_only: bool = True) -> DecodedCloud:
    """Decode a PointCloud2: finite x, y, z (every point with finite_only=False) plus the raw records of
    every point.

    Raises PointCloud2Error with reason 'empty_cloud', 'missing_xyz', 'bad_xyz_type', 'bad_layout' (unknown
    datatype, a field outside point_step, a repeated field name, overlapping x/y/z, row_step too small),
    'truncated_data', 'too_many_points' or (finite_only) 'no_finite_points'.
    """
    layout = parse_layout(msg)
    num = int(msg.width) * int(msg.height)
    if max_points is not None and num > max_points:
        raise PointCloud2Error("too_many_points", f"cloud has {num} points, max_points is {max_points}")
    records = _raw_records(msg, layout.point_step)
    views = _xyz_view(records, layout)
    if len(views) == 1 and views[0].dtype == layout.point_dtype and views[0].dtype.isnative:
        points = kernels.copy_rows(views[0])  # one compiled pass: numpy's strided copy is 5x slower
    else:  # byte-swapped or mixed coordinate types
        points = np.empty((num, 3), layout.point_dtype)
        for i, view in enumerate(views[0].T if len(views) == 1 else views):
            points[:, i] = view
    mask = None
    finite = np.isfinite(points) if finite_only else True
    if not np.all(finite):  # a flat reduction is ~50x faster than .all(axis=1); this path is the rare one
        mask = finite[:, 0] & finite[:, 1] & finite[:, 2]
        points = points.take(np.flatnonzero(mask), axis=0)  # ~20x faster than points[mask] on (n, 3)
        if len(points) == 0:
            raise PointCloud2Error("no_finite_points", f"all {num} points are NaN/Inf")
    return DecodedCloud(points=points, mask=mask, records=records, layout=layout, num_input=num)


def unpack_rgb(cloud: DecodedCloud) -> np.ndarray | None:
    """(K, 3) uint8 RGB of the kept points from a packed `rgb` (or `rgba`) UINT32/FLOAT32 field holding
    0x00RRGGBB (PCL's layout), or None if the cloud has no such field."""
    by_name = {f[0]: f for f in cloud.layout.fields}
    name = "rgb" if "rgb" in by_name else "rgba" if "rgba" in by_name else None
    if name is None or by_name[name][2] not in (PointField.UINT32, PointField.FLOAT32):
        return None
    records = cloud.records if cloud.mask is None else cloud.records.take(np.flatnonzero(cloud.mask), axis=0)
    dt = np.dtype(">u4" if cloud.layout.is_bigendian else "<u4")
    packed = np.ndarray((len(records),), dt, records, by_name[name][1], (cloud.layout.point_step,)).astype(np.uint32)
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)


def _to_data(buffer: np.ndarray) -> array.array:
    """The bytes of `buffer` in a new array.array('B') (one memcpy)."""
    data = array.array("B")
    data.frombytes(np.ascontiguousarray(buffer).reshape(-1).view(np.uint8))
    return data


def _new_cloud(data: array.array, **fields) -> PointCloud2:
    """A PointCloud2 that keeps `data` as is. With check_fields=True the generated setter stores an
    array.array('B') without copying it (otherwise it copies; a memoryview or ndarray would even go
    element by element). Distros without the check_fields argument get the copying path."""
    try:
        msg = PointCloud2(check_fields=True, **fields)
    except (AssertionError, TypeError):
        msg = PointCloud2(**fields)
    msg.data = data
    return msg


def replace_points(header: Header, cloud: DecodedCloud, points: np.ndarray) -> PointCloud2:
    """A copy of the kept points of `cloud` with x, y, z replaced by `points` (K, 3).

    Every other field, the field list, point_step and byte order are kept. The output is unorganised
    (height 1) and dense, since non-finite points were dropped.
    """
    if len(points) != len(cloud.points):
        raise ValueError(f"{len(points)} points given for a cloud of {len(cloud.points)} kept points")

    def fill(columns: list[np.ndarray]) -> None:
        for i, column in enumerate(columns):
            column[...] = points[:, i]

    return _rebuild(header, cloud, fill)


def transform_cloud(header: Header, cloud: DecodedCloud, T: np.ndarray) -> PointCloud2:
    """The kept points of `cloud` moved by the 4x4 transform T (x' = R x + t), every other field kept.

    Computed in the points' dtype with nine vector multiply-adds written straight into the output
    records: numpy's BLAS path for an (n, 3) x (3, 3) product is far slower on busy cores.
    """
    T = np.asarray(T, dtype=np.float64)
    pts = cloud.points
    R, t = T[:3, :3].astype(pts.dtype), T[:3, 3].astype(pts.dtype)
    acc, tmp = np.empty(len(pts), pts.dtype), np.empty(len(pts), pts.dtype)

    def fill(columns: list[np.ndarray]) -> None:
        for i, column in enumerate(columns):
            np.multiply(pts[:, 0], R[i, 0], out=acc)
            np.add(acc, t[i], out=acc)
            for j in (1, 2):
                np.multiply(pts[:, j], R[i, j], out=tmp)
                np.add(acc, tmp, out=acc)
            column[...] = acc

    return _rebuild(header, cloud, fill)


def _rebuild(header: Header, cloud: DecodedCloud, fill) -> PointCloud2:
    """Copy the kept records into a new message buffer and let `fill` write the x, y, z columns."""
    records = cloud.records
    if cloud.mask is not None:
        records = records.take(np.flatnonzero(cloud.mask), axis=0)  # row gather, not per-byte masking
    layout = cloud.layout
    data = _to_data(records)
    out = np.frombuffer(data, dtype=np.uint8).reshape(len(records), layout.point_step)
    views = _xyz_view(out, layout)
    fill([views[0][:, i] for i in range(3)] if len(views) == 1 else views)
    del out, views  # release the buffer exports of `data`
    return _new_cloud(
        data,
        header=header,
        height=1,
        width=len(records),
        fields=[PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in layout.fields],
        is_bigendian=layout.is_bigendian,
        point_step=layout.point_step,
        row_step=layout.point_step * len(records),
        is_dense=True,
    )


def field_layout(dt: np.dtype) -> tuple[list[tuple[str, int, int, int]], bool]:
    """(name, offset, datatype, count) of each field of a structured dtype, as a PointCloud2 describes its records
    (subarray fields become `count`), and whether they are big-endian. ValueError for a field type PointCloud2 has
    no datatype for, or fields of two byte orders."""
    if dt.names is None:
        raise ValueError("records must be a structured array")
    fields, orders = [], set()
    for name in dt.names:
        sub, offset = dt.fields[name][:2]
        base, count = (sub.base, int(np.prod(sub.shape))) if sub.shape else (sub, 1)
        code = _NUMPY_TO_DATATYPE.get((base.kind, base.itemsize))
        if code is None:
            raise ValueError(f"field '{name}' has unsupported dtype {base}")
        if base.itemsize > 1:
            orders.add(">" if base.byteorder == ">" or (base.byteorder == "=" and sys.byteorder == "big") else "<")
        fields.append((name, offset, code, count))
    if len(orders) > 1:
        raise ValueError("all fields must share one byte order")
    return fields, orders == {">"}


def array_to_msg(header: Header, records: np.ndarray, is_dense: bool = True) -> PointCloud2:
    """A PointCloud2 from a structured array: (n,) unorganised or (height, width) organised.

    Fields, offsets and point_step (itemsize, so padding is kept) come from the dtype (`field_layout`); subarray
    fields become `count`. All fields must share one byte order, which sets `is_bigendian`.
    """
    fields, bigendian = field_layout(records.dtype)
    height, width = (1, records.shape[0]) if records.ndim == 1 else records.shape
    return _new_cloud(
        _to_data(records),
        header=header,
        height=height,
        width=width,
        fields=[PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
        is_bigendian=bigendian,
        point_step=records.dtype.itemsize,
        row_step=records.dtype.itemsize * width,
        is_dense=is_dense,
    )


def records_cloud(records: np.ndarray) -> Any:
    """A rosbags PointCloud2 over the bytes of a contiguous (n,) structured array, without a copy (`read_points`
    decodes it as any cloud; its header empty): a file's records decoded by this codec. ValueError as
    `field_layout`."""
    fields, bigendian = field_layout(records.dtype)
    t = TYPESTORE.types
    field = t["sensor_msgs/msg/PointField"]
    stamp = t["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    return t[CLOUD_TYPE](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=""), height=1, width=len(records),
                         fields=[field(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
                         is_bigendian=bigendian, point_step=records.dtype.itemsize,
                         row_step=records.dtype.itemsize * len(records),
                         data=np.ascontiguousarray(records).view(np.uint8).reshape(-1), is_dense=False)


def xyz_to_msg(header: Header, points: np.ndarray) -> PointCloud2:
    """A plain x, y, z FLOAT32 cloud (point_step 12) from an (n, 3) array."""
    pts = np.ascontiguousarray(points, dtype="<f4")
    records = pts.view(np.dtype({"names": list(_XYZ), "formats": ["<f4"] * 3})).reshape(-1)
    return array_to_msg(header, records)

