"""The campus world and its maps (genreg_core.data.lidar_world) against truths written out here.

Signed distance functions of planes, boxes and capped vertical cylinders are written in this file, not taken
from the generator; culled scans are compared with `lidar_scan` of the whole scene (the plain caster); the
voxel map with `genreg_core.preprocess.voxel_downsample` of all scans at once; times with the azimuth of
each point. Small worlds (1 x 1 blocks) and small sensors keep the file fast."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from genreg_core.data.lidar_world import (
    SURVEY_SENSOR,
    World,
    build_map,
    campus_world,
    culled_scan,
    map_path,
    merge_scenes,
    movers,
    scene_near,
    survey_poses,
    test_poses,
    world_scan,
)
from genreg_core.data.synthetic_lidar import LidarScan, LidarSensor, Scene, lidar_scan, sensor_pose
from genreg_core.preprocess import voxel_downsample

SMALL = LidarSensor.uniform(16, (-25.0, 15.0), 512, max_range=40.0)  # culls most of a 1 x 1 world


@pytest.fixture(scope="module")
def world() -> World:
    return campus_world(0, (1, 1))


# ----------------------------------------------------------------------------- truths
def plane_sdf(s: Scene, p: np.ndarray) -> np.ndarray:
    """(N, P) signed distance of points (N, 3) to each plane (positive on the normal's side)."""
    return np.einsum("npk,pk->np", p[:, None, :] - s.plane_points[None], s.plane_normals)


def box_sdf(s: Scene, p: np.ndarray) -> np.ndarray:
    """(N, B) signed distance to each oriented box (negative inside)."""
    out = np.empty((len(p), len(s.box_yaw)))
    for i, (c, h, yaw) in enumerate(zip(s.box_centers, s.box_half, s.box_yaw)):
        r = p - c
        local = np.stack([np.cos(yaw) * r[:, 0] + np.sin(yaw) * r[:, 1],
                          -np.sin(yaw) * r[:, 0] + np.cos(yaw) * r[:, 1], r[:, 2]], 1)
        q = np.abs(local) - h
        out[:, i] = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)
    return out


def cylinder_sdf(s: Scene, p: np.ndarray) -> np.ndarray:
    """(N, C) signed distance to each capped vertical cylinder (negative inside)."""
    out = np.empty((len(p), len(s.cylinders)))
    for i, (x, y, r, z0, z1) in enumerate(s.cylinders):
        q = np.stack([np.hypot(p[:, 0] - x, p[:, 1] - y) - r, np.maximum(z0 - p[:, 2], p[:, 2] - z1)], 1)
        out[:, i] = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)
    return out


