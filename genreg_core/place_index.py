"""The place index of a gravity-aligned map: a descriptor per place, computed once with the map, and the
retrieval of the few places (and headings) a scan is likely taken from.

    index = PlaceIndex.build(map_xyz, IndexGeometry())     # once per map (cached with it by MapLocalizer)
    hits = index.retrieve(scan_xyz, count=8)                # [Hit(centre, yaw, distance, ground), ...]

A place is a point where a sensor could stand: the centre of a cell of a horizontal grid (`spacing` m)
that holds ground and no obstacle. Its descriptor is a polar height image of the map around it (Scan
Context, Kim and Kim 2018): `rings` x `sectors` bins out to `radius` m, each the highest point in the
bin between the ground and `band` m above it (taller structure - ceilings, canopies - is left out, so a
facade, a wall and a parked car read the same from any height of sensor), and nothing behind a wall
(what a sensor at the place would not see: the next corridor, the street behind a facade). Heights are above the local
ground: the lowest point within a cell's neighbourhood (`ground_cells`). A scan's descriptor is the same
image around its origin, the sensor, in its own frame, whose z axis must point up (REP-103: a LiDAR on a
robot base; within about 10 deg). Both are computed by one function (`height_image`, `describe`) on a
raster of `cell` m, so a scan and the map around its true place agree up to what the scan does not see.

Retrieval compares the scan's image with every place's at every sector shift (a circular
cross-correlation by FFT over the places' spectra, computed with the index and kept in place of the
descriptors, frequency by frequency: one matrix product per frequency over every place); the best shifts
give the heading. It costs rings x sectors multiply-adds per place, under a microsecond: a map of 4 x 10^4
places is searched in about 30 ms, a small share of a localisation's time at any map size the node holds in
memory. (Rotation-invariant keys, such as each ring's mean or its spectrum's magnitudes,
shortlisted the true place far less often on synthetic streets, so every place is compared.)

Conventions (`genreg_core.geometry`): metres, x forward, y left, z up; yaw counter-clockwise about z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy.ndimage import minimum_filter

from genreg_core.errors import TooFewPointsError

EMPTY = np.float32(np.inf)  # a raster cell without points
GROUND_REACH = 15.0  # a scan's ground under its sensor is estimated from the cells within this many metres
GROUND_QUANTILE = 0.2  # ... as this quantile of their local ground
VERSION = 4  # of the descriptors and their spectra's layout: part of a cached index's name (a change makes
# caches stale)
BLOCKING = 0.95  # a descriptor bin this high (a share of the band) is a wall: the bins behind it are hidden
ENCLOSING_REACH = 4.0  # m: structure this near the sensor encloses its direction (`PlaceIndex.enclosure`)


@dataclass(frozen=True)
class IndexGeometry:
    """The shape of the place descriptors (every field in metres unless counted)."""

    spacing: float = 1.0  # places: one per free grid cell of this size
    radius: float = 30.0  # descriptor reach around a place
    rings: int = 15
    sectors: int = 60
    band: float = 2.0  # heights above the ground considered
    cell: float = 0.5  # raster of the height images
    ground_cells: int = 5  # the local ground: the lowest point within this many raster cells (odd)
    free_below: float = 0.3  # a place's cell holds nothing higher than this above the ground

    def __post_init__(self) -> None:
        if min(self.spacing, self.radius, self.band, self.cell) <= 0 or self.rings < 1 or self.sectors < 2:
            raise ValueError(f"invalid place index geometry {self}")
        if self.ground_cells < 1 or self.ground_cells % 2 == 0:
            raise ValueError(f"ground_cells must be odd and positive, got {self.ground_cells}")


@dataclass(frozen=True)
class Raster:
    """Height above the local ground per raster cell (the highest point within the band; 0 for ground
    only; -inf where nothing was seen), and the ground itself (inf where nothing was seen)."""

    origin: np.ndarray  # (2,) xy of cell (0, 0)'s corner
    cell: float
    height: np.ndarray  # (X, Y) float32
    ground: np.ndarray  # (X, Y) float32, z of the local ground

    def cells(self, xy: np.ndarray) -> np.ndarray:
        """The (K, 2) integer cells of xy positions."""
        return np.floor((np.asarray(xy, dtype=np.float64) - self.origin) / self.cell).astype(np.int64)


def height_image(points: np.ndarray, g: IndexGeometry, margin: float = 0.0) -> Raster:
    """The raster of (N, 3) points (z up): per cell the highest point within `band` above the local ground
    (the lowest z within `ground_cells` cells)."""
    xy = points[:, :2]
    origin = xy.min(axis=0) - margin - g.cell
    ij = np.floor((xy - origin) / g.cell).astype(np.int64)
    shape = tuple(int(v) for v in ij.max(axis=0) + 1 + int(np.ceil(margin / g.cell)) + 1)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    z = points[:, 2].astype(np.float32)
    low = np.full(shape[0] * shape[1], EMPTY, np.float32)
    np.minimum.at(low, flat, z)
    ground = minimum_filter(low.reshape(shape), size=g.ground_cells, mode="constant", cval=EMPTY)
    h = z - ground.reshape(-1)[flat]
    keep = h <= g.band
    top = np.full(shape[0] * shape[1], -np.inf, np.float32)
    np.maximum.at(top, flat[keep], h[keep])
    return Raster(origin, g.cell, top.reshape(shape), ground)


class Stencil:
    """The raster offsets within `radius` of a place and the polar bin (ring, sector) of each, sorted by
    bin, so that a descriptor is one gather and one `np.maximum.reduceat`."""

    def __init__(self, g: IndexGeometry) -> None:
        reach = int(np.ceil(g.radius / g.cell))
        di, dj = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
        dx, dy = di.ravel() * g.cell, dj.ravel() * g.cell  # offsets of the cell centres from the place's cell
        r = np.hypot(dx, dy)
        inside = r < g.radius
        ring = np.minimum((r[inside] / g.radius * g.rings).astype(np.int64), g.rings - 1)
        theta = np.arctan2(dy[inside], dx[inside])
        sector = np.minimum(((theta + np.pi) / (2 * np.pi) * g.sectors).astype(np.int64), g.sectors - 1)
        bins = ring * g.sectors + sector
        order = np.argsort(bins, kind="stable")
        self.di, self.dj, self.bins = di.ravel()[inside][order], dj.ravel()[inside][order], bins[order]
        self.starts = np.flatnonzero(np.r_[True, np.diff(self.bins) > 0])
        self.present = self.bins[self.starts]  # bins that hold at least one cell (all, at these sizes)
        self.shape = (g.rings, g.sectors)
        self.reach = reach


def describe(raster: Raster, cells: np.ndarray, stencil: Stencil, band: float, chunk: int = 256) -> np.ndarray:
    """(K, rings, sectors) float32 descriptors of places at raster `cells` (K, 2): per polar bin the highest
    point above the ground (0 where the bin holds no structure or nothing was seen), and 0 behind a wall: a
    bin whose structure reaches the band's top (`BLOCKING` x `band`: a wall or a facade, not a parked car)
    hides the farther bins of its sector, as it hides them from a sensor there (the map holds what the
    sensor cannot see from the place: other corridors, the next street)."""
    padded = np.pad(np.maximum(raster.height, 0.0), stencil.reach)
    out = np.zeros((len(cells), stencil.shape[0] * stencil.shape[1]), np.float32)
    for start in range(0, len(cells), chunk):
        c = cells[start: start + chunk] + stencil.reach
        values = padded[c[:, :1] + stencil.di[None], c[:, 1:] + stencil.dj[None]]
        out[start: start + chunk, stencil.present] = np.maximum.reduceat(values, stencil.starts, axis=1)
    out = out.reshape(len(cells), *stencil.shape)
    wall = out >= BLOCKING * band
    out[np.cumsum(wall, axis=1) - wall > 0] = 0.0  # a wall nearer in the same sector
    return out


def spectra(descriptors: np.ndarray) -> np.ndarray:
    """(sectors // 2 + 1, K, rings) complex64: the sector spectra of (K, rings, sectors) descriptors whose
    columns are scaled to unit length (a column without structure stays zero), what `shift_distances` takes.
    Frequency-major, so that one frequency of every place is one (K, rings) matrix. In single precision
    without float64 temporaries (scipy's FFT keeps float32; numpy's would work in float64: seconds, not tens
    of milliseconds, on a map of 40,000 places)."""
    descriptors = np.asarray(descriptors, dtype=np.float32)
    norms = np.sqrt(np.einsum("krs,krs->ks", descriptors, descriptors))[:, None]
    unit = np.ascontiguousarray((descriptors / np.maximum(norms, np.float32(1e-6))).transpose(2, 0, 1))
    return scipy.fft.rfft(unit, axis=0).astype(np.complex64, copy=False)


def shift_distances(query: np.ndarray, candidates: np.ndarray, sectors: int) -> np.ndarray:
    """(K, sectors) Scan Context distances between a query and K candidates, both as `spectra` (the query's
    of one descriptor), at every shift s (the candidate's sector j + s against the query's j): 1 - the mean
    over the sectors of the columns' cosine similarity. Circular cross-correlation by FFT: per frequency,
    the candidates' (K, rings) spectra times the query's conjugate (one batched matrix product), then the
    inverse FFT; K x rings x sectors operations."""
    products = np.matmul(candidates, np.conj(query).transpose(0, 2, 1))[..., 0]  # (frequencies, K)
    # place by place (contiguous), so that the minimum over the shifts reads each place's row in one pass
    return 1.0 - scipy.fft.irfft(np.ascontiguousarray(products.T), n=sectors, axis=1) / sectors


def smallest(values: np.ndarray, count: int) -> np.ndarray:
    """The indices of the `count` smallest values, smallest first, ties in index order: np.argsort(values,
    kind="stable")[:count] without sorting them all."""
    if count >= len(values):
        return np.argsort(values, kind="stable")
    bound = values[np.argpartition(values, count - 1)[:count]].max()
    within = np.flatnonzero(values <= bound)  # in index order, every tie at the bound included
    return within[np.argsort(values[within], kind="stable")][:count]


@dataclass(frozen=True)
class Hit:
    """A retrieved place: where the sensor would stand (`centre`: x, y, the ground's z) and its heading
    (`yaw`, rad, of the scan's x axis in the map), with the descriptor distance (0: identical)."""

    centre: np.ndarray  # (3,)
    yaw: float
    distance: float


class PlaceIndex:
    """A map's places (their centres) and their descriptors' `spectra`, what retrieval compares."""

    def __init__(self, geometry: IndexGeometry, centres: np.ndarray, spectra: np.ndarray) -> None:
        """`spectra`: (sectors // 2 + 1, K, rings) complex64, `spectra` of the places' descriptors."""
        self.geometry = geometry
        self.centres = np.asarray(centres, dtype=np.float64)  # (K, 3): x, y, ground z
        self.spectra = np.asarray(spectra, dtype=np.complex64)
        if self.spectra.shape != (geometry.sectors // 2 + 1, len(self.centres), geometry.rings):
            raise ValueError(f"spectra of shape {self.spectra.shape} do not fit {len(self.centres)} places of {geometry}")
        self.stencil = Stencil(geometry)  # a scan's descriptor reuses it (built once, not per scan)

    def __len__(self) -> int:
        return len(self.centres)

    @classmethod
    def build(cls, map_xyz: np.ndarray, geometry: IndexGeometry = IndexGeometry()) -> PlaceIndex:
        """The places of a gravity-aligned map: the free cells of a `spacing` grid with ground under them
        (`IndexGeometry.free_below`), each described (`describe`)."""
        g = geometry
        raster = height_image(map_xyz, g, margin=g.radius)
        step = max(1, round(g.spacing / g.cell))
        # a place's cell: ground seen, nothing above free_below within the place's grid cell
        h = raster.height
        X, Y = (h.shape[0] // step) * step, (h.shape[1] // step) * step
        blocks = h[:X, :Y].reshape(X // step, step, Y // step, step)
        seen = np.isfinite(blocks).mean(axis=(1, 3)) >= 0.5
        free = np.nan_to_num(blocks, neginf=0.0).max(axis=(1, 3)) < g.free_below
        bi, bj = np.nonzero(seen & free)
        cells = np.stack([bi * step + step // 2, bj * step + step // 2], axis=1)
        ground = raster.ground[cells[:, 0], cells[:, 1]]
        ok = np.isfinite(ground)
        cells, ground = cells[ok], ground[ok]
        xy = raster.origin + (cells + 0.5) * g.cell
        return cls(g, np.column_stack([xy, ground]), spectra(describe(raster, cells, Stencil(g), g.band)))

    def describe_scan(self, scan_xyz: np.ndarray) -> tuple[np.ndarray, float]:
        """The scan's descriptor around its origin (the sensor) and the ground's z under it, scan frame."""
        g = self.geometry
        near = scan_xyz[np.einsum("ij,ij->i", scan_xyz[:, :2], scan_xyz[:, :2]) < (g.radius + g.cell) ** 2]
        if len(near) < 10:
            raise TooFewPointsError(f"the scan has {len(near)} points within {g.radius} m of its origin; "
                                    "the place index needs its surroundings")
        raster = height_image(near, g, margin=g.radius)
        at = raster.cells(np.zeros((1, 2)))
        # the ground under the sensor: a low quantile of the cells' lowest points within GROUND_REACH (most
        # cells near a sensor see the ground; walls and cars only raise the upper ones)
        reach = int(GROUND_REACH / g.cell)
        window = raster.ground[max(at[0, 0] - reach, 0): at[0, 0] + reach + 1,
                               max(at[0, 1] - reach, 0): at[0, 1] + reach + 1]
        seen = window[np.isfinite(window)]
        ground = float(np.quantile(seen, GROUND_QUANTILE)) if len(seen) else float(near[:, 2].min())
        return describe(raster, at, self.stencil, g.band)[0], float(ground)

    def enclosure(self, scan_xyz: np.ndarray) -> float:
        """The share of directions (the descriptor's sectors) in which structure (`free_below` to `band` above the
        scan's ground) stands within `ENCLOSING_REACH` m of the sensor (scan frame, z up): 0.53-0.85 in the
        corridors of the training campuses, at most 0.37 on their roads."""
        g = self.geometry
        _, ground = self.describe_scan(scan_xyz)
        height = scan_xyz[:, 2] - ground
        xy = scan_xyz[(height > g.free_below) & (height <= g.band), :2]
        near = xy[np.einsum("ij,ij->i", xy, xy) < ENCLOSING_REACH**2]
        sector = ((np.arctan2(near[:, 1], near[:, 0]) + np.pi) / (2 * np.pi) * g.sectors).astype(np.int64)
        return len(np.unique(np.minimum(sector, g.sectors - 1))) / g.sectors

    def retrieve(self, scan_xyz: np.ndarray, count: int, chunk: int = 16384) -> list[Hit]:
        """The `count` most similar (place, heading) pairs for a scan (sensor frame, z up): every place
        compared at every sector shift (`shift_distances`), each place at its best heading and, if it is a
        second local minimum, the heading half a turn from it (a street looks alike both ways)."""
        query, ground = self.describe_scan(scan_xyz)
        q, sectors = spectra(query[None]), self.geometry.sectors
        half = sectors // 2
        best, turned = np.empty(len(self), np.int64), np.empty(len(self), np.int64)
        d_best, d_turned = np.empty(len(self)), np.empty(len(self))
        for start in range(0, len(self), chunk):  # bounded memory on large maps
            d = shift_distances(q, self.spectra[:, start: start + chunk], sectors)
            rows = np.arange(len(d))
            k = np.argmin(d, axis=1)
            # the best shift within a quarter turn of the opposite heading (in d twice over: no wrapping)
            window = k[:, None] + (half + np.arange(-sectors // 4, sectors // 4 + 1))[None]
            j = window[rows, np.argmin(np.concatenate([d, d], axis=1)[rows[:, None], window], axis=1)] % sectors
            best[start: start + len(d)], turned[start: start + len(d)] = k, j
            d_best[start: start + len(d)], d_turned[start: start + len(d)] = d[rows, k], d[rows, j]
        places = np.concatenate([np.arange(len(self)), np.arange(len(self))])
        shifts, distances = np.concatenate([best, turned]), np.concatenate([d_best, d_turned])
        order = smallest(distances, count)
        step = 2 * np.pi / sectors
        hits = []
        for o in order:
            centre = self.centres[places[o]].copy()
            centre[2] -= ground  # the sensor stands as high above the map's ground as above the scan's
            hits.append(Hit(centre, float(np.angle(np.exp(1j * shifts[o] * step))), float(distances[o])))
        return hits


def hit_pose(hit: Hit) -> np.ndarray:
    """T_map_scan of a retrieved place: the scan turned by the hit's yaw about z, its origin at the centre."""
    c, s = np.cos(hit.yaw), np.sin(hit.yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = hit.centre
    return T


__all__ = ["Hit", "IndexGeometry", "PlaceIndex", "hit_pose"]
