"""RGB-D frame readers: 7-Scenes (redkitchen, stairs) and SUN3D in 3DMatch's format.

A sequence folder holds `frame-XXXXXX.depth.png` (16-bit, millimetres along the optical axis; 0 and
65535 are invalid), `frame-XXXXXX.pose.txt` (4x4 camera-to-world T_world_camera, metres) and
optionally `frame-XXXXXX.color.jpg`. Frames are addressed by the number in their file name.

Camera frame: the optical frame (x right, y down, z forward), metres as in REP-103; the ROS node
publishes it under a `*_camera_optical` frame id. `relative_pose(i, j)` = inv(T_j) @ T_i maps points
of camera i into camera j. Pairs follow the project convention: `transform` is T_target_source, so
target = R source + t.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image
from torch.utils.data import Dataset

from genreg_core.config import data_root
from genreg_core.errors import ConfigError, DataNotFoundError, TooFewPointsError
from genreg_core.geometry import (
    apply_transform,
    invert_transform,
    kidnap_motion,
    normalize_pair,
    random_transform,
    unit_box_normalization,
)
from genreg_core.preprocess import voxel_downsample

DEPTH_SCALE = 1000.0  # depth PNG units per metre (millimetres)
INVALID_DEPTH = (0, 65535)
# 7-Scenes depth camera (Kinect v1); the stairs folder ships no intrinsics file.
SEVEN_SCENES_INTRINSICS = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
INTRINSICS_FILE = "camera-intrinsics.txt"
REDKITCHEN_TRAIN_FRAMES = range(800)
REDKITCHEN_VAL_FRAMES = range(800, 1000)
# Shipped sequences: name -> (folder under the data root, intrinsics file under the data root or None).
SEQUENCES: dict[str, tuple[str, str | None]] = {
    "redkitchen": ("7scenes/redkitchen/seq-01", f"7scenes/redkitchen/{INTRINSICS_FILE}"),
    **{f"stairs-{k}": (f"7scenes/stairs/seq-0{k}", None) for k in range(1, 5)},
    **{f"sun3d-{k}": (f"sun3d/fragment-{k}", f"sun3d/{INTRINSICS_FILE}") for k in (1, 2)},
}
_FRAME_RE = re.compile(r"^frame-(\d+)\.depth\.png$")


def _require_file(path: Path) -> Path:
    if not path.is_file():
        raise DataNotFoundError(f"missing file {path}")
    return path


def read_depth(path: str | Path, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """16-bit depth PNG -> (H, W) float32 metres; pixels holding 0 or 65535 become NaN."""
    with Image.open(_require_file(Path(path))) as img:
        raw = np.asarray(img)
    if raw.ndim != 2:
        raise DataNotFoundError(f"{path} is not a single-channel depth image (shape {raw.shape})")
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[(raw == 0) | (raw == 65535)] = np.nan
    return depth


def read_intrinsics(path: str | Path) -> np.ndarray:
    """3x3 pinhole matrix K from a text file (space or tab separated), float64."""
    K = np.loadtxt(_require_file(Path(path)), dtype=np.float64)
    if K.shape != (3, 3):
        raise DataNotFoundError(f"{path} does not hold a 3x3 intrinsics matrix (shape {K.shape})")
    return K


def read_pose(path: str | Path, orthonormalize: bool = True) -> np.ndarray:
    """4x4 camera-to-world pose T_world_camera (metres), float64.

    The 7-Scenes rotations are orthonormal only to ~4e-4 (det ~0.9998), which breaks R^-1 = R^T and
    inflates trace-based angles of near-identity relative rotations to ~1 deg; orthonormalize=True
    replaces R by its nearest rotation (SVD), a change of < 1e-3 per entry.
    """
    T = np.loadtxt(_require_file(Path(path)), dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DataNotFoundError(f"{path} does not hold a finite 4x4 pose (shape {T.shape})")
    if orthonormalize:
        U, _, Vt = np.linalg.svd(T[:3, :3])
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        T[:3, :3] = U @ D @ Vt
    return T


def depth_to_points(
    depth: np.ndarray,
    K: np.ndarray,
    stride: int = 1,
    min_depth: float | None = None,
    max_depth: float | None = None,
    return_pixels: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Back-project a depth image (H, W metres, NaN/<=0 invalid) into the camera optical frame.

    Uses every `stride`-th row and column; point = z * K^-1 [u, v, 1] with u the column and v the row
    (pixel centres at integer coordinates). Returns (M, 3) float32 metres (x right, y down, z forward),
    row-major pixel order; with return_pixels also (M, 2) int64 (u, v) full-resolution pixel coordinates.
    """
    if stride < 1:
        raise ConfigError(f"stride must be >= 1, got {stride}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ConfigError(f"K must be 3x3, got shape {K.shape}")
    z = np.asarray(depth, dtype=np.float32)[::stride, ::stride]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0)
        if min_depth is not None:
            valid &= z >= min_depth
        if max_depth is not None:
            valid &= z <= max_depth
    v, u = np.nonzero(valid)
    u = u * stride
    v = v * stride
    zv = z[valid]
    Kinv = np.linalg.inv(K).astype(np.float32)
    uf, vf = u.astype(np.float32), v.astype(np.float32)
    points = np.empty((len(zv), 3), dtype=np.float32)
    points[:, 0] = (Kinv[0, 0] * uf + Kinv[0, 1] * vf + Kinv[0, 2]) * zv
    points[:, 1] = (Kinv[1, 1] * vf + Kinv[1, 2]) * zv
    points[:, 2] = zv
    if return_pixels:
        return points, np.stack([u, v], axis=1).astype(np.int64)
    return points