def near_sdf(s: Scene, p: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Per point (N, 3): the smallest |sdf| over all primitives (the distance to the nearest surface) and the
    signed distance to the union of the boxes and cylinders, both exact wherever below `reach` (primitives
    farther than that from a point, by their bounding spheres, are skipped)."""
    unsigned = np.abs(plane_sdf(s, p)).min(1, initial=np.inf)
    signed = np.full(len(p), np.inf)
    tree = cKDTree(p)
    radii = np.concatenate([np.linalg.norm(s.box_half, axis=1),
                            np.hypot(s.cylinders[:, 2], (s.cylinders[:, 4] - s.cylinders[:, 3]) / 2)])
    centres = np.concatenate([s.box_centers, np.column_stack([s.cylinders[:, :2], s.cylinders[:, 3:5].mean(1)])])
    nb = len(s.box_yaw)
    for i, (c, r) in enumerate(zip(centres, radii)):
        idx = np.asarray(tree.query_ball_point(c, r + reach), dtype=int)
        if not len(idx):
            continue
        if i < nb:
            one = Scene(box_centers=s.box_centers[i:i + 1], box_half=s.box_half[i:i + 1], box_yaw=s.box_yaw[i:i + 1])
            d = box_sdf(one, p[idx])[:, 0]
        else:
            d = cylinder_sdf(Scene(cylinders=s.cylinders[i - nb:i - nb + 1]), p[idx])[:, 0]
        unsigned[idx] = np.minimum(unsigned[idx], np.abs(d))
        signed[idx] = np.minimum(signed[idx], d)
    return unsigned, signed


def solids_sdf(s: Scene, p: np.ndarray) -> np.ndarray:
    """(N,) signed distance to the union of the boxes and cylinders (inf with none)."""
    parts = [box_sdf(s, p), cylinder_sdf(s, p)]
    return np.min(np.concatenate(parts, 1), axis=1, initial=np.inf)


def surface_distance(s: Scene, p: np.ndarray) -> np.ndarray:
    """(N,) distance to the nearest primitive surface: min over primitives of |sdf|."""
    parts = [np.abs(plane_sdf(s, p)), np.abs(box_sdf(s, p)), np.abs(cylinder_sdf(s, p))]
    return np.min(np.concatenate(parts, 1), axis=1)


def to_world(scan: LidarScan, T: np.ndarray) -> np.ndarray:
    return scan.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]


def same(a: LidarScan, b: LidarScan) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("points", "intensity", "ring", "time"))


def segments(lines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    a = np.concatenate([line[:-1] for line in lines])
    return a, np.concatenate([line[1:] for line in lines]) - a


def segment_distances(xy: np.ndarray, lines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(N, S) the distance from each point (N, 2) to each segment of the polylines; (S, 2) their directions."""
    a, ab = segments(lines)
    f = np.clip(np.einsum("nsk,sk->ns", xy[:, None] - a[None], ab) / (ab * ab).sum(1), 0.0, 1.0)
    d = np.linalg.norm(xy[:, None] - (a[None] + f[..., None] * ab[None]), axis=2)
    return d, ab / np.linalg.norm(ab, axis=1, keepdims=True)


def heading_along(T: np.ndarray, lines: list[np.ndarray], near: float, max_angle: float) -> np.ndarray:
    """(N,) whether each pose lies within `near` m of a segment and heads along it (forwards) within
    `max_angle` rad."""
    d, u = segment_distances(T[:, :2, 3], lines)
    cos = T[:, :2, 0] @ u.T  # (N, S)
    return ((d <= near) & (cos > np.cos(max_angle))).any(1)


# ----------------------------------------------------------------------------- the world
def test_world_sizes_and_parts() -> None:
    big = campus_world(0, (4, 3))
    assert big.area_m2 >= 50_000
    xmin, xmax, ymin, ymax = big.bounds
    assert big.area_m2 == pytest.approx((xmax - xmin) * (ymax - ymin))
    areas = [campus_world(0, b).area_m2 for b in ((1, 1), (2, 1), (2, 2), (4, 3))]
    assert areas == sorted(areas) and areas[0] > 5_000
    assert len(big.roads) == 5 + 4 + 1  # the street grid and the park's footpath
    assert len(big.indoor) == 3
    assert len(big.scene.box_yaw) + len(big.scene.cylinders) > 1000
    for line in big.roads + big.indoor:  # every centre-line inside the bounds
        assert (line[:, 0] > xmin).all() and (line[:, 0] < xmax).all()
        assert (line[:, 1] > ymin).all() and (line[:, 1] < ymax).all()
    again = campus_world(0, (4, 3))
    np.testing.assert_array_equal(again.scene.box_centers, big.scene.box_centers)
    assert not np.array_equal(campus_world(1, (4, 3)).scene.box_centers[:50], big.scene.box_centers[:50])


@pytest.mark.parametrize("seed", [0, 3])
def test_along_the_terraced_street_a_scan_repeats_every_period(seed: int) -> None:
    w = campus_world(seed, (2, 2))
    assert w.terrace is not None and w.terrace[0, 1] == w.terrace[1, 1]
    P, y = w.terrace_period, w.terrace[0, 1]
    reach = 14.0
    exact = LidarSensor.uniform(16, (-15.0, 15.0), 720, max_range=reach, range_noise=0.0, duplicate_share=0.0,
                                keep_misses=True)
    # the longest row of houses on the block side (7 x 10 x 8.5 m boxes south of the street), and a stretch
    # of street a sensor's reach inside both of its ends
    s = w.scene
    house = (np.abs(2 * s.box_half - (P, 10.0, 8.5)).max(1) < 1e-9) & (s.box_centers[:, 1] < y)
    xs = np.sort(s.box_centers[house, 0])
    rows = np.split(xs, np.flatnonzero(np.diff(xs) > P + 1e-6) + 1)
    row = max(rows, key=len)
    x0 = row[0] - P / 2 + reach + 0.5
    assert row[-1] + P / 2 - reach - 0.5 - x0 > P
    rng = np.random.default_rng(0)

    def look(x: float) -> np.ndarray:
        return culled_scan(s, sensor_pose(x, y, 1.8, 0.0), rng, exact).points

    here = look(x0)
    hit = np.linalg.norm(here, axis=1) > 0
    far = here[hit & (np.abs(here[:, 1]) > 5.0) & (here[:, 2] > 0.5)]  # facades, not the street
    assert (far[:, 1] > 0).sum() > 500 and (far[:, 1] < 0).sum() > 500  # houses on both sides
    np.testing.assert_allclose(look(x0 + P), here, atol=1e-4)  # the same scan one period along
    half = np.linalg.norm(look(x0 + P / 2) - here, axis=1)
    assert (half > 0.1).mean() > 0.1  # but not half a period along


# ----------------------------------------------------------------------------- scans
@pytest.mark.parametrize("where", ["roads", "indoor"])
def test_culled_scans_equal_the_full_scene_scan_bit_for_bit(world: World, where: str) -> None:
    tiny = LidarSensor.uniform(8, (-15.0, 15.0), 360, max_range=25.0, keep_misses=True, dropout=0.1)
    sensors = (SMALL, SURVEY_SENSOR) if where == "roads" else (SMALL, tiny)
    for T, sensor in zip(test_poses(world, 2, np.random.default_rng(11), where=where), sensors):
        extra = movers(world, T, np.random.default_rng(1), 4)
        scene = merge_scenes("campus", world.scene, extra)
        if sensor.max_range < 50:
            assert len(scene_near(scene, T[:3, 3], 40.0).box_yaw) < len(scene.box_yaw)  # culling removes some
        full = lidar_scan(scene, T, np.random.default_rng(5), sensor)  # every ray against every primitive
        assert len(full) > 1000
        assert same(culled_scan(scene, T, np.random.default_rng(5), sensor), full)
        assert same(culled_scan(scene, T, np.random.default_rng(5), sensor, sectors=7), full)
        if sensor is SURVEY_SENSOR:
            continue
        got = world_scan(world, T, np.random.default_rng(9), sensor, moving=4)
        rng9 = np.random.default_rng(9)
        extra9 = movers(world, T, rng9, 4)  # world_scan draws the movers first, then the scan
        assert same(got, lidar_scan(merge_scenes("campus", world.scene, extra9), T, rng9, sensor))


def test_world_scan_points_lie_on_surfaces_and_indoors_the_corridors_are_enclosed(world: World) -> None:
    sensor = LidarSensor.uniform(16, (-25.0, 25.0), 512, max_range=100.0, keep_misses=True, duplicate_share=0.0)
    cross = world.indoor[1]  # a cross corridor, a fifth of the way along: out of sight of the entrance
    x, y = cross[0] + 0.2 * (cross[1] - cross[0])
    T = sensor_pose(x, y, 0.6, 0.4)
    scan = world_scan(world, T, np.random.default_rng(3), sensor, moving=0)
    hit = np.linalg.norm(scan.points, axis=1) > 0
    assert hit.all()  # walls, floor and ceiling all round
    p = to_world(scan, T)[hit]
    assert (surface_distance(world.scene, p) < 5 * sensor.range_noise).all()
    assert p[:, 2].max() < 3.0 + 5 * sensor.range_noise  # nothing beyond the ceiling, 3 m up
    assert (np.abs(p[:, 2] - 3.0) < 5 * sensor.range_noise).sum() > 100


def test_time_runs_with_the_azimuth_and_duplicates_keep_it(world: World) -> None:
    sensor = LidarSensor.vlp32(1024, max_range=100.0, scan_period=0.1, duplicate_share=0.05)
    T = test_poses(world, 1, np.random.default_rng(4))[0]
    scan = world_scan(world, T, np.random.default_rng(4), sensor)
    assert scan.time is not None and scan.time.dtype == np.float32 and len(scan.time) == len(scan)
    assert (scan.time >= 0).all() and (scan.time < sensor.scan_period).all()
    for ring in np.unique(scan.ring):
        assert (np.diff(scan.time[scan.ring == ring]) >= 0).all()
    az = np.mod(np.arctan2(scan.points[:, 1], scan.points[:, 0]), 2 * np.pi)  # the column from the point itself
    column = np.mod(np.round(az / (2 * np.pi / sensor.columns)), sensor.columns)
    np.testing.assert_allclose(scan.time, column / sensor.columns * sensor.scan_period, atol=1e-6)
    twin = np.flatnonzero((np.diff(scan.points, axis=0) == 0).all(1))  # a duplicate right after its original
    assert len(twin) > 0.03 * len(scan)
    np.testing.assert_array_equal(scan.time[twin], scan.time[twin + 1])


def test_dropout_turns_a_share_of_the_rays_into_misses() -> None:
    wall = Scene("wall")
    wall.add_plane((5.0, 0.0, 0.0), (-1.0, 0.0, 0.0), 0.8)
    base: dict = {"max_range": 50.0, "keep_misses": True, "duplicate_share": 0.0}
    full = lidar_scan(wall, np.eye(4), np.random.default_rng(0), LidarSensor.uniform(32, columns=1024, **base))
    same_default = lidar_scan(wall, np.eye(4), np.random.default_rng(0),
                              LidarSensor.uniform(32, columns=1024, dropout=0.0, **base))
    assert same(full, same_default)
    dropped = lidar_scan(wall, np.eye(4), np.random.default_rng(0),
                         LidarSensor.uniform(32, columns=1024, dropout=0.3, **base))
    was, now = np.linalg.norm(full.points, axis=1) > 0, np.linalg.norm(dropped.points, axis=1) > 0
    assert not (now & ~was).any()
    assert now.sum() / was.sum() == pytest.approx(0.7, abs=0.02)
    np.testing.assert_array_equal(dropped.points[now], full.points[now])  # the same noise draw for the rest
    with pytest.raises(ValueError):
        LidarSensor.uniform(32, dropout=1.5)
    assert LidarSensor.os128().beams == 128 and LidarSensor.os128().elevations_deg[0] == -22.5


# ----------------------------------------------------------------------------- poses
def test_survey_poses_lie_on_the_centre_lines_in_free_space_heading_along(world: World) -> None:
    for rng in (None, np.random.default_rng(0)):
        P = survey_poses(world, spacing=3.0, rng=rng)
        out, ind = survey_poses(world, 3.0, indoor=False, rng=rng), survey_poses(world, 3.0, rng=rng)[-5:]
        assert len(P) > len(out) > 50 and len(P) - len(out) > 10
        road_len = sum(np.linalg.norm(np.diff(line, axis=0), axis=1).sum() for line in world.roads)
        assert len(out) == pytest.approx(road_len / 3.0, abs=len(world.roads) + 1)
        np.testing.assert_allclose(out[:, 2, 3], 1.8)
        np.testing.assert_allclose(ind[:, 2, 3], 0.6)
        xy = P[:, :2, 3]
        assert heading_along(out, world.roads, 0.1 + 1e-9, 0.05 + 1e-9).all()  # up to 0.1 m, 0.05 rad jitter
        assert heading_along(ind, world.indoor, 0.1 + 1e-9, 0.05 + 1e-9).all()
        if rng is None:
            assert heading_along(out, world.roads, 1e-9, 1e-6).all()  # exactly on the lines
        np.testing.assert_allclose(P[:, 2, :3], np.tile([0.0, 0.0, 1.0], (len(P), 1)), atol=1e-12)  # level
        assert (solids_sdf(world.scene, P[:, :3, 3]) > 0.5).all()  # in free space
        assert len(np.unique(np.round(xy, 3), axis=0)) > 0.9 * len(xy)


def test_corridors_can_be_surveyed_more_densely_than_roads(world: World) -> None:
    coarse, dense = survey_poses(world, 3.0), survey_poses(world, 3.0, indoor_spacing=1.0)
    roads = survey_poses(world, 3.0, indoor=False)
    np.testing.assert_array_equal(dense[:len(roads)], roads)  # the roads' survey unchanged
    indoor = dense[len(roads):]
    np.testing.assert_allclose(indoor[:, 2, 3], 0.6)
    assert heading_along(indoor, world.indoor, 1e-9, 1e-6).all()
    corridor_len = sum(np.linalg.norm(np.diff(line, axis=0), axis=1).sum() for line in world.indoor)
    assert len(indoor) == pytest.approx(corridor_len / 1.0, abs=len(world.indoor) + 1)
    assert len(coarse) - len(roads) == pytest.approx(corridor_len / 3.0, abs=len(world.indoor) + 1)
    for line in world.indoor:  # consecutive poses along each corridor 1 m apart
        on = indoor[heading_along(indoor, [line], 1e-9, 1e-6)]
        steps = np.linalg.norm(np.diff(on[:, :2, 3], axis=0), axis=1)
        assert np.isclose(steps, 1.0).mean() > 0.9
    np.testing.assert_array_equal(survey_poses(world, 3.0, indoor_spacing=3.0), coarse)
    with pytest.raises(ValueError):
        survey_poses(world, 3.0, indoor_spacing=0.0)


@pytest.mark.parametrize("where", ["roads", "indoor"])
def test_held_out_poses_are_free_and_never_survey_poses(world: World, where: str) -> None:
    T = test_poses(world, 200, np.random.default_rng(1), where=where)
    again = test_poses(world, 200, np.random.default_rng(1), where=where)
    np.testing.assert_array_equal(T, again)
    lines = world.roads if where == "roads" else world.indoor
    d, _ = segment_distances(T[:, :2, 3], lines)
    assert (d.min(1) <= (2.0 if where == "roads" else 1.1) + 1e-9).all()
    for rng in (None, np.random.default_rng(2)):
        for spacing in (1.0, 3.0):
            S = survey_poses(world, spacing, rng=rng)
            nearest, _ = cKDTree(S[:, :2, 3]).query(T[:, :2, 3])
            assert nearest.min() >= 0.5
    assert (solids_sdf(world.scene, T[:, :3, 3]) > 0.05).all()
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    assert np.histogram(yaw, bins=4, range=(-np.pi, np.pi))[0].min() > 25  # headings anywhere
    np.testing.assert_allclose(T[:, 2, 3], 1.8)


# ----------------------------------------------------------------------------- maps and movers
@pytest.fixture(scope="module")
def small_map(world: World) -> tuple[np.ndarray, list[np.ndarray]]:
    """The map of every 4th survey pose with `SMALL`, and the scans that made it (world frame)."""
    poses = survey_poses(world, 3.0)[::4]
    cloud = build_map(world, poses, SMALL, voxel=0.1, seed=0, progress=False)
    rng = np.random.default_rng(0)
    scans = [to_world(culled_scan(world.scene, T, rng, SMALL), T) for T in poses]
    return cloud, scans


def test_the_map_lies_on_the_surfaces_and_is_the_voxelised_scans(
        world: World, small_map: tuple[np.ndarray, list[np.ndarray]]) -> None:
    cloud, scans = small_map
    assert cloud.dtype == np.float32 and cloud.shape[1] == 3 and len(cloud) > 100_000
    tol = 3 * SMALL.range_noise + 0.1
    p = cloud.astype(np.float64)
    unsigned, signed = near_sdf(world.scene, p, 1.0)
    assert (unsigned < tol).all()  # on a surface
    assert (signed > -tol).all()  # not deep inside a solid
    assert (p[:, 2] > -tol).all()  # nor under the ground
    xmin, xmax, ymin, ymax = np.array(world.bounds) + np.array([-1, 1, -1, 1]) * 5 * SMALL.range_noise
    assert ((p[:, 0] > xmin) & (p[:, 0] < xmax) & (p[:, 1] > ymin) & (p[:, 1] < ymax)).all()  # no ray gets out
    expected = voxel_downsample(np.concatenate(scans), 0.1)  # the whole survey voxelised at once
    assert len(expected) == len(cloud)
    d, _ = cKDTree(expected).query(p)
    assert d.max() < 1e-5
    d, _ = cKDTree(p).query(expected)
    assert d.max() < 1e-5
    keys = np.floor(cloud.astype(np.float64) / 0.1)
    assert len(np.unique(keys, axis=0)) >= 0.999 * len(cloud)  # one point per voxel


def test_movers_are_in_the_scan_and_not_in_the_map(world: World,
                                                    small_map: tuple[np.ndarray, list[np.ndarray]]) -> None:
    cloud, _ = small_map
    map_tree = cKDTree(cloud)
    seen = 0
    for k, T in enumerate(test_poses(world, 4, np.random.default_rng(8))):
        extra = movers(world, T, np.random.default_rng(k), 6)
        assert len(extra.box_yaw) >= 3
        dist = np.hypot(*(extra.box_centers[:, :2] - T[:2, 3]).T)
        assert (dist >= 5.0).all() and (dist <= 30.0).all()
        sizes = np.round(2 * extra.box_half, 6).tolist()
        assert all(s in ([4.5, 1.8, 1.5], [0.5, 0.5, 1.8]) for s in sizes)
        np.testing.assert_allclose(extra.box_centers[:, 2], extra.box_half[:, 2])  # standing on the ground
        local = extra.box_half[:, None, :] * np.array(
            [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-0.6, 0.0, 1.0)])[None]  # (M, 12, 3)
        c, sn = np.cos(extra.box_yaw)[:, None], np.sin(extra.box_yaw)[:, None]
        corners = extra.box_centers[:, None, :] + np.stack(
            [c * local[..., 0] - sn * local[..., 1], sn * local[..., 0] + c * local[..., 1], local[..., 2]], -1)
        static = world.scene
        assert (solids_sdf(static, corners.reshape(-1, 3)) > 0.0).all()  # clear of every static solid
        scan = world_scan(world, T, np.random.default_rng(k), SURVEY_SENSOR, moving=6)
        p = to_world(scan, T)
        on_mover = (np.abs(box_sdf(extra, p)).min(1) < 0.06) & (near_sdf(static, p, 0.6)[0] > 0.5)
        seen += on_mover.sum()
        if on_mover.any():
            assert map_tree.query(p[on_mover])[0].min() > 0.3  # the map never saw them
        inside = (box_sdf(extra, cloud.astype(np.float64)) < -0.05).any(1) & (cloud[:, 2] > 0.3)
        assert not inside.any()
    assert seen > 200


