"""genreg-make-bag: turn a 7-Scenes-format frame folder into a rosbag2 bag (see genreg_ros.bag.writer).

    genreg-make-bag --sequence redkitchen --start 800 --count 100 --out cache/bags/redkitchen_val
    genreg-make-bag --folder ../shared/data/sun3d/fragment-2 --storage sqlite3 --out cache/bags/sun3d2

A folder holds frame-XXXXXX.depth.png (mm), frame-XXXXXX.pose.txt (T_world_camera) and optional
frame-XXXXXX.color.jpg; the intrinsics come from camera-intrinsics.txt in or above it, or --intrinsics.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from genreg_core.data.rgbd import SEQUENCES, SEVEN_SCENES_INTRINSICS, RGBDSequence
from genreg_core.errors import GenRegError
from genreg_ros.bag.writer import (
    DEFAULT_CLOUD_TOPIC,
    DEFAULT_FRAME_ID,
    DEFAULT_POSE_TOPIC,
    DEFAULT_RATE,
    DEFAULT_START_NS,
    DEFAULT_WORLD_FRAME,
    STORAGES,
    write_sequence_bag,
)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="genreg-make-bag", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sequence", choices=sorted(SEQUENCES), help="a shipped sequence (data root ../shared/data)")
    src.add_argument("--folder", type=Path, help="a 7-Scenes-format frame folder")
    p.add_argument("--intrinsics", help="K file for --folder, or '7scenes' (fx=fy=585, cx=320, cy=240)")
    p.add_argument("--out", type=Path, required=True, help="bag folder to create (keep it under cache/ or build/)")
    p.add_argument("--storage", choices=sorted(STORAGES), default="mcap")
    p.add_argument("--start", type=int, help="first frame number (default: the first on disk)")
    p.add_argument("--stop", type=int, help="last frame number, inclusive")
    p.add_argument("--count", type=int, help="at most this many frames (after --stride)")
    p.add_argument("--stride", type=int, default=1, help="keep every stride-th frame (timing stays original)")
    p.add_argument("--pixel-stride", type=int, default=4, help="back-project every n-th pixel row and column")
    p.add_argument("--rate", type=float, default=DEFAULT_RATE, help="capture rate for the stamps, Hz")
    p.add_argument("--start-time", type=float, default=DEFAULT_START_NS / 1e9, help="first stamp, s")
    p.add_argument("--no-color", action="store_true", help="XYZ only, even where colour exists")
    p.add_argument("--cloud-topic", default=DEFAULT_CLOUD_TOPIC)
    p.add_argument("--pose-topic", default=DEFAULT_POSE_TOPIC)
    p.add_argument("--frame-id", default=DEFAULT_FRAME_ID, help="the camera optical frame")
    p.add_argument("--world-frame", default=DEFAULT_WORLD_FRAME, help="parent frame of the poses (world, map)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag folder")
    return p.parse_args(argv)


def open_sequence(args: argparse.Namespace) -> RGBDSequence:
    if args.sequence:
        return RGBDSequence.open(args.sequence)
    intrinsics = SEVEN_SCENES_INTRINSICS if args.intrinsics == "7scenes" else args.intrinsics
    return RGBDSequence(args.folder, intrinsics=intrinsics)


def select_frames(available: tuple[int, ...], start: int | None, stop: int | None, stride: int,
                  count: int | None) -> list[int]:
    """Frame numbers on disk within [start, stop], every stride-th of them, at most count."""
    if stride < 1:
        raise ValueError(f"--stride must be >= 1, got {stride}")
    lo = available[0] if start is None else start
    hi = available[-1] if stop is None else stop
    frames = [i for i in available if lo <= i <= hi][::stride]
    return frames[:count] if count is not None else frames


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        seq = open_sequence(args)
        frames = select_frames(seq.frame_indices, args.start, args.stop, args.stride, args.count)
        if not frames:
            raise ValueError(f"no frames selected in {seq.folder}")
        t0 = time.perf_counter()
        info = write_sequence_bag(
            seq, args.out, frames, pixel_stride=args.pixel_stride, rate=args.rate, storage=args.storage,
            start_ns=round(args.start_time * 1e9), color=not args.no_color, overwrite=args.overwrite,
            cloud_topic=args.cloud_topic, pose_topic=args.pose_topic, frame_id=args.frame_id,
            world_frame=args.world_frame,
        )
    except (GenRegError, ValueError, FileExistsError, OSError) as exc:
        print(f"genreg-make-bag: error: {exc}", file=sys.stderr)
        return 1
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"wrote {args.out} ({args.storage}, {size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s: "
          f"{len(frames)} frames {frames[0]}-{frames[-1]} of {seq.name}, {info['colored_frames']} with colour, "
          f"{np.round(info['mean_points']):.0f} points per cloud on average, {args.rate:g} Hz stamps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
