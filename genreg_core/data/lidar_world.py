"""Large synthetic LiDAR worlds and the maps fused from their scans (`genreg_core.data.synthetic_lidar`).

    world = campus_world(seed=0, blocks=(4, 3))          # ~ 320 x 285 m, 1,600 primitives
    poses = survey_poses(world)                           # T_world_sensor every 3 m along roads and corridors
    cloud = cached_map(world)                             # the fused, voxelised map (cache/lidar_world/*.npy)
    pose = test_poses(world, 1, rng)[0]                   # a held-out place, any heading
    scan = world_scan(world, pose, rng)                   # one revolution there, with moving cars and people

Conventions as in `synthetic_lidar`: metres and radians, REP-103 (z up), T_world_sensor maps sensor-frame
points into the world; scans are in the sensor frame, maps in the world frame. The ground is the plane
z = 0 (roads, intersections, the park, the building's ground floor); city blocks and the outer ring stand on
kerbed platforms 0.15 m high (the sidewalks).

The campus (`campus_world`): a grid of `blocks` city blocks 50-70 m square between streets 10-14 m wide,
ringed by an outer strip of gapless buildings so no ray leaves the world at street level. Streets have
kerbs, sidewalks with trees, lamp and sign poles and bins, and parked cars. Blocks hold buildings of varied
footprint, height and setback with gaps, porches, balconies, towers, rooftop boxes and arcades, sometimes a
turned building in the courtyard. Block (0, 0) holds a building whose ground floor is a corridor network
(a main corridor entered from the street through a doorway, two cross corridors, rooms behind thin walls
with doorways, furniture), a ceiling 3 m above the floor; `World.indoor` runs along its corridors. One block
(the last of the bottom row; with one column, the top one; none in a single block) is a park: open ground,
trees, benches, lamps, a fountain and a pavilion, crossed diagonally by a footpath that is also a road. The
northern perimeter street is lined on both sides by identical terraced houses repeating every
`TERRACE_PERIOD` m (in phase on both sides, a lamp pole at every party wall, no other furniture; on the
blocks' side only where the top row has ordinary blocks, so from (2, 2) on): along it, out of reach of the
side streets, a scan matches the scans a whole number of periods along (`World.terrace`: its centre-line).

Free space: every primitive reaching into the height band 0.2-3 m keeps at least `ROAD_CLEARANCE` m away
from a road centre-line and `CORRIDOR_CLEARANCE` m from a corridor centre-line, so sensors placed by
`survey_poses` and `test_poses` are never inside a box or cylinder.

Speed: `Scene.cast` intersects every ray with every primitive. `culled_scan` first keeps the primitives whose
bounding circle (xy) reaches within the sensor's range of the sensor (`scene_near`), then casts each ray only
against the primitives whose bounding circle its azimuth can meet (`SectorScene`: the rays are binned into
azimuth sectors). Both steps only drop ray-primitive pairs that cannot hit, and every remaining pair is
computed by the same arithmetic, so the scan is bit for bit the one `lidar_scan` takes of the full scene.

Measured (scripts/lidar_world_maps.py, seed 0, survey every 3 m, 0.1 m voxels, `SURVEY_SENSOR` = VLP-32-like
32 x 1024 rays to 100 m; one thread on 2 cores shared with other jobs, load average 4-5):

    blocks  area m^2  boxes  cylinders  survey poses  scan s (mean, p95)  full-scene scan s  map points  build s
    1x1       15,039    229         70           143        0.15  0.21                 2.2   1,295,948       19
    2x1       22,664    300        190           237        0.21  0.26                 4.0   2,306,470       52
    2x2       35,540    428        217           351        0.21  0.26                 5.8   3,594,165       70
    4x3       91,223  1,040        563           837        0.16  0.25                12.8   8,847,849      180

(scan s: `world_scan` with 6 movers at 20 held-out poses; full-scene: `lidar_scan` of the whole scene, the
same scan.) The survey sensor alone gives ~ 100 map points per m^2 at 0.1 m voxels (8.8 M over 91,000 m^2 in
the 4 x 3 world); a denser one (HDL-64-like, 64 x 2048) adds only 12 % (1 x 1: 1.46 M points; the voxels
near the roads are already full) at 3 times the build time, so maps use the scans' own sensor. Map points lie within the
bounds up to the range noise (a roof edge's return, a centimetre beyond).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from genreg_core.data.synthetic_lidar import LidarScan, LidarSensor, Scene, lidar_scan, sensor_pose

WORLD_VERSION = 3  # bump when the generator's output changes: part of the map cache key
KERB = 0.15  # platform (sidewalk) height, m
SIDEWALK = 3.0  # sidewalk width between the kerb and the building zone, m
OUTER = 20.0  # depth of the outer ring of buildings, m
STOREY = 3.0  # indoor floor-to-ceiling height, m
CORRIDOR = 3.0  # indoor corridor width, m
WALL = 0.15  # indoor partition wall thickness, m
TERRACE_PERIOD = 7.0  # terraced house width (= repeat period along the terraced street), m
LANE = 2.0  # test poses: the largest lateral offset from a road centre-line, m
INDOOR_LANE = 1.1  # test poses: the largest lateral offset from a corridor centre-line, m
MIN_OFFSET = 0.6  # test poses: the smallest distance to any centre-line, m
JITTER_LATERAL = 0.1  # survey poses: the largest lateral jitter, m
JITTER_YAW = 0.05  # survey poses: the largest yaw jitter, rad
ROAD_CLEARANCE = 2.3  # free half-width around road centre-lines (height band 0.2-3 m), m
CORRIDOR_CLEARANCE = 1.0  # free space around corridor centre-lines (walls 1.5 m aside, ends 1 m beyond), m
SURVEY_SENSOR = LidarSensor.vlp32(1024, max_range=100.0)  # the default of scans and maps: VLP-32-like, 100 m


@dataclass
class World:
    """A static world: its primitives and the centre-lines a robot drives along."""

    name: str
    scene: Scene  # all static primitives, world frame
    roads: list[np.ndarray]  # drivable centre-lines, each (K, 2) xy polyline, m
    indoor: list[np.ndarray]  # corridor centre-lines inside the building, (K, 2); may be empty
    bounds: tuple[float, float, float, float]  # xmin, xmax, ymin, ymax
    seed: int = 0
    blocks: tuple[int, int] = (1, 1)
    terrace: np.ndarray | None = None  # (2, 2) ends of the terraced stretch of street (centre-line)
    terrace_period: float = TERRACE_PERIOD  # its facades repeat every this many metres

    @property
    def area_m2(self) -> float:
        xmin, xmax, ymin, ymax = self.bounds
        return (xmax - xmin) * (ymax - ymin)

    @property
    def key(self) -> str:
        """Names this world in cache keys: generator version, name, seed and blocks."""
        return f"{self.name}-v{WORLD_VERSION}-s{self.seed}-{self.blocks[0]}x{self.blocks[1]}"


# ----------------------------------------------------------------------------- building the scene
class _Builder:
    """Collects primitives in lists (a `Scene` re-stacks its arrays on every add)."""

    def __init__(self) -> None:
        self.boxes: list[tuple[float, ...]] = []  # cx, cy, cz, hx, hy, hz, yaw, reflectivity
        self.cylinders: list[tuple[float, ...]] = []  # x, y, r, z0, z1, reflectivity

    def box(self, center: tuple[float, float, float], size: tuple[float, float, float], yaw: float = 0.0,
            reflectivity: float = 0.5) -> None:
        self.boxes.append((*(float(v) for v in center), *(float(v) / 2 for v in size), float(yaw),
                           float(reflectivity)))

    def rect(self, x0: float, x1: float, y0: float, y1: float, z0: float, z1: float,
             reflectivity: float = 0.5) -> None:
        """An axis-aligned box by its extents."""
        self.box(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2), (abs(x1 - x0), abs(y1 - y0), z1 - z0), 0.0,
                 reflectivity)

    def cylinder(self, x: float, y: float, r: float, z0: float, z1: float, reflectivity: float = 0.5) -> None:
        self.cylinders.append((float(x), float(y), float(r), float(z0), float(z1), float(reflectivity)))

    def tree(self, rng: np.random.Generator, x: float, y: float) -> None:
        self.cylinder(x, y, rng.uniform(0.15, 0.3), 0.0, 3.0, 0.3)  # trunk
        self.cylinder(x, y, rng.uniform(1.0, 2.0), 3.0, rng.uniform(5.0, 8.0), 0.2)  # crown

    def pole(self, rng: np.random.Generator, x: float, y: float) -> None:
        self.cylinder(x, y, rng.uniform(0.06, 0.15), 0.0, rng.uniform(3.0, 8.0), 0.9)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.boxes, dtype=np.float64).reshape(-1, 8), \
            np.asarray(self.cylinders, dtype=np.float64).reshape(-1, 6)


def _scene(name: str, boxes: np.ndarray, cylinders: np.ndarray) -> Scene:
    s = Scene(name)
    s.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.25)  # the ground
    s.box_centers, s.box_half, s.box_yaw, s.box_reflectivity = boxes[:, :3], boxes[:, 3:6], boxes[:, 6], boxes[:, 7]
    s.cylinders, s.cylinder_reflectivity = cylinders[:, :5], cylinders[:, 5]
    return s


@dataclass
class _Edge:
    """A kerb line seen from its block: `s` runs along `u` from `origin`, `t` runs inward (away from the road)
    along `v`; u and v are axis-aligned."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def point(self, s: float, t: float) -> np.ndarray:
        return self.origin + self.u * s + self.v * t

    def box(self, b: _Builder, s: float, t: float, along: float, across: float, z0: float, z1: float,
            reflectivity: float) -> None:
        """A box centred at (s, t), `along` x `across` m, from z0 to z1."""
        c = self.point(s, t)
        size = (along, across) if abs(self.u[0]) > 0.5 else (across, along)
        b.box((c[0], c[1], (z0 + z1) / 2), (size[0], size[1], z1 - z0), 0.0, reflectivity)


