"""The place index (genreg_core.place_index) and MapLocalizer's global localisation with it, against
independent truths: brute-force reference code for the FFT shift search and the descriptors, the sensor
poses that made synthetic LiDAR scans, and the period of a street whose facades repeat exactly (every
position along it one period apart looks the same: no pose may be confident there)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from genreg_core import refine, score
from genreg_core.config import LocalizationConfig
from genreg_core.data.synthetic_lidar import LidarSensor, Scene, lidar_scan, sensor_pose, street_scene
from genreg_core.errors import TooFewPointsError
from genreg_core.geometry import apply_transform
from genreg_core.localization import MapLocalizer
from genreg_core.metrics import transform_errors
from genreg_core.place_index import (
    IndexGeometry,
    PlaceIndex,
    Stencil,
    describe,
    height_image,
    shift_distances,
    smallest,
    spectra,
)
from genreg_core.preprocess import voxel_downsample
from genreg_core.score import TargetIndex

SENSOR = LidarSensor.uniform(16, (-25.0, 15.0), 720, max_range=60.0)
PLACED_RE_DEG, PLACED_TE_M = 2.0, 0.25  # a LiDAR scan is placed within these


def fused_map(scene: Scene, xs: np.ndarray, voxel: float = 0.15) -> np.ndarray:
    """Scans along the line y = 0 at 1.8 m (heading +x), moved into the world by their poses, voxelised."""
    rng = np.random.default_rng(0)
    parts = []
    for x in xs:
        T = sensor_pose(float(x), 0.0, 1.8)
        parts.append(apply_transform(T, lidar_scan(scene, T, rng, SENSOR).points.astype(np.float64)))
    return voxel_downsample(np.concatenate(parts), voxel)


@pytest.fixture(scope="module")
def street() -> tuple[Scene, np.ndarray]:
    scene = street_scene(3, length=160.0)
    return scene, fused_map(scene, np.arange(-70.0, 70.1, 4.0))


def terrace() -> Scene:
    """A straight street 360 m long with identical houses every 12 m on both sides: along x, the world
    repeats with a period of 12 m (the sensor's 60 m range never sees an end)."""
    s = Scene("terrace")
    s.add_plane((0, 0, 0), (0, 0, 1), 0.3)
    for x in np.arange(-180.0, 180.1, 12.0):
        for side in (1, -1):
            s.add_box((x, side * 12.0, 4.0), (9.0, 6.0, 8.0), 0.0, 0.6)  # a house
            s.add_box((x - 3.0, side * 8.6, 1.0), (1.5, 0.8, 2.0), 0.0, 0.8)  # its porch
        s.add_cylinder(x + 4.0, 6.5, 0.15, 0.0, 5.0, 0.9)  # a lamp post
    return s


def test_fft_shift_distances_equal_the_brute_force_scan_context_distance() -> None:
    rng = np.random.default_rng(1)
    rings, sectors = 7, 24
    query = rng.random((rings, sectors)) * (rng.random((rings, sectors)) < 0.6)
    candidates = rng.random((5, rings, sectors)) * (rng.random((5, rings, sectors)) < 0.6)
    got = shift_distances(spectra(query[None]), spectra(candidates), sectors)

    def cosine(a: np.ndarray, b: np.ndarray) -> float:
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        return 0.0 if na == 0 or nb == 0 else float(a @ b / (na * nb))

    for k in range(5):
        for s in range(sectors):
            # candidate sector j + s against the query's sector j
            expected = 1.0 - np.mean([cosine(query[:, j], candidates[k, :, (j + s) % sectors]) for j in range(sectors)])
            assert got[k, s] == pytest.approx(expected, abs=1e-5)


@given(st.lists(st.integers(0, 6), min_size=1, max_size=60), st.integers(1, 70))
def test_the_smallest_values_are_those_a_stable_sort_puts_first(values: list[int], count: int) -> None:
    # few distinct values: ties at the boundary, broken by index as a stable sort breaks them
    array = np.asarray(values, dtype=np.float64)
    np.testing.assert_array_equal(smallest(array, count), np.argsort(array, kind="stable")[:count])


def test_descriptor_bins_hold_the_highest_point_of_each_polar_bin_and_nothing_behind_a_wall() -> None:
    g = IndexGeometry(radius=10.0, rings=5, sectors=8, band=2.0, cell=0.25, ground_cells=3)
    rng = np.random.default_rng(2)
    ground = np.column_stack([rng.uniform(-12, 12, (40_000, 2)), np.zeros(40_000)])  # flat ground at z = 0
    # one post of known height in each of a few bins, well inside them (away from bin edges)
    posts = []
    # 2.6 and 2.5: above the band (walls); the 1.0 post stands behind the 2.5 one in its sector
    for ring, sector, height in [(1, 0, 0.7), (3, 2, 1.5), (4, 5, 1.9), (2, 7, 2.6), (1, 3, 2.5), (3, 3, 1.0)]:
        r = (ring + 0.5) * g.radius / g.rings
        a = -np.pi + (sector + 0.5) * 2 * np.pi / g.sectors
        z = np.linspace(0.0, height, 30)
        posts.append(np.column_stack([np.full(30, r * np.cos(a)), np.full(30, r * np.sin(a)), z]))
    cloud = np.vstack([ground, *posts])
    raster = height_image(cloud, g, margin=g.radius)
    got = describe(raster, raster.cells(np.zeros((1, 2))), Stencil(g), g.band)[0]
    expected = np.zeros((g.rings, g.sectors))
    expected[1, 0], expected[3, 2], expected[4, 5] = 0.7, 1.5, 1.9
    expected[2, 7] = max(z for z in np.linspace(0.0, 2.6, 30) if z <= 2.0)  # its highest point within the band
    expected[1, 3] = max(z for z in np.linspace(0.0, 2.5, 30) if z <= 2.0)  # a wall: (3, 3) behind it stays 0
    np.testing.assert_allclose(got, expected, atol=1e-5)


def test_retrieval_finds_the_place_and_heading_of_held_out_scans(street: tuple[Scene, np.ndarray]) -> None:
    scene, map_xyz = street
    index = PlaceIndex.build(map_xyz, IndexGeometry())
    rng = np.random.default_rng(3)
    found = 0
    for _ in range(10):
        x, y, yaw = rng.uniform(-55, 55), rng.uniform(-1.5, 1.5), rng.uniform(-np.pi, np.pi)
        scan = lidar_scan(scene, sensor_pose(x, y, 1.8, yaw), rng, SENSOR).points.astype(np.float64)
        hits = index.retrieve(scan, 8)
        turned = [abs(np.angle(np.exp(1j * (h.yaw - yaw)))) for h in hits]
        near = [np.hypot(h.centre[0] - x, h.centre[1] - y) for h in hits]
        found += any(d <= 1.5 and a <= np.radians(9.0) for d, a in zip(near, turned, strict=True))
        assert all(abs(h.centre[2] - 1.8) < 0.3 for h in hits[:1])  # the sensor's height above the ground
    assert found >= 8


def test_retrieval_is_the_same_in_chunks_and_its_best_hit_is_the_best_place_and_shift(street: tuple[Scene, np.ndarray]
                                                                                      ) -> None:
    scene, map_xyz = street
    index = PlaceIndex.build(map_xyz, IndexGeometry())
    scan = lidar_scan(scene, sensor_pose(12.0, 0.5, 1.8, 0.7), np.random.default_rng(5), SENSOR).points
    hits = index.retrieve(scan.astype(np.float64), 12)
    chunked = index.retrieve(scan.astype(np.float64), 12, chunk=5)  # chunks of 5 places: many boundaries
    assert [(tuple(h.centre), h.yaw, h.distance) for h in hits] == [(tuple(h.centre), h.yaw, h.distance) for h in chunked]
    # the best hit is the smallest distance of every place at every shift, worked out on all places at once
    query, _ = index.describe_scan(scan.astype(np.float64))
    every = shift_distances(spectra(query[None]), index.spectra, index.geometry.sectors)
    place, shift = np.unravel_index(np.argmin(every), every.shape)
    np.testing.assert_allclose(hits[0].centre[:2], index.centres[place, :2])
    assert hits[0].yaw == pytest.approx(np.angle(np.exp(2j * np.pi * shift / index.geometry.sectors)))
    assert hits[0].distance == pytest.approx(float(every[place, shift]), abs=1e-6)
    assert [h.distance for h in hits] == sorted(h.distance for h in hits)


def test_global_localisation_with_the_index_places_held_out_scans_and_never_confidently_wrong(
        street: tuple[Scene, np.ndarray], tmp_path: object) -> None:
    scene, map_xyz = street
    config = LocalizationConfig(retrieve=8, map_voxel=0.2)
    loc = MapLocalizer(map_xyz, config=config, cache_dir=tmp_path)
    rng = np.random.default_rng(4)
    placed = 0
    for _ in range(8):
        T = sensor_pose(rng.uniform(-55, 55), rng.uniform(-1.5, 1.5), 1.8, rng.uniform(-np.pi, np.pi))
        result = loc.localize(lidar_scan(scene, T, rng, SENSOR).points)
        re, te = transform_errors(result.transformation, T)
        right = re < PLACED_RE_DEG and te < PLACED_TE_M
        placed += right
        assert right or result.confidence < 0.5, (re, te, result.confidence)
        assert result.timings["retrieve"] < result.timings["total"]
    assert placed >= 6
    # the index was cached with the map: a second localizer reads the same places and spectra, and they are
    # the ones built afresh
    again = MapLocalizer(map_xyz, config=config, cache_dir=tmp_path)
    fresh = PlaceIndex.build(loc.map, loc.place_index().geometry)
    for index in (again.place_index(), loc.place_index()):
        np.testing.assert_array_equal(index.centres, fresh.centres)
        np.testing.assert_array_equal(index.spectra, fresh.spectra)
    # read from the files, not copied: read-only (nothing can write into a cache through them)
    assert not again.place_index().spectra.flags.writeable and not again.map.flags.writeable
    # cut short (a full disk, a killed writer): the arrays are worked out again, the same, and written whole
    for path in tmp_path.glob("*.npy"):
        path.write_bytes(path.read_bytes()[:200])
    rebuilt = MapLocalizer(map_xyz, config=config, cache_dir=tmp_path)
    np.testing.assert_array_equal(rebuilt.map, loc.map)
    np.testing.assert_array_equal(rebuilt.place_index().spectra, fresh.spectra)
    assert not MapLocalizer(map_xyz, config=config, cache_dir=tmp_path).place_index().spectra.flags.writeable


def test_tracking_finds_the_sensor_pose_and_the_voxelised_map_is_cached(
        street: tuple[Scene, np.ndarray], tmp_path: object) -> None:
    scene, map_xyz = street
    config = LocalizationConfig(retrieve=8, map_voxel=0.2)
    loc = MapLocalizer(map_xyz, config=config, cache_dir=tmp_path)
    np.testing.assert_array_equal(loc.map, voxel_downsample(map_xyz.astype(np.float64), 0.2))
    assert loc.whole_map().index.points is loc.map  # GICP and the scores on the map itself
    again = MapLocalizer(map_xyz, config=config, cache_dir=tmp_path)  # the voxelised map read from the cache
    assert [f.name.split("-")[0] for f in tmp_path.glob("*.npy") if not f.name.startswith("index")] == ["map"]
    np.testing.assert_array_equal(again.map, loc.map)
    rng = np.random.default_rng(8)
    for _ in range(3):
        T = sensor_pose(rng.uniform(-50, 50), rng.uniform(-1.0, 1.0), 1.8, rng.uniform(-np.pi, np.pi))
        off = sensor_pose(0.3, -0.2, 0.05, np.radians(3.0))  # the guess: 0.36 m and 3 deg from the truth
        result = again.localize(lidar_scan(scene, T, rng, SENSOR).points, initial_guess=T @ off)
        re, te = transform_errors(result.transformation, T)
        assert re < 0.5 and te < 0.05 and result.confidence >= 0.5, (re, te, result.confidence)


def test_a_guess_that_puts_the_scan_off_the_map_is_not_tracked_and_the_index_places_it(
        street: tuple[Scene, np.ndarray]) -> None:
    """A guess hundreds of metres off the map (as a pose moved on at the speed of a kidnap): `track` does not
    align from it (None: GICP would run off the map, whose k-d tree is slow to search far from it), and the
    scan is still placed from it, by the place index; a guess 2 m and 5 deg off (a stale pose) is tracked."""
    scene, map_xyz = street
    loc = MapLocalizer(map_xyz, config=LocalizationConfig(retrieve=8, map_voxel=0.2))
    rng = np.random.default_rng(11)
    T = sensor_pose(12.0, 0.6, 1.8, 0.3)
    scan = lidar_scan(scene, T, rng, SENSOR).points.astype(np.float64)
    voxelised = voxel_downsample(scan, loc.voxel_size)
    for wild in (sensor_pose(400.0, 0.0, 1.8), sensor_pose(12.0, 0.6, -150.0, 0.3)):
        assert loc.track(voxelised, wild, local=loc.whole_map()) is None
        result = loc.localize(scan, initial_guess=wild)
        re, te = transform_errors(result.transformation, T)
        assert re < PLACED_RE_DEG and te < PLACED_TE_M and result.confidence >= 0.5, (re, te, result.confidence)
    stale = loc.track(voxelised, T @ sensor_pose(2.0, 0.0, 0.0, np.radians(5.0)), local=loc.whole_map())
    assert stale is not None


def test_warming_up_places_nothing_differently(street: tuple[Scene, np.ndarray]) -> None:
    """`warm_up` (the node runs it before it is ready) localises a scan carved from the map and leaves no
    trace: with and without the place index, a localizer warmed up gives every scan, with a guess and
    without, the same pose and confidence as one that was not."""
    scene, map_xyz = street
    rng = np.random.default_rng(21)
    T = sensor_pose(-20.0, 0.8, 1.8, 2.0)
    scan = lidar_scan(scene, T, rng, SENSOR).points.astype(np.float64)
    guess = T @ sensor_pose(0.3, -0.2, 0.05, np.radians(3.0))
    for config in (LocalizationConfig(retrieve=8, map_voxel=0.2), LocalizationConfig(map_voxel=0.2)):
        warmed, cold = MapLocalizer(map_xyz, config=config), MapLocalizer(map_xyz, config=config)
        warmed.warm_up()
        for start in (guess, None, guess):  # the guess again: tracking's local map as the first scan left it
            a, b = warmed.localize(scan, initial_guess=start), cold.localize(scan, initial_guess=start)
            np.testing.assert_allclose(a.transformation, b.transformation, atol=1e-9)
            assert a.confidence == pytest.approx(b.confidence, abs=1e-9) and a.start == b.start
            if start is not None or config.retrieve:  # (a street's places, screened without a guess: not asked)
                re, te = transform_errors(a.transformation, T)
                assert re < PLACED_RE_DEG and te < PLACED_TE_M, (re, te)


def test_a_warm_up_the_registration_refuses_is_left_to_the_first_scan(street: tuple[Scene, np.ndarray],
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The node warms a map up while it configures: a named registration error there does not escape (the
    first scan meets it and reports it), and tracking's local map stays as it was."""
    loc = MapLocalizer(street[1], config=LocalizationConfig(map_voxel=0.2))

    def refuse(scan: np.ndarray, initial_guess: np.ndarray | None = None) -> None:
        loc.local(np.zeros(3), 10.0)  # as tracking does before it can fail
        raise TooFewPointsError("source has 3 points after voxelising")

    monkeypatch.setattr(loc, "localize", refuse)
    loc.warm_up()
    assert loc._local is None


@given(st.integers(0, 2**32 - 1), st.floats(0.05, 3.0))
def test_near_share_is_the_share_of_queries_in_a_cell_holding_target_points(seed: int, cell: float) -> None:
    """`TargetIndex.near_share` against a set of the target's floored cells, for queries near, inside and far
    outside the target (beyond its grid on every side), with the grid's occupancy held either way."""
    rng = np.random.default_rng(seed)
    target = rng.normal(0.0, 5.0, (rng.integers(1, 400), 3))
    query = np.concatenate([target[rng.integers(0, len(target), 50)] + rng.normal(0.0, cell, (50, 3)),
                            rng.uniform(-1e4, 1e4, (20, 3)), rng.normal(0.0, 8.0, (30, 3))])
    cells = {tuple(c) for c in np.floor(target / cell).astype(np.int64)}
    truth = np.mean([tuple(c) in cells for c in np.floor(query / cell).astype(np.int64)])
    dense = score.DENSE_CELLS
    try:
        for score.DENSE_CELLS in (dense, 0):  # a flag per cell of the grid (unless too many), sorted keys
            index = TargetIndex(target)
            assert index.near_share(query, cell) == pytest.approx(truth)
            assert index.near_share(target, cell) == 1.0 and index.near_share(query[:0], cell) == 0.0
    finally:
        score.DENSE_CELLS = dense


def test_a_street_that_repeats_is_never_confident_and_the_slide_along_it_is_named() -> None:
    scene = terrace()
    map_xyz = fused_map(scene, np.arange(-96.0, 96.1, 8.0))
    loc = MapLocalizer(map_xyz, config=LocalizationConfig(retrieve=8, map_voxel=0.2))
    rng = np.random.default_rng(5)
    for x in (-30.0, 5.0, 41.0):
        T = sensor_pose(x, rng.uniform(-1.0, 1.0), 1.8, rng.uniform(-np.pi, np.pi))
        result = loc.localize(lidar_scan(scene, T, rng, SENSOR).points)
        offset = result.transformation[:3, 3] - T[:3, 3]
        assert result.confidence < 0.5, (offset, result.confidence)
        # wherever it was put, it is a whole number of periods along the street from the truth
        assert abs(offset[1]) < 0.3 and abs(offset[0] / 12.0 - round(offset[0] / 12.0)) < 0.05
        slides = [u for u in result.unconstrained if "rival pose" in u]
        assert slides and slides[0].startswith("translation along (1.00, ")
        assert result.covariance[0, 0] > 1.0  # the covariance spans the rival, metres along the street


def test_a_scan_of_another_place_is_not_confident(street: tuple[Scene, np.ndarray]) -> None:
    _, map_xyz = street
    loc = MapLocalizer(map_xyz, config=LocalizationConfig(retrieve=8, map_voxel=0.2))
    rng = np.random.default_rng(6)
    other = street_scene(11, length=160.0)
    for _ in range(3):
        T = sensor_pose(rng.uniform(-50, 50), rng.uniform(-1.0, 1.0), 1.8, rng.uniform(-np.pi, np.pi))
        assert loc.localize(lidar_scan(other, T, rng, SENSOR).points).confidence < 0.5


def test_a_scan_no_retrieved_place_fits_is_not_slid_and_not_confident(street: tuple[Scene, np.ndarray]) -> None:
    scene, map_xyz = street
    loc = MapLocalizer(map_xyz, config=LocalizationConfig(retrieve=8, map_voxel=0.2, verify_fitness=0.8))
    rng = np.random.default_rng(9)
    other = street_scene(11, length=160.0)
    for _ in range(2):
        T = sensor_pose(rng.uniform(-50, 50), rng.uniform(-1.0, 1.0), 1.8, rng.uniform(-np.pi, np.pi))
        result = loc.localize(lidar_scan(other, T, rng, SENSOR).points)
        assert result.confidence < 0.5
    for _ in range(3):  # the map's own scans fit: placed as without the setting
        T = sensor_pose(rng.uniform(-50, 50), rng.uniform(-1.5, 1.5), 1.8, rng.uniform(-np.pi, np.pi))
        result = loc.localize(lidar_scan(scene, T, rng, SENSOR).points)
        re, te = transform_errors(result.transformation, T)
        assert re < PLACED_RE_DEG and te < PLACED_TE_M and result.confidence >= 0.5, (re, te, result.confidence)


def corridor_and_street(street: tuple[Scene, np.ndarray]) -> list[tuple[Scene, np.ndarray, bool]]:
    """(scene, its map, whether it is a corridor): a uniform corridor along x (walls 1.5 m either side of the line
    y = 0, 3 m high, a 1 m doorway every 10 m, a ceiling), and the street."""
    corridor = Scene("corridor")
    corridor.add_plane((0, 0, 0), (0, 0, 1), 0.3)
    for side in (1, -1):
        for x in np.arange(-150.0, 150.0, 10.0):
            corridor.add_box((x + 4.5, side * 1.6, 1.5), (9.0, 0.2, 3.0), 0.0, 0.6)
    corridor.add_box((0.0, 0.0, 3.1), (300.0, 3.4, 0.2), 0.0, 0.6)  # the ceiling
    return [(corridor, fused_map(corridor, np.arange(-60.0, 60.1, 4.0)), True), (street[0], street[1], False)]


def scan_along(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A scan of `scene` (and its T_world_sensor) 1.8 m up near the line y = 0, at any heading."""
    T = sensor_pose(rng.uniform(-20, 20), rng.uniform(-0.5, 0.5), 1.8, rng.uniform(-np.pi, np.pi))
    return T, lidar_scan(scene, T, rng, SENSOR).points


@given(st.floats(0.8, 3.5), st.floats(-np.pi, np.pi))
def test_enclosure_is_the_share_of_directions_with_a_wall_within_reach(half_width: float, heading: float) -> None:
    """Walls either side of a straight corridor `half_width` m from the sensor, at any heading: a direction at
    angle a from the corridor meets a wall at half_width / |sin a|, within 4 m when |sin a| > half_width / 4,
    so the share is 1 - 2 arcsin(half_width / 4) / pi, up to a partly covered sector (of 60) at each of the four
    ends of the walls' reach (a sector counts when any of its points is within reach); a floor alone: 0."""
    x, z = np.meshgrid(np.arange(-30.0, 30.0, 0.05), np.arange(0.5, 1.6, 0.25))
    walls = np.concatenate([np.c_[x.ravel(), np.full(x.size, side * half_width), z.ravel()] for side in (1, -1)])
    gx, gy = np.meshgrid(np.arange(-25.0, 25.0, 0.25), np.arange(-25.0, 25.0, 0.25))
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)] - [0.0, 0.0, 0.6]  # the sensor 0.6 m up
    walls[:, 2] -= 0.6
    c, s = np.cos(heading), np.sin(heading)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    index = PlaceIndex(IndexGeometry(), np.zeros((0, 3)), np.zeros((31, 0, 15), np.complex64))
    expected = 1.0 - 2.0 * np.arcsin(half_width / 4.0) / np.pi
    assert expected - 1 / 60 <= index.enclosure(np.concatenate([walls, ground]) @ turn.T) <= expected + 4 / 60
    assert index.enclosure(ground @ turn.T) == 0.0


def test_a_corridor_scan_placed_without_a_guess_is_named_and_held_and_a_tracked_one_is_kept(
        street: tuple[Scene, np.ndarray]) -> None:
    """With `corridor_share`, a scan in a corridor localised without a guess is named (a corridor alike to
    others) and its confidence held at 1 - its own; from a guess (tracking) it is not named; a street scan is
    not named either way."""
    config = LocalizationConfig(retrieve=8, map_voxel=0.2, corridor_share=0.45)
    rng = np.random.default_rng(17)
    for scene, map_xyz, enclosed in corridor_and_street(street):
        loc = MapLocalizer(map_xyz, config=config)
        T, scan = scan_along(scene, rng)
        found = loc.localize(scan)
        named = [u for u in found.unconstrained if u.startswith("place: a corridor")]
        assert bool(named) == enclosed, (scene.name, found.unconstrained)
        if enclosed:
            assert found.confidence <= 0.5, found.confidence
            loc.config = replace(config, corridor_share=0.0)  # the same scan without the rule: not held
            free = loc.localize(scan)
            assert found.confidence == pytest.approx(min(free.confidence, 1.0 - free.confidence))
            loc.config = config
        tracked = loc.localize(scan, initial_guess=T)
        assert not [u for u in tracked.unconstrained if u.startswith("place: a corridor")], tracked.unconstrained
        # a guess to the side, just beyond tracking's reach of the true pose: in the corridor whatever is found
        # there is searched for (the index's answer, or a track that moved beyond reach) and held
        side = T.copy()
        side[:3, 3] += (loc.config.track_distance * loc.voxel_size + 0.3) * T[:3, 1]
        assert not loc.within_reach(T, side)
        moved = loc.localize(scan, initial_guess=side)
        if enclosed:
            assert moved.confidence <= 0.5, (moved.confidence, moved.unconstrained)


def test_a_track_on_a_plateau_along_a_road_is_checked_by_the_place_index(street: tuple[Scene, np.ndarray]) -> None:
    """A track named as well fitted along the scan's main axis outside a corridor (GICP stopped on a plateau short
    of the place, from a guess metres behind) is checked by the place index and held at 1 - its own: the index's
    pose wins, bounded by it; where the index is unsure too, the held track is not confident; in a corridor, or
    without `corridor_share`, the track stands as tracked. The scans are the corridor test's (the same seed): the
    corridor's enclosed, the street's not."""
    config = LocalizationConfig(retrieve=8, map_voxel=0.2, flat_fit=0.92, corridor_share=0.45)
    rng = np.random.default_rng(17)
    for scene, map_xyz, enclosed in corridor_and_street(street):
        loc = MapLocalizer(map_xyz, config=config)
        T, scan = scan_along(scene, rng)
        truth = loc.localize(scan, initial_guess=T)  # tracked from the truth: the index's answer stands in for it
        assert transform_errors(truth.transformation, T)[1] < 0.1
        short = T.copy()
        short[:3, 3] -= 1.8 * T[:3, 0]  # 1.8 m behind along the sensor's heading
        plateau = replace(truth, transformation=short, confidence=0.7,
                          unconstrained=("translation along (1.00, 0.00, 0.00): as well fitted 0.60 m along it",))
        asked = []
        loc.track = lambda *args, plateau=plateau, **kw: plateau
        loc.retrieved = lambda scan, truth=truth, asked=asked: asked.append(1) or replace(truth, confidence=0.95)
        found = loc.localize(scan, initial_guess=short)
        if enclosed:  # in a corridor the robot's last pose holds the track
            assert not asked and found is plateau
        else:
            assert asked and np.allclose(found.transformation, truth.transformation)
            assert found.confidence == pytest.approx(min(0.95, 1.0 - min(0.7, 0.3)))
            loc.retrieved = lambda scan, truth=truth: replace(truth, confidence=0.2)  # the index is unsure
            held = loc.localize(scan, initial_guess=short)
            assert np.allclose(held.transformation, short) and held.confidence == pytest.approx(0.3)
        loc.config = replace(config, corridor_share=0.0)  # no corridors told apart: every track as tracked
        assert loc.localize(scan, initial_guess=short) is plateau


def test_a_track_as_well_fitted_along_a_uniform_corridor_names_it_and_a_street_does_not(
        street: tuple[Scene, np.ndarray]) -> None:
    config = LocalizationConfig(retrieve=8, map_voxel=0.2, flat_fit=0.92)
    rng = np.random.default_rng(13)
    for scene, map_xyz, flat in corridor_and_street(street):
        loc = MapLocalizer(map_xyz, config=config)
        T, scan = scan_along(scene, rng)
        result = loc.localize(scan, initial_guess=T)
        named = [u for u in result.unconstrained if "as well fitted" in u]
        assert bool(named) == flat, (scene.name, result.unconstrained)
        if flat:  # along the corridor (x), and the covariance spans the shift there
            shift = 3.0 * loc.voxel_size
            assert named[0].startswith("translation along (1.00, ") and f"{shift:.2f} m" in named[0]
            assert result.covariance[0, 0] >= shift ** 2
            # found without a guess (a retrieved place), such a pose is bounded as by a rival as probable: the
            # chosen candidate stands in for the place index's choice here
            sure = replace(result, confidence=0.9)
            loc.chosen = lambda results, sure=sure: sure
            assert loc.retrieved(voxel_downsample(scan.astype(np.float64), loc.voxel_size)).confidence == \
                pytest.approx(0.1)
            del loc.chosen
        off = replace(config, flat_fit=0.0)  # the same track without the test: nothing named
        loc.config = off
        assert not [u for u in loc.localize(scan, initial_guess=T).unconstrained if "as well fitted" in u]


def test_a_track_in_a_flat_valley_is_aligned_again_from_the_valleys_best_fit(
        street: tuple[Scene, np.ndarray], monkeypatch: pytest.MonkeyPatch) -> None:
    """A tracked pose 0.3 m along the street from the sensor's true pose (where GICP from a guess may stop on a
    ripple of a flat valley) is named as well fitted along it, and the valley's best fit, searched half a map
    spacing at a time up to 3 spacings either way along the scan's main axis, lies beyond one spacing (GICP's
    basin) and within 0.06 m of the truth; `track` aligns again from there (here with a GICP that stops where it
    starts: the search alone moves it). At the true pose, or half a spacing from it, no valley is given; without
    the test (`flat_fit` 0), or where a street is told from a corridor (`corridor_share` 0.6: these street scans
    are enclosed in 7-58 % of directions, the corridor's of `corridor_and_street` in 77-78 %; a valley along a
    road is a plateau, `on_a_plateau`), the track stays where it stopped."""
    scene, map_xyz = street
    config = LocalizationConfig(retrieve=8, map_voxel=0.2, flat_fit=0.92)
    loc = MapLocalizer(map_xyz, config=config)
    index, half = loc.whole_map().index, loc.voxel_size / 2
    rng = np.random.default_rng(13)
    monkeypatch.setattr(refine.GICPTarget, "align", lambda self, source, init, **_: np.asarray(init, float).copy())
    for _ in range(4):
        T, points = scan_along(scene, rng)
        scan = voxel_downsample(points.astype(np.float64), loc.voxel_size)
        sample = scan[np.sort(np.random.default_rng(0).permutation(len(scan))[:config.track_points])]
        short = T.copy()
        short[0, 3] += 0.3  # along the street (x)
        named, valley = loc.flat(*loc.verified(scan, sample, index, short), sample, index)
        assert [u for u in named.unconstrained if "as well fitted" in u] and valley is not None
        move = valley[:3, 3] - short[:3, 3]  # level, unturned, by a multiple of half a spacing
        steps = np.linalg.norm(move) / half
        assert np.allclose(valley[:3, :3], short[:3, :3]) and abs(move[2]) < 1e-9
        assert abs(steps - round(steps)) < 1e-6 and 3 <= round(steps) <= 6  # beyond GICP's basin (1 spacing)
        assert transform_errors(valley, T)[1] < 0.06
        assert loc.flat(*loc.verified(scan, sample, index, short), sample, index, search=False)[1] is None
        tracked = loc.track(scan, short, local=loc.whole_map())
        assert tracked is not None and np.allclose(tracked.transformation, valley)
        at_truth, none = loc.flat(*loc.verified(scan, sample, index, T), sample, index)
        assert none is None and not [u for u in at_truth.unconstrained if "as well fitted" in u]
        near = T.copy()
        near[0, 3] += 0.5 * loc.voxel_size  # within GICP's basin of the truth: GICP finds it, no search needed
        assert loc.flat(*loc.verified(scan, sample, index, near), sample, index)[1] is None
        for off in (replace(config, flat_fit=0.0), replace(config, corridor_share=0.6)):
            loc.config = off  # the test off, or a street told from a corridor: a plateau, left to the place index
            still = loc.track(scan, short, local=loc.whole_map())
            assert still is not None and np.allclose(still.transformation, short)
        loc.config = config


def corridor_with(pillar: tuple[float, float, float]) -> Scene:
    """A straight corridor along x (walls 1.6 m either side of y = 0, 3 m high, a ceiling) with one pillar (0.4 m
    square) at this centre against its wall: otherwise uniform."""
    s = Scene("corridor")
    s.add_plane((0, 0, 0), (0, 0, 1), 0.3)
    for side in (1, -1):
        s.add_box((0.0, side * 1.6, 1.5), (300.0, 0.2, 3.0), 0.0, 0.6)
    s.add_box((0.0, 0.0, 3.1), (300.0, 3.4, 0.2), 0.0, 0.6)
    s.add_box(pillar, (0.4, 0.4, 3.0), 0.0, 0.8)
    return s


def test_a_rough_guess_metres_off_along_a_corridor_is_checked_as_far_as_it_may_be_off() -> None:
    """Operator's clicks 1, 2 and 3 m along a corridor from the sensor's true pose (a pillar 1 m ahead the only
    feature): tracked from them as tracked poses are, GICP leaves the scan 1.5 m or more off at a high confidence,
    named as well fitted along the corridor (the hazard). As rough guesses (`rough_reach` 4 m) the scan is
    aligned again from poses along the corridor: from 1 and 2 m the pose that seats the most points is the
    truth's, within 0.06 m, confident and counted as within reach of the click (not of a tracked guess); from 3 m
    a pose 4 m away seats as many (`rough_rival`): the scan is not placed confidently and the rival is named."""
    config = LocalizationConfig(retrieve=8, map_voxel=0.2, flat_fit=0.92, rough_reach=4.0)
    scene = corridor_with((1.0, 1.3, 1.5))
    loc = MapLocalizer(fused_map(scene, np.arange(-40.0, 40.1, 4.0)), config=config)
    T = sensor_pose(0.0, 0.2, 1.8, 0.3)
    scan = lidar_scan(scene, T, np.random.default_rng(3), SENSOR).points
    for metres in (1.0, 2.0, 3.0):
        click = T.copy()
        click[0, 3] += metres  # along the corridor (x)
        tracked = loc.localize(scan, initial_guess=click)
        assert tracked.confidence > 0.9 and transform_errors(tracked.transformation, T)[1] > 1.5, metres
        assert [u for u in tracked.unconstrained if "as well fitted" in u]
        rough = loc.localize(scan, initial_guess=click, rough=True)
        if metres < 3.0:
            assert transform_errors(rough.transformation, T)[1] < 0.06 and rough.confidence > 0.9, metres
            assert loc.within_reach(rough.transformation, click, rough=True)
            assert metres < 1.5 or not loc.within_reach(rough.transformation, click)
        else:
            assert rough.confidence < 0.5 and [u for u in rough.unconstrained if "to a rival pose" in u]
