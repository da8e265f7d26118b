"""`genreg_ros.cloud_file`'s fast path for binary PCD files against Open3D's tensor reader (the reference;
Open3D's legacy reader reads 8-byte float fields as zeros: `read_quietly` uses the tensor one)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from genreg_ros.cloud_file import CloudFileError, read_binary_pcd, read_cloud, read_quietly

EXTRA = [("intensity", "F", 4), ("ring", "U", 2), ("t", "U", 4), ("tag", "I", 1), ("range", "F", 8), ("id", "I", 4)]


def write_pcd(path: Path, fields: list[tuple[str, str, int, int]], records: np.ndarray, data: str = "binary") -> None:
    """A PCD v0.7 file of these (name, TYPE, SIZE, COUNT) fields and records (a structured array in that
    layout), as PCL writes one."""
    header = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
              "FIELDS " + " ".join(f[0] for f in fields), "SIZE " + " ".join(str(f[2]) for f in fields),
              "TYPE " + " ".join(f[1] for f in fields), "COUNT " + " ".join(str(f[3]) for f in fields),
              f"WIDTH {len(records)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(records)}", f"DATA {data}"]
    path.write_bytes(("\n".join(header) + "\n").encode() + records.tobytes())


def layout(fields: list[tuple[str, str, int, int]]) -> np.dtype:
    kinds = {"F": "f", "I": "i", "U": "u"}
    return np.dtype([(name, f"<{kinds[t]}{z}", (c,)) if c > 1 else (name, f"<{kinds[t]}{z}")
                     for name, t, z, c in fields])


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 400), st.sampled_from([4, 8]), st.permutations(range(len(EXTRA) + 3)),
       st.integers(0, len(EXTRA)), st.integers(1, 3), st.integers(0, 2**32 - 1))
def test_binary_pcd_points_are_open3ds(tmp_path_factory, count, xyz_size, order, extras, repeat, seed):
    """Any layout PCL writes (x, y, z as 4- or 8-byte floats anywhere among other fields of 1-8 bytes, some
    repeated), non-finite points included: the fast path reads the same points as Open3D."""
    rng = np.random.default_rng(seed)
    named = [(a, "F", xyz_size, 1) for a in ("x", "y", "z")] + [(n, t, z, repeat if k == 0 else 1)
                                                                for k, (n, t, z) in enumerate(EXTRA[:extras])]
    fields = [named[k] for k in order if k < len(named)]
    records = np.zeros(count, dtype=layout(fields))
    for name, t, _, _ in fields:
        values = rng.uniform(-50, 50, records[name].shape) if t == "F" else rng.integers(0, 100, records[name].shape)
        records[name] = values
    records["x"][rng.random(count) < 0.1] = np.nan
    records["z"][rng.random(count) < 0.05] = np.inf
    path = tmp_path_factory.mktemp("pcd") / "cloud.pcd"
    write_pcd(path, fields, records)
    assert read_binary_pcd(path, path.read_bytes()[:65536]) is not None  # the fast path was taken
    reference, printed = read_quietly(path)
    assert not printed
    expected = reference[np.isfinite(reference).all(axis=1)]
    if len(expected) == 0:
        with pytest.raises(CloudFileError, match="no points read"):
            read_cloud(path)
        return
    got = read_cloud(path)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, expected)


def test_other_pcds_go_to_open3d_and_truncated_ones_are_errors(tmp_path):
    """ASCII data and an integer x are left to Open3D (the same points); a binary file that holds fewer records
    than it declares is the one-line 'malformed or truncated' error."""
    fields = [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)]
    records = np.zeros(5, dtype=layout(fields))
    records["x"], records["y"], records["z"] = np.arange(5), 1.0, 2.0
    write_pcd(tmp_path / "ascii.pcd", fields, np.zeros(0, dtype=records.dtype), data="ascii")
    (tmp_path / "ascii.pcd").write_bytes((tmp_path / "ascii.pcd").read_bytes().replace(b"POINTS 0", b"POINTS 5")
                                         .replace(b"WIDTH 0", b"WIDTH 5")
                                         + b"".join(b"%d 1 2\n" % i for i in range(5)))
    head = (tmp_path / "ascii.pcd").read_bytes()
    assert read_binary_pcd(tmp_path / "ascii.pcd", head) is None
    np.testing.assert_array_equal(read_cloud(tmp_path / "ascii.pcd"), np.c_[np.arange(5), np.ones(5), 2 * np.ones(5)])
    integer = [("x", "I", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)]
    write_pcd(tmp_path / "int.pcd", integer, np.zeros(5, dtype=layout(integer)))
    assert read_binary_pcd(tmp_path / "int.pcd", (tmp_path / "int.pcd").read_bytes()) is None
    write_pcd(tmp_path / "cut.pcd", fields, records)
    (tmp_path / "cut.pcd").write_bytes((tmp_path / "cut.pcd").read_bytes()[:-7])
    with pytest.raises(EOFError):
        read_binary_pcd(tmp_path / "cut.pcd", (tmp_path / "cut.pcd").read_bytes())
    with pytest.raises(CloudFileError, match="malformed or truncated"):
        read_cloud(tmp_path / "cut.pcd")
