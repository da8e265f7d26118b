"""PointCloud2 <-> numpy: checked against messages built byte by byte with `struct` (independent truth)."""

from __future__ import annotations

import array
import math
import struct

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from genreg_ros.pointcloud2 import (
    PointCloud2Error,
    array_to_msg,
    read_points,
    replace_points,
    transform_cloud,
    xyz_to_msg,
)

F32, F64, U8, U16 = PointField.FLOAT32, PointField.FLOAT64, PointField.UINT8, PointField.UINT16
_FMT = {F32: "f", F64: "d", U8: "B", U16: "H"}


def build(fields, rows, point_step, big=False, height=1, row_pad=0, frame="sensor"):
    """A PointCloud2 packed with struct: `fields` = [(name, offset, datatype)], `rows` = per-point tuples."""
    order = ">" if big else "<"
    width = len(rows) // height
    row_step = width * point_step + row_pad
    data = bytearray(row_step * height)
    for i, values in enumerate(rows):
        r, c = divmod(i, width)
        base = r * row_step + c * point_step
        for (_, offset, dt), value in zip(fields, values):
            struct.pack_into(order + _FMT[dt], data, base + offset, value)
    return PointCloud2(
        header=Header(frame_id=frame), height=height, width=width,
        fields=[PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=big, point_step=point_step, row_step=row_step, data=array.array("B", bytes(data)),
        is_dense=False)


def unpack(msg, name):
    """One field of every point of an unorganised message, read with struct."""
    f = next(f for f in msg.fields if f.name == name)
    order = ">" if msg.is_bigendian else "<"
    raw = bytes(msg.data)
    return [struct.unpack_from(order + _FMT[f.datatype], raw, i * msg.point_step + f.offset)[0]
            for i in range(msg.width * msg.height)]


XYZI_PADDED = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32)]  # 4 bytes gap, tail pad


@pytest.mark.parametrize("big", [False, True])
def test_reads_padded_layout_both_endiannesses(big):
    rows = [(1.5, -2.0, 3.25, 10.0), (0.0, 1e-3, -7.0, 20.0), (100.0, 200.0, 300.0, 30.0)]
    msg = build(XYZI_PADDED, rows, point_step=24, big=big)
    cloud = read_points(msg)
    np.testing.assert_array_equal(cloud.points, np.array([r[:3] for r in rows], np.float32))
    assert cloud.points.dtype == np.float32 and cloud.mask is None and cloud.num_input == 3


def test_reads_float64_fields_in_any_order_with_other_types():
    # z first, y float32 between, x float64 last: not a packed x,y,z block.
    fields = [("z", 0, F64), ("ring", 8, U16), ("y", 10, F32), ("flag", 14, U8), ("x", 16, F64)]
    rows = [(0.1, 7, 0.5, 1, 1.0 / 3.0), (-5.0, 9, 2.0, 0, 12345.678901234)]
    msg = build(fields, rows, point_step=32, big=True)
    cloud = read_points(msg)
    expected = np.array([[r[4], np.float32(r[2]), r[0]] for r in rows])
    assert cloud.points.dtype == np.float64
    np.testing.assert_array_equal(cloud.points, expected)


def test_organised_cloud_with_row_padding_and_nonfinite_points():
    nan, inf = math.nan, math.inf
    rows = [(i, 10 + i, 20 + i, 0.5 * i) for i in range(12)]
    rows[1] = (nan, 0.0, 0.0, 1.0)
    rows[6] = (0.0, inf, 0.0, 2.0)
    rows[11] = (0.0, 0.0, -inf, 3.0)
    msg = build(XYZI_PADDED, rows, point_step=20, height=3, row_pad=7)  # 3 rows x 4 columns
    cloud = read_points(msg)
    keep = [i for i in range(12) if i not in (1, 6, 11)]
    np.testing.assert_array_equal(cloud.mask, [i in keep for i in range(12)])
    np.testing.assert_array_equal(cloud.points, np.array([rows[i][:3] for i in keep], np.float32))
    assert cloud.num_dropped == 3


@pytest.mark.parametrize("big", [False, True])
def test_replace_points_keeps_other_fields_and_layout(big):
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 12, F32), ("ring", 16, U16)]
    rows = [(1.0, 2.0, 3.0, 0.25, 4), (math.nan, 0.0, 0.0, 0.5, 5), (4.0, 5.0, 6.0, 0.75, 6)]
    msg = build(fields, rows, point_step=20, big=big)
    cloud = read_points(msg)
    new = np.array([[-1.0, -2.0, -3.0], [7.5, 8.5, 9.5]], np.float32)
    out = replace_points(Header(frame_id="map"), cloud, new)
    assert (out.height, out.width, out.point_step, out.row_step) == (1, 2, 20, 40)
    assert out.is_bigendian == big and out.is_dense and out.header.frame_id == "map"
    assert [(f.name, f.offset, f.datatype) for f in out.fields] == [f[:3] for f in fields]
    assert unpack(out, "x") == [-1.0, 7.5] and unpack(out, "y") == [-2.0, 8.5] and unpack(out, "z") == [-3.0, 9.5]
    assert unpack(out, "intensity") == [0.25, 0.75] and unpack(out, "ring") == [4, 6]
    assert isinstance(out.data, array.array)  # the fast setter path