def _buildings(b: _Builder, rng: np.random.Generator, edge: _Edge, s0: float, s1: float,
               gapless: bool = False, back: float | None = None) -> None:
    """Buildings along an edge from s0 to s1: varied width, setback, depth, height, gaps (unless `gapless`),
    porches, balconies, towers, rooftop boxes and arcades. `back`: their backs flush at this t."""
    s = s0 + (0.0 if gapless else rng.uniform(0.0, 3.0))
    while s < s1 - (0.01 if gapless else 4.0):
        if not gapless and rng.random() < 0.3:
            s += rng.uniform(2.0, 8.0)
            continue
        w = min(rng.uniform(8.0, 24.0), s1 - s)
        if not gapless and w < 4.0:
            break
        setback = rng.uniform(0.0, 2.0) if gapless else rng.uniform(0.5, 4.0)
        f = SIDEWALK + setback  # the facade's t
        depth = back - f if back is not None else rng.uniform(10.0, 18.0)
        h = rng.uniform(5.0, 12.0) if rng.random() < 0.6 else rng.uniform(12.0, 30.0)
        refl = rng.uniform(0.3, 0.8)
        edge.box(b, s + w / 2, f + depth / 2, w, depth, 0.0, h, refl)
        if w > 10.0 and rng.random() < 0.25:  # a tower
            tw = w * rng.uniform(0.3, 0.5)
            edge.box(b, s + rng.uniform(tw / 2, w - tw / 2), f + depth * 0.6, tw, depth * 0.6, 0.0,
                     h + rng.uniform(4.0, 15.0), rng.uniform(0.3, 0.8))
        if rng.random() < 0.5:  # a porch or shop front
            pw, pd, ph = rng.uniform(1.5, 4.0), rng.uniform(0.6, 1.5), rng.uniform(2.5, 3.5)
            edge.box(b, s + rng.uniform(pw / 2, max(pw / 2, w - pw / 2)), f - pd / 2, pw, pd, 0.0, ph,
                     rng.uniform(0.3, 0.9))
        if h > 8.0 and rng.random() < 0.4:  # a balcony row
            z = rng.uniform(4.0, 6.0)
            edge.box(b, s + w / 2, f - 0.6, w * 0.7, 1.2, z, z + 0.3, 0.6)
        if rng.random() < 0.3:  # a rooftop box (plant room)
            rw = min(w * 0.4, rng.uniform(2.0, 6.0))
            edge.box(b, s + rng.uniform(rw / 2, w - rw / 2), f + depth / 2, rw, min(depth * 0.5, 5.0), h,
                     h + rng.uniform(1.5, 3.0), 0.5)
        if w > 8.0 and rng.random() < 0.3:  # bay windows: shallow boxes proud of the facade
            bay, step = rng.uniform(1.2, 2.0), rng.uniform(3.0, 5.0)
            top = rng.uniform(0.6, 0.95) * h
            for x in np.arange(s + step / 2, s + w - bay / 2, step):
                edge.box(b, float(x), f - 0.2, bay, 0.4, 0.8, top, refl * 0.9)
        if not gapless and w > 10.0 and setback > 2.6 and rng.random() < 0.15:  # an arcade
            for x in np.arange(s + 1.0, s + w - 0.5, 3.0):
                b.cylinder(*edge.point(float(x), f - 2.0), 0.25, 0.0, 3.5, 0.6)
            edge.box(b, s + w / 2, f - 1.25, w, 2.5, 3.5, 3.9, 0.6)
        s += w


def _terrace(b: _Builder, edge: _Edge, s0: float, s1: float, phase: float, fill_ends: bool,
             rng: np.random.Generator, back: float | None = None) -> None:
    """Identical terraced houses along an edge, one every `TERRACE_PERIOD` m at s = phase + k period (whole
    houses within [s0, s1]). `fill_ends`: plain buildings close what is left at both ends."""
    p = TERRACE_PERIOD
    f = SIDEWALK + 1.5
    depth = back - f if back is not None else 10.0
    k0, k1 = int(np.ceil((s0 - phase) / p - 1e-9)), int(np.floor((s1 - phase) / p + 1e-9))
    for k in range(k0, k1):
        s = phase + k * p
        edge.box(b, s + p / 2, f + depth / 2, p, depth, 0.0, 8.5, 0.55)  # the house
        edge.box(b, s + p / 2 + 1.6, f - 0.6, 2.2, 1.2, 0.0, 2.8, 0.7)  # its porch
        edge.box(b, s + p / 2 - 1.2, f + 2.0, 2.0, 2.0, 8.5, 10.0, 0.45)  # its dormer
    if fill_ends:
        for a, c in ((s0, phase + k0 * p), (phase + k1 * p, s1)):
            if c - a > 0.01:
                edge.box(b, (a + c) / 2, f + depth / 2, c - a, depth, 0.0, rng.uniform(6.0, 12.0), 0.4)


