"""Pipeline stage "score": how well a transform explains the pair (fitness, inlier RMSE, overlap score).

fitness: the share of (refinement-resolution) source points that land within `FITNESS_SPACINGS` target
point spacings of a target point; tight fitness: the same within `TIGHT_SPACINGS`; inlier ratio: the share
of the generated correspondences (both directions) that the transform maps within PDSAC's inlier
threshold; overlap score: the geometric mean of the three (`overlap_score`: what the guard and the
fallback test, and the confidence of a registrar without a calibration, `genreg_core.result`).

Every score of a pair queries the same target cloud: `TargetIndex` builds its k-d tree (small_gicp) once
and serves the spacing, the fitness queries and the normals of the covariance from it. The score functions
take the target as its `TargetIndex` (the pipeline passes `PreparedPair.target_index`, one per pair) or as
an array (indexed afresh).
"""

from __future__ import annotations

import os

import numpy as np
import small_gicp

from genreg_core import kernels
from genreg_core.geometry import apply_transform

FITNESS_SPACINGS = 3.0  # fitness counts a source point as overlapping within this many target spacings
TIGHT_SPACINGS = 1.0  # tight fitness: within this many (the guard's comparison, a third of the overlap score)
NORMAL_NEIGHBOURS = 20  # target normals (covariance, point-to-plane ICP) from this many nearest neighbours
DENSE_CELLS = 1 << 25  # TargetIndex.occupied: a grid of at most this many cells is a flag per cell (32 MB)
REMEMBERED_QUERIES = 3  # TargetIndex.nearest answers the same points again from memory (last this many)
# pose_covariance's model error, calibrated on redkitchen training pairs by scripts/calibrate_covariance.py
# (MODEL_CARD.md): the Gauss-Newton covariance times COVARIANCE_INFLATION (residuals of neighbouring points
# are correlated) plus a floor of COVARIANCE_FLOOR_M (m) and COVARIANCE_FLOOR_RAD (rad) standard deviation
# per axis (errors that no residual shows: depth distortion, the ground truth's own error).
COVARIANCE_INFLATION = 48.5
# pose_covariance sums its Gauss-Newton Hessian over at most this many correspondences (evenly spread over
# the found ones) and scales it up to all of them: the target normals it needs are most of its cost.
COVARIANCE_ROWS = 1000
COVARIANCE_FLOOR_M = 0.0029
COVARIANCE_FLOOR_RAD = 0.0020
# unconstrained_directions: a motion whose normalised point-to-plane Hessian eigenvalue is below this share
# of the largest is unconstrained by the geometry (the ratios measured at true poses: MODEL_CARD
# "Verification and confidence", degeneracy)
DEGENERACY_RATIO = 0.005


# see_through: a scan's rays are binned by direction in bins of SEE_THROUGH_BIN_DEG degrees; a map point lies in
# front of the surface the scan saw along its bin when it is nearer to the sensor than the bin's nearest scan
# point by more than SEE_THROUGH_SPACINGS map spacings plus SEE_THROUGH_RELATIVE of that range (depth noise
# grows with range). Chosen on redkitchen training maps (MODEL_CARD "Map relocalisation": beyond the map).
SEE_THROUGH_BIN_DEG = 1.0
SEE_THROUGH_SPACINGS = 3.0
SEE_THROUGH_RELATIVE = 0.02


