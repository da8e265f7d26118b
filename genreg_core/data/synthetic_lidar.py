"""A synthetic spinning LiDAR: analytic ray casting into scenes of primitives, for tests and benchmarks.

    scene = make_scene("street")                      # or "room"; `seed` varies the layout
    sensor = LidarSensor.uniform(beams=64, columns=2048)
    scan = lidar_scan(scene, T_world_sensor, np.random.default_rng(0), sensor)
    scan.points  # (N, 3) float32, sensor frame; scan.intensity (N,), scan.ring (N,)

Conventions:
- Metres and radians (degrees only where a name ends in `_deg`), REP-103 frames: x forward, y left, z up.
- `T_world_sensor` (4x4) maps points in the sensor frame into the world (scene) frame, x_w = R x_s + t
  (`genreg_core.geometry`). Points of a scan are in the sensor frame.
- The sensor spins about its z axis: beam b has elevation `elevations_deg[b]` (its ring is b), column c
  has azimuth 2 pi c / columns, counter-clockwise from +x. A ray's range is the analytic distance to the
  nearest primitive surface, plus Gaussian noise of `range_noise` metres along the ray; hits nearer than
  `min_range` or farther than `max_range` are misses.
- Misses are dropped, or with `keep_misses` emitted as (0, 0, 0) with intensity 0 (as some drivers do).
  With `dropout` > 0 that share of the rays (drawn at random) returns nothing: a miss whatever it would hit.
- Intensity in [0, 1]: the hit primitive's reflectivity times |cos| of the incidence angle.
- Dual returns: a share `duplicate_share` of the hits (rounded to a whole count, drawn without replacement)
  is emitted twice, the exact copy right after its original, as drivers do when both returns coincide.
- Time: `scan.time` is each point's firing time in seconds since the scan's start, column / columns x
  `scan_period` (all beams of a column fire together); a duplicate carries its original's time.
- Deterministic given the rng (one noise draw, one dropout draw only when `dropout` > 0, and one duplicate
  draw per scan); no per-ray Python loops: every primitive is intersected with all rays at once.

Primitives (`Scene`): infinite planes (ground, room walls), oriented boxes (a yaw about z), and vertical
cylinders with caps (poles, trunks, crowns, pillars). The sensor must not start inside a box or cylinder.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from genreg_core.geometry import make_transform

SCENES = ("room", "street")
_CHUNK = 4_000_000  # rays x primitives intersected at once (bounds the temporary arrays)
DRIVER_POINT = np.dtype({  # a Velodyne driver's point: x, y, z, intensity, ring, time, packed (22 bytes)
    "names": ["x", "y", "z", "intensity", "ring", "time"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
    "offsets": [0, 4, 8, 12, 16, 18],
    "itemsize": 22,
})


@dataclass(frozen=True)
class LidarSensor:
    """Beam pattern, resolution, range limits and the noise model of a spinning LiDAR."""

    elevations_deg: tuple[float, ...]  # one per beam (ring index = position here)
    columns: int = 1024  # azimuth steps per revolution
    max_range: float = 100.0
    min_range: float = 0.3
    range_noise: float = 0.015  # standard deviation along the ray, m
    duplicate_share: float = 0.04  # share of hits emitted twice (dual returns)
    keep_misses: bool = False  # emit misses as (0, 0, 0) instead of dropping them
    scan_period: float = 0.1  # seconds per revolution (10 Hz)
    dropout: float = 0.0  # share of rays that return nothing (drawn at random per scan)

    def __post_init__(self) -> None:
        if len(self.elevations_deg) < 1 or self.columns < 1:
            raise ValueError("a sensor needs at least one beam and one column")
        if not 0.0 <= self.duplicate_share <= 1.0:
            raise ValueError(f"duplicate_share must be in [0, 1], got {self.duplicate_share}")
        if not 0.0 <= self.dropout <= 1.0:
            raise ValueError(f"dropout must be in [0, 1], got {self.dropout}")
        if not self.scan_period > 0.0:
            raise ValueError(f"scan_period must be positive, got {self.scan_period}")
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= min_range < max_range")

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @classmethod
    def uniform(cls, beams: int = 32, fov_deg: tuple[float, float] = (-25.0, 15.0), columns: int = 1024,
                **kwargs: float | bool) -> LidarSensor:
        """`beams` elevations evenly spaced over the vertical field of view `fov_deg` (lowest, highest)."""
        return cls(tuple(np.linspace(fov_deg[0], fov_deg[1], beams).tolist()), columns, **kwargs)  # type: ignore[arg-type]

    @classmethod
    def vlp32(cls, columns: int = 1024, **kwargs: float | bool) -> LidarSensor:
        """VLP-32C-like: 32 beams over -25..+15 deg, dense (0.33 deg) around the horizon, sparse at the ends."""
        elev = np.concatenate([np.linspace(-25.0, -8.0, 7, endpoint=False), np.linspace(-8.0, 2.33, 32 - 13),
                               np.linspace(3.33, 15.0, 6)])
        return cls(tuple(np.sort(elev).tolist()), columns, **kwargs)  # type: ignore[arg-type]

    @classmethod
    def hdl64(cls, columns: int = 2048, **kwargs: float | bool) -> LidarSensor:
        """HDL-64E-like: 64 beams over -24.9..+2 deg, two blocks of 32 (upper 1/3 deg, lower 1/2 deg)."""
        elev = np.concatenate([np.linspace(-24.9, -8.83, 32), np.linspace(-8.33, 2.0, 32)])
        return cls(tuple(elev.tolist()), columns, **kwargs)  # type: ignore[arg-type]

    @classmethod
    def os128(cls, columns: int = 1024, **kwargs: float | bool) -> LidarSensor:
        """OS1-128-like: 128 beams evenly spaced over -22.5..+22.5 deg."""
        return cls.uniform(128, (-22.5, 22.5), columns, **kwargs)

    def directions(self) -> np.ndarray:
        """(beams * columns, 3) unit ray directions in the sensor frame, beam-major (ray = b * columns + c)."""
        elev = np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))[:, None]
        az = (2.0 * np.pi / self.columns) * np.arange(self.columns, dtype=np.float64)[None, :]
        d = np.stack(np.broadcast_arrays(np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)), -1)
        return d.reshape(-1, 3)


@dataclass
class Scene:
    """Primitives in the world frame, each with a reflectivity in (0, 1]."""

    name: str = "scene"
    # planes: a point on each and its unit normal, (P, 3)
    plane_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # boxes: centre (B, 3), half extents (B, 3), yaw about z (B,)
    box_centers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    box_half: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    box_yaw: np.ndarray = field(default_factory=lambda: np.zeros(0))
    box_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # vertical cylinders: x, y, radius, z_min, z_max (C, 5)
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    cylinder_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def add_plane(self, point: tuple[float, float, float], normal: tuple[float, float, float],
                  reflectivity: float) -> None:
        n = np.asarray(normal, dtype=np.float64)
        self.plane_points = np.vstack([self.plane_points, point])
        self.plane_normals = np.vstack([self.plane_normals, n / np.linalg.norm(n)])
        self.plane_reflectivity = np.append(self.plane_reflectivity, reflectivity)

    def add_box(self, center: tuple[float, float, float], size: tuple[float, float, float], yaw: float = 0.0,
                reflectivity: float = 0.5) -> None:
        """A box of full edge lengths `size` (x, y, z in its own frame), turned by `yaw` rad about z."""
        self.box_centers = np.vstack([self.box_centers, center])
        self.box_half = np.vstack([self.box_half, np.asarray(size, dtype=np.float64) / 2])
        self.box_yaw = np.append(self.box_yaw, yaw)
        self.box_reflectivity = np.append(self.box_reflectivity, reflectivity)

    def add_cylinder(self, x: float, y: float, radius: float, z_min: float, z_max: float,
                     reflectivity: float = 0.5) -> None:
        self.cylinders = np.vstack([self.cylinders, (x, y, radius, z_min, z_max)])
        self.cylinder_reflectivity = np.append(self.cylinder_reflectivity, reflectivity)

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit of rays from one `origin` (3,) along unit `directions` (R, 3), world frame:
        (distance (R,), inf on a miss; unit surface normal (R, 3); reflectivity (R,))."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        best = np.full(len(d), np.inf)
        normal = np.zeros((len(d), 3))
        refl = np.zeros(len(d))

        def keep(t: np.ndarray, n: np.ndarray, r: np.ndarray) -> None:
            closer = t < best
            best[closer], normal[closer], refl[closer] = t[closer], n[closer], r[closer]

        for t, n, r in (*_planes(self, o, d), *_boxes(self, o, d), *_cylinders(self, o, d)):
            keep(t, n, r)
        return best, normal, refl


def _chunks(rays: int, count: int) -> range:
    return range(0, count, max(1, _CHUNK // max(rays, 1)))


def _nearest(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ray (row) the smallest t over the primitives (columns) and its column."""
    k = np.argmin(t, axis=1)
    return t[np.arange(len(t)), k], k


