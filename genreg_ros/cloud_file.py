"""Point cloud files (PLY, PCD) as register_node reads them: `target_file`, the fixed target or the map.

`read_cloud` checks the file's header itself first (`header_problem`), then lets Open3D read it with
Open3D's messages and RPly's (which RPly writes straight to stderr and which can quote the file) captured
and discarded, so no content of the file reaches the log. Whatever is wrong is a `CloudFileError` with a
one-line message that names the problem and never quotes the file.

A fast path: a PCD file of PCL's uncompressed binary records (`DATA binary`, the form PCL's tools and most
LiDAR mappers write maps in) is read by numpy as a structured array of its records and decoded by the
PointCloud2 codec (`read_binary_pcd`: 0.3-0.9 s for a 9 M-point map, which Open3D reads in 1.0-1.6 s), the
same points as Open3D's (test: `test_cloud_file.py`).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from genreg_ros.pointcloud2 import PointCloud2Error, read_points, records_cloud

HEADER_BYTES = 65536  # a PLY or PCD header must end within this many bytes
PCD_KINDS = {"F": "f", "I": "i", "U": "u"}  # a PCD field's TYPE -> numpy's kind (its records are little-endian)
PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
PCD_DATA = ("ascii", "binary", "binary_compressed")


class CloudFileError(ValueError):
    """A cloud file that cannot be used: missing, a directory, unreadable or not a well-formed PLY / PCD
    cloud; one line, without the file's content."""


def header_problem(suffix: str, head: bytes) -> str:
    """Why `head` (a file's first bytes) is no PLY / PCD point cloud header for a file ending in `suffix`
    ("" if it is one). Names what is wrong, never quotes the file."""
    if suffix not in (".ply", ".pcd"):
        return f"a .ply or .pcd file is expected, not {suffix or 'no extension'}"
    text = head.decode("latin-1")
    end = "end_header" if suffix == ".ply" else "\nDATA "
    if end not in text:
        return f"no complete {suffix[1:].upper()} header in its first {HEADER_BYTES} bytes"
    lines = [ln.split() for ln in text.split(end)[0].splitlines()]
    if suffix == ".ply":
        if not lines or lines[0] != ["ply"]:
            return "not a PLY file (its first line is not 'ply')"
        fmt = [ln for ln in lines if ln[:1] == ["format"]]
        if len(fmt) != 1 or len(fmt[0]) != 3 or fmt[0][1] not in PLY_FORMATS:
            return f"PLY header without a valid format line ({', '.join(PLY_FORMATS)})"
        vertex = [ln for ln in lines if ln[:2] == ["element", "vertex"]]
        props = {ln[-1] for ln in lines if ln[:1] == ["property"]}
        if not vertex or not {"x", "y", "z"} <= props:
            return "PLY header without a vertex element with x, y, z properties"
        return ""
    fields = next((ln[1:] for ln in lines if ln[:1] == ["FIELDS"]), [])
    data = text.split(end, 1)[1].split(maxsplit=1)[:1]
    if not {"x", "y", "z"} <= set(fields):
        return "PCD header without x, y, z fields"
    if data and data[0] not in PCD_DATA:
        return f"PCD header with an unknown DATA type (one of {', '.join(PCD_DATA)} is expected)"
    return ""


def read_quietly(path: Path) -> tuple[np.ndarray, bool]:
    """(points, whether the readers printed anything) of a PLY / PCD file read by Open3D (its tensor reader),
    with its output and RPly's captured and discarded."""
    import ctypes
    import tempfile

    import open3d as o3d

    sys.stderr.flush()
    sys.stdout.flush()
    saved = os.dup(2), os.dup(1)
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 2)
            os.dup2(sink.fileno(), 1)
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Warning):
                # the tensor reader: the legacy one reads 8-byte float fields of binary PCD files as zeros
                cloud = o3d.t.io.read_point_cloud(str(path)).point
                points = cloud.positions.numpy().astype(np.float64) if "positions" in cloud else np.zeros((0, 3))
        finally:
            ctypes.CDLL(None).fflush(None)  # C stdio buffers into the sink, not after it is gone
            os.dup2(saved[0], 2)
            os.dup2(saved[1], 1)
            os.close(saved[0])
            os.close(saved[1])
        printed = sink.seek(0, os.SEEK_END) > 0
    return points, printed


