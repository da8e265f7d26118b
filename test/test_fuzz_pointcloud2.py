"""Property-based tests of the PointCloud2 decoder (`parse_layout`, `read_points`) on random messages.

Random field layouts (names, offsets, datatypes, counts, repeated names, overlapping fields), endianness,
point_step / row_step, width / height, data that is short, exact or long, and random bytes (so NaN and Inf
coordinates are common). Whatever a message holds, only PointCloud2Error may escape, and a decoded cloud is
exactly the coordinates a byte-by-byte `struct` reader finds, finite with `finite_only`.

Examples per test: the hypothesis profile (test/conftest.py): "ci" by default, HYPOTHESIS_PROFILE=local for
the long run.
"""

from __future__ import annotations

import array
import struct
from itertools import pairwise

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import PointCloud2, PointField

from genreg_ros.pointcloud2 import PointCloud2Error, parse_layout, read_points

UINT32_MAX = 2**32 - 1
_STRUCT = {PointField.FLOAT32: "f", PointField.FLOAT64: "d"}
NAMES = st.sampled_from(["x", "y", "z", "intensity", "rgb", "_", ""]) | st.text(max_size=4)
DATATYPES = st.sampled_from([*range(10), 255])  # 1..8 valid, 0, 9 and 255 not
SMALL_OR_HUGE = st.integers(0, 48) | st.integers(0, UINT32_MAX)


@st.composite
def valid_fields(draw) -> list[tuple[str, int, int, int]]:
    """(name, offset, datatype, count) of a decodable layout: x, y, z in any order with gaps, plus other fields."""
    out, offset = [], 0
    names = draw(st.permutations(["x", "y", "z", *draw(st.lists(st.sampled_from(["intensity", "rgb", "_"]),
                                                                 max_size=3, unique=True))]))
    for name in names:
        offset += draw(st.sampled_from([0, 0, 1, 2, 4]))
        datatype = draw(st.sampled_from([PointField.FLOAT32, PointField.FLOAT64] if name in "xyz" else [*range(1, 9)]))
        count = draw(st.sampled_from([1, 1, 0])) if name in "xyz" else draw(st.integers(0, 3))
        out.append((name, offset, datatype, count))
        offset += {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}[datatype] * max(count, 1)
    return out


@st.composite
def any_fields(draw) -> list[tuple[str, int, int, int]]:
    """Any (name, offset, datatype, count): repeated names, overlaps, bad datatypes, huge offsets and counts."""
    return draw(st.lists(st.tuples(NAMES, SMALL_OR_HUGE, DATATYPES, st.integers(0, 3) | st.integers(0, UINT32_MAX)),
                         max_size=6))


@st.composite
def mutated(draw, layout: list[tuple[str, int, int, int]]) -> list[tuple[str, int, int, int]]:
    """`layout` with one field's name, offset, datatype or count changed, or a field repeated."""
    if not layout or draw(st.booleans()):
        return layout
    layout = list(layout)
    i = draw(st.integers(0, len(layout) - 1))
    name, offset, datatype, count = layout[i]
    change = draw(st.sampled_from(["name", "offset", "datatype", "count", "repeat"]))
    if change == "repeat":
        layout.insert(draw(st.integers(0, len(layout))), (name, draw(st.integers(0, 24)), datatype, count))
    else:
        layout[i] = (draw(NAMES) if change == "name" else name, draw(SMALL_OR_HUGE) if change == "offset" else offset,
                     draw(DATATYPES) if change == "datatype" else datatype,
                     draw(st.integers(0, 4)) if change == "count" else count)
    return layout


@st.composite
def clouds(draw) -> PointCloud2:
    """Half plausible clouds (decodable, or with one thing wrong), half anything."""
    if draw(st.booleans()):
        layout = draw(valid_fields())
        end = max(o + 8 * max(c, 1) for _, o, _, c in layout)
        point_step = draw(st.integers(end, end + 8))
        layout = draw(mutated(layout))
        width, height = draw(st.integers(1, 6)), draw(st.integers(1, 3))
        row_step = width * point_step + draw(st.sampled_from([0, 0, 0, 3, 8]))
    else:
        layout = draw(any_fields())
        point_step = draw(SMALL_OR_HUGE)
        width, height = draw(st.integers(0, 6) | st.integers(0, UINT32_MAX)), draw(st.integers(0, 3) | st.integers(0, UINT32_MAX))
        row_step = min(draw(st.sampled_from([width * point_step, width * point_step + 3]) | SMALL_OR_HUGE), UINT32_MAX)
    needed = row_step * height
    size = draw(st.sampled_from([needed, needed, needed - 1, needed + 5, 0]) | st.integers(0, 600))
    size = max(0, min(size, 4096))
    data = draw(st.binary(min_size=size, max_size=size))
    return PointCloud2(
        height=height, width=width, is_bigendian=draw(st.booleans()), point_step=point_step, row_step=row_step,
        is_dense=draw(st.booleans()), data=array.array("B", data),
        fields=[PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in layout])


def struct_xyz(msg: PointCloud2) -> np.ndarray:
    """Every point's x, y, z read with struct (independent of the decoder), as float64, row-major."""
    by_name = {f.name: f for f in msg.fields}
    order = ">" if msg.is_bigendian else "<"
    raw = bytes(msg.data)
    out = np.empty((msg.width * msg.height, 3))
    for r in range(msg.height):
        for c in range(msg.width):
            base = r * msg.row_step + c * msg.point_step
            for i, name in enumerate("xyz"):
                f = by_name[name]
                out[r * msg.width + c, i] = struct.unpack_from(order + _STRUCT[f.datatype], raw, base + f.offset)[0]
    return out


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(msg=clouds(), finite_only=st.booleans(), max_points=st.none() | st.integers(0, 20))
def test_random_messages_decode_exactly_or_raise_pointcloud2error(msg, finite_only, max_points):
    try:
        parse_layout(msg)
    except PointCloud2Error as exc:
        assert exc.reason and "\n" not in str(exc)
    try:
        cloud = read_points(msg, max_points=max_points, finite_only=finite_only)
    except PointCloud2Error as exc:
        assert exc.reason in {"empty_cloud", "missing_xyz", "bad_xyz_type", "bad_layout", "truncated_data",
                              "too_many_points", "no_finite_points"}, exc.reason
        hypothesis.event(exc.reason)
        return
    names = [f.name for f in msg.fields]
    assert all(names.count(n) == 1 for n in names if n != "_"), names  # no repeated field name decodes
    spans = sorted((f.offset, f.offset + (8 if f.datatype == PointField.FLOAT64 else 4) * max(f.count, 1))
                   for f in msg.fields if f.name in "xyz" and f.name)
    assert all(a[1] <= b[0] for a, b in pairwise(spans)), spans  # nor do overlapping x, y, z
    hypothesis.event("decoded")
    pts = cloud.points
    assert pts.ndim == 2 and pts.shape[1] == 3 and pts.dtype in (np.float32, np.float64)
    expected = struct_xyz(msg).astype(pts.dtype)
    if finite_only:
        assert len(pts) > 0 and np.isfinite(pts).all()
        expected = expected[np.isfinite(expected).all(axis=1)]
    np.testing.assert_array_equal(pts, expected)
    assert cloud.num_input == msg.width * msg.height == len(cloud.records)
    assert max_points is None or cloud.num_input <= max_points