def _furniture(b: _Builder, rng: np.random.Generator, a: np.ndarray, c: np.ndarray, half: float,
               crossings: list[tuple[float, float]]) -> None:
    """Trees, poles, bins on both sidewalks and parked cars on both edges of the straight road a -> c of
    half-width `half`, clear of the intersections (`crossings`: position along the road, crossing half-width)."""
    length = float(np.linalg.norm(c - a))
    u = (c - a) / length
    n = np.array([-u[1], u[0]])
    yaw = float(np.arctan2(u[1], u[0]))

    def clear(s: float, margin: float) -> bool:
        return all(abs(s - sc) > hc + margin for sc, hc in crossings) and margin / 2 < s < length - margin / 2

    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 6.0)
        while s < length:  # trees and poles, 1-2 m behind the kerb
            if clear(s, SIDEWALK + 2.0):
                x, y = a + u * s + n * side * (half + rng.uniform(1.0, 2.0))
                (b.tree if rng.random() < 0.5 else b.pole)(rng, x, y)
            s += rng.uniform(6.0, 14.0)
        for _ in range(rng.integers(1, 4)):  # bins, boxes, benches
            s = rng.uniform(0.0, length)
            if clear(s, SIDEWALK + 2.0):
                x, y = a + u * s + n * side * (half + rng.uniform(0.8, 2.4))
                size = tuple(rng.uniform((0.5, 0.5, 0.6), (1.2, 1.0, 1.2)))
                b.box((x, y, size[2] / 2), size, rng.uniform(0, np.pi), rng.uniform(0.3, 0.8))
        s = rng.uniform(0.0, 8.0)
        while s < length:  # parked cars along the kerb
            if clear(s, 8.0) and rng.random() < 0.6:
                turn = rng.normal(0.0, 0.04) if rng.random() < 0.85 else rng.uniform(0.1, 0.25)
                x, y = a + u * s + n * side * (half - 1.1 - rng.uniform(0.0, 0.15))
                b.box((x, y, 0.75), (4.5, 1.8, 1.5), yaw + turn, rng.uniform(0.3, 0.9))
            s += rng.uniform(5.5, 11.0)


def _polyline_samples(lines: list[np.ndarray], step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every <= `step` m along polylines: (xy (S, 2), unit direction (S, 2), line index (S,))."""
    pts, dirs, idx = [], [], []
    for i, line in enumerate(lines):
        for a, c in itertools.pairwise(line):
            length = float(np.linalg.norm(c - a))
            k = max(1, int(np.ceil(length / step)))
            f = np.linspace(0.0, 1.0, k + 1)[:, None]
            pts.append(a + f * (c - a))
            dirs.append(np.repeat(((c - a) / length)[None], k + 1, 0))
            idx.append(np.full(k + 1, i))
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=int)
    return np.concatenate(pts), np.concatenate(dirs), np.concatenate(idx)


def _footprint_distance(points: np.ndarray, boxes: np.ndarray, cylinders: np.ndarray,
                        reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Per box and per cylinder (arrays as in `_Builder.arrays`) the smallest xy distance from its footprint
    to `points` (S, 2), 0 inside; `inf` when farther than `reach`."""
    tree = cKDTree(points) if len(points) else None
    box_d = np.full(len(boxes), np.inf)
    cyl_d = np.full(len(cylinders), np.inf)
    if tree is None:
        return box_d, cyl_d
    for i, (cx, cy, _, hx, hy, _, yaw, _) in enumerate(boxes):
        near = tree.query_ball_point((cx, cy), np.hypot(hx, hy) + reach)
        if near:
            rel = points[near] - (cx, cy)
            c, s = np.cos(yaw), np.sin(yaw)
            local = np.abs(np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], 1))
            box_d[i] = np.linalg.norm(np.maximum(local - (hx, hy), 0.0), axis=1).min()
    for i, (x, y, r, *_) in enumerate(cylinders):
        near = tree.query_ball_point((x, y), r + reach)
        if near:
            cyl_d[i] = max(0.0, float(np.linalg.norm(points[near] - (x, y), axis=1).min() - r))
    return box_d, cyl_d