class TargetIndex:
    """One target cloud's k-d tree (small_gicp, exact search) with what the scores need from it, each
    computed on first use: the point spacing and the normals at the rows asked (PCA of `NORMAL_NEIGHBOURS`
    neighbours, as Open3D's KNN normals). Queries run on `threads` threads (default: OMP_NUM_THREADS,
    else 1)."""

    def __init__(self, points: np.ndarray, threads: int | None = None, spacing: float | None = None,
                 build_threads: int = 1) -> None:
        """`spacing`: the point spacing when known (a voxelised map's), else measured on first use;
        `build_threads`: the threads that build the k-d tree (a map's, once)."""
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.threads = threads or int(os.environ.get("OMP_NUM_THREADS") or 1)
        self.cloud = small_gicp.PointCloud(self.points)  # the tree's points; GICP's too (`refine.gicp_target`)
        self.tree = small_gicp.KdTree(self.cloud, num_threads=build_threads)
        self._spacing: float | None = spacing
        self._normals = np.zeros(self.points.shape)  # calloc'd: pages touched only where normals are asked
        self._has_normal = np.zeros(len(self.points), dtype=bool)
        self._mean: np.ndarray | None = None  # the points' mean, the normals' centre (`plane_normals`)
        self._queries: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # the last few `nearest` calls
        self._cells: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # `near_share`'s grids
        self.gicp: object | None = None  # the points prepared for GICP, on first use (`refine.gicp_target`)

    @classmethod
    def of(cls, target: np.ndarray | TargetIndex) -> TargetIndex:
        """`target` if it is an index, else a new index of the array."""
        return target if isinstance(target, TargetIndex) else cls(target)

    def nearest(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, squared distance) of each query point's nearest target point. The last `REMEMBERED_QUERIES`
        answers are kept: the same points asked again (the fitness and then the covariance of one pose) are
        answered from memory."""
        query = np.ascontiguousarray(query, dtype=np.float64)
        for asked, rows, squared in self._queries:
            if asked.shape == query.shape and np.array_equal(asked, query):
                return rows, squared
        found, squared = self.tree.batch_knn_search(query, 1, num_threads=self.threads)  # arrays, not lists
        rows, squared = found[:, 0].astype(np.int64), squared[:, 0]
        self._queries = [(query.copy(), rows, squared), *self._queries[:REMEMBERED_QUERIES - 1]]
        return rows, squared

    def occupied(self, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cells of a grid of edge `cell` that hold target points, found once per `cell` and kept: the
        grid's lowest cell (3,), its size in cells (3,) and its occupancy: a flag per cell by key (`grid_keys`)
        when the grid has at most `DENSE_CELLS` cells, else the sorted keys of the occupied ones."""
        if cell not in self._cells:
            low, size, keys = grid_keys(self.points, cell)
            if keys is None:
                raise ValueError(f"cells of {cell} m are too small for a target {size.tolist()} cells wide")
            total = int(np.prod(size))
            if total <= DENSE_CELLS:
                occupancy = np.zeros(total, dtype=bool)
                occupancy[keys] = True
            else:
                occupancy = sorted_distinct(keys)
            self._cells[cell] = (low, size, occupancy)
        return self._cells[cell]

    def near_share(self, query: np.ndarray, cell: float) -> float:
        """The share of the query points that fall in a cell of a grid of edge `cell` holding target points
        (`occupied`; each within `cell` x sqrt(3) of one): found by hashing, as fast far from the target as
        near it, where the k-d tree's nearest-neighbour search is not (points tens of metres from a map of
        millions visit much of its tree: seconds for a scan's 1,500)."""
        low, size, occupancy = self.occupied(cell)
        if len(query) == 0:
            return 0.0
        cells = np.floor(np.asarray(query, dtype=np.float64) / cell).astype(np.int64) - low
        wanted = cell_key(cells[((cells >= 0) & (cells < size)).all(axis=1)], size)
        if occupancy.dtype == bool:
            found = occupancy[wanted]
        else:
            found = occupancy[np.minimum(np.searchsorted(occupancy, wanted), len(occupancy) - 1)] == wanted
        return float(np.count_nonzero(found)) / len(query)

    @property
    def spacing(self) -> float:
        """Median distance from a target point to its nearest other target point."""
        if self._spacing is None:
            _, squared = self.tree.batch_knn_search(self.points, 2, num_threads=self.threads)
            self._spacing = float(np.median(np.sqrt(squared[:, 1])))
        return self._spacing

    @spacing.setter
    def spacing(self, value: float) -> None:
        """The point spacing, measured elsewhere (a map's, on a sample of its points)."""
        self._spacing = float(value)

    def normals(self, rows: np.ndarray) -> np.ndarray:
        """Unit normals (unoriented: only their line matters here) at these target rows: the PCA normal of
        each row's `NORMAL_NEIGHBOURS` nearest target points (as Open3D's KNN normals), computed once per
        row and only for the rows asked."""
        missing = sorted_distinct(rows[~self._has_normal[rows]])
        if len(missing):
            k = min(NORMAL_NEIGHBOURS, len(self.points))
            neighbours, _ = self.tree.batch_knn_search(self.points[missing], k, num_threads=self.threads)
            if self._mean is None:  # a map's mean once, not on every call (3 ms on a 3 M-point map)
                self._mean = kernels.cloud_mean(self.points)
            self._normals[missing] = plane_normals(self.points, neighbours.astype(np.int64), self._mean)
            self._has_normal[missing] = True
        return self._normals[rows]