def test_replace_points_rejects_wrong_count():
    cloud = read_points(build(XYZI_PADDED, [(1.0, 2.0, 3.0, 4.0)], point_step=20))
    with pytest.raises(ValueError):
        replace_points(Header(), cloud, np.zeros((2, 3), np.float32))


def test_array_to_msg_round_trip_with_subarray_and_big_endian():
    dt = np.dtype({"names": ["x", "y", "z", "normal", "label"], "formats": [">f8", ">f8", ">f8", (">f4", (3,)), "u1"],
                   "offsets": [0, 8, 16, 24, 36], "itemsize": 40})
    rec = np.zeros((2, 3), dt)  # organised 2 x 3
    rec["x"] = np.arange(6).reshape(2, 3)
    rec["y"], rec["z"], rec["label"] = -1.0, 0.5, 9
    msg = array_to_msg(Header(frame_id="f"), rec)
    assert (msg.height, msg.width, msg.point_step, msg.is_bigendian) == (2, 3, 40, True)
    normal = next(f for f in msg.fields if f.name == "normal")
    assert (normal.offset, normal.datatype, normal.count) == (24, F32, 3)
    assert unpack(msg, "x") == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0] and unpack(msg, "label") == [9] * 6
    np.testing.assert_array_equal(read_points(msg).points[:, 0], np.arange(6))


def test_xyz_to_msg():
    pts = np.array([[1, 2, 3], [4, 5, 6]], np.float64)
    msg = xyz_to_msg(Header(frame_id="f"), pts)
    assert msg.point_step == 12 and [f.name for f in msg.fields] == ["x", "y", "z"]
    assert unpack(msg, "z") == [3.0, 6.0]


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("empty", "empty_cloud"),
        ("no_xyz", "missing_xyz"),
        ("int_x", "bad_xyz_type"),
        ("truncated", "truncated_data"),
        ("field_outside_point", "bad_layout"),
        ("row_step_small", "bad_layout"),
        ("all_nan", "no_finite_points"),
        ("too_many", "too_many_points"),
    ],
)
def test_bad_clouds_raise_with_reason(case, reason):
    rows = [(1.0, 2.0, 3.0, 4.0)] * 4
    msg = build(XYZI_PADDED, rows, point_step=20)
    max_points = None
    if case == "empty":
        msg = build(XYZI_PADDED, [], point_step=20)
    elif case == "no_xyz":
        msg.fields = [f for f in msg.fields if f.name != "y"]
    elif case == "int_x":
        msg.fields[0].datatype = PointField.INT32
    elif case == "truncated":
        msg.data = msg.data[:-1]
    elif case == "field_outside_point":
        msg.fields[3].offset = 18
    elif case == "row_step_small":
        msg.row_step = 60
    elif case == "all_nan":
        msg = build(XYZI_PADDED, [(math.nan, 0.0, 0.0, 1.0)] * 3, point_step=20)
    elif case == "too_many":
        max_points = 3
    with pytest.raises(PointCloud2Error) as err:
        read_points(msg, max_points=max_points)
    assert err.value.reason == reason


@pytest.mark.parametrize(
    ("fields", "text"),
    [
        (XYZI_PADDED + [("x", 12, F32)], "'x' appear more than once"),  # a second x
        (XYZI_PADDED[:3] + [("intensity", 12, F32), ("intensity", 16, F32)], "'intensity' appear more than once"),
        ([("x", 0, F32), ("y", 0, F32), ("z", 0, F32)], "overlap"),  # all three at offset 0
        ([("x", 0, F64), ("y", 4, F32), ("z", 12, F32)], "fields 'x' and 'y' overlap"),  # x's 8 bytes cover y
        ([("z", 0, F32), ("x", 8, F32), ("y", 2, F32)], "fields 'z' and 'y' overlap"),  # any field order
    ],
)
def test_repeated_names_and_overlapping_xyz_are_bad_layouts(fields, text):
    """A repeated field name or x/y/z sharing bytes would decode to a silently wrong cloud: rejected."""
    msg = build(fields, [(1.0, 2.0, 3.0, 4.0, 5.0)] * 3, point_step=20)
    with pytest.raises(PointCloud2Error, match=text) as err:
        read_points(msg)
    assert err.value.reason == "bad_layout" and "\n" not in str(err.value)


