"""Localisation of a scan in a prebuilt map: T_map_scan with GenReg, with or without an initial guess.

    loc = MapLocalizer(map_xyz)                      # (M, 3) map in metres, e.g. fused and voxelised frames
    loc = MapLocalizer(map_xyz, registrar=registrar, config=LocalizationConfig(candidates=5))  # other settings
    result = loc.localize(scan_xyz)                  # (N, 3) scan in its sensor frame
    result.transformation                            # T_map_scan; result.confidence: P(the pose is right)

Every setting is a field of `genreg_core.config.LocalizationConfig` (its help says what it does, its
range what it accepts); the names below are those fields. A raw depth scan is dense near the camera and
sparse far away, a fused map even: the scan is first voxelised to the map's resolution (its median
nearest-neighbour spacing, or `voxel_size`), so the model's 512 samples of both clouds see the same
surfaces alike.

Registrations against the map (`Registrar`) run without the refinement guard (`RefineConfig.guard_below`:
its ICP from the scan's and the map's centroids put together is no pose in a map). Without a guess, the
scan is first registered against the whole map, or, when the map is in parts (rooms or floors mapped apart,
more than `part_gap` scan radii from each other: `parts`), against each part, in the order of the scan's
screening against each (below); a pose stands when its confidence reaches `accept_whole`, or when the map
is not much larger than the scan (extent below `whole_map_ratio` x the scan's). Otherwise (a room larger
than the view, a floor, a building: too few of the model's map samples lie where the scan is; MODEL_CARD
"Map relocalisation") the map is cut into candidate places: the centres of occupied cells of a grid with
spacing `place_spacing` x the scan's radius, each place the map points within `place_radius` x that radius
of its centre, at most `place_points` of them (built on first use per radius, kept in memory and, with
`cache_dir`, on disk by the map's content hash). The scan is registered against every place in batched
`Registrar.register_many` calls at `screen_model_points` points (the same weights), unrefined (GenReg is
rotation invariant: no orientation is searched); the best `candidates` by confidence are verified against
a crop of the whole map around each (registration from the candidate's pose as the initial guess), and the most
confident pose, the whole map's included, wins, bounded by its distinct rivals (below). Each of these global
results is `judged` first: its confidence becomes the calibration's map model's (`MAP_CALIBRATION`, fitted
on training maps with scans on and beyond them: `scripts/calibrate_confidence.py fit-map`) over its
registration's probability and the share of the map its pose says the scan saw through
(`score.see_through`): a scan that reaches past the mapped stretch may seat as well slid along the room as
at its place, but the slid pose puts the map's walls in front of surfaces the scan saw.

A gravity-aligned map (z up, as LiDAR maps are) can instead be searched through its place index
(`retrieve` > 0; `genreg_core.place_index`, built once per map and cached with it): the scan's polar height
image is compared with every place's at every heading, and the `retrieve` best places and headings are
aligned by GICP against the whole map (prepared once, `whole_map`) and verified as tracked scans are; the
most confident wins. Neither the whole-map registration nor the place screening runs then. Whenever several
results are verified for one scan, a distinct pose among them is the chosen one's rival (`chosen`): two
distinct poses cannot both be right, so the confidence is at most 1 - the rival's; the rival is named
among the result's `unconstrained` motions ("translation along (x, y, z) to a rival pose d m away": a
slide along a road or a corridor whose structure repeats) and widens the covariance. The map may be
voxelised on load (`map_voxel`; with `cache_dir`, once: kept there). With the index, tracking aligns against the whole map too (no local maps
to rebuild as the robot moves), and an unsure track, one that moved beyond GICP's reach from its guess
(`track_distance`: the guess was stale), or one on a plateau along a road (`on_a_plateau`: as well fitted moved
along it, outside a corridor), is checked by the index's search rather than GenReg.

With a guess (tracking), the scan is aligned by GICP from the guess against the map around the guessed
scan position (`local_radius` scan radii; the whole map when it fits), prepared once per region
(`refine.gicp_target`: its covariances and k-d tree), with no network pass. Its result is built as a
registration's (`result.build_result`); its confidence is the calibration's tracking model
(`TRACKING_CALIBRATION`, fitted on training maps from guesses near and far from the truth:
`scripts/calibrate_confidence.py fit-tracking`) over the same verification features, the inlier ratio
taken as 1 (no generated correspondences). When that probability is below `track_below` (a guess too far
off), the map is cropped around the guessed scan position (`crop_radius` x the scan's radius) and GenReg
registers the scan from the guess; the more probable pose wins. A checkpoint whose calibration has no
tracking model always takes that second path.

`accept_whole` and `track_below` steer the search's effort; whether a pose is good enough is the caller's
decision from its confidence (the node's `min_confidence`). A scan the map does not hold gets a low
confidence, not an exception; bad input raises the named errors the Registrar raises
(`genreg_core.errors`). The defaults were chosen on redkitchen training frames 0-799 (MODEL_CARD "Map
relocalisation": their measurements).
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from genreg_core.checkpoint import resized
from genreg_core.confidence import MAP_CALIBRATION, MAP_FEATURES, SPACINGS, map_features
from genreg_core.config import SCENE_MODEL, SCENE_REGISTRATION, LocalizationConfig
from genreg_core.errors import ConfigError, GenRegError, TooFewPointsError
from genreg_core.geometry import apply_transform, make_transform, moved_along
from genreg_core.place_index import ENCLOSING_REACH, IndexGeometry, PlaceIndex, hit_pose
from genreg_core.place_index import VERSION as INDEX_VERSION
from genreg_core.prepare import check_transform, robust_extent, validate_cloud
from genreg_core.preprocess import voxel_downsample
from genreg_core.refine import GICPTarget, VoxelTarget, gicp_target
from genreg_core.registration import COARSE_ITERATIONS, Registrar, distinct_poses
from genreg_core.result import (
    AS_WELL_FITTED,
    TRACKING_CALIBRATION,
    Aligned,
    Confidence,
    RegistrationResult,
    Verified,
    as_well_fitted,
    below_rival,
    build_result,
    rivalled,
)
from genreg_core.score import (
    FITNESS_SPACINGS,
    TIGHT_SPACINGS,
    TargetIndex,
    grid_keys,
    overlap_shares,
    see_through,
)

# The settings are `LocalizationConfig`'s (their measurements: MODEL_CARD "Map relocalisation"). Below:
# implementation details that change no result.
SPACING_SAMPLES = 20_000  # the map's resolution is the median nearest-neighbour spacing of this many points
RADIUS_QUANTILE = 0.9  # a scan's radius: this quantile of its points' distances from their centroid
PLACE_CHUNK = 256  # place centres searched at once (bounds the memory of the neighbour lists)
EXTENT_SAMPLES = 200_000  # the map's robust extent from this many of its points
WARM_UP_POINTS = 20_000  # `MapLocalizer.warm_up`'s scan: this many map points
# `MapLocalizer.track` aligns from a guess only when at least this share of the scan's sampled points lies in a
# map-occupied cell of GICP's correspondence distance (`TargetIndex.near_share`): on a training campus every guess
# tracked and every retrieved candidate had 0.48 or more (1,052 alignments: drives at 10 and 20 m/s, corridors
# from guesses 1 m off, off-map scans); a guess moved on at the speed of a kidnap 0.001
MIN_NEAR_SHARE = 0.05
IN_A_CORRIDOR = "place: a corridor alike to others"  # `retrieved`'s name of a scan enclosed as in a corridor
FLAT_SHIFT_SPACINGS = 3  # a tracked pose's fit is tested this many map spacings along the scan's main axis
# (`MapLocalizer.flat`), and a flat valley's best fit searched as far, half a spacing at a time: on the training
# campuses (0.11 m spacings) tracked corridor scans stop up to 0.3 m along the corridor
VALLEY_BASIN = 1.0  # GICP aligned again from a flat valley's best fit within this many map spacings of where it
# stopped comes back there (the training campuses: 17 of 17 such tracks within 3 mm; from 1.5 spacings and more,
# 29 of 29 moved 0.15-0.30 m): only a best fit farther away is aligned from


def median_spacing(points: np.ndarray, samples: int = SPACING_SAMPLES, seed: int = 0,
                   tree: cKDTree | None = None, index: TargetIndex | None = None) -> float:
    """The median distance from a point to its nearest other point, over up to `samples` points (`tree`:
    the points' scipy k-d tree, or `index`: their `TargetIndex`, if built)."""
    rows = np.random.default_rng(seed).choice(len(points), size=min(samples, len(points)), replace=False)
    if index is not None and tree is None:
        _, squared = index.tree.batch_knn_search(points[rows], 2, num_threads=index.threads)
        return float(np.median(np.sqrt(squared[:, 1])))
    tree = tree if tree is not None else cKDTree(points)
    distances, _ = tree.query(points[rows], k=2)
    return float(np.median(distances[:, 1]))


def kd_tree(points: np.ndarray) -> cKDTree:
    """A k-d tree of (M, 3) float64 points that builds fast (unbalanced, leaves of 64, sharing the array;
    MODEL_CARD "Large maps") and answers radius queries as fast."""
    return cKDTree(points, leafsize=64, balanced_tree=False, compact_nodes=False, copy_data=False)


def occupied_cells(points: np.ndarray, spacing: float) -> np.ndarray:
    """The distinct integer cells (K, 3) of a grid with this spacing that hold points, in lexicographic
    order (as np.unique(..., axis=0), by one integer key per cell: far faster on large maps, MODEL_CARD
    "Large maps")."""
    return cells_of(points, spacing, rows=False)[0]


def cells_of(points: np.ndarray, spacing: float, rows: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """`occupied_cells` and, with `rows`, each point's row among them."""
    low, size, keys = grid_keys(points, spacing)
    if keys is None:  # too large a grid for one int64 key per cell
        found = np.unique(np.floor(points / spacing).astype(np.int64), axis=0, return_inverse=rows)
        return (found[0], found[1].ravel()) if rows else (found, None)
    keys, inverse = np.unique(keys, return_inverse=True) if rows else (np.unique(keys), None)
    return np.stack([keys // (size[1] * size[2]), keys // size[2] % size[1], keys % size[2]], axis=1) + low, inverse


def main_axis(points: np.ndarray) -> np.ndarray:
    """The unit (x, y, 0) principal axis of the points' xy (a road's or a corridor's direction in a scan)."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    axis = np.linalg.eigh(xy.T @ xy)[1][:, -1]
    return np.array([axis[0], axis[1], 0.0])


def map_parts(points: np.ndarray, gap: float) -> np.ndarray:
    """Each point's part: the points joined wherever their cells of a grid of size `gap` touch (face, edge
    or corner), numbered by connected component (scipy's csgraph). Points less than `gap` apart are always
    in one part, so points in two parts lie at least `gap` apart (and points up to 2 sqrt(3) `gap` apart may
    be joined)."""
    cells, inverse = cells_of(points, gap)
    assert inverse is not None
    pairs = cKDTree(cells).query_pairs(1.75, output_type="ndarray")  # the 26 neighbours lie within sqrt(3)
    graph = coo_matrix((np.ones(len(pairs), dtype=bool), (pairs[:, 0], pairs[:, 1])), shape=(len(cells),) * 2)
    _, labels = connected_components(graph, directed=False)
    return labels[inverse]


def mapped(path: Path) -> np.ndarray:
    """A cached .npy array, read-only, mapped from the file rather than read into new memory: the pages the
    system already caches are shared, not copied (a map's arrays in tens of milliseconds, not seconds)."""
    return np.asarray(np.load(path, mmap_mode="r", allow_pickle=False))


def read_places(path: Path) -> list[np.ndarray] | None:
    """Places written by `write_places`, or None when the file cannot be read (it is then built again)."""
    try:
        with np.load(path) as cached:
            return np.split(cached["rows"], cached["ends"][:-1])
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None


def write_places(path: Path, places: list[np.ndarray]) -> None:
    """Places as one file, whole or absent (written aside, then renamed); a folder that cannot be written
    leaves them in memory only, with a warning."""
    rows = np.concatenate(places) if places else np.zeros(0, np.int32)
    ends = np.cumsum([len(r) for r in places], dtype=np.int64)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path.with_suffix(".tmp.npz"), rows=rows, ends=ends)
        os.replace(path.with_suffix(".tmp.npz"), path)
    except OSError as exc:
        warnings.warn(f"map places not cached in {path.parent}: {exc.strerror or exc}", stacklevel=3)


def read_points(path: Path) -> np.ndarray | None:
    """(M, 3) float64 points written by `write_points`, read-only, or None when the file cannot be read
    (they are then worked out again). Mapped, not read (`mapped`)."""
    try:
        points = mapped(path)
    except (OSError, ValueError):
        return None
    return points if points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3 else None


def save_whole(path: Path, array: np.ndarray) -> None:
    """An array as a .npy file, whole or absent: written aside, then renamed (OSError if it cannot be)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path.with_suffix(".tmp.npy"), array)
    os.replace(path.with_suffix(".tmp.npy"), path)


def write_points(path: Path, points: np.ndarray) -> None:
    """Points as one .npy file (`save_whole`); a folder that cannot be written leaves them in memory only,
    with a warning."""
    try:
        save_whole(path, points)
    except OSError as exc:
        warnings.warn(f"map points not cached in {path.parent}: {exc.strerror or exc}", stacklevel=3)


def content_key(points: np.ndarray) -> str:
    """A short hash of an array's values, dtype and shape (cache file names)."""
    digest = hashlib.sha1(np.ascontiguousarray(points).data)
    digest.update(f"{points.dtype.str}{points.shape}".encode())
    return digest.hexdigest()[:16]


INDEX_PARTS = ("centres", "spectra")  # a cached place index's arrays, one .npy file each


def read_index(stem: Path, geometry: IndexGeometry) -> PlaceIndex | None:
    """A place index written by `write_index` (its files `stem`.<part>.npy), or None when one cannot be read
    (it is then built again)."""
    try:
        parts = {name: mapped(stem.with_name(f"{stem.name}.{name}.npy")) for name in INDEX_PARTS}
    except (OSError, ValueError):
        return None
    try:
        return PlaceIndex(geometry, parts["centres"], parts["spectra"])
    except ValueError:  # written with another geometry, or cut short
        return None


def write_index(stem: Path, index: PlaceIndex) -> None:
    """A place index as one .npy file per array (`save_whole`: plain files, mapped on reading); a folder that
    cannot be written leaves it in memory only, with a warning."""
    try:
        for name in INDEX_PARTS:
            save_whole(stem.with_name(f"{stem.name}.{name}.npy"), getattr(index, name))
    except OSError as exc:
        warnings.warn(f"place index not cached in {stem.parent}: {exc.strerror or exc}", stacklevel=3)


@dataclass(frozen=True)
class LocalMap:
    """Tracking's part of the map: the map within a radius of `centre`, indexed for scoring and GICP
    (`refine.gicp_target`)."""

    centre: np.ndarray  # (3,)
    radius: float
    whole: bool  # it holds the whole map (never rebuilt)
    index: TargetIndex


class MapLocalizer:
    """A map (float64, with a k-d tree) and a GenReg `Registrar` (default: the scene model and profile)
    that place scans in it. Thread-compatible, not thread-safe (the place grids are cached)."""

    def __init__(
        self,
        map_xyz: np.ndarray,
        *,
        registrar: Registrar | None = None,
        config: LocalizationConfig = LocalizationConfig(),
        cache_dir: str | os.PathLike | None = None,
    ) -> None:
        """`map_xyz`: (M, 3) map points (metres, or any units the scans share); `registrar`: the loaded
        Registrar to localise with (None: the scene model `SCENE_MODEL` with the scene profile
        `SCENE_REGISTRATION`); `config`: the localisation settings (their limits are checked when it is
        built); `cache_dir`: where the candidate places, the place index and the voxelised map (`map_voxel`)
        are kept between runs (files keyed by the map's content hash and the settings; None: in
        memory only)."""
        if not isinstance(config, LocalizationConfig):
            raise ConfigError(f"config must be a LocalizationConfig, got {type(config).__name__}")
        self.registrar = registrar or Registrar.from_checkpoint(SCENE_MODEL, SCENE_REGISTRATION)
        min_points = self.registrar.config.min_points
        if config.place_points < min_points:
            raise ConfigError(f"localization.place_points ({config.place_points}) must be at least the "
                              f"registration's min_points ({min_points})")
        finite, _ = validate_cloud(map_xyz, "map", min_points)
        self.config = config
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        if config.map_voxel > 0:
            finite = self.voxelised(finite, config.map_voxel)
        self.map = np.ascontiguousarray(finite, dtype=np.float64)
        self.threads = config.threads or int(os.environ.get("OMP_NUM_THREADS") or 1)
        self.map_threads = config.map_threads or int(os.environ.get("OMP_NUM_THREADS") or 1)
        self._tree: cKDTree | None = None  # the map's scipy k-d tree (places, crops, local maps), on first use
        # with the place index, the whole map's TargetIndex (small_gicp's k-d tree: GICP's, the scores') is
        # the only tree it needs; the map's resolution is measured on it
        self._map_index = TargetIndex(self.map, self.threads, build_threads=self.map_threads) \
            if config.retrieve else None
        self.voxel_size = float(config.voxel_size) or (
            median_spacing(self.map, tree=self.tree) if self._map_index is None
            else median_spacing(self.map, index=self._map_index))
        if self._map_index is not None:
            self._map_index.spacing = self.voxel_size
        self._local: LocalMap | None = None
        self._whole: LocalMap | None = None  # the whole map prepared for GICP (retrieved places' alignment)
        self._voxels: VoxelTarget | None = None  # ... and for VGICP (their coarse alignment)
        self._index: PlaceIndex | None = None
        self._enclosed: tuple[np.ndarray, float] | None = None  # the last scan asked and its enclosure
        rng = np.random.default_rng(0)
        sample = self.map if len(self.map) <= EXTENT_SAMPLES else self.map[rng.choice(len(self.map), EXTENT_SAMPLES)]
        _, self.extent = robust_extent(sample)
        self._key = content_key(self.map) if cache_dir is not None else ""
        self._places: dict[float, list[np.ndarray]] = {}  # scan radius -> the places' map rows
        self._parts: dict[float, list[np.ndarray]] = {}  # scan radius -> the parts' points
        # candidates are screened without refinement and with one PDSAC mode (ranking only: no probability is asked
        # before the result, `modes_below` 0), then verified with the full profile
        cfg = self.registrar.config
        # the map's registrations run without the refinement guard: its ICP from the scan's and the map's
        # centroids put together is no pose in a map (on redkitchen training maps it never placed a scan that
        # registration had not, and tripled the median time: MODEL_CARD "Maps: load and rejection")
        self._mapper = Registrar(self.registrar.model, replace(cfg, refine=replace(cfg.refine, guard_below=0.0)),
                                 self.registrar.calibration)
        self._screen_config = replace(cfg, refine=replace(cfg.refine, method="none", num_points=config.screen_points),
                                      pdsac=replace(cfg.pdsac, modes=1, modes_below=0.0))
        self._screen_model = resized(self.registrar.model, config.screen_model_points) or self.registrar.model
        self._screener = Registrar(self._screen_model, self._screen_config, self.registrar.calibration)

    def voxelised(self, points: np.ndarray, size: float) -> np.ndarray:
        """`voxel_downsample` of the map's points (as float64) to `size`; with `cache_dir`, read from and kept
        in it by the points' content hash and the size (a large map's voxels once: seconds on millions of
        points)."""
        path = None if self.cache_dir is None else self.cache_dir / f"map-{content_key(points)}-v{size:.6g}.npy"
        cached = read_points(path) if path is not None and path.is_file() else None
        if cached is not None:
            return cached
        voxels = voxel_downsample(np.asarray(points, dtype=np.float64), size)
        if path is not None:
            write_points(path, voxels)
        return voxels

    @property
    def tree(self) -> cKDTree:
        """The map's scipy k-d tree (`kd_tree`), built on first use (the place index's path needs none)."""
        if self._tree is None:
            self._tree = kd_tree(self.map)
        return self._tree

    def places(self, radius: float) -> list[np.ndarray]:
        """The candidate places for scans of this radius, as map row indices: the map points within
        `place_radius` x `radius` of each centre of an occupied grid cell (grid spacing `place_spacing` x
        `radius`) as sorted int32 rows, at most `place_points` of them (a random subset: places overlap,
        about 60 per map point at the default spacing and radius); places with fewer points than
        registration needs are dropped. Built on first use, kept by radius (and in `cache_dir`)."""
        if radius not in self._places:
            c = self.config
            path = None if self.cache_dir is None else self.cache_dir / (
                f"places-{self._key}-r{radius:.6g}-s{c.place_spacing:.6g}-p{c.place_radius:.6g}"
                f"-n{c.place_points}-m{self.registrar.config.min_points}.npz")
            cached = read_places(path) if path is not None and path.is_file() else None
            self._places[radius] = cached if cached is not None else self.build_places(radius)
            if path is not None and cached is None:
                write_places(path, self._places[radius])
        return self._places[radius]

    def parts(self, radius: float) -> list[np.ndarray]:
        """The map's parts for scans of this radius, each registered whole: the parts of `map_parts` at
        `part_gap` x `radius` that hold at least `place_points` points, largest first; the whole map alone
        when there are fewer than two or more than `max_parts` (built on first use per radius)."""
        if radius not in self._parts:
            c, self._parts[radius] = self.config, [self.map]
            if c.part_gap > 0 and c.max_parts > 1:
                labels = map_parts(self.map, c.part_gap * radius)
                sizes = np.bincount(labels)
                big = [k for k in np.argsort(-sizes, kind="stable") if sizes[k] >= c.place_points]
                if 2 <= len(big) <= c.max_parts:
                    self._parts[radius] = [self.map[labels == k] for k in big]
        return self._parts[radius]

    def build_places(self, radius: float) -> list[np.ndarray]:
        """`places` built from the map (seeded: the same map gives the same places). When places are much
        larger than `place_points` (a building), they are searched in a random share of the map that
        leaves them about twice that many points (a random subset of a random subset; MODEL_CARD "Large
        maps"); maps whose places are smaller are searched whole."""
        cap = self.config.place_points
        spacing, reach = self.config.place_spacing * radius, self.config.place_radius * radius
        centres = (occupied_cells(self.map, spacing) + 0.5) * spacing
        minimum, kept, rng = self.registrar.config.min_points, [], np.random.default_rng(0)
        probe = centres[rng.choice(len(centres), min(len(centres), 64), replace=False)]
        typical = float(np.median(self.tree.query_ball_point(probe, reach, return_length=True)))
        share = min(1.0, 2.0 * cap / max(typical, 1.0))
        rows_of = np.flatnonzero(rng.random(len(self.map)) < share) if share < 1.0 else None
        tree = self.tree if rows_of is None else kd_tree(self.map[rows_of])
        for start in range(0, len(centres), PLACE_CHUNK):  # a chunk at a time: large maps, few lists alive
            for rows in tree.query_ball_point(centres[start: start + PLACE_CHUNK], reach, workers=self.threads):
                if len(rows) >= minimum:
                    rows = np.asarray(rows, dtype=np.int64) if rows_of is None else rows_of[rows]
                    if len(rows) > cap:
                        rows = rng.choice(rows, cap, replace=False)
                    kept.append(np.sort(rows).astype(np.int32))
        return kept

    def crop(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """The map points within `radius` of `centre`."""
        return self.map[np.asarray(self.tree.query_ball_point(np.reshape(centre, 3), radius), dtype=np.int64)]

    def scan_geometry(self, scan: np.ndarray) -> tuple[np.ndarray, float, float]:
        """(centroid, radius rounded up to a power of `radius_step`, robust extent) of a voxelised scan."""
        centroid, step = scan.mean(axis=0), self.config.radius_step
        radius = float(np.quantile(np.linalg.norm(scan - centroid, axis=1), RADIUS_QUANTILE))
        radius = step ** np.ceil(np.log(max(radius, 1e-9)) / np.log(step))
        return centroid, float(radius), robust_extent(scan)[1]

    def localize(self, scan_xyz: np.ndarray, initial_guess: np.ndarray | None = None, *, rough: bool = False
                 ) -> RegistrationResult:
        """T_map_scan of a scan (`transformation`) and its calibrated confidence; `initial_guess`: a 4x4
        T_map_scan to start from; `rough`: the guess may be `rough_reach` m off (an operator's click), not a
        tracked pose. A scan the map does not hold gets a low confidence; bad input raises the Registrar's named
        errors. The result's clouds and masks are those of the voxelised scan."""
        reg = self.registrar
        finite, _ = validate_cloud(scan_xyz, "source", reg.config.min_points)
        guess = None if initial_guess is None else check_transform(initial_guess)
        scan = voxel_downsample(np.asarray(finite, dtype=np.float64), self.voxel_size)
        if len(scan) < reg.config.min_points:
            raise TooFewPointsError(f"source has {len(scan)} points after voxelising to the map's "
                                    f"{self.voxel_size:.3g}; registration needs at least {reg.config.min_points}")
        indexed, c = self.config.retrieve > 0, self.config
        # with the index every alignment is against the whole map: no local map or places, so the scan's
        # geometry (centroid, radius, extent) is not needed
        geometry = None if indexed else self.scan_geometry(scan)
        if guess is not None:  # tracking runs with the calibration's tracking model only
            tracked = self.track(scan, guess, None if geometry is None else geometry[:2],
                                 self.whole_map() if indexed else None, rough=rough) if self.tracking_calibrated else None
            # with the index, a track that moved beyond GICP's reach from its guess (a stale guess, which may
            # have slid onto a look-alike place along a repeating street) is checked like an unsure one
            far = indexed and tracked is not None and not self.within_reach(tracked.transformation, guess, rough)
            # a track as well fitted moved along a road as where GICP left it, outside a corridor: stopped on a
            # plateau short of the place (a guess metres behind a vehicle), not in the place's own fit
            plateau = indexed and tracked is not None and not far and self.on_a_plateau(tracked, scan)
            if tracked is not None and tracked.confidence >= c.track_below and not far and not plateau:
                return tracked
            if indexed:  # an unsure track: the place index's answer, bounded by the track's if they differ
                if tracked is not None and far:  # not tracked from its guess but found away from it: in a
                    # corridor, a look-alike place as the index's answer may be
                    tracked = self.in_a_corridor(tracked, scan, "found beyond tracking's reach of its guess")
                if tracked is not None and plateau:  # its place along the road is its guess's, not its fit's
                    tracked = replace(tracked, confidence=below_rival(tracked.confidence, tracked.confidence))
                return self.chosen([self.retrieved(scan), *([tracked] if tracked else [])])
            assert geometry is not None
            centroid, radius, _ = geometry
            searched = self.judged(self.refined(scan, guess, apply_transform(guess, centroid[None])[0], radius), scan)
            return searched if tracked is None else max(tracked, searched, key=lambda r: r.confidence)
        if indexed:
            return self.retrieved(scan)
        assert geometry is not None
        return self.chosen(self.searched(scan, geometry))

    def in_a_corridor(self, result: RegistrationResult, scan: np.ndarray, how: str = "placed by the place index"
                      ) -> RegistrationResult:
        """A pose searched for (the place index's, without a guess or checking an unsure track; or a track found
        beyond reach of its guess: `how`), held at 1 - its confidence (at most 0.5) and named when the scan is
        enclosed as in a corridor (`PlaceIndex.enclosure` at least `corridor_share`): one scan does not tell a
        building's look-alike corridors apart."""
        share = self.config.corridor_share
        enclosure = self.enclosure(scan) if share > 0 else 0.0
        if share <= 0 or enclosure < share:
            return result
        named = f"{IN_A_CORRIDOR}: structure within {ENCLOSING_REACH:g} m in {enclosure:.0%} of directions, {how}"
        return replace(result, unconstrained=(*result.unconstrained, named),
                       confidence=below_rival(result.confidence, result.confidence))

    def on_a_plateau(self, result: RegistrationResult, scan: np.ndarray) -> bool:
        """Whether a tracked result is named as well fitted along the scan's main axis (`flat`) while the scan is
        not enclosed as in a corridor (`PlaceIndex.enclosure` below `corridor_share`; 0: never). In a uniform
        corridor GICP stops anywhere along it and the robot's last pose holds it there; on a road a pose as well
        fitted moved 3 spacings either way may lie on a plateau short of the place's own fit (on the training
        campuses' drives from guesses 2 m behind, every such track was 1.4-1.8 m off, and no right one was named).
        Such a track is checked by the place index, held at 1 - its own as the index's rival: where the index
        cannot place the scan either, nothing is published."""
        share = self.config.corridor_share
        return share > 0 and any(AS_WELL_FITTED in u for u in result.unconstrained) and self.enclosure(scan) < share

    def enclosure(self, scan: np.ndarray) -> float:
        """`PlaceIndex.enclosure` of a voxelised scan, kept for the last scan asked (a scan's track, its plateau test
        and its search may each ask)."""
        if self._enclosed is None or self._enclosed[0] is not scan:
            self._enclosed = (scan, self.place_index().enclosure(scan))
        return self._enclosed[1]

    def within_reach(self, T: np.ndarray, guess: np.ndarray, rough: bool = False) -> bool:
        """Whether the pose T_map_scan `T` lies within tracking's reach of `guess`: GICP's correspondence
        distance (`track_distance` map voxels; of a `rough` guess, at least `rough_reach` m) and PDSAC's mode
        separation (a pose beyond it was not tracked from the guess but found elsewhere)."""
        distance = self.config.track_distance * self.voxel_size
        return not distinct_poses(T, guess, np.radians(self.registrar.config.pdsac.mode_separation),
                                  max(distance, self.config.rough_reach) if rough else distance)

    def searched(self, scan: np.ndarray, geometry: tuple[np.ndarray, float, float]) -> list[RegistrationResult]:
        """The global results of a voxelised scan without a guess or an index (`geometry`: its `scan_geometry`),
        each `judged`: its registrations against the whole map (or its `parts`, in the order of the scan's
        screening against each, until one is confident enough to stand) and, unless that stands (a map not much
        larger than the scan, or confident enough), the `candidates` best screened places that screened at
        `verify_above` or more, verified against crops."""
        centroid, radius, extent = geometry
        c = self.config
        parts, wholes = self.parts(radius), list[RegistrationResult]()
        if len(parts) > 1:  # the likeliest part first: by the scan's screening against each
            screened = self.screen(scan, parts)
            parts = [parts[k] for k in np.argsort([-r.confidence for r in screened], kind="stable")]
        for part in parts:  # until a pose is confident enough to stand
            wholes.append(self.judged(self._mapper.register(scan, part), scan))
            if wholes[-1].confidence >= c.accept_whole:
                return wholes
        places = self.places(radius)
        if self.extent < c.whole_map_ratio * extent or not places:
            return wholes
        screened = self.screen(scan, [self.map[rows] for rows in places])
        best = [k for k in sorted(range(len(screened)), key=lambda k: -screened[k].confidence)[: c.candidates]
                if screened[k].confidence >= c.verify_above]
        return [*wholes, *(self.judged(self.refined(scan, screened[k].transformation, apply_transform(
            screened[k].transformation, centroid[None])[0], radius), scan) for k in best)]

    @property
    def map_confidence(self) -> Confidence:
        """How global results' confidence is worked out: the registrar's calibration's map model."""
        return Confidence(self.registrar.calibration, MAP_CALIBRATION)

    def judged(self, result: RegistrationResult, scan: np.ndarray) -> RegistrationResult:
        """A global result (a registration against the map) with the confidence of the calibration's map model
        (`map_confidence`) over its registration's probability and the share of the map its pose says the
        scan (voxelised, sensor frame) saw through (`score.see_through`: a pose slid along a room puts walls in
        front of what the scan saw); both are added to its `verification`. Without that model the confidence
        stays the registration's."""
        T = result.transformation
        reach = float(np.linalg.norm(scan, axis=1).max())
        share, _ = see_through(scan, self.crop(T[:3, 3], reach), T, self.voxel_size)
        x = map_features(result.confidence, share)
        judge = self.map_confidence
        return replace(result, confidence=judge.probability(x) if judge.calibrated else result.confidence,
                       verification={**result.verification, **dict(zip(MAP_FEATURES, x.tolist(), strict=True))})

    @property
    def tracking_confidence(self) -> Confidence:
        """How tracking results' confidence is worked out: the registrar's calibration's tracking model."""
        return Confidence(self.registrar.calibration, TRACKING_CALIBRATION)

    @property
    def tracking_calibrated(self) -> bool:
        """Whether the registrar's calibration has a model of tracking results (`TRACKING_CALIBRATION`)."""
        return self.tracking_confidence.calibrated

    def local(self, centre: np.ndarray, radius: float) -> LocalMap | None:
        """Tracking's local map for a scan of this radius guessed at `centre`: the map within `local_radius`
        x `radius` of it, prepared once and kept while the guessed centre stays within `local_keep` x
        `radius` of the local map's (or it holds the whole map); None when it holds too few points."""
        local, c = self._local, self.config
        if local is not None and local.radius == radius and (
                local.whole or np.linalg.norm(centre - local.centre) <= c.local_keep * radius):
            return local
        rows = np.sort(np.asarray(self.tree.query_ball_point(centre, c.local_radius * radius), dtype=np.int64))
        if len(rows) < self.registrar.config.min_points:
            return None
        points = self.map[rows]
        index = TargetIndex(points, self.threads, spacing=self.voxel_size)
        gicp_target(index)  # prepared with the region, not on the first scan
        self._local = LocalMap(np.array(centre, dtype=np.float64), radius, len(rows) == len(self.map), index)
        return self._local

    def track(self, scan: np.ndarray, guess: np.ndarray, geometry: tuple[np.ndarray, float] | None = None,
              local: LocalMap | None = None, iterations: int | None = None, search: bool = True,
              rough: bool = False) -> RegistrationResult | None:
        """The voxelised scan aligned by GICP from `guess` (T_map_scan) against the local map around it
        (`local`), verified and built into a result as a registration is (`result.build_result`: inlier ratio
        NaN, taken as 1: no network pass; no generated clouds; `start` "initial_guess"; `verified`); a result as
        well fitted moved along the scan's main axis is named and, with `search`, aligned again from that
        valley's best fit (`flat`) unless it lies on a plateau along a road (`on_a_plateau`); from a `rough` guess
        (a click), a confident track in such a valley or beyond GICP's reach is checked along the corridor as far
        as `rough_reach` (`along`). `geometry`: the
        scan's (centroid, radius) from `scan_geometry`, if known (used only to find the local map). Its confidence is the calibration's tracking
        model's (`tracking_confidence`; without one, uncalibrated as `genreg_core.result` says). None when the
        map holds too few points around the guess, or when the guess puts less than `MIN_NEAR_SHARE` of the
        scan's sampled points near the map (a stale or wild guess: GICP from it would run off the map).
        `local`: the map to align against (default: `local`'s); `iterations`: GICP's (default
        `track_iterations`)."""
        t0 = time.perf_counter()
        if local is None:
            centroid, radius = geometry or self.scan_geometry(scan)[:2]
            local = self.local(apply_transform(guess, centroid[None])[0], radius)
            if local is None:
                return None
        c = self.config
        rows = np.random.default_rng(self.registrar.config.seed).permutation(len(scan))[:c.track_points]
        sample = scan[np.sort(rows)]
        voxel, index = self.voxel_size, local.index
        if index.near_share(apply_transform(guess, sample), c.track_distance * voxel) < MIN_NEAR_SHARE:
            return None  # the guess puts the scan off the map: GICP would wander (and search the tree far from it)
        gicp = gicp_target(index)

        def aligned(start: np.ndarray) -> np.ndarray:
            return gicp.align(sample, start, max_distance=c.track_distance * voxel,
                              max_iterations=iterations or c.track_iterations, threads=self.threads)

        def settled(T: np.ndarray) -> RegistrationResult:
            """A GICP pose verified; in a flat valley, aligned again from the valley's best fit (a corridor's: GICP
            stopped on a ripple; a valley along a road is a plateau, which the place index checks: `on_a_plateau`)."""
            result, valley = self.flat(*self.verified(scan, sample, index, T), sample, index, search)
            if valley is not None and not (self.config.retrieve > 0 and self.on_a_plateau(result, scan)):
                result, _ = self.flat(*self.verified(scan, sample, index, aligned(valley)), sample, index, search=False)
            return result

        T = aligned(guess)
        t1 = time.perf_counter()
        result = settled(T)
        # from a click (`rough`), a confident track in a valley or moved beyond GICP's reach of it: checked along the
        # corridor as far as the click may be off
        if rough and search and c.rough_reach > 0 and result.confidence >= c.track_below and (
                any(AS_WELL_FITTED in u for u in result.unconstrained)
                or not self.within_reach(result.transformation, guess)):
            result = self.along(result, sample, lambda S: settled(aligned(S)))
        t2 = time.perf_counter()
        result.timings = {"refine": t1 - t0, "result": t2 - t1, "total": t2 - t0}
        return result

    def verified(self, scan: np.ndarray, sample: np.ndarray, index: TargetIndex, T: np.ndarray
                 ) -> tuple[RegistrationResult, float]:
        """A tracked pose T (of `sample`, the scan's tracked points) verified against the map's `index` and built
        into a result as a registration is (`result.build_result`), with the share of the sample it seats within
        one map spacing (`TIGHT_SPACINGS`)."""
        voxel = self.voxel_size
        moved = apply_transform(T, sample)
        distance = FITNESS_SPACINGS * voxel
        within = overlap_shares(sample, index, T, np.multiply([*SPACINGS, FITNESS_SPACINGS, TIGHT_SPACINGS], voxel))
        _, squared = index.nearest(moved)  # the query overlap_shares asked, answered from memory
        close = squared < distance * distance
        verified = Verified(within[:len(SPACINGS)], float(within[-2]), float(within[-1]),
                            float(np.sqrt(squared[close].mean())) if close.any() else float("nan"), float("nan"))
        result = build_result(T, verified, Aligned(moved, index, T[:3, 3], distance), self.tracking_confidence,
                              start="initial_guess", aligned_source=apply_transform(T, scan).astype(np.float32),
                              source_valid_mask=np.ones(len(scan), bool))
        return result, float(within[-1])

    def flat(self, result: RegistrationResult, tight: float, sample: np.ndarray, index: TargetIndex,
             search: bool = True) -> tuple[RegistrationResult, np.ndarray | None]:
        """A tracked result whose fit is as good moved along the scan's main horizontal axis (a uniform
        corridor or road): `sample` (the tracked scan points, scan frame) seats within one map spacing as
        many points (at least `flat_fit` x `tight`, the pose's own share) at the pose moved
        `FLAT_SHIFT_SPACINGS` map spacings either way along the axis. GICP stops anywhere in such a valley,
        which its Hessian does not see; the axis is named among the result's unconstrained motions and the
        covariance widened by the shift's square along it. The confidence is kept (the robot's last pose holds
        a tracked scan in its corridor; `retrieved` bounds a pose found without one). Poses less confident than
        `track_below` are not tested (they are not kept as tracked; off: `flat_fit` 0).

        With `search`, a named result also gives the valley's best fit: the pose moved by the multiple of half a
        spacing, up to `FLAT_SHIFT_SPACINGS` spacings either way, that seats the most points, when that is more
        than the pose's own and lies beyond GICP's basin around it (`VALLEY_BASIN`; else None). GICP from a guess off along a corridor can stop on a ripple of the valley's
        floor (a thin wall's other face, the map's voxels) 0.2-0.3 m from the place; from the best fit it reaches
        the place."""
        ratio = self.config.flat_fit
        if ratio <= 0 or tight <= 0 or result.confidence < self.config.track_below:  # an unsure pose is not kept
            return result, None
        T = result.transformation
        u = T[:3, :3] @ main_axis(sample)
        voxel = self.voxel_size

        def seated(spacings: Sequence[float]) -> list[float]:
            return [float(overlap_shares(sample, index, S, np.array([TIGHT_SPACINGS * voxel]))[0])
                    for S in moved_along(T, u, np.multiply(spacings, voxel))]

        ends = (FLAT_SHIFT_SPACINGS, -FLAT_SHIFT_SPACINGS)
        shares = dict(zip(ends, seated(ends), strict=True))
        if max(shares.values()) < ratio * tight:
            return result, None
        shift = FLAT_SHIFT_SPACINGS * voxel
        named = as_well_fitted(result, shift * u)
        if not search:
            return named, None
        inner = [k / 2 for k in range(1 - 2 * FLAT_SHIFT_SPACINGS, 2 * FLAT_SHIFT_SPACINGS) if k != 0]
        shares |= dict(zip(inner, seated(inner), strict=True))
        best = max(shares, key=lambda k: (shares[k], -abs(k)))  # the nearer of equally fitting shifts
        beyond = shares[best] > tight and abs(best) > VALLEY_BASIN  # else GICP from it comes back to T
        return named, moved_along(T, u, [best * voxel])[0] if beyond else None

    def along(self, result: RegistrationResult, sample: np.ndarray,
              settled: Callable[[np.ndarray], RegistrationResult]) -> RegistrationResult:
        """A track from a rough guess (an operator's click, up to `rough_reach` m off; `sample`: its tracked points)
        checked along the scan's main horizontal axis (a corridor's direction) as far as the click may be off: from a click metres off GICP stays near it in a
        uniform stretch, or slides to a look-alike fit (doors as far apart as the place's). The scan is aligned
        again (`settled`: tracking's GICP, verified, its valley searched) from the pose moved along the axis by
        every multiple of GICP's correspondence distance (`track_distance` map spacings: their basins cover the
        stretch) up to `rough_reach` either way; of these and the track, those at least `track_below` confident,
        the one that seats the most points wins (within a map spacing, its `tight_fitness`; of equals, within two:
        a valley's ripples seat alike within one). When a pose distinct from it (`distinct`) seats `rough_rival` x as
        many, the fits do not tell where along the corridor the scan is: that pose is named as its rival, the
        covariance widened as for two poses as probable, and the confidence held at 1 - its own."""
        T, c = result.transformation, self.config
        step = c.track_distance * self.voxel_size
        shifts = np.arange(step, c.rough_reach + 1e-9, step)
        found = [settled(S) for S in moved_along(T, T[:3, :3] @ main_axis(sample), [*shifts, *-shifts])]
        poses = [result, *(r for r in found if r.confidence >= c.track_below)]
        best = max(poses, key=lambda r: (r.tight_fitness, r.verification["log_share_2"]))  # then within two spacings
        rivals = [r for r in poses if r.tight_fitness >= c.rough_rival * best.tight_fitness
                  and self.distinct(r.transformation, best.transformation)]
        if not rivals:
            return best
        return rivalled(best, rivals[0], 0.25, best.confidence)

    def prepare(self) -> None:
        """Build now what localisation would build on first use: with the place index, the index and the
        whole map prepared for GICP (seconds on a map of millions of points)."""
        if self.config.retrieve:
            self.place_index()
            self.whole_map()

    def warm_up(self) -> None:
        """Localise once, as the first scans will, a scan carved from the map (its `WARM_UP_POINTS` points
        nearest the map's median point, moved to the origin): from its true pose (tracking) and, with the place
        index, without a guess, so that the first real scan does not pay for loading compiled kernels (half a
        second and more). Tracking's local map is left as it was; a piece the registration refuses (a map of
        too few or degenerate points) is left to the first scan, which reports the error."""
        centre = np.median(self.map, axis=0)
        _, rows = self.tree.query(centre, k=min(len(self.map), WARM_UP_POINTS))
        scan = self.map[np.sort(np.atleast_1d(rows))] - centre
        local = self._local
        try:
            self.localize(scan, initial_guess=make_transform(np.eye(3), centre))
            if self.config.retrieve:
                self.localize(scan)
        except GenRegError:
            pass
        finally:
            self._local = local

    def place_index(self) -> PlaceIndex:
        """The map's place index (`genreg_core.place_index`; the index settings), built on first use and kept
        (and in `cache_dir`, by the map's content hash and the settings)."""
        if self._index is None:
            c = self.config
            geometry = IndexGeometry(spacing=c.index_spacing, radius=c.index_radius, band=c.index_band)
            path = None if self.cache_dir is None else self.cache_dir / (
                f"index-v{INDEX_VERSION}-{self._key}-s{c.index_spacing:.6g}-r{c.index_radius:.6g}-b{c.index_band:.6g}"
                f"-m{c.map_voxel:.6g}")
            self._index = read_index(path, geometry) if path is not None else None
            if self._index is None:
                self._index = PlaceIndex.build(self.map, geometry)
                if path is not None:
                    write_index(path, self._index)
        return self._index

    def whole_map(self) -> LocalMap:
        """The whole map indexed and prepared for GICP and VGICP (voxels of `screen_voxels` map voxels), once:
        what retrieved places are aligned against. Built on `map_threads`."""
        if self._whole is None:
            index = self._map_index or TargetIndex(self.map, self.threads, spacing=self.voxel_size,
                                                   build_threads=self.map_threads)
            index.gicp = GICPTarget(index, threads=self.threads, build_threads=self.map_threads)
            index.occupied(self.config.track_distance * self.voxel_size)  # `track`'s test of a guess, built now
            self._voxels = VoxelTarget(gicp_target(index), self.config.screen_voxels * self.voxel_size)
            self._whole = LocalMap(self.map.mean(axis=0), float("inf"), True, index)
        return self._whole

    def retrieved(self, scan: np.ndarray) -> RegistrationResult:
        """A scan without a guess placed by the place index: each of the `retrieve` places and headings it
        retrieves is aligned coarsely by VGICP against the whole map (`screen_points` of the scan's points,
        `COARSE_ITERATIONS` iterations, voxels of `screen_voxels`) and scored by the share of the points it
        seats in the voxels, and so is the
        fittest of them slid along the scan's main axis (`slides`: look-alike places along a road or a
        corridor); the `candidates` best distinct poses are
        aligned and verified as tracked scans are (`track`, from the coarse pose), and the most confident
        wins, bounded by its distinct rivals (`chosen`). When even the fittest retrieved pose seats fewer
        than `verify_fitness` of the points, no slides are tried and the candidates are aligned by
        `unfit_iterations` GICP iterations."""
        t0 = time.perf_counter()
        c = self.config
        hits = self.place_index().retrieve(scan, c.retrieve)
        t1 = time.perf_counter()
        whole = self.whole_map()
        assert self._voxels is not None
        rows = np.random.default_rng(self.registrar.config.seed).permutation(len(scan))[:c.screen_points]
        sample = scan[np.sort(rows)]
        aligned = [self._voxels.align(sample, hit_pose(h), max_iterations=COARSE_ITERATIONS) for h in hits]
        # no retrieved place fits (a scan the map does not hold): no look-alikes of it to look for
        unfit = bool(aligned) and max(share for _, share in aligned) < c.verify_fitness
        if aligned and c.slide_reach > 0 and not unfit:  # the fittest pose slid along the scan's main axis: a look-alike rival?
            fittest = max(aligned, key=lambda a: a[1])[0]
            aligned += [self._voxels.align(sample, T, max_iterations=COARSE_ITERATIONS)
                        for T in self.slides(sample, fittest)]
        coarse, fitness = [T for T, _ in aligned], [share for _, share in aligned]
        kept: list[int] = []
        for k in np.argsort(fitness, kind="stable")[::-1]:  # the fittest distinct poses
            if len(kept) < c.candidates and all(self.distinct(coarse[k], coarse[j]) for j in kept):
                kept.append(int(k))
        t2 = time.perf_counter()
        iterations = c.unfit_iterations if unfit else c.track_iterations
        # a candidate named as well fitted along the scan's axis is held (below): where it lies in its valley
        # decides nothing, and is not searched
        results = [r for k in kept
                   if (r := self.track(scan, coarse[k], local=whole, iterations=iterations, search=False)) is not None]
        if not results:  # nothing retrieved near enough to the map to align: the whole map from the identity
            results = [self.track(scan, np.eye(4), local=whole, search=False) or self._mapper.register(scan, self.map)]
        best = self.in_a_corridor(self.chosen(results), scan)
        if any(AS_WELL_FITTED in motion for motion in best.unconstrained):  # a uniform corridor, and no guess
            best = replace(best, confidence=below_rival(best.confidence, best.confidence))
        best.timings = {"retrieve": t1 - t0, "screen": t2 - t1, "refine": time.perf_counter() - t2,
                        "total": time.perf_counter() - t0}
        return best

    def slides(self, sample: np.ndarray, T: np.ndarray) -> list[np.ndarray]:
        """T moved along the scan's main horizontal axis (the principal axis of its points' xy: a road's or
        a corridor's direction), both ways, by every multiple of two VGICP voxels (`screen_voxels`) up to
        `slide_reach` m: where a repeating street or corridor would put a look-alike pose."""
        direction = T[:3, :3] @ main_axis(sample)
        step = 2.0 * self.config.screen_voxels * self.voxel_size
        shifts = np.arange(step, self.config.slide_reach + 1e-9, step)
        return moved_along(T, direction, (*shifts, *-shifts))

    def distinct(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        """Whether two map poses are distinct (`rival_distance` map voxels or PDSAC's mode separation apart): two
        distinct poses of one scan cannot both be right."""
        return distinct_poses(T_a, T_b, np.radians(self.registrar.config.pdsac.mode_separation),
                              self.config.rival_distance * self.voxel_size)

    def chosen(self, results: Sequence[RegistrationResult]) -> RegistrationResult:
        """The most confident of several results for one scan, its confidence bounded by the most confident
        distinct one (`rival_distance` map voxels or PDSAC's mode separation apart: two distinct poses cannot
        both be right). A rival that lowers the confidence, or is at least half as probable as the pose, is named
        among the result's unconstrained motions ("translation along (x,
        y, z) to a rival pose d m away") and its offset widens the covariance as a mixture of the two poses
        would (p (1 - p) d d^T on the translation block, p the rival's probability)."""
        best = max(results, key=lambda r: r.confidence)
        rivals = [r for r in results if r.confidence > 0 and self.distinct(r.transformation, best.transformation)]
        if not rivals:
            return best
        rival = max(rivals, key=lambda r: r.confidence)
        p = rival.confidence
        if p <= 1.0 - best.confidence and p < best.confidence / 2:  # it neither bounds nor rivals the pose
            return best
        return rivalled(best, rival, p * (1.0 - p), p)

    def screen(self, scan: np.ndarray, places: Sequence[np.ndarray]) -> list[RegistrationResult]:
        """The scan registered against every place (point sets), unrefined, in batches of `batch_size`."""
        results: list[RegistrationResult] = []
        batch = self.config.batch_size
        for start in range(0, len(places), batch):
            results += self._screener.register_many([(scan, place) for place in places[start: start + batch]])
        return results

    def refined(self, scan: np.ndarray, guess: np.ndarray, centre: np.ndarray, radius: float) -> RegistrationResult:
        """The scan registered from `guess` against the map cropped to `crop_radius` x `radius` around
        `centre` (the whole map when the crop holds too few points)."""
        crop = self.crop(centre, self.config.crop_radius * radius)
        target = crop if len(crop) >= self.registrar.config.min_points else self.map
        return self._mapper.register(scan, target, guess)


__all__ = ["TRACKING_CALIBRATION", "MapLocalizer", "map_parts", "median_spacing"]