def grid_keys(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The cells floor(p / cell) of finite (N >= 1, 3) points on the grid that bounds them: its lowest cell (3,),
    its size in cells (3,) and one int64 key per point's cell (`cell_key`); keys None when the grid has 2^62
    cells or more (no such key). Float32 points are divided in float32, as numpy would; compiled
    (`kernels.cell_bounds`, `kernels.cell_keys`: a 3 M-point map without its (N, 3) temporaries)."""
    points = np.asarray(points)
    points = np.ascontiguousarray(points, dtype=points.dtype if points.dtype in (np.float32, np.float64) else np.float64)
    edge = np.array([cell], dtype=points.dtype)
    low, high = kernels.cell_bounds(points, edge)
    size = high - low + 1
    if float(np.prod(size.astype(np.float64))) >= 2.0 ** 62:
        return low, size, None
    return low, size, kernels.cell_keys(points, edge, low, size)


def cell_key(offsets: np.ndarray, size: np.ndarray) -> np.ndarray:
    """One integer per cell of a grid of `size` cells, from its (N, 3) offsets from the lowest cell, x-major."""
    return (offsets[:, 0] * size[1] + offsets[:, 1]) * size[2] + offsets[:, 2]


def sorted_distinct(values: np.ndarray) -> np.ndarray:
    """np.unique of an integer array by sorting (numpy 2's hash-based np.unique is 10x slower here)."""
    ordered = np.sort(values)
    return ordered[np.concatenate([[True], ordered[1:] != ordered[:-1]])] if len(ordered) else ordered


def plane_normals(points: np.ndarray, neighbours: np.ndarray, mean: np.ndarray | None = None) -> np.ndarray:
    """(m, 3) unit normals of the point sets `points[neighbours]` ((m, k) rows of an (M, 3) cloud): each
    set's least-variance direction (zero for a set with no spread), the eigenvector of the smallest
    eigenvalue of its covariance. The covariances come from moments about the cloud's mean (as Open3D's
    cumulants); the eigenvector in closed form: the eigenvalue by the trigonometric formula of a
    symmetric 3x3 matrix, the vector as the longest cross product of two rows of (C - lambda I). Matches
    LAPACK / Open3D to ~1e-13 on planar neighbourhoods. Compiled (`kernels.plane_normals`), one pass per set.
    `mean`: the cloud's mean if known (`kernels.cloud_mean` of these points: the same normals)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    if mean is None:
        return kernels.plane_normals(points, neighbours)
    return kernels.plane_normals_about(points, neighbours, np.ascontiguousarray(mean, dtype=np.float64))


def point_spacing(points: np.ndarray | TargetIndex) -> float:
    """Median distance from a point to its nearest neighbour in the same cloud (its sampling density)."""
    return TargetIndex.of(points).spacing


def fitness_distance(target: np.ndarray | TargetIndex) -> float:
    """The distance within which a moved source point counts as overlapping `target`."""
    return FITNESS_SPACINGS * point_spacing(target)


def overlap_fitness(src: np.ndarray, tgt: np.ndarray | TargetIndex, T: np.ndarray, threshold: float
                    ) -> tuple[float, float]:
    """Share of moved source points with a target point within `threshold`, and their RMS distance (Open3D
    `evaluate_registration`'s fitness and inlier RMSE; 0 RMSE when none is within)."""
    _, squared = TargetIndex.of(tgt).nearest(apply_transform(T, np.asarray(src, dtype=np.float64)))
    inliers = squared[squared < threshold * threshold]
    return len(inliers) / len(squared), float(np.sqrt(inliers.mean())) if len(inliers) else 0.0


def overlap_shares(src: np.ndarray, tgt: np.ndarray | TargetIndex, T: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """The share of moved source points with a target point within each of `distances` (one query: the
    fitness of `overlap_fitness` at several radii)."""
    _, squared = TargetIndex.of(tgt).nearest(apply_transform(T, np.asarray(src, dtype=np.float64)))
    return (squared[None, :] < np.square(np.asarray(distances, dtype=np.float64))[:, None]).mean(axis=1)


def overlap_score(fitness: float, tight_fitness: float, inlier_ratio: float) -> float:
    """In [0, 1]: the geometric mean of fitness, tight fitness and inlier ratio. The tight fitness tells a
    pose that seats a partial source on the target from one that only overlaps it loosely (MODEL_CARD
    "The confidence")."""
    return float(np.cbrt(fitness * tight_fitness * inlier_ratio))


def plane_residuals(moved: np.ndarray, target: np.ndarray | TargetIndex, max_distance: float,
                    max_rows: int | None = COVARIANCE_ROWS) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The point-to-plane correspondences of aligned clouds: each moved source point x_i with its nearest
    target point q_i within `max_distance` and the target normal n_i there. Returns (x, n, x - q, weight),
    or None when fewer than 12 are found. With more than `max_rows` correspondences (None: no limit),
    `max_rows` of them spread evenly over the found ones (the source rows are a random sample) and
    `weight` = found / max_rows, so that sums over them times `weight` estimate sums over all."""
    index = TargetIndex.of(target)
    rows, squared = index.nearest(moved)
    found = np.flatnonzero(squared <= max_distance * max_distance)
    if len(found) < 12:
        return None
    weight = 1.0
    if max_rows is not None and len(found) > max_rows:
        weight = len(found) / max_rows
        found = found[np.linspace(0, len(found) - 1, max_rows).astype(np.int64)]
    rows = rows[found]
    x = moved[found]
    return x, index.normals(rows), x - index.points[rows], weight


def plane_jacobian(x: np.ndarray, normals: np.ndarray, origin: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(n, 6) derivatives of the point-to-plane residuals n_i . (x_i - q_i) (times `scale`) by a pose
    perturbation in the parent frame, R' = exp(dtheta) R, t' = t + dt, with rotations about `origin`:
    (n_i, (x_i - origin) x n_i) in (dt, dtheta) order (ROS: x, y, z, rotation about x, y, z)."""
    return np.concatenate([normals, scale * np.cross(x - origin, normals)], axis=1)


def unconstrained_directions(moved: np.ndarray, target: np.ndarray | TargetIndex, max_distance: float,
                             limit: float = DEGENERACY_RATIO) -> tuple[tuple[str, ...], float]:
    """The motions that the aligned clouds' geometry does not constrain, and how well the worst is.

    The point-to-plane Hessian J^T J (`plane_jacobian`) about the correspondences' centroid, rotations in
    radians times the correspondences' RMS radius (so both blocks are in lengths), normalised by its
    largest eigenvalue: eigenvalues below `limit` are unconstrained directions (a plane leaves its two
    in-plane translations and the rotation about its normal free; a line the translation along it and the
    rotation about it), each described as "translation along (x, y, z)" or "rotation about (x, y, z)"
    (unit vectors in the clouds' frame; the larger of the eigenvector's two parts). Returns those texts
    and min(1, smallest ratio / `limit`): 1 for well-constrained geometry, towards 0 as it degenerates.
    Clouds with too few correspondences for a Hessian give ((), 1.0): nothing to judge."""
    found = plane_residuals(moved, target, max_distance)
    if found is None:
        return (), 1.0
    x, normals, _, _ = found
    centre = x.mean(axis=0)
    radius = float(np.sqrt(((x - centre) ** 2).sum(axis=1).mean())) or 1.0
    J = plane_jacobian(x, normals, centre, 1.0 / radius)
    values, vectors = np.linalg.eigh(J.T @ J)
    top = values[-1]
    if not top > 0:
        return ("translation along any axis", "rotation about any axis"), 0.0
    ratios = np.clip(values / top, 0.0, 1.0)
    texts = []
    for ratio, v in zip(ratios, vectors.T, strict=True):
        if ratio < limit:
            part, kind = (v[:3], "translation along") if np.linalg.norm(v[:3]) >= np.linalg.norm(v[3:]) \
                else (v[3:], "rotation about")
            texts.append(motion(kind, part))
    return tuple(texts), float(min(1.0, ratios[0] / limit))


def motion(kind: str, direction: np.ndarray) -> str:
    """An unconstrained motion's text: `kind` ("translation along", "rotation about") and the unit
    direction, one sign for a line of directions (its largest component positive): "translation along (x,
    y, z)"."""
    u = np.asarray(direction, dtype=np.float64) / max(float(np.linalg.norm(direction)), 1e-12)
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    return f"{kind} ({u[0]:.2f}, {u[1]:.2f}, {u[2]:.2f})"


def pose_covariance(moved: np.ndarray, target: np.ndarray | TargetIndex, origin: np.ndarray, max_distance: float,
                    inflation: float = 1.0, floor: tuple[float, float] = (0.0, 0.0), scale: float = 1.0,
                    max_rows: int | None = COVARIANCE_ROWS) -> np.ndarray | None:
    """6x6 covariance of a pose, in ROS order (x, y, z, rotation about x, y, z), from the point-to-plane
    residuals of the aligned clouds; None when fewer than 12 correspondences remain.

    Model: each moved source point x_i and its nearest target point q_i (within `max_distance`) with the
    target normal n_i give r_i = n_i . (x_i - q_i). The pose is perturbed in the parent (target) frame:
    R' = exp(dtheta) R, t' = t + dt, so dr_i/d(dt, dtheta) = (n_i, (x_i - origin) x n_i) with `origin`
    the pose's position t. Gauss-Newton: C = inflation * s^2 (J^T J)^-1 + diag(f_t^2 I, f_r^2 I), with
    s^2 = sum r_i^2 / (n - 6) and `floor` = (f_t, f_r). The residuals of neighbouring points are not
    independent, so the plain formula is over-confident; `inflation` and `floor` are calibrated on
    training pairs (MODEL_CARD.md). Units: `moved`, `target`, `origin` and `max_distance` share one frame
    whose lengths times `scale` are the output's (m), so normalised clouds give a metric covariance; radians.
    With more than `max_rows` correspondences (None: no limit), J^T J and s^2 are estimated on `max_rows`
    of them spread evenly over the found ones (the source rows are a random sample), J^T J scaled by
    n / max_rows: an unbiased estimate of the full sum, at a fraction of the normals' cost.
    """
    found = plane_residuals(moved, target, max_distance, max_rows)
    if found is None:
        return None
    x, normals, d, weight = found
    r = scale * np.einsum("ij,ij->i", normals, d)
    J = plane_jacobian(x, normals, origin, scale)
    H = weight * (J.T @ J)
    if np.linalg.cond(H) > 1e12:
        return None
    sigma2 = float(r @ r) / max(len(r) - 6, 1)
    C = inflation * sigma2 * np.linalg.inv(H) + np.diag([floor[0] ** 2] * 3 + [floor[1] ** 2] * 3)
    return 0.5 * (C + C.T)


def view_angles(points: np.ndarray, pole: np.ndarray, ahead: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range, elevation from the plane normal to `pole`, azimuth about `pole` from `ahead`) of sensor-frame points."""
    ranges = np.linalg.norm(points, axis=1)
    elevation = np.arcsin(np.clip(points @ pole / np.maximum(ranges, 1e-12), -1.0, 1.0))
    return ranges, elevation, np.arctan2(points @ np.cross(pole, ahead), points @ ahead)


def see_through(scan: np.ndarray, map_points: np.ndarray, T: np.ndarray, spacing: float) -> tuple[float, int]:
    """How much of the map a pose says the scan saw through: of the map points (`map_points`, map frame) that
    fall in a viewing direction the scan (sensor frame, the sensor at its origin) has returns in, and lie at
    or before its nearest return there (within `SEE_THROUGH_SPACINGS` x `spacing` + `SEE_THROUGH_RELATIVE`
    of its range), the share that lie in front of it: surfaces the sensor would have seen had it stood at
    T_map_scan `T`. A right pose leaves few (noise, moving things); a pose slid along a room or a corridor
    puts walls in front of what the scan saw. Returns (share, points counted); directions are binned in
    `SEE_THROUGH_BIN_DEG` degrees about the scan's least-seen axis (a camera's vertical, a LiDAR's up)."""
    scan = np.asarray(scan, dtype=np.float64)
    directions = scan / np.maximum(np.linalg.norm(scan, axis=1), 1e-12)[:, None]
    axes = np.linalg.eigh(directions.T @ directions)[1]  # ascending: the least-seen axis first, the most-seen last
    pole, ahead, step = axes[:, 0], axes[:, 2], np.radians(SEE_THROUGH_BIN_DEG)

    def bins(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ranges, elevation, azimuth = view_angles(points, pole, ahead)
        row, column = np.floor(elevation / step).astype(np.int64), np.floor(azimuth / step).astype(np.int64)
        return ranges, (row + 1024) * 4096 + column + 2048

    ranges, keys = bins(scan)
    order = np.argsort(keys)
    keys = keys[order]
    first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])  # each direction's first return, sorted
    seen, nearest = keys[first], np.minimum.reduceat(ranges[order], first)
    R, t = T[:3, :3], T[:3, 3]
    local = (np.asarray(map_points, dtype=np.float64) - t) @ R  # map points in the scan's frame
    map_ranges, map_keys = bins(local)
    at = np.clip(np.searchsorted(seen, map_keys), 0, len(seen) - 1)
    looked = seen[at] == map_keys
    margin = SEE_THROUGH_SPACINGS * spacing + SEE_THROUGH_RELATIVE * nearest[at]
    front = looked & (map_ranges < nearest[at] - margin)
    counted = int(np.count_nonzero(front | (looked & (map_ranges <= nearest[at] + margin))))
    return float(np.count_nonzero(front)) / max(counted, 1), counted