def test_repeated_padding_fields_are_accepted():
    """PCL names padding fields '_', and may repeat them."""
    msg = build([("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("_", 12, F32), ("_", 16, F32)],
                [(1.0, 2.0, 3.0, 0.0, 0.0)] * 2, point_step=20)
    np.testing.assert_array_equal(read_points(msg).points, [[1.0, 2.0, 3.0]] * 2)


def test_large_cloud_round_trip_matches_struct_on_a_sample():
    rng = np.random.default_rng(1)
    n = 50_000
    dt = np.dtype({"names": ["x", "y", "z", "rgb"], "formats": ["<f4"] * 3 + ["<u4"]})
    rec = np.zeros(n, dt)
    for k in "xyz":
        rec[k] = rng.normal(size=n)
    rec["rgb"] = rng.integers(0, 2**24, n)
    rec["x"][::7] = np.nan
    msg = array_to_msg(Header(), rec)
    cloud = read_points(msg)
    kept = np.flatnonzero(~np.isnan(rec["x"]))
    np.testing.assert_array_equal(cloud.points[:, 2], rec["z"][kept])
    out = replace_points(Header(), cloud, cloud.points * 2)
    for i in (0, 1, 12345, len(kept) - 1):
        x, y, z, rgb = struct.unpack_from("<fffI", bytes(out.data[i * 16:(i + 1) * 16]))
        j = kept[i]
        assert (x, y, z, rgb) == (2 * rec["x"][j], 2 * rec["y"][j], 2 * rec["z"][j], rec["rgb"][j])


@pytest.mark.parametrize(("fmt", "big"), [("f", False), ("d", True)])
def test_transform_cloud_matches_independent_math(fmt, big):
    dt = F32 if fmt == "f" else F64
    size = 4 if fmt == "f" else 8
    fields = [("x", 0, dt), ("y", size, dt), ("z", 2 * size, dt), ("ring", 3 * size, U16)]
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(50, 3)) * 10
    pts[7, 1] = math.nan
    rows = [(*p, i) for i, p in enumerate(pts)]
    msg = build(fields, rows, point_step=3 * size + 4, big=big)
    T = np.eye(4)
    c, s = math.cos(0.3), math.sin(0.3)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [1.0, -2.0, 0.5]
    out = transform_cloud(Header(frame_id="map"), read_points(msg), T)
    keep = [i for i in range(50) if i != 7]
    src = pts[keep].astype(np.float32 if fmt == "f" else np.float64).astype(np.float64)
    expected = np.array([[c * x - s * y + 1.0, s * x + c * y - 2.0, z + 0.5] for x, y, z in src])
    got = np.c_[unpack(out, "x"), unpack(out, "y"), unpack(out, "z")]
    np.testing.assert_allclose(got, expected, atol=1e-5 if fmt == "f" else 1e-12)
    assert unpack(out, "ring") == keep and out.is_bigendian == big


def test_from_cdr_reads_serialised_clouds_as_the_rclpy_message_and_names_bad_bytes():
    """The node's raw subscriptions: `from_cdr` of rclpy-serialised clouds (little and big endian, NaN rows,
    float64) decodes to exactly what the rclpy message decodes to, its data a view of the bytes; bytes that are no
    PointCloud2 raise PointCloud2Error('undecodable_message')."""
    from rclpy.serialization import serialize_message

    from genreg_ros.pointcloud2 import PointCloud2Error, from_cdr

    rng = np.random.default_rng(2)
    for order, kind in (("<", "f4"), (">", "f4"), ("<", "f8")):
        dt = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": [order + kind] * 3 + [order + "f4"]})
        rec = np.zeros(1000, dt)
        for name in dt.names:
            rec[name] = rng.normal(size=1000)
        rec["x"][::7] = np.nan
        msg = array_to_msg(Header(frame_id="lidar"), rec, is_dense=False)
        msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
        serialised = serialize_message(msg)
        raw = from_cdr(serialised)
        assert raw.header.frame_id == "lidar" and (raw.header.stamp.sec, raw.header.stamp.nanosec) == (12, 345)
        assert np.shares_memory(raw.data, np.frombuffer(serialised, np.uint8))  # a view of the bytes: no copy
        ours, theirs = read_points(raw), read_points(msg)
        np.testing.assert_array_equal(ours.points, theirs.points)
        np.testing.assert_array_equal(ours.mask, theirs.mask)
        np.testing.assert_array_equal(ours.records, theirs.records)
    with pytest.raises(PointCloud2Error) as info:
        from_cdr(serialize_message(msg)[:40])
    assert info.value.reason == "undecodable_message"


def test_little_endian_data_flagged_big_endian_never_escapes_registration_unnamed():
    """A driver that flags little-endian data as big-endian: the decoder cannot know, the values are byte-swapped
    garbage (huge, tiny, NaN). Registration raised a bare RuntimeError; now a named error or a finite result."""
    from genreg_core.config import SCENE_REGISTRATION
    from genreg_core.data import RGBDSequence
    from genreg_core.errors import GenRegError
    from genreg_core.registration import Registrar

    seq = RGBDSequence.redkitchen()
    reg = Registrar.from_checkpoint("7scenes", SCENE_REGISTRATION)
    for i in (800, 900):
        msg = xyz_to_msg(Header(frame_id="camera"), seq.points(i)[::8])
        msg.is_bigendian = True
        swapped = read_points(msg).points
        assert len(swapped) > 1000 and not np.allclose(swapped[:10], seq.points(i)[::8][:10])
        try:
            result = reg.register(swapped, seq.points(i + 10)[::8])
        except GenRegError:
            continue
        assert np.isfinite(result.transformation).all() and 0.0 <= result.confidence <= 1.0
