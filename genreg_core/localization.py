"""Localisation of a scan in a prebuilt map: T_map_scan with GenReg, with or without an initial guess.

    loc = MapLocalizer(map_xyz)                      # (M, 3) map in metres, e.g. fused and voxelised frames
    result = loc.localize(scan_xyz)                  # (N, 3) scan in its sensor frame
    result.transformation                            # T_map_scan; result.confidence: P(the pose is right)

A raw depth scan is dense near the camera and sparse far away, a fused map even: the scan is first
voxelised to the map's resolution (its median nearest-neighbour spacing, or `voxel_size`), so the model's
512 samples of both clouds see the same surfaces alike.

Without a guess, the scan is first registered against the whole map; that pose stands when the map is
not much larger than the scan (extent below `whole_map_ratio` x the scan's) or its confidence reaches
`accept_whole`. Otherwise (a room larger than the view, a floor, a building: too few of the model's map
samples lie where the scan is; on redkitchen training maps 1.8-1.9x a scan's extent the whole map placed
11 of 13 and 5 of 11 scans, the places 13 of 13 each) the map is cut into candidate places: the centres
of occupied cells of a grid with spacing `place_spacing` x the scan's radius, each place the map points
within `place_radius` x that radius of its centre (built on first use per radius, cached). The scan is
registered against every place in batched `Registrar.register_many` calls, unrefined (GenReg is rotation
invariant: no orientation is searched); the best `candidates` by confidence are verified against a crop
of the whole map around each (registration from the candidate's pose as the initial guess), and the most
confident pose, the whole map's included, wins.

With a guess (tracking), the scan is aligned by GICP from the guess against the whole map, prepared once
at load (`refine.GICPTarget`: its covariances and k-d tree), with no network pass: about 10 ms on a
kitchen map. Its confidence is the calibration's `TRACKING` model (fitted on training maps from guesses
near and far from the truth: `scripts/calibrate_confidence.py fit-tracking`) over the same verification
features, the inlier ratio taken as 1 (no generated correspondences). When that probability is below
`track_below` (a guess too far off), the map is cropped around the guessed scan position (`crop_radius` x
the scan's radius) and GenReg registers the scan from the guess; the more probable pose wins. A
checkpoint whose calibration has no `TRACKING` model always takes that second path.

A scan the map does not hold gets a low confidence, not an exception; bad input raises the named errors
the Registrar raises (`genreg_core.errors`). Constants were chosen on redkitchen training frames 0-799.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from genreg_core.confidence import FEATURES, SPACINGS, features
from genreg_core.config import SCENE_MODEL, SCENE_REGISTRATION, RegistrationConfig
from genreg_core.errors import ConfigError, TooFewPointsError
from genreg_core.geometry import apply_transform
from genreg_core.prepare import check_transform, robust_extent, validate_cloud
from genreg_core.preprocess import voxel_downsample
from genreg_core.refine import GICPTarget
from genreg_core.registration import Registrar, RegistrationResult
from genreg_core.score import (
    COVARIANCE_FLOOR_M,
    COVARIANCE_FLOOR_RAD,
    COVARIANCE_INFLATION,
    FITNESS_SPACINGS,
    TIGHT_SPACINGS,
    TargetIndex,
    overlap_shares,
    pose_covariance,
    unconstrained_directions,
)

SPACING_SAMPLES = 20_000  # the map's resolution is the median nearest-neighbour spacing of this many points
RADIUS_QUANTILE = 0.9  # a scan's radius: this quantile of its points' distances from their centroid
SCREEN_POINTS = 1000  # candidate places are scored on this many points (the verification on the profile's)
PLACE_CHUNK = 256  # place centres searched at once
RADIUS_STEP = 1.25  # scan radii are rounded up to powers of this, so nearby radii share one place grid
TRACKING = "map_tracking"  # the calibration's model of tracking results (`ConfidenceModel.by_refinement` key)
TRACK_POINTS = 2500  # tracking aligns and verifies at most this many of the voxelised scan's points (speed: 17 ms on a kitchen map, 42 with 5000, as accurate)
TRACK_DISTANCE = 10.0  # tracking's GICP correspondence distance, map voxels
TRACK_ITERATIONS = 30  # and its iterations


def median_spacing(points: np.ndarray, samples: int = SPACING_SAMPLES, seed: int = 0) -> float:
    """The median distance from a point to its nearest other point, over up to `samples` points."""
    tree = cKDTree(points)
    rows = np.random.default_rng(seed).choice(len(points), size=min(samples, len(points)), replace=False)
    distances, _ = tree.query(points[rows], k=2)
    return float(np.median(distances[:, 1]))


class MapLocalizer:
    """A map (float64, with a k-d tree) and a GenReg `Registrar` (default: the scene model and profile)
    that place scans in it. Thread-compatible, not thread-safe (the place grids are cached)."""

    def __init__(
        self,
        map_xyz: np.ndarray,
        config: RegistrationConfig | None = None,
        checkpoint: str = SCENE_MODEL,
        *,
        voxel_size: float | None = None,
        registrar: Registrar | None = None,
        candidates: int = 3,
        whole_map_ratio: float = 1.25,
        accept_whole: float = 0.9,
        place_spacing: float = 0.5,
        place_radius: float = 1.2,
        crop_radius: float = 1.5,
        batch_size: int = 16,
        track_below: float = 0.5,
        threads: int | None = None,
    ) -> None:
        """`map_xyz`: (M, 3) map points (metres, or any units the scans share); `voxel_size`: the map's
        resolution (None: its median nearest-neighbour spacing); `registrar`: a loaded one instead of
        `checkpoint` + `config`; `threads`: tracking's threads (default: OMP_NUM_THREADS, else 1); the other
        settings as in the module docstring."""
        config = config or SCENE_REGISTRATION
        self.registrar = registrar or Registrar.from_checkpoint(checkpoint, config)
        min_points = self.registrar.config.min_points
        finite, _ = validate_cloud(map_xyz, "map", min_points)
        for name, value, low in (("candidates", candidates, 1), ("batch_size", batch_size, 1)):
            if not isinstance(value, int) or value < low:
                raise ConfigError(f"{name} must be an integer >= {low}, got {value!r}")
        for name, value in (("accept_whole", accept_whole), ("track_below", track_below)):
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {value!r}")
        for name, value in (("whole_map_ratio", whole_map_ratio), ("place_spacing", place_spacing),
                            ("place_radius", place_radius), ("crop_radius", crop_radius)):
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number, got {value!r}")
        if voxel_size is not None and not (np.isfinite(voxel_size) and voxel_size >= 0):
            raise ConfigError(f"voxel_size must be >= 0, got {voxel_size!r}")
        self.map = np.ascontiguousarray(finite, dtype=np.float64)
        self.tree = cKDTree(self.map)
        self.voxel_size = median_spacing(self.map) if voxel_size is None else float(voxel_size)
        self.index = TargetIndex(self.map, threads, spacing=self.voxel_size)  # tracking's scores
        self.gicp = GICPTarget(self.map, tree=self.index.tree, threads=self.index.threads)  # tracking's GICP
        self.track_below = track_below
        _, self.extent = robust_extent(self.map)
        self.candidates = candidates
        self.whole_map_ratio = whole_map_ratio
        self.accept_whole = accept_whole
        self.place_spacing = place_spacing
        self.place_radius = place_radius
        self.crop_radius = crop_radius
        self.batch_size = batch_size
        self._places: dict[float, list[np.ndarray]] = {}  # scan radius -> the places' map rows
        # candidates are screened without refinement (ranking only), then verified with the full profile
        cfg = self.registrar.config
        self._screen_config = replace(cfg, refine=replace(cfg.refine, method="none", num_points=SCREEN_POINTS),
                                      pdsac=replace(cfg.pdsac, modes=1))

    def places(self, radius: float) -> list[np.ndarray]:
        """The candidate places for scans of this radius, as map row indices: the map points within
        `place_radius` x `radius` of each centre of an occupied grid cell (grid spacing `place_spacing` x
        `radius`) as int32 rows (places overlap: about 60 per map point at the default spacing and radius;
        a random subset per place placed fewer redkitchen training scans); places with fewer points than
        registration needs are dropped. Built on first use, cached by radius."""
        if radius not in self._places:
            spacing = self.place_spacing * radius
            cells = np.unique(np.floor(self.map / spacing).astype(np.int64), axis=0)
            centres = (cells + 0.5) * spacing
            minimum, kept = self.registrar.config.min_points, []
            for start in range(0, len(centres), PLACE_CHUNK):  # a chunk at a time: large maps, few lists alive
                for rows in self.tree.query_ball_point(centres[start: start + PLACE_CHUNK], self.place_radius * radius):
                    if len(rows) >= minimum:
                        kept.append(np.asarray(rows, dtype=np.int32))
            self._places[radius] = kept
        return self._places[radius]

    def crop(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """The map points within `radius` of `centre`."""
        return self.map[np.asarray(self.tree.query_ball_point(np.reshape(centre, 3), radius), dtype=np.int64)]

    def scan_geometry(self, scan: np.ndarray) -> tuple[np.ndarray, float, float]:
        """(centroid, radius rounded up to a power of `RADIUS_STEP`, robust extent) of a voxelised scan."""
        centroid = scan.mean(axis=0)
        radius = float(np.quantile(np.linalg.norm(scan - centroid, axis=1), RADIUS_QUANTILE))
        radius = RADIUS_STEP ** np.ceil(np.log(max(radius, 1e-9)) / np.log(RADIUS_STEP))
        return centroid, float(radius), robust_extent(scan)[1]

    def localize(self, scan_xyz: np.ndarray, initial_guess: np.ndarray | None = None) -> RegistrationResult:
        """T_map_scan of a scan (`transformation`) and its calibrated confidence; `initial_guess`: a 4x4
        T_map_scan to start from. A scan the map does not hold gets a low confidence; bad input raises
        the Registrar's named errors. The result's clouds and masks are those of the voxelised scan."""
        reg = self.registrar
        finite, _ = validate_cloud(scan_xyz, "source", reg.config.min_points)
        guess = None if initial_guess is None else check_transform(initial_guess)
        scan = voxel_downsample(np.asarray(finite, dtype=np.float64), self.voxel_size)
        if len(scan) < reg.config.min_points:
            raise TooFewPointsError(f"source has {len(scan)} points after voxelising to the map's "
                                    f"{self.voxel_size:.3g}; registration needs at least {reg.config.min_points}")
        centroid, radius, extent = self.scan_geometry(scan)
        if guess is not None:
            tracked = self.track(scan, guess) if self.tracking_calibrated else None
            if tracked is not None and tracked.confidence >= self.track_below:
                return tracked
            searched = self.refined(scan, guess, apply_transform(guess, centroid[None])[0], radius)
            return searched if tracked is None else max(tracked, searched, key=lambda r: r.confidence)
        whole = reg.register(scan, self.map)
        places = self.places(radius)
        if self.extent < self.whole_map_ratio * extent or whole.confidence >= self.accept_whole or not places:
            return whole
        screened = self.screen(scan, [self.map[rows] for rows in places])
        best = sorted(range(len(screened)), key=lambda k: -screened[k].confidence)[: self.candidates]
        verified = [self.refined(scan, screened[k].transformation,
                                 apply_transform(screened[k].transformation, centroid[None])[0], radius) for k in best]
        return max([whole, *verified], key=lambda r: r.confidence)

    @property
    def tracking_calibrated(self) -> bool:
        """Whether the registrar's calibration has a model of tracking results (`TRACKING`)."""
        calibration = self.registrar.calibration
        return calibration is not None and calibration.serves(TRACKING)

    def track(self, scan: np.ndarray, guess: np.ndarray) -> RegistrationResult:
        """The voxelised scan aligned by GICP from `guess` (T_map_scan) against the whole map, verified as a
        registration is (`confidence.FEATURES`, inlier ratio 1: no network pass; the result's `inlier_ratio`
        and generated clouds are empty: NaN and (0, 3)). Its confidence is the `TRACKING` model's
        probability, else (uncalibrated) the geometric mean of fitness and tight fitness; both times the
        degeneracy factor."""
        t0 = time.perf_counter()
        rows = np.random.default_rng(self.registrar.config.seed).permutation(len(scan))[:TRACK_POINTS]
        sample = scan[np.sort(rows)]
        voxel, threads = self.voxel_size, self.index.threads
        T = self.gicp.align(sample, guess, max_distance=TRACK_DISTANCE * voxel, max_iterations=TRACK_ITERATIONS,
                            threads=threads)
        t1 = time.perf_counter()
        moved = apply_transform(T, sample)
        distance = FITNESS_SPACINGS * voxel
        shares = overlap_shares(sample, self.index, T, np.multiply(SPACINGS, voxel))
        fitness, tight = (float(x) for x in overlap_shares(sample, self.index, T, np.array([distance, TIGHT_SPACINGS * voxel])))
        _, squared = self.index.nearest(moved)
        close = squared < distance * distance
        unconstrained, constraint = unconstrained_directions(moved, self.index, distance)
        covariance = pose_covariance(moved, self.index, T[:3, 3], distance, COVARIANCE_INFLATION,
                                     (COVARIANCE_FLOOR_M, COVARIANCE_FLOOR_RAD))
        verification = features(shares, 1.0, constraint)
        calibration = self.registrar.calibration
        probability = (calibration.probability(verification, TRACKING) if self.tracking_calibrated
                       else float(np.sqrt(fitness * tight)))
        t2 = time.perf_counter()
        return RegistrationResult(
            transformation=T, source_generated=np.zeros((0, 3), np.float32), target_generated=np.zeros((0, 3), np.float32),
            aligned_source=apply_transform(T, scan).astype(np.float32), source_valid_mask=np.ones(len(scan), bool),
            fitness=fitness, tight_fitness=tight, inlier_ratio=float("nan"),
            inlier_rmse=float(np.sqrt(squared[close].mean())) if close.any() else float("nan"),
            confidence=constraint * probability, start="initial_guess", covariance=covariance,
            unconstrained=unconstrained, verification=dict(zip(FEATURES, verification.tolist(), strict=True)),
            timings={"refine": t1 - t0, "postprocess": t2 - t1, "total": t2 - t0})

    def screen(self, scan: np.ndarray, places: Sequence[np.ndarray]) -> list[RegistrationResult]:
        """The scan registered against every place (point sets), unrefined, in batches of `batch_size`."""
        screener = Registrar(self.registrar.model, self._screen_config, self.registrar.calibration)
        results: list[RegistrationResult] = []
        for start in range(0, len(places), self.batch_size):
            results += screener.register_many([(scan, place) for place in places[start: start + self.batch_size]])
        return results

    def refined(self, scan: np.ndarray, guess: np.ndarray, centre: np.ndarray, radius: float) -> RegistrationResult:
        """The scan registered from `guess` against the map cropped to `crop_radius` x `radius` around
        `centre` (the whole map when the crop holds too few points)."""
        crop = self.crop(centre, self.crop_radius * radius)
        target = crop if len(crop) >= self.registrar.config.min_points else self.map
        return self.registrar.register(scan, target, guess)


__all__ = ["TRACKING", "MapLocalizer", "median_spacing"]
