#!/usr/bin/env python3
"""PointCloud2 <-> numpy speed at 300k points (goal: <= 10 ms each way), medians over repeats.

    python scripts/bench_pointcloud2.py [--points 300000] [--repeats 30]

msg -> numpy is `read_points` (finite x, y, z plus the raw records); numpy -> msg is `replace_points`
(new x, y, z written into a copy of the records, every other field kept) and `xyz_to_msg`.
No DDS involved: this is the converter alone.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from std_msgs.msg import Header

from genreg_ros.pointcloud2 import array_to_msg, read_points, replace_points, xyz_to_msg


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def cloud(n: int, fmt: str, nan_fraction: float = 0.0, organised: bool = False):
    dt = np.dtype({"names": ["x", "y", "z", "rgb"], "formats": [fmt, fmt, fmt, fmt[0] + "u4"]})
    rng = np.random.default_rng(0)
    rec = np.zeros(n, dt)
    for k in "xyz":
        rec[k] = rng.normal(size=n)
    if nan_fraction:
        rec["x"][rng.uniform(size=n) < nan_fraction] = np.nan
    if organised:
        rec = rec.reshape(-1, 1000)
    return array_to_msg(Header(frame_id="sensor"), rec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    n, r = args.points, args.repeats
    cases = {
        "x,y,z,rgb float32 LE (16 B/pt)": cloud(n, "<f4"),
        "  same, 5 % NaN points": cloud(n, "<f4", nan_fraction=0.05),
        "  same, organised 300 x 1000": cloud(n, "<f4", organised=True),
        "x,y,z float64 + rgb, big-endian": cloud(n, ">f8"),
    }
    print(f"PointCloud2 <-> numpy, {n} points, median of {r} (goal <= 10 ms each way)")
    print(f"{'layout':34s} {'msg->numpy':>11s} {'numpy->msg':>11s} {'MB':>6s}")
    for name, msg in cases.items():
        decoded = read_points(msg)
        moved = decoded.points + np.asarray([1.0, 2.0, 3.0], decoded.points.dtype)
        t_read = median_ms(lambda m=msg: read_points(m), r)
        t_write = median_ms(lambda d=decoded, p=moved: replace_points(Header(frame_id="map"), d, p), r)
        print(f"{name:34s} {t_read:9.2f} ms {t_write:9.2f} ms {len(msg.data) / 1e6:6.1f}")
    pts = np.random.default_rng(1).normal(size=(n, 3)).astype(np.float32)
    print(f"{'xyz_to_msg (x,y,z float32)':34s} {'':>11s} {median_ms(lambda: xyz_to_msg(Header(), pts), r):9.2f} ms")


if __name__ == "__main__":
    main()