class RGBDSequence:
    """One folder of RGB-D frames, addressed by frame number (`frame_indices`, sorted, found on disk).

    intrinsics: 3x3 K, a path to a K file, or None to read `camera-intrinsics.txt` from the folder or
    its parent. Points are in the camera optical frame (metres); `pose(i)` is T_world_camera.
    """

    def __init__(self, folder: str | Path, intrinsics: np.ndarray | str | Path | None = None, name: str = ""):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DataNotFoundError(f"RGB-D sequence folder not found: {self.folder}")
        if intrinsics is None:
            candidates = [self.folder / INTRINSICS_FILE, self.folder.parent / INTRINSICS_FILE]
            found = next((p for p in candidates if p.is_file()), None)
            if found is None:
                raise DataNotFoundError(f"no {INTRINSICS_FILE} in or above {self.folder}: pass intrinsics")
            intrinsics = found
        if isinstance(intrinsics, (str, Path)):
            self.K = read_intrinsics(intrinsics)
        else:
            self.K = np.asarray(intrinsics, dtype=np.float64)
            if self.K.shape != (3, 3):
                raise ConfigError(f"intrinsics must be 3x3, got shape {self.K.shape}")
        self.name = name or self.folder.name
        matches = (_FRAME_RE.match(p.name) for p in self.folder.iterdir())
        self._stems = {int(m.group(1)): f"frame-{m.group(1)}" for m in matches if m}
        self.frame_indices: tuple[int, ...] = tuple(sorted(self._stems))
        if not self.frame_indices:
            raise DataNotFoundError(f"no frame-*.depth.png files in {self.folder}")
        self._depth_cache: tuple[int, np.ndarray] | None = None

    # Shipped datasets (root = data root; env GENREG_DATA overrides it, see config.data_root).
    @classmethod
    def open(cls, name: str, root: str | Path | None = None) -> RGBDSequence:
        """A shipped sequence by name: 'redkitchen', 'stairs-1'..'stairs-4', 'sun3d-1', 'sun3d-2'."""
        if name not in SEQUENCES:
            raise ConfigError(f"unknown sequence {name!r}; known: {sorted(SEQUENCES)}")
        base = data_root(root)
        folder, k_file = SEQUENCES[name]
        intrinsics = SEVEN_SCENES_INTRINSICS if k_file is None else base / k_file
        return cls(base / folder, intrinsics=intrinsics, name=name)

    @classmethod
    def redkitchen(cls, root: str | Path | None = None) -> RGBDSequence:
        """7-Scenes redkitchen seq-01, frames 0-999 (train 0-799, validation 800-999)."""
        return cls.open("redkitchen", root)

    @classmethod
    def stairs(cls, seq: int = 1, root: str | Path | None = None) -> RGBDSequence:
        """7-Scenes stairs seq-01..04 (3 frames each, unseen scene; fx = fy = 585, cx = 320, cy = 240)."""
        return cls.open(f"stairs-{seq}", root)

    @classmethod
    def sun3d(cls, fragment: int = 1, root: str | Path | None = None) -> RGBDSequence:
        """SUN3D fragment-1 (frames 935-984) or fragment-2 (3160-3209), unseen scene, no colour."""
        return cls.open(f"sun3d-{fragment}", root)

    def __len__(self) -> int:
        return len(self.frame_indices)

    def __contains__(self, index: int) -> bool:
        return index in self._stems

    def _path(self, index: int, suffix: str) -> Path:
        if index not in self._stems:
            raise DataNotFoundError(f"frame {index} not found in {self.folder}")
        return self.folder / f"{self._stems[index]}.{suffix}"

    def depth(self, index: int) -> np.ndarray:
        """(H, W) float32 metres, NaN where invalid (the last frame read is cached)."""
        if self._depth_cache is None or self._depth_cache[0] != index:
            self._depth_cache = (index, read_depth(self._path(index, "depth.png")))
        return self._depth_cache[1]

    def points(
        self, index: int, stride: int = 1, min_depth: float | None = None, max_depth: float | None = None
    ) -> np.ndarray:
        """(M, 3) float32 valid points of frame `index` in its camera optical frame (metres)."""
        return depth_to_points(self.depth(index), self.K, stride, min_depth, max_depth)

    def pose(self, index: int) -> np.ndarray:
        """4x4 T_world_camera of frame `index` (metres)."""
        return read_pose(self._path(index, "pose.txt"))

    def fused(self, frames: Iterable[int], stride: int = 1, voxel_size: float = 0.02) -> np.ndarray:
        """A map: the frames' points moved by their poses into the world frame, concatenated and voxelised
        (`preprocess.voxel_downsample`), (M, 3) float64 metres."""
        world = np.concatenate([apply_transform(self.pose(i), self.points(i, stride=stride).astype(np.float64))
                                for i in frames])
        return voxel_downsample(world, voxel_size)

    def relative_pose(self, i: int, j: int) -> np.ndarray:
        """T_j_i = inv(T_world_j) @ T_world_i: maps points of camera i into camera j."""
        return invert_transform(self.pose(j)) @ self.pose(i)

    def has_color(self, index: int) -> bool:
        return self._path(index, "color.jpg").is_file()

    def colors(
        self, index: int, stride: int = 1, min_depth: float | None = None, max_depth: float | None = None
    ) -> np.ndarray | None:
        """(M, 3) uint8 RGB at the pixels of `points(index, stride, ...)` (same order), or None without a
        colour image. 7-Scenes colour is not pixel-registered to depth: the colours are approximate."""
        path = self._path(index, "color.jpg")
        if not path.is_file():
            return None
        with Image.open(path) as img:
            rgb = np.asarray(img.convert("RGB"))
        depth = self.depth(index)
        _, pixels = depth_to_points(depth, self.K, stride, min_depth, max_depth, return_pixels=True)
        h, w = depth.shape
        cols = np.minimum(pixels[:, 0] * rgb.shape[1] // w, rgb.shape[1] - 1)
        rows = np.minimum(pixels[:, 1] * rgb.shape[0] // h, rgb.shape[0] - 1)
        return rgb[rows, cols]


def _subset(points: np.ndarray, num_points: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) == 0:
        raise TooFewPointsError("frame has no valid depth pixels")
    idx = rng.choice(len(points), num_points, replace=len(points) < num_points)
    return points[idx]


class FramePairs(Dataset):
    """Real pairs of one sequence: target = frame i, source = frame i + gap (both in `frames` and on disk).

    Item k -> dict(source, target, transform, source_index, target_index), clouds float32 in their camera
    optical frames (metres), transform = T_target_source = relative_pose(i + gap, i) (float32). With
    num_points, each cloud is an independent random subset of that size (with replacement only if the
    frame has fewer valid points) drawn with rng (seed, epoch, k); otherwise all valid points (sizes vary,
    so batch with a custom collate). kidnap=True moves the source by a further `geometry.kidnap_motion`
    about its centroid (rng (seed, epoch, index, 2)) and adjusts the transform (a robot that lost its pose).
    normalize=True applies `geometry.normalize_pair`: the source fills [0, 1]^3 and the transform is
    adjusted (unit-box units); the item then also holds offset and scale.
    """

    def __init__(
        self,
        sequence: RGBDSequence,
        gap: int,
        frames: Iterable[int] | None = None,
        num_points: int | None = None,
        seed: int = 0,
        normalize: bool = False,
        stride: int = 1,
        kidnap: bool = False,
    ) -> None:
        if gap < 1:
            raise ConfigError(f"gap must be >= 1, got {gap}")
        if num_points is not None and num_points < 1:
            raise ConfigError(f"num_points must be >= 1 or None, got {num_points}")
        allowed = set(sequence.frame_indices if frames is None else frames) & set(sequence.frame_indices)
        self.pairs: list[tuple[int, int]] = [(i, i + gap) for i in sorted(allowed) if i + gap in allowed]
        if not self.pairs:
            raise ConfigError(f"no frame pairs with gap {gap} in {sequence.folder} for the given frames")
        self.sequence = sequence
        self.gap = int(gap)
        self.num_points = num_points
        self.seed = int(seed)
        self.normalize = bool(normalize)
        self.stride = int(stride)
        self.kidnap = bool(kidnap)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for {n} pairs")
        index = int(index) % n
        target_index, source_index = self.pairs[index]
        source = self.sequence.points(source_index, self.stride)
        target = self.sequence.points(target_index, self.stride)
        T = self.sequence.relative_pose(source_index, target_index)
        if self.kidnap:
            M = kidnap_motion(np.random.default_rng((self.seed, self.epoch, index, 2)), source.mean(axis=0))
            source, T = apply_transform(M, source), T @ invert_transform(M)
        if self.num_points is not None:
            rng = np.random.default_rng((self.seed, self.epoch, index))
            source = _subset(source, self.num_points, rng)
            target = _subset(target, self.num_points, rng)
        item = {"source_index": source_index, "target_index": target_index}
        if self.normalize:
            source, target, T, offset, scale = normalize_pair(source, target, T)
            item.update(offset=offset.astype(np.float32), scale=np.float32(scale))
        item.update(
            source=source.astype(np.float32), target=target.astype(np.float32), transform=T.astype(np.float32)
        )
        return item


class FMRPairs(Dataset):
    """FMR-style synthetic pairs from real frames: frame f is sampled twice (two independent subsets of
    num_points of its valid points) after normalising the whole frame into [0, 1]^3 once; target =
    T applied to the second sample with T = `random_transform(rng, max_angle_deg, max_translation)`.

    Item k (frame frames[k]) -> dict(source, target, transform = T_target_source, source_index,
    target_index), unit-box units, float32; rng (seed, epoch, k) as in `ModelNetPairs`.
    """

    def __init__(
        self,
        sequence: RGBDSequence,
        frames: Iterable[int] | None = None,
        num_points: int = 512,
        seed: int = 0,
        max_angle_deg: float = 45.0,
        max_translation: float = 0.8,
        stride: int = 1,
    ) -> None:
        self.frames = list(sequence.frame_indices if frames is None else frames)
        missing = [f for f in self.frames if f not in sequence]
        if missing:
            raise DataNotFoundError(f"frames {missing[:5]} not found in {sequence.folder}")
        if not self.frames:
            raise ConfigError("frames is empty")
        if num_points < 1:
            raise ConfigError(f"num_points must be >= 1, got {num_points}")
        self.sequence = sequence
        self.num_points = int(num_points)
        self.seed = int(seed)
        self.max_angle_deg = float(max_angle_deg)
        self.max_translation = float(max_translation)
        self.stride = int(stride)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for {n} pairs")
        index = int(index) % n
        frame = self.frames[index]
        cloud = self.sequence.points(frame, self.stride).astype(np.float64)
        if len(cloud) == 0:
            raise TooFewPointsError(f"frame {frame} has no valid depth pixels")
        offset, scale = unit_box_normalization(cloud)
        cloud = (cloud - offset) / scale
        rng = np.random.default_rng((self.seed, self.epoch, index))
        T = random_transform(rng, self.max_angle_deg, self.max_translation)
        source = _subset(cloud, self.num_points, rng)
        target = apply_transform(T, _subset(cloud, self.num_points, rng))
        return {
            "source": source.astype(np.float32),
            "target": target.astype(np.float32),
            "transform": T.astype(np.float32),
            "source_index": frame,
            "target_index": frame,
        }