def _planes(s: Scene, o: np.ndarray, d: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    if not len(s.plane_normals):
        return []
    n = s.plane_normals
    denom = d @ n.T  # (R, P)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((s.plane_points - o) * n).sum(1)[None, :] / denom
    t = np.where((np.abs(denom) > 1e-12) & (t > 1e-9), t, np.inf)
    tmin, k = _nearest(t)
    return [(tmin, n[k], s.plane_reflectivity[k])]


def _boxes(s: Scene, o: np.ndarray, d: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Slab test in each box's frame (rotation by -yaw about z); the entry face gives the normal."""
    out = []
    for lo in _chunks(len(d), len(s.box_yaw)):
        sl = slice(lo, lo + max(1, _CHUNK // max(len(d), 1)))
        c, h, yaw = s.box_centers[sl], s.box_half[sl], s.box_yaw[sl]
        cos, sin = np.cos(yaw), np.sin(yaw)
        rel = o - c  # (B, 3)
        o_local = np.stack([cos * rel[:, 0] + sin * rel[:, 1], -sin * rel[:, 0] + cos * rel[:, 1], rel[:, 2]], -1)
        d_local = np.stack([d[:, :1] * cos + d[:, 1:2] * sin, -d[:, :1] * sin + d[:, 1:2] * cos,
                            np.broadcast_to(d[:, 2:], (len(d), len(yaw)))], -1)  # (R, B, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d_local
            t1 = (-h - o_local) * inv
            t2 = (h - o_local) * inv
        t1 = np.where(np.isnan(t1), -np.inf, t1)  # a ray parallel to a slab from inside it: no bound
        t2 = np.where(np.isnan(t2), np.inf, t2)
        near, far = np.minimum(t1, t2), np.maximum(t1, t2)
        axis = np.argmax(near, axis=2)  # (R, B): the face entered last
        t_in = np.take_along_axis(near, axis[..., None], 2)[..., 0]
        t_out = far.min(axis=2)
        t = np.where((t_in <= t_out) & (t_in > 1e-9), t_in, np.inf)
        tmin, k = _nearest(t)
        rows = np.arange(len(d))
        ax = axis[rows, k]
        sign = -np.sign(d_local[rows, k, ax])  # the face normal points against the ray
        n_local = np.zeros((len(d), 3))
        n_local[rows, ax] = sign
        ck, sk = cos[k], sin[k]
        n_world = np.stack([ck * n_local[:, 0] - sk * n_local[:, 1], sk * n_local[:, 0] + ck * n_local[:, 1],
                            n_local[:, 2]], -1)
        out.append((tmin, n_world, s.box_reflectivity[sl][k]))
    return out


def _cylinders(s: Scene, o: np.ndarray, d: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Side: the quadratic in xy, hit within [z_min, z_max]; caps: discs at z_min and z_max."""
    out = []
    step = max(1, _CHUNK // max(len(d), 1))
    for lo in _chunks(len(d), len(s.cylinders)):
        cyl = s.cylinders[lo: lo + step]
        cx, cy, r, z0, z1 = (cyl[:, i] for i in range(5))
        ox, oy = o[0] - cx, o[1] - cy  # (C,)
        dx, dy, dz = d[:, :1], d[:, 1:2], d[:, 2:]
        a = dx * dx + dy * dy  # (R, 1)
        b = 2.0 * (dx * ox + dy * oy)  # (R, C)
        cc = ox * ox + oy * oy - r * r  # (C,)
        disc = b * b - 4.0 * a * cc
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(np.where(disc >= 0, disc, np.nan))) / (2.0 * a)
        z_side = o[2] + t_side * dz
        t_side = np.where((t_side > 1e-9) & (z_side >= z0) & (z_side <= z1), t_side, np.inf)
        t_side = np.where(np.isnan(t_side), np.inf, t_side)
        caps = []
        for zc in (z0, z1):
            with np.errstate(divide="ignore", invalid="ignore"):
                tc = (zc - o[2]) / dz
            px, py = ox + tc * dx, oy + tc * dy
            tc = np.where((tc > 1e-9) & (px * px + py * py <= r * r), tc, np.inf)
            caps.append(np.where(np.isnan(tc), np.inf, tc))
        t_all = np.stack([t_side, *caps], -1)  # (R, C, 3)
        part = np.argmin(t_all, axis=2)
        t = np.take_along_axis(t_all, part[..., None], 2)[..., 0]
        tmin, k = _nearest(t)
        rows = np.arange(len(d))
        pk = part[rows, k]
        hit = o + np.where(np.isfinite(tmin), tmin, 0.0)[:, None] * d
        radial = np.stack([hit[:, 0] - cx[k], hit[:, 1] - cy[k], np.zeros(len(d))], -1)
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
        cap_n = np.zeros((len(d), 3))
        cap_n[:, 2] = np.where(pk == 1, -1.0, 1.0)
        out.append((tmin, np.where((pk == 0)[:, None], radial, cap_n), s.cylinder_reflectivity[lo: lo + step][k]))
    return out


@dataclass
class LidarScan:
    """One revolution, sensor frame. Duplicate returns follow their original; misses kept only on request."""

    points: np.ndarray  # (N, 3) float32, m
    intensity: np.ndarray  # (N,) float32 in [0, 1]; 0 for an emitted miss
    ring: np.ndarray  # (N,) uint16, the beam index
    time: np.ndarray | None = None  # (N,) float32 s since the scan's start, in [0, scan_period); None: unknown

    def __len__(self) -> int:
        return len(self.points)

    def records(self) -> np.ndarray:
        """The revolution as a driver publishes it: (N,) `DRIVER_POINT` records, an emitted miss (0, 0, 0)
        as NaN, time 0 when unknown (`genreg_ros.pointcloud2.array_to_msg` makes a PointCloud2 of them,
        `is_dense` False when misses are kept)."""
        records = np.zeros(len(self), DRIVER_POINT)
        points = self.points.copy()
        points[~points.any(axis=1)] = np.nan
        records["x"], records["y"], records["z"] = points.T
        records["intensity"], records["ring"] = self.intensity, self.ring
        if self.time is not None:
            records["time"] = self.time
        return records


def lidar_scan(scene: Scene, pose_world_sensor: np.ndarray, rng: np.random.Generator,
               sensor: LidarSensor | None = None) -> LidarScan:
    """One revolution of `sensor` (default: 32 uniform beams, 1024 columns) at `pose_world_sensor`
    (T_world_sensor) in `scene`."""
    sensor = sensor or LidarSensor.uniform()
    T = np.asarray(pose_world_sensor, dtype=np.float64)
    d_sensor = sensor.directions()
    t, normal, refl = scene.cast(T[:3, 3], d_sensor @ T[:3, :3].T)
    noisy = t + rng.normal(0.0, sensor.range_noise, size=len(t)) if sensor.range_noise > 0 else t
    hit = np.isfinite(t) & (noisy >= sensor.min_range) & (noisy <= sensor.max_range)
    if sensor.dropout > 0:
        hit &= rng.random(len(t)) >= sensor.dropout
    ring = np.repeat(np.arange(sensor.beams, dtype=np.uint16), sensor.columns)
    cos_incidence = np.abs((normal * (d_sensor @ T[:3, :3].T)).sum(1))
    intensity = np.where(hit, refl * cos_incidence, 0.0)
    points = np.where(hit[:, None], np.where(hit, noisy, 0.0)[:, None] * d_sensor, 0.0)
    emitted = np.ones(len(t), dtype=bool) if sensor.keep_misses else hit
    idx = np.flatnonzero(emitted)
    hits = np.flatnonzero(hit)
    n_dup = round(sensor.duplicate_share * len(hits))
    if n_dup:
        dup = np.sort(rng.choice(hits, size=n_dup, replace=False))
        idx = np.sort(np.concatenate([idx, dup]), kind="stable")  # each copy right after its original
    time = (idx % sensor.columns) / sensor.columns * sensor.scan_period
    return LidarScan(points[idx].astype(np.float32), intensity[idx].astype(np.float32), ring[idx],
                     time.astype(np.float32))


def scan(scene: Scene | str, pose_world_sensor: np.ndarray, rng: np.random.Generator,
         sensor: LidarSensor | None = None) -> LidarScan:
    """`lidar_scan`, with a scene given by name (`make_scene(name)`, seed 0) or as a `Scene`."""
    return lidar_scan(make_scene(scene) if isinstance(scene, str) else scene, pose_world_sensor, rng, sensor)


# ----------------------------------------------------------------------------- scenes
def room_scene(seed: int = 0) -> Scene:
    """An indoor room 10 x 8 x 3 m (x in [-5, 5], y in [-4, 4], z in [0, 3]): floor, ceiling and four walls
    as planes, furniture boxes (tables, shelves, cabinets, a sofa; some turned), two pillars and a column
    of pipes as cylinders. The free space around the centre (|x| < 1.5, |y| < 1.2) is kept clear."""
    rng = np.random.default_rng(seed)
    s = Scene("room")
    s.add_plane((0, 0, 0), (0, 0, 1), 0.4)
    s.add_plane((0, 0, 3.0), (0, 0, -1), 0.7)
    s.add_plane((5.0, 0, 0), (-1, 0, 0), 0.6)
    s.add_plane((-5.0, 0, 0), (1, 0, 0), 0.6)
    s.add_plane((0, 4.0, 0), (0, -1, 0), 0.55)
    s.add_plane((0, -4.0, 0), (0, 1, 0), 0.55)
    # fixed furniture along the walls (distinct sizes so no two walls look alike)
    s.add_box((4.55, -2.5, 1.0), (0.8, 2.0, 2.0), 0.0, 0.3)  # shelf
    s.add_box((-4.6, 1.5, 0.45), (0.7, 1.6, 0.9), 0.0, 0.5)  # cabinet
    s.add_box((1.0, 3.5, 0.4), (2.2, 0.9, 0.8), 0.0, 0.35)  # sofa
    s.add_box((1.0, 3.8, 0.8), (2.2, 0.3, 0.8), 0.0, 0.35)  # its back
    s.add_box((-2.5, -3.6, 1.1), (1.2, 0.6, 2.2), 0.0, 0.45)  # wardrobe
    s.add_box((3.0, 1.9, 0.375), (1.6, 0.8, 0.75), np.deg2rad(25), 0.6)  # desk, turned
    s.add_box((-2.8, 1.0, 0.375), (1.2, 1.2, 0.75), np.deg2rad(-10), 0.6)  # table
    s.add_box((4.7, 2.5, 1.6), (0.5, 1.0, 0.4), 0.0, 0.8)  # wall-mounted box (air conditioner)
    s.add_box((0.0, -3.9, 2.0), (3.0, 0.2, 1.2), 0.0, 0.9)  # whiteboard
    s.add_box((-4.9, -1.0, 1.05), (0.2, 1.0, 2.1), 0.0, 0.2)  # door frame, proud of the wall
    # a few random small boxes (chairs, boxes) outside the free centre
    for _ in range(6):
        while True:
            x, y = rng.uniform(-4.3, 4.3), rng.uniform(-3.3, 3.3)
            if abs(x) > 1.8 or abs(y) > 1.5:
                break
        size = rng.uniform((0.4, 0.4, 0.4), (0.8, 0.8, 1.0))
        s.add_box((x, y, size[2] / 2), tuple(size), rng.uniform(0, np.pi / 2), rng.uniform(0.2, 0.8))
    s.add_cylinder(2.2, -1.6, 0.25, 0.0, 3.0, 0.5)  # pillars
    s.add_cylinder(-1.8, 2.3, 0.3, 0.0, 3.0, 0.5)
    s.add_cylinder(-4.85, -3.85, 0.08, 0.0, 3.0, 0.9)  # a pipe in the corner
    return s


def street_scene(seed: int = 0, length: float = 90.0) -> Scene:
    """A street along x (x in [-length/2, length/2]): the ground plane (z = 0), a kerb on both sides,
    building facades on both sides with varying setbacks (|y| 7-11 m), widths, heights (5-22 m), gaps and
    protrusions (porches, balconies), a building closing the far end (+x), parked cars (some turned), poles,
    trees (trunk + crown cylinders), bins and a bus shelter. The lane |y| < 1.4 is kept clear up to 3 m."""
    rng = np.random.default_rng(seed)
    s = Scene("street")
    half = length / 2
    s.add_plane((0, 0, 0), (0, 0, 1), 0.25)
    for side in (1, -1):
        s.add_box((0.0, side * 4.5, 0.075), (length, 3.0, 0.15), 0.0, 0.35)  # kerb + sidewalk
        x = -half
        while x < half:
            width = rng.uniform(6.0, 16.0)
            gap = rng.uniform(0.0, 4.0) if rng.random() < 0.35 else 0.0
            setback = rng.uniform(7.0, 11.0)
            height = rng.uniform(5.0, 22.0)
            depth = rng.uniform(8.0, 14.0)
            cx = x + gap + width / 2
            s.add_box((cx, side * (setback + depth / 2), height / 2), (width, depth, height), 0.0,
                      rng.uniform(0.3, 0.8))
            if rng.random() < 0.5:  # a porch or shop front
                pw, pd, ph = rng.uniform(1.5, 4.0), rng.uniform(0.6, 1.5), rng.uniform(2.5, 3.5)
                px = cx + rng.uniform(-width / 2 + pw / 2, width / 2 - pw / 2)
                s.add_box((px, side * (setback - pd / 2), ph / 2), (pw, pd, ph), 0.0, rng.uniform(0.3, 0.9))
            if height > 8 and rng.random() < 0.5:  # a balcony row
                s.add_box((cx, side * (setback - 0.6), rng.uniform(4.0, 6.0)), (width * 0.7, 1.2, 0.3), 0.0, 0.6)
            x = cx + width / 2
        # parked cars: 4.5 x 1.8 x 1.5 at |y| 2.4-2.6
        x = -half + rng.uniform(0, 8)
        while x < half - 3:
            if rng.random() < 0.6:
                yaw = rng.normal(0, 0.05) if rng.random() < 0.8 else rng.uniform(0.3, 0.6)
                s.add_box((x, side * (2.4 + rng.uniform(0, 0.2)), 0.75), (4.5, 1.8, 1.5), yaw, rng.uniform(0.3, 0.9))
            x += rng.uniform(5.5, 11.0)
        # poles (street lights, signs) and trees on the sidewalk
        x = -half + rng.uniform(0, 5)
        while x < half:
            y = side * (3.5 + rng.uniform(0.3, 2.0))
            if rng.random() < 0.5:
                s.add_cylinder(x, y, rng.uniform(0.06, 0.15), 0.0, rng.uniform(3.0, 8.0), 0.9)
            else:
                s.add_cylinder(x, y, rng.uniform(0.15, 0.3), 0.0, 3.0, 0.3)  # trunk
                s.add_cylinder(x, y, rng.uniform(1.0, 2.0), 3.0, rng.uniform(5.0, 8.0), 0.2)  # crown
            x += rng.uniform(4.0, 12.0)
        for _ in range(3):  # bins, boxes, benches
            s.add_box((rng.uniform(-half, half), side * rng.uniform(3.4, 5.8), 0.5),
                      tuple(rng.uniform((0.5, 0.5, 0.6), (1.5, 1.0, 1.2))), rng.uniform(0, np.pi), rng.uniform(0.3, 0.8))
    s.add_box((-8.0, 5.5, 1.25), (3.5, 1.2, 2.5), 0.0, 0.7)  # bus shelter
    s.add_box((half + 6.0, 0.0, 9.0), (12.0, 40.0, 18.0), 0.0, 0.5)  # the building closing the far end
    return s


def make_scene(name: str, seed: int = 0) -> Scene:
    """A scene by name: "room" (`room_scene`) or "street" (`street_scene`)."""
    if name == "room":
        return room_scene(seed)
    if name == "street":
        return street_scene(seed)
    raise ValueError(f"unknown scene {name!r}; one of {SCENES}")


# ----------------------------------------------------------------------------- poses and pairs
def sensor_pose(x: float, y: float, z: float, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0
                ) -> np.ndarray:
    """T_world_sensor at (x, y, z) m, turned by yaw, pitch, roll rad (intrinsic z-y-x)."""
    return make_transform(Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix(), np.array([x, y, z]))


def default_sensor(scene: str) -> LidarSensor:
    """The sensor of the tests and benchmarks: 32 beams, 1024 columns; indoors -25..+15 deg and 30 m,
    outdoors VLP-32-like and 100 m."""
    return LidarSensor.uniform(32, (-25.0, 15.0), 1024, max_range=30.0) if scene == "room" else \
        LidarSensor.vlp32(1024, max_range=100.0)


def random_sensor_pose(scene: str, rng: np.random.Generator) -> np.ndarray:
    """A T_world_sensor in the scene's free space: indoors 1.0-1.5 m high near the room's centre,
    outdoors 1.7-2.0 m high (a car roof) on the carriageway, heading along it."""
    if scene == "room":
        return sensor_pose(rng.uniform(-1.0, 1.0), rng.uniform(-0.7, 0.7), rng.uniform(1.0, 1.5),
                           rng.uniform(-np.pi, np.pi))
    return sensor_pose(rng.uniform(-25.0, 25.0), rng.uniform(-1.0, 1.0), rng.uniform(1.7, 2.0),
                       rng.normal(0.0, 0.1) + (np.pi if rng.random() < 0.5 else 0.0))


def nearby_pose(T_world_sensor: np.ndarray, rng: np.random.Generator, distance: tuple[float, float] = (0.5, 1.0),
                max_yaw_deg: float = 10.0) -> np.ndarray:
    """A second sensor pose `distance` m away horizontally (uniform in the range, random heading), yawed by
    up to `max_yaw_deg` and raised or lowered by up to 5 cm: the next scan of a moving robot."""
    heading = rng.uniform(-np.pi, np.pi)
    step = rng.uniform(*distance) * np.array([np.cos(heading), np.sin(heading), 0.0]) + [0, 0, rng.uniform(-0.05, 0.05)]
    R = Rotation.from_euler("z", rng.uniform(-max_yaw_deg, max_yaw_deg), degrees=True).as_matrix()
    return make_transform(T_world_sensor[:3, :3] @ R, T_world_sensor[:3, 3] + step)


def kidnap(rng: np.random.Generator, center: np.ndarray, max_angle_deg: float = 45.0, max_translation: float = 2.0,
           yaw_share: float = 0.75) -> np.ndarray:
    """A 4x4 motion x -> R (x - center) + center + t: an angle uniform in [0, max_angle_deg] about, with
    probability `yaw_share`, an axis within about 10 deg of z (yaw), else a uniformly random axis; t of random
    direction and length uniform in [0, max_translation] m."""
    axis = rng.normal(size=3)
    if rng.random() < yaw_share:
        axis = np.array([0.0, 0.0, 1.0 if axis[2] >= 0 else -1.0]) + 0.1 * rng.normal(size=3)
    angle = np.deg2rad(rng.uniform(0.0, max_angle_deg))
    R = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
    direction = rng.normal(size=3)
    t = rng.uniform(0.0, max_translation) * direction / np.linalg.norm(direction)
    return make_transform(R, center - R @ center + t)


@dataclass
class ScanPair:
    """A registration pair: `source` (kidnapped) and `target` scans and the truth `T_target_source`
    (target_from_source: target ~ T source), plus the poses that made them."""

    source: LidarScan
    target: LidarScan
    T_target_source: np.ndarray
    pose_source: np.ndarray  # T_world_sensor of the source scan (before the kidnap)
    pose_target: np.ndarray
    kidnap: np.ndarray  # the motion applied to the source points in its sensor frame


def scan_pair(scene: Scene, rng: np.random.Generator, sensor: LidarSensor | None = None,
              max_angle_deg: float = 45.0, max_translation: float = 2.0) -> ScanPair:
    """Two scans from sensor poses 0.5-1 m apart (`random_sensor_pose`, `nearby_pose`); the source points are
    moved by a `kidnap` about their centroid. T_target_source = T_target_world T_world_source K^-1."""
    sensor = sensor or default_sensor(scene.name)
    pose_t = random_sensor_pose(scene.name, rng)
    pose_s = nearby_pose(pose_t, rng)
    target = lidar_scan(scene, pose_t, rng, sensor)
    source = lidar_scan(scene, pose_s, rng, sensor)
    K = kidnap(rng, source.points.astype(np.float64).mean(0), max_angle_deg, max_translation)
    moved = source.points.astype(np.float64) @ K[:3, :3].T + K[:3, 3]
    source = LidarScan(moved.astype(np.float32), source.intensity, source.ring, source.time)
    truth = np.linalg.inv(pose_t) @ pose_s @ np.linalg.inv(K)
    return ScanPair(source, target, truth, pose_s, pose_t, K)