def _in_band(z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """Primitives reaching into the height band 0.2-3 m (where sensors and movers are)."""
    return (z0 < 3.0) & (z1 > 0.2)


def _indoor_building(b: _Builder, rng: np.random.Generator, x0: float, x1: float, y0: float,
                     y1: float) -> list[np.ndarray]:
    """A building on the footprint [x0, x1] x [y0, y1] whose ground floor is corridors and rooms; returns the
    corridor centre-lines. Entrance: a doorway in the west wall at the main corridor."""
    ext = 0.3
    top = rng.uniform(8.0, 14.0)
    refl = rng.uniform(0.4, 0.7)
    X0, X1, Y0, Y1 = x0 + ext, x1 - ext, y0 + ext, y1 - ext  # the inner faces of the outer walls
    hc = CORRIDOR / 2
    yc = (Y0 + Y1) / 2 + rng.uniform(-2.0, 2.0)
    xs = [X0 + (X1 - X0) * f + rng.uniform(-2.0, 2.0) for f in (1 / 3, 2 / 3)]
    b.rect(x0, x1, y0, y1, STOREY, top, refl)  # the upper storeys; their underside is the ceiling
    b.rect(x0, X0, y0, yc - hc, 0.0, STOREY, refl)  # west wall, the entrance between
    b.rect(x0, X0, yc + hc, y1, 0.0, STOREY, refl)
    b.rect(X1, x1, y0, y1, 0.0, STOREY, refl)  # east
    b.rect(X0, X1, y0, Y0, 0.0, STOREY, refl)  # south
    b.rect(X0, X1, Y1, y1, 0.0, STOREY, refl)  # north
    b.rect(x0 - 1.5, x0, yc - hc - 0.5, yc + hc + 0.5, STOREY - 0.2, STOREY + 0.2, 0.8)  # a canopy over the door

    def wall_x(y: float, a: float, c: float, gaps: list[tuple[float, float]]) -> None:
        """A wall along x at y from a to c, open over `gaps`."""
        for lo, hi in _open(a, c, gaps):
            b.rect(lo, hi, y - WALL / 2, y + WALL / 2, 0.0, STOREY, 0.65)

    def wall_y(x: float, a: float, c: float, gaps: list[tuple[float, float]]) -> None:
        for lo, hi in _open(a, c, gaps):
            b.rect(x - WALL / 2, x + WALL / 2, lo, hi, 0.0, STOREY, 0.65)

    cross_open = [(x - hc, x + hc) for x in xs]
    columns = [(X0, xs[0] - hc - WALL), (xs[0] + hc + WALL, xs[1] - hc - WALL), (xs[1] + hc + WALL, X1)]
    for side in (-1.0, 1.0):
        wall_at = yc + side * (hc + WALL / 2)
        far = Y1 if side > 0 else Y0
        near = yc + side * (hc + WALL)  # the room side of the corridor wall
        doors: list[tuple[float, float]] = []
        for ci, (ca, cb) in enumerate(columns):
            splits = [ca]
            while cb - splits[-1] > 11.0:  # rooms 4-9 m wide
                splits.append(splits[-1] + rng.uniform(5.0, min(9.0, cb - splits[-1] - 4.0)))
            splits.append(cb)
            for ra, rb in itertools.pairwise(splits):
                d = rng.uniform(ra + 0.8, rb - 1.8)
                doors.append((d, d + 1.0))
                lo_y, hi_y = sorted((near, far))
                for _ in range(rng.integers(1, 4)):  # furniture in the back half of the room
                    sx, sy = rng.uniform(0.6, 2.0), rng.uniform(0.5, 1.2)
                    h = rng.choice([0.75, 1.2, 1.8])
                    fx = rng.uniform(ra + 0.3 + sx / 2, rb - 0.3 - sx / 2)
                    mid = (near + far) / 2
                    fy = rng.uniform(min(mid, far - side * (0.3 + sy / 2)), max(mid, far - side * (0.3 + sy / 2)))
                    b.box((fx, fy, h / 2), (sx, sy, h), 0.0, rng.uniform(0.3, 0.8))
                if rb < cb:
                    wall_y(rb + WALL / 2, lo_y, hi_y, [])  # the partition to the next room
            for xk, at_end in ((ca, ci > 0), (cb, ci < 2)):  # a door onto the cross corridor beside the column
                if at_end:
                    lo_y, hi_y = sorted((near, far))
                    d = rng.uniform(lo_y + 1.0, hi_y - 2.0)
                    wall_y(xk - WALL / 2 if xk == ca else xk + WALL / 2, lo_y, hi_y, [(d, d + 1.0)])
        wall_x(wall_at, X0, X1, doors + cross_open)
    return [np.array([[X0 + 1.0, yc], [X1 - 1.0, yc]]),
            *(np.array([[x, Y0 + 1.0], [x, Y1 - 1.0]]) for x in xs)]


def _open(a: float, c: float, gaps: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """[a, c] minus the `gaps`, as intervals longer than 5 cm."""
    out, lo = [], a
    for ga, gb in sorted(gaps):
        if ga > lo:
            out.append((lo, min(ga, c)))
        lo = max(lo, gb)
    if c > lo:
        out.append((lo, c))
    return [(p, q) for p, q in out if q - p > 0.05]


def _park(b: _Builder, rng: np.random.Generator, x0: float, x1: float, y0: float, y1: float,
          path: np.ndarray) -> None:
    """Park furniture in the block [x0, x1] x [y0, y1] (ground level) around the footpath `path`."""
    samples, dirs, _ = _polyline_samples([path], 0.25)
    tree = cKDTree(samples)

    def free(x: float, y: float, clearance: float) -> bool:
        return tree.query((x, y))[0] > clearance

    placed: list[tuple[float, float, float]] = []  # x, y, radius of what stands on the grass

    def spot(clearance: float, radius: float) -> tuple[float, float] | None:
        for _ in range(200):
            x = rng.uniform(x0 + SIDEWALK + 1.0 + radius, x1 - SIDEWALK - 1.0 - radius)
            y = rng.uniform(y0 + SIDEWALK + 1.0 + radius, y1 - SIDEWALK - 1.0 - radius)
            if free(x, y, clearance + radius) and all(np.hypot(x - px, y - py) > radius + pr + 1.5
                                                     for px, py, pr in placed):
                placed.append((x, y, radius))
                return x, y
        return None

    if (p := spot(6.0, 3.5)) is not None:  # a fountain: basin and column
        r = rng.uniform(2.5, 3.5)
        b.cylinder(p[0], p[1], r, 0.0, 0.8, 0.6)
        b.cylinder(p[0], p[1], 0.3, 0.0, 2.5, 0.7)
    if (p := spot(6.0, 4.0)) is not None:  # a pavilion: four pillars and a roof
        yaw = rng.uniform(0, np.pi / 2)
        c, s = np.cos(yaw), np.sin(yaw)
        for dx, dy in ((-2.5, -1.5), (2.5, -1.5), (2.5, 1.5), (-2.5, 1.5)):
            b.cylinder(p[0] + c * dx - s * dy, p[1] + s * dx + c * dy, 0.2, 0.0, 3.0, 0.7)
        b.box((p[0], p[1], 3.2), (6.0, 4.0, 0.4), yaw, 0.5)
    for _ in range(rng.integers(20, 40)):  # trees
        if (p := spot(4.0, 0.5)) is not None:
            b.tree(rng, *p)
    for _ in range(rng.integers(2, 5)):  # hedges
        if (p := spot(4.0, 3.0)) is not None:
            b.box((p[0], p[1], 0.4), (rng.uniform(3.0, 6.0), 0.8, 0.8), rng.uniform(0, np.pi), 0.3)
    yaw_path = np.arctan2(dirs[:, 1], dirs[:, 0])
    normal = np.stack([-dirs[:, 1], dirs[:, 0]], 1)
    for i in range(0, len(samples), 60):  # benches and lamps along the path, alternating sides
        side = 1.0 if (i // 60) % 2 else -1.0
        x, y = samples[i] + normal[i] * side * 3.3
        if x0 + SIDEWALK + 1 < x < x1 - SIDEWALK - 1 and y0 + SIDEWALK + 1 < y < y1 - SIDEWALK - 1:
            b.box((x, y, 0.25), (1.8, 0.6, 0.5), yaw_path[i], 0.5)
        x, y = samples[i] - normal[i] * side * 2.8
        if x0 + SIDEWALK + 1 < x < x1 - SIDEWALK - 1 and y0 + SIDEWALK + 1 < y < y1 - SIDEWALK - 1:
            b.cylinder(x, y, 0.1, 0.0, 4.5, 0.9)


def _ring(b: _Builder, x0: float, x1: float, y0: float, y1: float,
          path: np.ndarray | None = None) -> None:
    """Sidewalk strips (kerbed, `SIDEWALK` wide) around the block [x0, x1] x [y0, y1], open where `path`
    crosses them (4 m either side)."""
    w = SIDEWALK
    strips = [((x0, x1), (y0, y0 + w), 0), ((x0, x1), (y1 - w, y1), 0),
              ((x0, x0 + w), (y0 + w, y1 - w), 1), ((x1 - w, x1), (y0 + w, y1 - w), 1)]
    samples = _polyline_samples([path], 0.25)[0] if path is not None else np.zeros((0, 2))
    for (ax, bx), (ay, by), along in strips:
        inside = samples[(samples[:, 0] > ax - 3) & (samples[:, 0] < bx + 3) & (samples[:, 1] > ay - 3)
                         & (samples[:, 1] < by + 3)]
        lo, hi = (ax, bx) if along == 0 else (ay, by)
        gaps = [(inside[:, along].min() - 4.0, inside[:, along].max() + 4.0)] if len(inside) else []
        for p, q in _open(lo, hi, gaps):
            if along == 0:
                b.rect(p, q, ay, by, 0.0, KERB, 0.35)
            else:
                b.rect(ax, bx, p, q, 0.0, KERB, 0.35)


def campus_world(seed: int = 0, blocks: tuple[int, int] = (4, 3)) -> World:
    """A campus of `blocks` = (columns, rows) city blocks (see the module docstring), centred on the origin.
    (4, 3) spans about 300 x 240 m (>= 50,000 m^2), (1, 1) about 110 x 110 m."""
    nx, ny = int(blocks[0]), int(blocks[1])
    if nx < 1 or ny < 1:
        raise ValueError(f"blocks must be at least (1, 1), got {blocks}")
    rng = np.random.default_rng(seed)
    bw, bh = rng.uniform(50.0, 70.0, nx), rng.uniform(50.0, 70.0, ny)
    rwx, rwy = rng.uniform(10.0, 14.0, nx + 1), rng.uniform(10.0, 14.0, ny + 1)

    def layout(block: np.ndarray, road: np.ndarray) -> tuple[np.ndarray, list[tuple[float, float]], float]:
        centres, spans, x = [], [], OUTER
        for i in range(len(road)):
            centres.append(x + road[i] / 2)
            x += road[i]
            if i < len(block):
                spans.append((x, x + block[i]))
                x += block[i]
        total = x + OUTER
        return np.asarray(centres) - total / 2, [(a - total / 2, c - total / 2) for a, c in spans], total / 2

    rx, bxs, hx = layout(bw, rwx)
    ry, bys, hy = layout(bh, rwy)
    xmin, xmax, ymin, ymax = -hx, hx, -hy, hy
    b = _Builder()

    roads = [np.array([[x, ry[0]], [x, ry[-1]]]) for x in rx] + [np.array([[rx[0], y], [rx[-1], y]]) for y in ry]
    indoor_block = (0, 0)
    park_block = (nx - 1, 0) if nx > 1 else ((0, ny - 1) if ny > 1 else None)
    path = None
    if park_block is not None:
        i, j = park_block
        (x0, x1), (y0, y1) = bxs[i], bys[j]
        path = np.array([[rx[i], ry[j]], [x0 + 0.35 * (x1 - x0), y0 + 0.6 * (y1 - y0)], [rx[i + 1], ry[j + 1]]])
        roads.append(path)
    phase = 0.0  # terraced houses at x = phase + k period on both sides of the northern street

    # blocks
    indoor: list[np.ndarray] = []
    for i, (x0, x1) in enumerate(bxs):
        for j, (y0, y1) in enumerate(bys):
            if (i, j) == indoor_block:
                _ring(b, x0, x1, y0, y1)
                indoor = _indoor_building(b, rng, x0 + SIDEWALK + 2.0, x1 - SIDEWALK - 2.0, y0 + SIDEWALK + 2.0,
                                          y1 - SIDEWALK - 2.0)
                continue
            if (i, j) == park_block:
                _ring(b, x0, x1, y0, y1, path)
                _park(b, rng, x0, x1, y0, y1, path)  # type: ignore[arg-type]
                continue
            b.rect(x0, x1, y0, y1, 0.0, KERB, 0.35)  # the block's platform: sidewalks and courtyard
            south = _Edge(np.array([x0, y0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]))
            north = _Edge(np.array([x0, y1]), np.array([1.0, 0.0]), np.array([0.0, -1.0]))
            west = _Edge(np.array([x0, y0]), np.array([0.0, 1.0]), np.array([1.0, 0.0]))
            east = _Edge(np.array([x1, y0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]))
            inner = SIDEWALK + 8.0  # the side streets' buildings start behind the corner ones
            _buildings(b, rng, south, SIDEWALK, x1 - x0 - SIDEWALK)
            if j == ny - 1:  # on the terraced street
                _terrace(b, north, SIDEWALK, x1 - x0 - SIDEWALK, phase - x0, False, rng)
            else:
                _buildings(b, rng, north, SIDEWALK, x1 - x0 - SIDEWALK)
            _buildings(b, rng, west, inner, y1 - y0 - inner)
            _buildings(b, rng, east, inner, y1 - y0 - inner)
            deep = SIDEWALK + 4.0 + 18.0 + 1.0  # sidewalk, setback and depth of the buildings around
            cx0, cx1, cy0, cy1 = x0 + deep, x1 - deep, y0 + deep, y1 - deep
            if cx1 - cx0 > 14.0 and cy1 - cy0 > 14.0 and rng.random() < 0.5:  # a turned courtyard building
                h = rng.uniform(4.0, 10.0)
                b.box(((cx0 + cx1) / 2, (cy0 + cy1) / 2, h / 2), (rng.uniform(6.0, 10.0), rng.uniform(5.0, 8.0), h),
                      rng.uniform(0.0, np.pi), rng.uniform(0.3, 0.8))
            if cx1 - cx0 > 4.0 and cy1 - cy0 > 4.0:
                for _ in range(rng.integers(0, 4)):
                    b.tree(rng, rng.uniform(cx0, cx1), rng.uniform(cy0, cy1))

    # the outer ring: platforms and gapless buildings backing onto the bounds
    kerb_s, kerb_n = ry[0] - rwy[0] / 2, ry[-1] + rwy[-1] / 2
    kerb_w, kerb_e = rx[0] - rwx[0] / 2, rx[-1] + rwx[-1] / 2
    b.rect(xmin, xmax, ymin, kerb_s, 0.0, KERB, 0.35)
    b.rect(xmin, xmax, kerb_n, ymax, 0.0, KERB, 0.35)
    b.rect(xmin, kerb_w, kerb_s, kerb_n, 0.0, KERB, 0.35)
    b.rect(kerb_e, xmax, kerb_s, kerb_n, 0.0, KERB, 0.35)
    for cx0, cx1 in ((xmin, kerb_w - SIDEWALK), (kerb_e + SIDEWALK, xmax)):  # corners: close the sidewalks' ends
        for cy0, cy1 in ((ymin, kerb_s), (kerb_n, ymax)):
            b.rect(cx0, cx1, cy0, cy1, 0.0, rng.uniform(8.0, 20.0), rng.uniform(0.3, 0.8))
    _buildings(b, rng, _Edge(np.array([xmin, kerb_s]), np.array([1.0, 0.0]), np.array([0.0, -1.0])),
               0.0, xmax - xmin, gapless=True, back=kerb_s - ymin)
    _terrace(b, _Edge(np.array([xmin, kerb_n]), np.array([1.0, 0.0]), np.array([0.0, 1.0])), 0.0, xmax - xmin,
             phase - xmin, True, rng, back=ymax - kerb_n)
    _buildings(b, rng, _Edge(np.array([kerb_w, kerb_s]), np.array([0.0, 1.0]), np.array([-1.0, 0.0])),
               0.0, kerb_n - kerb_s, gapless=True, back=kerb_w - xmin)
    _buildings(b, rng, _Edge(np.array([kerb_e, kerb_s]), np.array([0.0, 1.0]), np.array([1.0, 0.0])),
               0.0, kerb_n - kerb_s, gapless=True, back=xmax - kerb_e)

    # street furniture (the terraced street: a lamp pole at every party wall, both sides, nothing else)
    for k, x in enumerate(rx):
        crossings = [(y - ry[0], rwy[m] / 2) for m, y in enumerate(ry)]
        _furniture(b, rng, np.array([x, ry[0]]), np.array([x, ry[-1]]), rwx[k] / 2, crossings)
    for k, y in enumerate(ry[:-1]):
        crossings = [(x - rx[0], rwx[m] / 2) for m, x in enumerate(rx)]
        _furniture(b, rng, np.array([rx[0], y]), np.array([rx[-1], y]), rwy[k] / 2, crossings)
    for x in np.arange(phase + TERRACE_PERIOD * np.ceil((rx[0] - phase) / TERRACE_PERIOD), rx[-1], TERRACE_PERIOD):
        if all(abs(x - xc) > rwx[m] / 2 + 1.0 for m, xc in enumerate(rx)):
            for side in (1.0, -1.0):
                b.cylinder(x, ry[-1] + side * (rwy[-1] / 2 + 1.0), 0.1, 0.0, 6.0, 0.9)

    boxes, cylinders = b.arrays()
    # free space around the centre-lines: drop what reaches into the sensors' height band there
    box_z0, box_z1 = boxes[:, 2] - boxes[:, 5], boxes[:, 2] + boxes[:, 5]
    samples = _polyline_samples(roads, 0.25)[0]
    reach = ROAD_CLEARANCE + 0.125  # the samples are 0.25 m apart
    box_d, cyl_d = _footprint_distance(samples, boxes, cylinders, reach)
    boxes = boxes[~((box_d < reach) & _in_band(box_z0, box_z1))]
    drop = (cyl_d < reach) & _in_band(cylinders[:, 3], cylinders[:, 4])
    drop |= (cylinders[:, None, :2] == cylinders[drop][None, :, :2]).all(2).any(1)  # a dropped trunk's crown
    cylinders = cylinders[~drop]
    terrace = np.array([[rx[0], ry[-1]], [rx[-1], ry[-1]]])
    return World("campus", _scene("campus", boxes, cylinders), roads, indoor, (xmin, xmax, ymin, ymax), seed,
                 (nx, ny), terrace, TERRACE_PERIOD)


# ----------------------------------------------------------------------------- fast scans
def merge_scenes(name: str, *scenes: Scene) -> Scene:
    """One scene holding the primitives of `scenes`, in order."""
    s = Scene(name)
    s.plane_points = np.concatenate([x.plane_points for x in scenes]).reshape(-1, 3)
    s.plane_normals = np.concatenate([x.plane_normals for x in scenes]).reshape(-1, 3)
    s.plane_reflectivity = np.concatenate([x.plane_reflectivity for x in scenes])
    s.box_centers = np.concatenate([x.box_centers for x in scenes]).reshape(-1, 3)
    s.box_half = np.concatenate([x.box_half for x in scenes]).reshape(-1, 3)
    s.box_yaw = np.concatenate([x.box_yaw for x in scenes])
    s.box_reflectivity = np.concatenate([x.box_reflectivity for x in scenes])
    s.cylinders = np.concatenate([x.cylinders for x in scenes]).reshape(-1, 5)
    s.cylinder_reflectivity = np.concatenate([x.cylinder_reflectivity for x in scenes])
    return s


def subset(scene: Scene, boxes: np.ndarray, cylinders: np.ndarray, planes: bool = True) -> Scene:
    """The sub-scene of the boxes and cylinders selected by the masks or indices (order kept); all planes
    unless `planes` is False."""
    s = Scene(scene.name)
    if planes:
        s.plane_points, s.plane_normals = scene.plane_points, scene.plane_normals
        s.plane_reflectivity = scene.plane_reflectivity
    s.box_centers, s.box_half = scene.box_centers[boxes], scene.box_half[boxes]
    s.box_yaw, s.box_reflectivity = scene.box_yaw[boxes], scene.box_reflectivity[boxes]
    s.cylinders, s.cylinder_reflectivity = scene.cylinders[cylinders], scene.cylinder_reflectivity[cylinders]
    return s


def bounding_circles(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """xy centres and radii of circles holding each box's and each cylinder's footprint:
    (box centres (B, 2), box radii (B,), cylinder centres (C, 2), cylinder radii (C,))."""
    return (scene.box_centers[:, :2], np.hypot(scene.box_half[:, 0], scene.box_half[:, 1]),
            scene.cylinders[:, :2], scene.cylinders[:, 2])


def scene_near(scene: Scene, center: np.ndarray, radius: float) -> Scene:
    """The sub-scene a sensor at `center` (xy, or xyz) can see within `radius` m: every plane, and the boxes
    and cylinders whose bounding circle (xy) comes within `radius` of the centre. Order is kept."""
    c = np.asarray(center, dtype=np.float64)[:2]
    bc, br, cc, cr = bounding_circles(scene)
    return subset(scene, np.linalg.norm(bc - c, axis=1) - br <= radius,
                  np.linalg.norm(cc - c, axis=1) - cr <= radius)


def cull_radius(sensor: LidarSensor) -> float:
    """How far to keep primitives for `sensor`: its range, plus room for the range noise to pull a hit just
    beyond the range back into it (20 standard deviations) and a metre."""
    return sensor.max_range + 20.0 * sensor.range_noise + 1.0


@dataclass
class SectorScene(Scene):
    """A `Scene` whose `cast` bins the rays into `sectors` azimuth sectors (world frame; 0: one per 1024 rays,
    64 to 256) and intersects each ray only with the boxes and cylinders whose bounding circle its sector can
    meet; planes meet all rays.
    A ray's xy path is a half-line at its azimuth, so it can only hit a footprint inside a circle of radius r
    at distance D if its azimuth is within asin(r / D) of the circle's; circles holding the origin meet every
    sector. Same hits, same arithmetic per ray and primitive, same ties (planes before boxes before
    cylinders, lower index first) as `Scene.cast`: results are identical, bit for bit."""

    sectors: int = 0

    @classmethod
    def of(cls, scene: Scene, sectors: int = 0) -> SectorScene:
        return cls(**{f.name: getattr(scene, f.name) for f in dataclasses.fields(Scene)}, sectors=sectors)

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        best, normal, refl = Scene.cast(subset(self, np.zeros(0, dtype=int), np.zeros(0, dtype=int)), o, d)
        if not (len(self.box_yaw) or len(self.cylinders)):
            return best, normal, refl
        S = self.sectors or int(np.clip(len(d) // 1024, 64, 256))
        scale = S / (2.0 * np.pi)
        ray_sector = np.minimum(((np.arctan2(d[:, 1], d[:, 0]) + np.pi) * scale).astype(np.int64), S - 1)
        order = np.argsort(ray_sector, kind="stable")
        starts = np.searchsorted(ray_sector[order], np.arange(S + 1))
        bc, br, cc, cr = bounding_circles(self)
        centres, radii = np.concatenate([bc, cc]), np.concatenate([br, cr])
        radii = radii * (1.0 + 1e-9) + 1e-9  # rounding room: a grazing ray still meets its circle
        rel = centres - o[:2]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        phi = np.arctan2(rel[:, 1], rel[:, 0])
        with np.errstate(divide="ignore", invalid="ignore"):
            half = np.arcsin(np.clip(radii / dist, 0.0, 1.0)) + 1e-7
        lo = np.floor((phi - half + np.pi) * scale).astype(np.int64)
        span = np.floor((phi + half + np.pi) * scale).astype(np.int64) - lo + 1
        span = np.where(dist <= radii + 1e-6, S, span)  # the circle holds the origin: every azimuth
        member = (np.arange(S)[:, None] - lo[None, :]) % S < span[None, :]  # (S, B + C)
        nb = len(bc)
        for k in range(S):
            rays = order[starts[k]:starts[k + 1]]
            if not len(rays) or not member[k].any():
                continue
            sub = subset(self, member[k, :nb], member[k, nb:], planes=False)
            t, n, r = Scene.cast(sub, o, d[rays])
            closer = t < best[rays]
            hit = rays[closer]
            best[hit], normal[hit], refl[hit] = t[closer], n[closer], r[closer]
        return best, normal, refl


def culled_scan(scene: Scene, pose_world_sensor: np.ndarray, rng: np.random.Generator,
                sensor: LidarSensor | None = None, sectors: int = 0) -> LidarScan:
    """`lidar_scan` of `scene` at the pose, fast in large scenes: the primitives within `cull_radius` of the
    sensor (`scene_near`), cast by azimuth sector (`SectorScene`). The same scan as `lidar_scan(scene, ...)`
    given the same rng, bit for bit."""
    sensor = sensor or SURVEY_SENSOR
    T = np.asarray(pose_world_sensor, dtype=np.float64)
    near = scene_near(scene, T[:3, 3], cull_radius(sensor))
    return lidar_scan(SectorScene.of(near, sectors), T, rng, sensor)


# ----------------------------------------------------------------------------- poses
def _yaw_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    return sensor_pose(float(x), float(y), float(z), float(yaw))


def survey_poses(world: World, spacing: float = 3.0, height: float = 1.8, indoor: bool = True,
                 rng: np.random.Generator | None = None, indoor_height: float = 0.6,
                 indoor_spacing: float | None = None) -> np.ndarray:
    """(P, 4, 4) T_world_sensor every `spacing` m along every road (from its start, `height` m above the
    ground) and, with `indoor`, every `indoor_spacing` m (default `spacing`) along every corridor
    (`indoor_height` m, a floor robot), heading along the line. With `rng`: lateral jitter up to
    `JITTER_LATERAL` m and yaw jitter up to `JITTER_YAW` rad."""
    indoor_spacing = spacing if indoor_spacing is None else indoor_spacing
    if spacing <= 0 or indoor_spacing <= 0:
        raise ValueError(f"spacings must be positive, got {spacing} and {indoor_spacing}")
    out = []
    for lines, z, step in ((world.roads, height, spacing), (world.indoor if indoor else [], indoor_height, indoor_spacing)):
        for line in lines:
            seg = np.diff(line, axis=0)
            lengths = np.linalg.norm(seg, axis=1)
            cum = np.concatenate([[0.0], np.cumsum(lengths)])
            for s in np.arange(0.0, cum[-1] + 1e-9, step):
                k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
                u = seg[k] / lengths[k]
                p = line[k] + u * (s - cum[k])
                yaw = np.arctan2(u[1], u[0])
                if rng is not None:
                    p = p + np.array([-u[1], u[0]]) * np.clip(rng.normal(0.0, JITTER_LATERAL / 2), -JITTER_LATERAL,
                                                              JITTER_LATERAL)
                    yaw += np.clip(rng.normal(0.0, JITTER_YAW / 2), -JITTER_YAW, JITTER_YAW)
                out.append(_yaw_pose(p[0], p[1], z, yaw))
    return np.asarray(out).reshape(-1, 4, 4)


def distance_to_lines(points: np.ndarray, lines: list[np.ndarray]) -> np.ndarray:
    """(N,) the xy distance from each point (N, >= 2) to the nearest of the polylines; inf with none."""
    p = np.asarray(points, dtype=np.float64)[:, :2]
    best = np.full(len(p), np.inf)
    for line in lines:
        for a, c in itertools.pairwise(line):
            ab = c - a
            f = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(p - (a + f[:, None] * ab), axis=1))
    return best


def inside(scene: Scene, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N,) whether each point (N, 3) lies inside (or within `margin` m of) a box or cylinder of `scene`."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(p), dtype=bool)
    for c, h, yaw in zip(scene.box_centers, scene.box_half, scene.box_yaw):
        rel = p - c
        cs, sn = np.cos(yaw), np.sin(yaw)
        local = np.abs(np.stack([cs * rel[:, 0] + sn * rel[:, 1], -sn * rel[:, 0] + cs * rel[:, 1], rel[:, 2]], 1))
        out |= (local <= h + margin).all(1)
    for x, y, r, z0, z1 in scene.cylinders:
        out |= (np.hypot(p[:, 0] - x, p[:, 1] - y) <= r + margin) & (p[:, 2] >= z0 - margin) & (p[:, 2] <= z1 + margin)
    return out


def test_poses(world: World, n: int, rng: np.random.Generator, height: float = 1.8,
               where: str = "roads") -> np.ndarray:
    """(n, 4, 4) held-out T_world_sensor: a point uniform along the roads (`where="roads"`, a road chosen with
    probability proportional to its length) or corridors (`where="indoor"`), offset sideways by
    `MIN_OFFSET`..`LANE` m (corridors: ..`INDOOR_LANE`), `height` m above the ground, yaw uniform in
    [-pi, pi). At least `MIN_OFFSET` m from every centre-line (so at least 0.5 m from every survey pose, even
    jittered) and never inside a box or cylinder."""
    if where not in ("roads", "indoor"):
        raise ValueError(f"where must be 'roads' or 'indoor', got {where!r}")
    lines = world.roads if where == "roads" else world.indoor
    if not lines:
        raise ValueError(f"world {world.name!r} has no {where} centre-lines")
    lane = LANE if where == "roads" else INDOOR_LANE
    a, c = (np.array([seg[k] for line in lines for seg in itertools.pairwise(line)]) for k in (0, 1))
    lengths = np.linalg.norm(c - a, axis=1)
    u = (c - a) / lengths[:, None]
    everything = world.roads + world.indoor
    out: list[np.ndarray] = []
    for _ in range(100):  # batches of candidates; the free ones kept in order
        if sum(len(o) for o in out) >= n:
            break
        m = max(2 * n, 64)
        k = rng.choice(len(a), size=m, p=lengths / lengths.sum())
        along, side = rng.uniform(0.0, 1.0, m), rng.choice([-1.0, 1.0], size=m)
        offset, yaw = rng.uniform(MIN_OFFSET, lane, m), rng.uniform(-np.pi, np.pi, m)
        xy = a[k] + along[:, None] * (c[k] - a[k]) + np.stack([-u[k, 1], u[k, 0]], 1) * (side * offset)[:, None]
        p = np.column_stack([xy, np.full(m, height)])
        ok = (distance_to_lines(p, everything) >= MIN_OFFSET) & ~inside(world.scene, p, 0.05)
        out.append(np.array([_yaw_pose(x, y, height, h) for (x, y, _), h in zip(p[ok], yaw[ok])]).reshape(-1, 4, 4))
    poses = np.concatenate(out)[:n] if out else np.zeros((0, 4, 4))
    if len(poses) < n:
        raise RuntimeError(f"found only {len(poses)} of {n} free test poses")
    return poses


test_poses.__test__ = False  # type: ignore[attr-defined]  # a pose sampler, not a pytest test (when imported)


# ----------------------------------------------------------------------------- movers and scans
CAR = (4.5, 1.8, 1.5)
PEDESTRIAN = (0.5, 0.5, 1.8)


def movers(world: World, pose: np.ndarray, rng: np.random.Generator, count: int = 6) -> Scene:
    """`count` moving objects near the sensor at `pose`: cars (`CAR` boxes) in the lanes and pedestrians
    (`PEDESTRIAN` boxes) on the roads and in the corridors, 5-30 m from the sensor (centre, xy), heading
    along their line, clear of every static box and cylinder in their height band and of each other. They
    are in scans (`world_scan`), never in maps. Fewer when no free place is found (a dead-end corridor)."""
    T = np.asarray(pose, dtype=np.float64)
    origin = T[:2, 3]
    out = _Builder()
    if count <= 0:
        return _scene("movers", *out.arrays())
    road_pts, road_dir, _ = _polyline_samples(world.roads, 0.5)
    in_pts, in_dir, _ = _polyline_samples(world.indoor, 0.5)
    pts = np.concatenate([road_pts, in_pts])
    dirs = np.concatenate([road_dir, in_dir])
    is_road = np.concatenate([np.ones(len(road_pts), bool), np.zeros(len(in_pts), bool)])
    dist = np.linalg.norm(pts - origin, axis=1)
    ok = np.flatnonzero((dist >= 5.0) & (dist <= 30.0))
    static = scene_near(world.scene, origin, 40.0)
    sz0, sz1 = static.box_centers[:, 2] - static.box_half[:, 2], static.box_centers[:, 2] + static.box_half[:, 2]
    boxes = np.concatenate([static.box_centers, static.box_half, static.box_yaw[:, None],
                            static.box_reflectivity[:, None]], 1)[_in_band(sz0, sz1)]
    cyls = np.concatenate([static.cylinders, static.cylinder_reflectivity[:, None]], 1)[
        _in_band(static.cylinders[:, 3], static.cylinders[:, 4])]
    placed: list[tuple[float, ...]] = []
    for _ in range(50 * count):
        if len(out.boxes) == count or not len(ok):
            break
        i = ok[rng.integers(len(ok))]
        car = bool(is_road[i]) and rng.random() < 0.6
        size = CAR if car else PEDESTRIAN
        lane = (0.3, 2.0) if car else ((0.0, 4.0) if is_road[i] else (0.0, 1.0))
        u = dirs[i]
        xy = pts[i] + np.array([-u[1], u[0]]) * rng.choice([-1.0, 1.0]) * rng.uniform(*lane)
        if not 5.0 <= np.linalg.norm(xy - origin) <= 30.0:
            continue
        yaw = np.arctan2(u[1], u[0]) + (rng.normal(0.0, 0.05) if car else rng.uniform(-np.pi, np.pi))
        if rng.random() < 0.5:
            yaw += np.pi  # either direction
        hx, hy = size[0] / 2, size[1] / 2
        cs, sn = np.cos(yaw), np.sin(yaw)
        gx, gy = np.meshgrid(np.linspace(-hx, hx, max(2, int(np.ceil(2 * hx / 0.25)) + 1)),
                             np.linspace(-hy, hy, max(2, int(np.ceil(2 * hy / 0.25)) + 1)))
        foot = xy + np.stack([cs * gx.ravel() - sn * gy.ravel(), sn * gx.ravel() + cs * gy.ravel()], 1)
        others = np.asarray(placed, dtype=np.float64).reshape(-1, 8)
        box_d, cyl_d = _footprint_distance(foot, np.concatenate([boxes, others]), cyls, 0.3)
        if (box_d < 0.3).any() or (cyl_d < 0.3).any():
            continue
        refl = rng.uniform(0.2, 0.9)
        out.box((xy[0], xy[1], size[2] / 2), size, yaw, refl)
        placed.append(out.boxes[-1])
    bx, _ = out.arrays()
    s = Scene("movers")
    s.box_centers, s.box_half, s.box_yaw, s.box_reflectivity = bx[:, :3], bx[:, 3:6], bx[:, 6], bx[:, 7]
    return s


def world_scan(world: World, pose: np.ndarray, rng: np.random.Generator, sensor: LidarSensor | None = None,
               moving: int = 6) -> LidarScan:
    """One revolution of `sensor` (default `SURVEY_SENSOR`) at `pose` with `moving` movers (drawn first from
    `rng`, `movers`), by `culled_scan` of the world plus the movers."""
    extra = movers(world, pose, rng, moving)
    scene = merge_scenes(world.name, world.scene, extra) if len(extra.box_yaw) else world.scene
    return culled_scan(scene, pose, rng, sensor)


# ----------------------------------------------------------------------------- maps
class VoxelAccumulator:
    """Centroids of points in cubic voxels of edge `voxel` (grid anchored at 0, as
    `genreg_core.preprocess.voxel_downsample`), accumulated chunk by chunk: memory grows with the occupied
    voxels, not with the points. `lo`, `hi`: corners (3,) of the box every point lies in."""

    def __init__(self, voxel: float, lo: np.ndarray, hi: np.ndarray, chunk: int = 4_000_000) -> None:
        if voxel <= 0:
            raise ValueError(f"voxel must be positive, got {voxel}")
        self.voxel = float(voxel)
        self.k0 = np.floor(np.asarray(lo, dtype=np.float64) / voxel).astype(np.int64) - 1
        self.dims = np.floor(np.asarray(hi, dtype=np.float64) / voxel).astype(np.int64) + 2 - self.k0
        if float(np.prod(self.dims.astype(np.float64))) >= 2.0**62:
            raise ValueError("the voxel grid is too large for int64 keys")
        self.chunk = chunk
        self.buffer: list[np.ndarray] = []
        self.buffered = 0
        self.keys = np.zeros(0, dtype=np.int64)
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0, dtype=np.int64)

    def add(self, points: np.ndarray) -> None:
        self.buffer.append(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        self.buffered += len(self.buffer[-1])
        if self.buffered >= self.chunk:
            self.flush()

    def flush(self) -> None:
        if not self.buffer:
            return
        p = np.concatenate(self.buffer)
        self.buffer, self.buffered = [], 0
        k = np.floor(p / self.voxel).astype(np.int64) - self.k0
        if (k < 0).any() or (k >= self.dims).any():
            raise ValueError("a point lies outside the accumulator's box")
        flat = (k[:, 0] * self.dims[1] + k[:, 1]) * self.dims[2] + k[:, 2]
        keys = np.concatenate([self.keys, flat])
        u, inverse = np.unique(keys, return_inverse=True)
        inverse = inverse.reshape(-1)
        n_old = len(self.keys)
        sums = np.zeros((len(u), 3))
        for i in range(3):
            sums[:, i] = np.bincount(inverse[:n_old], weights=self.sums[:, i], minlength=len(u)) + \
                np.bincount(inverse[n_old:], weights=p[:, i], minlength=len(u))
        counts = np.bincount(inverse[:n_old], weights=self.counts, minlength=len(u)).astype(np.int64) + \
            np.bincount(inverse[n_old:], minlength=len(u))
        self.keys, self.sums, self.counts = u, sums, counts

    def __len__(self) -> int:
        self.flush()
        return len(self.keys)

    def points(self) -> np.ndarray:
        """(M, 3) float32 voxel centroids, ordered by voxel (x, then y, then z)."""
        self.flush()
        return (self.sums / self.counts[:, None]).astype(np.float32)


def build_map(world: World, poses: np.ndarray, sensor: LidarSensor | None = None, voxel: float = 0.1,
              seed: int = 0, progress: bool = True) -> np.ndarray:
    """The map: a scan (`culled_scan`, static world, no movers; `sensor` default `SURVEY_SENSOR`) at each of
    `poses` (true T_world_sensor), moved into the world frame, fused and voxel-downsampled to centroids of
    `voxel` m voxels (`VoxelAccumulator`, incrementally). (M, 3) float32, world frame. One rng
    (`default_rng(seed)`) draws the noise of all scans in order. Progress bar on stderr."""
    sensor = sensor or SURVEY_SENSOR
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    rng = np.random.default_rng(seed)
    reach = sensor.max_range + 1.0
    lo = np.array([world.bounds[0] - reach, world.bounds[2] - reach, -reach])
    hi = np.array([world.bounds[1] + reach, world.bounds[3] + reach, reach])
    if len(poses):
        lo = np.minimum(lo, poses[:, :3, 3].min(0) - reach)
        hi = np.maximum(hi, poses[:, :3, 3].max(0) + reach)
    acc = VoxelAccumulator(voxel, lo, hi)
    for T in tqdm(poses, desc=f"map {world.key}", unit="scan", file=sys.stderr, disable=not progress):
        scan = culled_scan(world.scene, T, rng, sensor)
        acc.add(scan.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3])
    return acc.points()


def sensor_key(sensor: LidarSensor) -> str:
    """A short digest of every field of `sensor` (beam pattern, columns, ranges, noise...)."""
    return hashlib.sha1(repr(sensor).encode()).hexdigest()[:10]


def map_path(world: World, spacing: float = 3.0, voxel: float = 0.1, cache_dir: str | Path = "cache/lidar_world",
             sensor: LidarSensor | None = None, indoor_spacing: float | None = None) -> Path:
    """Where `cached_map` keeps the map of these arguments."""
    sensor = sensor or SURVEY_SENSOR
    indoor = "" if indoor_spacing is None or indoor_spacing == spacing else f"-in{indoor_spacing:g}"
    return Path(cache_dir) / f"{world.key}-sp{spacing:g}{indoor}-vox{voxel:g}-{sensor_key(sensor)}.npy"


def cached_map(world: World, spacing: float = 3.0, voxel: float = 0.1, cache_dir: str | Path = "cache/lidar_world",
               sensor: LidarSensor | None = None, progress: bool = True, indoor_spacing: float | None = None
               ) -> np.ndarray:
    """`build_map(world, survey_poses(world, spacing, indoor_spacing=indoor_spacing), sensor, voxel)` (no jitter,
    corridors included, build seed 0), loaded from `map_path(...)` when there, else built and saved there (with
    a .json beside it: poses, points, area, build seconds, the sensor); `progress`: a progress bar while
    building."""
    sensor = sensor or SURVEY_SENSOR
    path = map_path(world, spacing, voxel, cache_dir, sensor, indoor_spacing)
    if path.exists():
        return np.load(path)
    poses = survey_poses(world, spacing, indoor_spacing=indoor_spacing)
    start = time.perf_counter()
    cloud = build_map(world, poses, sensor, voxel, progress=progress)
    seconds = time.perf_counter() - start
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npy")
    np.save(tmp, cloud)
    os.replace(tmp, path)
    info = {"world": world.key, "blocks": list(world.blocks), "seed": world.seed, "area_m2": world.area_m2,
            "bounds": list(world.bounds), "spacing": spacing,
            "indoor_spacing": spacing if indoor_spacing is None else indoor_spacing, "voxel": voxel, "poses": len(poses),
            "points": len(cloud), "build_seconds": round(seconds, 1), "sensor": repr(sensor)}
    path.with_suffix(".json").write_text(json.dumps(info, indent=1) + "\n")
    return cloud