def read_binary_pcd(path: Path, head: bytes) -> np.ndarray | None:
    """The (N, 3) float64 points of a PCD file (`head`: its first bytes, `header_problem`'s check passed) of
    uncompressed binary records: the records read as one structured array and decoded by the PointCloud2 codec
    (`genreg_ros.pointcloud2`; every point, non-finite ones included). None for any other PCD, or records it
    cannot decode (Open3D reads those). EOFError when the file holds fewer records than its header declares."""
    header, _, rest = head.decode("latin-1").partition("\nDATA ")
    data_line = rest.split("\n", 1)[0]
    if data_line.strip() != "binary":
        return None
    lines = {words[0]: words[1:] for words in map(str.split, header.splitlines()) if words}
    names, types = lines.get("FIELDS", []), lines.get("TYPE", [])
    try:
        sizes = [int(x) for x in lines.get("SIZE", [])]
        counts = [int(x) for x in lines.get("COUNT", ["1"] * len(names))]
        n = int(lines.get("POINTS", [""])[0])
        fields = [(f"_{k}" if name == "_" else name, f"<{PCD_KINDS[kind]}{size}", (count,) if count > 1 else ())
                  for k, (name, kind, size, count) in enumerate(zip(names, types, sizes, counts, strict=True))]
        records = np.dtype(fields)
    except (ValueError, KeyError, TypeError):  # a malformed or unknown field: Open3D's to read or to refuse
        return None
    if n < 0 or min(counts, default=1) < 1:
        return None
    start = len(header) + len("\nDATA ") + len(data_line) + 1  # latin-1: one character a byte
    if path.stat().st_size < start + n * records.itemsize:
        raise EOFError("fewer records than the header declares")
    try:
        points = read_points(records_cloud(np.fromfile(path, dtype=records, count=n, offset=start)),
                             finite_only=False).points
    except (PointCloud2Error, ValueError):  # e.g. integer coordinates, a field type PointCloud2 has no code for
        return None
    return points.astype(np.float64, copy=False)


def read_cloud(path: str | os.PathLike, what: str = "target_file") -> np.ndarray:
    """The finite points, (N, 3) float64, of the PLY / PCD file `path` (`~` expanded); CloudFileError (its
    message starts with `what` and the path) for anything unusable, an empty cloud included."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise CloudFileError(f"{what} {path} is a directory (a PLY or PCD file is expected)")
    if not path.exists():
        raise CloudFileError(f"{what} not found: {path}")
    try:
        with path.open("rb") as f:
            head = f.read(HEADER_BYTES)
    except OSError as exc:
        raise CloudFileError(f"{what} {path} cannot be read: {exc.strerror or type(exc).__name__}") from None
    problem = header_problem(path.suffix.lower(), head)
    if problem:
        raise CloudFileError(f"{what} {path}: {problem}")
    try:  # the fast path, else Open3D
        fast = read_binary_pcd(path, head) if path.suffix.lower() == ".pcd" else None
    except EOFError:
        raise CloudFileError(f"{what} {path}: malformed or truncated (PCD cloud)") from None
    points, printed = (fast, False) if fast is not None else read_quietly(path)
    finite = np.isfinite(points).all(axis=1)
    points = points if finite.all() else points[finite]  # a copy only where one is needed (0.7 s for 9 M points)
    if printed or len(points) == 0:
        raise CloudFileError(f"{what} {path}: {'malformed or truncated' if printed else 'no points read'} "
                             f"({path.suffix[1:].upper()} cloud)")
    return points