def test_cached_map_paths_name_the_world_and_the_survey(world: World, tmp_path: Path) -> None:
    a = map_path(world, 3.0, 0.1, tmp_path)
    assert a != map_path(world, 2.0, 0.1, tmp_path) != map_path(world, 3.0, 0.2, tmp_path)
    assert a != map_path(world, 3.0, 0.1, tmp_path, LidarSensor.hdl64())
    assert a != map_path(campus_world(1, (1, 1)), 3.0, 0.1, tmp_path)
    assert a != map_path(campus_world(0, (2, 1)), 3.0, 0.1, tmp_path)
    assert a.parent == tmp_path and a.suffix == ".npy"
    assert map_path(world, 3.0, 0.1, tmp_path, indoor_spacing=3.0) == a  # the default survey keeps its name
    assert map_path(world, 3.0, 0.1, tmp_path, indoor_spacing=1.0) not in (a, map_path(world, 1.0, 0.1, tmp_path))


def test_sensor_pose_defaults_keep_old_scans_identical() -> None:
    """New sensor fields at their defaults leave scans as they were: the same draws, the same points."""
    s = Scene("ground")
    s.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.5)
    old = LidarSensor(tuple(np.linspace(-25.0, 15.0, 32).tolist()), 1024, 100.0, 0.3, 0.015, 0.04, False)
    a = lidar_scan(s, sensor_pose(1.0, 2.0, 1.8, 0.3), np.random.default_rng(0), old)
    b = lidar_scan(s, sensor_pose(1.0, 2.0, 1.8, 0.3), np.random.default_rng(0), LidarSensor.uniform(32))
    assert same(a, b)
