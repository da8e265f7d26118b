"""Compiled inner loops of genreg's inference (numba; no gradient, CPU, one thread each, the GIL released).

PDSAC and the encoder work on thousands of tiny problems: 1,024 minimal sets of 3-4 correspondences, each
hypothesis against 1,024 correspondences, 512 neighbourhoods of 20 points per cloud. In torch each is a few
hundred small tensor operations or a batched LAPACK call that solves one 3x3 matrix after another, so their
cost was dispatch, not arithmetic (an SVD of 1,024 3x3 matrices: 2 ms; scoring 2 x 512 hypotheses: 2 ms and
a 2 MB residual table). Here each problem is one pass of scalar code, with the formulas of the torch form:

- PDSAC (`pdsac`):
  - `fit_rigid`: the weighted least-squares rigid transform of each set (Kabsch's problem: target ~ R source +
    t, det R = +1), by Horn's quaternion method in Theobald's QCP form. R is the rotation of the unit
    quaternion that is the top eigenvector of the symmetric, traceless 4x4 key matrix K of the
    cross-covariance; its top eigenvalue is the largest root of det(K - x I) = x^4 + c2 x^2 + c1 x + c0,
    which Newton's method reaches monotonically from the upper bound (sum of both spreads) / 2; the
    eigenvector is the longest row of the adjugate of K - x I. Float64 inside. Sets whose top eigenvalue
    repeats (collinear or coinciding points) get one of their equally good rotations, or identity when the
    adjugate vanishes, as the SVD picks arbitrarily there.
  - `truncated_scores`: s_h = sum_i w_i min(|R_h src_i + t_h - dst_i|, tau) / sum_i w_i, without storing the
    residuals.
  - `consensus`: the local optimisation of the best hypotheses, the choice among them and the tightened
    refits.
  - `weighted_sets`: the inverse-CDF mapping of uniform draws to weighted minimal sets.
- Encoder (`model.gcnn`, `model.invariant`): `knn_self` (the kNN graph), `invariant_geometry` (the
  rotation-invariant point-pair features), `neighbour_max` (the edge convolution's max over neighbours);
  interact and generate (`model.genreg`): `first_index` (each point's best match, given its log weight),
  `neighbour_mix` (the generated point from the best match's neighbours).
- Clouds (`preprocess`): `voxel_centroids` (each occupied voxel's centroid, the voxels by a hash table);
  grids (`score.grid_keys`): `cell_bounds`, `cell_keys` (the cells of a map of millions of points, without
  its (N, 3) temporaries).
- Scores and output (`score`, `prepare`): `plane_normals` (target normals; `plane_normals_about` about a known mean), `transform_rows` (the aligned
  full-resolution cloud); `copy_rows` (x, y, z out of a PointCloud2's records, `genreg_ros.pointcloud2`).

Their callers use them where `usable` says so, and the torch forms elsewhere (training's gradients, other
devices, tracing and compiling). Compiled on first use and cached beside this file (numba's `cache`):
`compile_all` does it ahead."""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit


def usable(*tensors: torch.Tensor | None) -> bool:
    """Whether a compiled kernel may stand in for torch on these tensors: all on the CPU, no gradient to
    record, and no torch.jit trace or torch.compile capturing the graph (the kernels are opaque to both)."""
    present = [x for x in tensors if x is not None]
    return (all(x.device.type == "cpu" for x in present)
            and not (torch.is_grad_enabled() and any(x.requires_grad for x in present))
            and not torch.jit.is_tracing() and not torch.compiler.is_compiling())


_OPTIONS = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}  # IEEE division, as torch


@njit(**_OPTIONS)
def _cross4(a: np.ndarray, b: np.ndarray, c: np.ndarray, out: np.ndarray) -> None:
    """out = the generalised cross product of three 4-vectors (orthogonal to each: the cofactor expansion
    of det[e; a; b; c] along its first row)."""
    m01, m02, m03 = b[0] * c[1] - b[1] * c[0], b[0] * c[2] - b[2] * c[0], b[0] * c[3] - b[3] * c[0]
    m12, m13, m23 = b[1] * c[2] - b[2] * c[1], b[1] * c[3] - b[3] * c[1], b[2] * c[3] - b[3] * c[2]
    out[0] = a[1] * m23 - a[2] * m13 + a[3] * m12
    out[1] = -a[0] * m23 + a[2] * m03 - a[3] * m02
    out[2] = a[0] * m13 - a[1] * m03 + a[3] * m01
    out[3] = -a[0] * m12 + a[1] * m02 - a[2] * m01


@njit(**_OPTIONS)
def _fit_one(src: np.ndarray, dst: np.ndarray, w: np.ndarray, out: np.ndarray) -> None:
    """The weighted rigid fit of one set src (K, 3) -> dst (K, 3) into out (4, 4) (module docstring)."""
    K = src.shape[0]
    total = 0.0
    ms, md = np.zeros(3), np.zeros(3)
    for i in range(K):
        wi = max(float(w[i]), 0.0)
        total += wi
        for a in range(3):
            ms[a] += wi * src[i, a]
            md[a] += wi * dst[i, a]
    out[:] = 0.0
    for a in range(4):
        out[a, a] = 1.0
    if not total > 0.0:
        return
    ms /= total
    md /= total
    S = np.zeros((3, 3))
    spread = 0.0
    for i in range(K):
        wi = max(float(w[i]), 0.0) / total
        s0, s1, s2 = src[i, 0] - ms[0], src[i, 1] - ms[1], src[i, 2] - ms[2]
        d0, d1, d2 = dst[i, 0] - md[0], dst[i, 1] - md[1], dst[i, 2] - md[2]
        spread += wi * (s0 * s0 + s1 * s1 + s2 * s2 + d0 * d0 + d1 * d1 + d2 * d2)
        S[0, 0] += wi * s0 * d0
        S[0, 1] += wi * s0 * d1
        S[0, 2] += wi * s0 * d2
        S[1, 0] += wi * s1 * d0
        S[1, 1] += wi * s1 * d1
        S[1, 2] += wi * s1 * d2
        S[2, 0] += wi * s2 * d0
        S[2, 1] += wi * s2 * d1
        S[2, 2] += wi * s2 * d2
    sxx, sxy, sxz = S[0, 0], S[0, 1], S[0, 2]
    syx, syy, syz = S[1, 0], S[1, 1], S[1, 2]
    szx, szy, szz = S[2, 0], S[2, 1], S[2, 2]
    Kq = np.empty((4, 4))
    Kq[0, 0], Kq[0, 1], Kq[0, 2], Kq[0, 3] = sxx + syy + szz, syz - szy, szx - sxz, sxy - syx
    Kq[1, 1], Kq[1, 2], Kq[1, 3] = sxx - syy - szz, sxy + syx, szx + sxz
    Kq[2, 2], Kq[2, 3] = syy - sxx - szz, syz + szy
    Kq[3, 3] = szz - sxx - syy
    for a in range(4):
        for b in range(a):
            Kq[a, b] = Kq[b, a]
    c2 = 0.0
    for a in range(3):
        for b in range(3):
            c2 += S[a, b] * S[a, b]
    c2 *= -2.0
    c1 = -8.0 * (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx) + sxz * (syx * szy - syy * szx))
    c0 = _det4(Kq)
    x = 0.5 * spread
    for _ in range(60):  # from above the largest root: monotone
        x2 = x * x
        value = ((x2 + c2) * x + c1) * x + c0
        slope = (4.0 * x2 + 2.0 * c2) * x + c1
        if slope == 0.0:
            break
        step = value / slope
        x -= step
        if abs(step) <= 1e-13 * abs(x) + 1e-300:
            break
    A = Kq.copy()
    for a in range(4):
        A[a, a] -= x
    q, row = np.empty(4), np.empty(4)
    best = -1.0
    for drop in range(4):  # adjugate row `drop`: orthogonal to the other three rows
        first, second, third = int(drop == 0), 2 - int(drop == 2) - int(drop == 3), 3 - int(drop == 3)
        _cross4(A[first], A[second], A[third], row)
        length = row[0] * row[0] + row[1] * row[1] + row[2] * row[2] + row[3] * row[3]
        if length > best:
            best = length
            q[:] = row
    if not best > 0.0:
        return
    q /= math.sqrt(best)
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    R = out[:3, :3]
    R[0, 0], R[0, 1], R[0, 2] = qw * qw + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (qx * qy + qw * qz), qw * qw - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - qw * qx)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz
    for a in range(3):
        out[a, 3] = md[a] - (R[a, 0] * ms[0] + R[a, 1] * ms[1] + R[a, 2] * ms[2])


@njit(**_OPTIONS)
def _det4(M: np.ndarray) -> float:
    """Determinant of a 4x4 matrix from the 2x2 minors of its top and bottom row pairs (Laplace)."""
    s0, s1 = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0], M[0, 0] * M[1, 2] - M[0, 2] * M[1, 0]
    s2, s3 = M[0, 0] * M[1, 3] - M[0, 3] * M[1, 0], M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]
    s4, s5 = M[0, 1] * M[1, 3] - M[0, 3] * M[1, 1], M[0, 2] * M[1, 3] - M[0, 3] * M[1, 2]
    c0, c1 = M[2, 0] * M[3, 1] - M[2, 1] * M[3, 0], M[2, 0] * M[3, 2] - M[2, 2] * M[3, 0]
    c2, c3 = M[2, 0] * M[3, 3] - M[2, 3] * M[3, 0], M[2, 1] * M[3, 2] - M[2, 2] * M[3, 1]
    c4, c5 = M[2, 1] * M[3, 3] - M[2, 3] * M[3, 1], M[2, 2] * M[3, 3] - M[2, 3] * M[3, 2]
    return s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0


@njit(**_OPTIONS)
def fit_rigid(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares rigid fits of P sets: src, dst (P, K, 3), weights (P, K) -> (P, 4, 4) float64
    with dst ~ R src + t (module docstring). Non-positive weights count as zero; a set without weight gets
    identity."""
    out = np.empty((src.shape[0], 4, 4))
    for p in range(src.shape[0]):
        _fit_one(src[p], dst[p], w[p], out[p])
    return out


@njit(**{**_OPTIONS, "fastmath": True})
def truncated_scores(T: np.ndarray, src: np.ndarray, dst: np.ndarray, w: np.ndarray, tau: float) -> np.ndarray:
    """Scores of hypotheses T (B, m, 4, 4) on correspondences src, dst (B, 3, N) (coordinates as rows) with
    weights w (B, N): sum_i w_i min(|R src_i + t - dst_i|, tau) / sum_i w_i -> (B, m), in src's dtype."""
    B, m, N = T.shape[0], T.shape[1], src.shape[2]
    out = np.empty((B, m), dtype=src.dtype)
    for b in range(B):
        sx, sy, sz, dx, dy, dz, wb = src[b, 0], src[b, 1], src[b, 2], dst[b, 0], dst[b, 1], dst[b, 2], w[b]
        total = max(wb.sum(), 1e-9)
        for h in range(m):
            r = T[b, h]
            r00, r01, r02, t0 = r[0, 0], r[0, 1], r[0, 2], r[0, 3]
            r10, r11, r12, t1 = r[1, 0], r[1, 1], r[1, 2], r[1, 3]
            r20, r21, r22, t2 = r[2, 0], r[2, 1], r[2, 2], r[2, 3]
            acc = 0.0
            for i in range(N):
                e0 = r00 * sx[i] + r01 * sy[i] + r02 * sz[i] + t0 - dx[i]
                e1 = r10 * sx[i] + r11 * sy[i] + r12 * sz[i] + t1 - dy[i]
                e2 = r20 * sx[i] + r21 * sy[i] + r22 * sz[i] + t2 - dz[i]
                acc += wb[i] * min(math.sqrt(e0 * e0 + e1 * e1 + e2 * e2), tau)
            out[b, h] = acc / total
    return out


@njit(**_OPTIONS)
def _morton_order(x: np.ndarray) -> np.ndarray:
    """Indices that sort the rows of x (N, 3) along a Z-order curve of a 1024^3 grid over their bounding box:
    points close in that order are close in space."""
    lo = np.array([x[:, 0].min(), x[:, 1].min(), x[:, 2].min()])
    span = max(x[:, 0].max() - lo[0], x[:, 1].max() - lo[1], x[:, 2].max() - lo[2], 1e-30)
    keys = np.zeros(x.shape[0], dtype=np.int64)
    for i in range(x.shape[0]):
        key = 0
        for a in range(3):
            cell = min(int((x[i, a] - lo[a]) / span * 1024.0), 1023)
            for bit in range(10):
                key |= ((cell >> bit) & 1) << (3 * bit + a)
        keys[i] = key
    return np.argsort(keys)


@njit(**_OPTIONS, inline="always")  # inlined: a call per candidate would cost more than the insertion
def _insert(d: float, j: int, dist: np.ndarray, index: np.ndarray, count: int) -> int:
    """Insert (d, j) into the first `count` entries of the ascending lists dist, index (capacity k; (distance,
    index) order, so ties go to the lower index), dropping the last when full; returns the new count."""
    k = dist.shape[0]
    slot = min(count, k - 1)
    if count == k and (d > dist[k - 1] or (d == dist[k - 1] and j > index[k - 1])):
        return count
    while slot > 0 and (dist[slot - 1] > d or (dist[slot - 1] == d and index[slot - 1] > j)):
        dist[slot], index[slot] = dist[slot - 1], index[slot - 1]
        slot -= 1
    dist[slot], index[slot] = d, j
    return min(count + 1, k)


@njit(**_OPTIONS)
def knn_self(points: np.ndarray, k: int) -> np.ndarray:
    """(B, N, 3) -> (B, N, k) int64: each point's k nearest points of its own cloud (itself included), nearest
    first, ties to the lower index; squared distances in float64. Exhaustive, so exact: each query first
    takes its 2k neighbours along a Z-order curve, whose k-th distance bounds the search, then one pass over
    the cloud inserts only the points below that bound (rare, so the pass is compares, not sorting). At
    N = 512 this beats a k-d tree: the cloud sits in cache."""
    B, N = points.shape[0], points.shape[1]
    k = min(k, N)
    out = np.empty((B, N, k), dtype=np.int64)
    dist, row = np.empty(k), np.empty(N)
    for b in range(B):
        x = points[b].astype(np.float64)
        order = _morton_order(x)
        position = np.empty(N, dtype=np.int64)
        position[order] = np.arange(N)
        x0, x1, x2 = x[:, 0].copy(), x[:, 1].copy(), x[:, 2].copy()
        for p in range(N):
            i = order[p]
            for j in range(N):
                row[j] = (x0[j] - x0[i]) * (x0[j] - x0[i]) + (x1[j] - x1[i]) * (x1[j] - x1[i]) + (
                    x2[j] - x2[i]) * (x2[j] - x2[i])
            index = out[b, i]
            count = 0
            for q in range(max(0, p - k), min(N, p + k + 1)):
                count = _insert(row[order[q]], order[q], dist, index, count)
            for j in range(N):
                if row[j] <= dist[k - 1] and abs(position[j] - p) > k:  # the window's points are in already
                    count = _insert(row[j], j, dist, index, count)
    return out


@njit(**{**_OPTIONS, "fastmath": True})
def neighbour_max(values: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Max of values (B, N, C) over each point's neighbours (B, M, k) -> (B, M, C), without the (B, M, k, C)
    gather."""
    B, M, k, C = neighbours.shape[0], neighbours.shape[1], neighbours.shape[2], values.shape[2]
    out = np.empty((B, M, C), dtype=values.dtype)
    for b in range(B):
        for i in range(M):
            row = out[b, i]
            row[:] = values[b, neighbours[b, i, 0]]
            for j in range(1, k):
                other = values[b, neighbours[b, i, j]]
                for c in range(C):
                    row[c] = max(row[c], other[c])
    return out


@njit(**{**_OPTIONS, "fastmath": True})
def first_index(x: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The first index (B, N) int64 at which each row of x (B, N, M) holds its value in `values` (B, N), which
    every row holds (its max: with torch's `amax`, torch's `max(dim=-1)` index). Branch-free and vectorised:
    the largest of M - j over the matching positions j."""
    B, N, M = x.shape[0], x.shape[1], x.shape[2]
    out = np.empty((B, N), dtype=np.int64)
    for b in range(B):
        for i in range(N):
            row, value = x[b, i], values[b, i]
            code = np.int32(0)
            for j in range(M):
                code = max(code, np.int32(M - j) if row[j] == value else np.int32(0))
            out[b, i] = M - code
    return out


@njit(**_OPTIONS)
def neighbour_mix(log_w: np.ndarray, best: np.ndarray, y: np.ndarray, knn: np.ndarray, k: int) -> np.ndarray:
    """For each row i of log_w (B, N, M): the mean of y's (B, M, 3) rows knn[best[i], :k] (B, M, >= k),
    weighted by the softmax of their log weights in row i -> (B, N, 3), in y's dtype (`genreg.neighbour_mix`)."""
    B, N = best.shape[0], best.shape[1]
    out = np.empty((B, N, 3), dtype=y.dtype)
    w = np.empty(k, dtype=log_w.dtype)
    for b in range(B):
        for i in range(N):
            c = knn[b, best[b, i]]
            m = log_w[b, i, c[0]]
            for j in range(1, k):
                m = max(m, log_w[b, i, c[j]])
            total = 0.0
            for j in range(k):
                w[j] = np.exp(log_w[b, i, c[j]] - m)
                total += w[j]
            o0, o1, o2 = 0.0, 0.0, 0.0
            for j in range(k):
                p = y[b, c[j]]
                o0 += w[j] * p[0]
                o1 += w[j] * p[1]
                o2 += w[j] * p[2]
            out[b, i, 0], out[b, i, 1], out[b, i, 2] = o0 / total, o1 / total, o2 / total
    return out


@njit(**_OPTIONS, inline="always")
def _longest_cross(m00: float, m01: float, m02: float, m11: float, m12: float, m22: float
                   ) -> tuple[float, float, float, float]:
    """The longest of the cross products r0 x r1, r0 x r2, r1 x r2 of the rows of a symmetric 3x3 matrix M
    (given by its upper triangle) and its squared length: for M = C - lambda I with lambda an eigenvalue of C,
    an (unnormalised) eigenvector for it, the longest being the best conditioned."""
    best, v0, v1, v2 = -1.0, 0.0, 0.0, 0.0
    for c in range(3):
        if c == 0:
            u0, u1, u2, w0, w1, w2 = m00, m01, m02, m01, m11, m12
        elif c == 1:
            u0, u1, u2, w0, w1, w2 = m00, m01, m02, m02, m12, m22
        else:
            u0, u1, u2, w0, w1, w2 = m01, m11, m12, m02, m12, m22
        x0, x1, x2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        length = x0 * x0 + x1 * x1 + x2 * x2
        if length > best:
            best, v0, v1, v2 = length, x0, x1, x2
    return v0, v1, v2, best


@njit(**_OPTIONS)
def invariant_geometry(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`model.invariant.invariant_geometry` of (B, N, 3) clouds on their kNN graph (B, N, k), the same formulas:
    edge features (B, N, k, 4) (|d|, |n_i . d^|, |n_j . d^|, |n_i . n_j|), point features (B, N, 4) (roots of
    the neighbourhood covariance eigenvalues, ascending, and |x|) and unoriented normals (B, N, 3), in the
    points' dtype; the eigenproblem in float64 (`smallest_eigenpair3`'s closed form)."""
    B, N, k = neighbours.shape[0], neighbours.shape[1], neighbours.shape[2]
    dtype = points.dtype
    normals = np.empty((B, N, 3), dtype=dtype)
    point = np.empty((B, N, 4), dtype=dtype)
    edge = np.empty((B, N, k, 4), dtype=dtype)
    third = 2.0 * math.pi / 3.0
    for b in range(B):
        x = points[b]
        for i in range(N):
            m0 = m1 = m2 = 0.0
            for j in range(k):
                n = neighbours[b, i, j]
                m0 += x[n, 0]
                m1 += x[n, 1]
                m2 += x[n, 2]
            m0, m1, m2 = m0 / k, m1 / k, m2 / k
            a00 = a11 = a22 = a01 = a02 = a12 = 0.0
            for j in range(k):
                n = neighbours[b, i, j]
                e0, e1, e2 = x[n, 0] - m0, x[n, 1] - m1, x[n, 2] - m2
                a00 += e0 * e0
                a11 += e1 * e1
                a22 += e2 * e2
                a01 += e0 * e1
                a02 += e0 * e2
                a12 += e1 * e2
            a00, a11, a22, a01, a02, a12 = a00 / k, a11 / k, a22 / k, a01 / k, a02 / k, a12 / k
            q = (a00 + a11 + a22) / 3
            b00, b11, b22 = a00 - q, a11 - q, a22 - q
            p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6)
            det_b = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
            ratio = det_b / (2 * p ** 3) if p > 1e-100 else 0.0  # no spread (repeated points): all equal
            phi = math.acos(min(max(ratio, -1.0), 1.0)) / 3
            largest, smallest = q + 2 * p * math.cos(phi), q + 2 * p * math.cos(phi + third)
            evals = (smallest, 3 * q - smallest - largest, largest)
            v0, v1, v2, best = _longest_cross(a00 - smallest, a01, a02, a11 - smallest, a12, a22 - smallest)
            best = max(math.sqrt(best), 1e-300)
            normals[b, i, 0], normals[b, i, 1], normals[b, i, 2] = v0 / best, v1 / best, v2 / best
            for c in range(3):
                point[b, i, c] = math.sqrt(max(dtype.type(evals[c]), 0.0))
            point[b, i, 3] = math.sqrt(x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2])
        for i in range(N):
            ni = normals[b, i]
            for j in range(k):
                n = neighbours[b, i, j]
                nj = normals[b, n]
                d0, d1, d2 = x[n, 0] - x[i, 0], x[n, 1] - x[i, 1], x[n, 2] - x[i, 2]
                dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                inv = 1.0 / max(dist, 1e-9)
                u0, u1, u2 = d0 * inv, d1 * inv, d2 * inv
                edge[b, i, j, 0] = dist
                edge[b, i, j, 1] = abs(u0 * ni[0] + u1 * ni[1] + u2 * ni[2])
                edge[b, i, j, 2] = abs(u0 * nj[0] + u1 * nj[1] + u2 * nj[2])
                edge[b, i, j, 3] = abs(ni[0] * nj[0] + ni[1] * nj[1] + ni[2] * nj[2])
    return edge, point, normals


@njit(**_OPTIONS, inline="always")
def _residual(T: np.ndarray, s: np.ndarray, d: np.ndarray) -> float:
    """|R s + t - d| for a 4x4 T (float64) and 3-vectors s, d."""
    e0 = T[0, 0] * s[0] + T[0, 1] * s[1] + T[0, 2] * s[2] + T[0, 3] - d[0]
    e1 = T[1, 0] * s[0] + T[1, 1] * s[1] + T[1, 2] * s[2] + T[1, 3] - d[1]
    e2 = T[2, 0] * s[0] + T[2, 1] * s[1] + T[2, 2] * s[2] + T[2, 3] - d[2]
    return math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@njit(**_OPTIONS)
def _refit(T: np.ndarray, src: np.ndarray, dst: np.ndarray, w: np.ndarray, limit: float, mask: np.ndarray,
           fitted: np.ndarray) -> None:
    """One least-squares refit of T (4, 4) in place on its correspondences within `limit` (weights w), kept
    when fewer than 3 are; mask and fitted are scratch."""
    count = 0
    for i in range(src.shape[0]):
        inside = _residual(T, src[i], dst[i]) < limit
        mask[i] = w[i] if inside else 0.0
        count += inside
    if count >= 3:
        _fit_one(src, dst, mask, fitted)
        T[:] = fitted


@njit(**_OPTIONS)
def consensus(candidates: np.ndarray, src: np.ndarray, dst: np.ndarray, w: np.ndarray, tau: float,
              limits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PDSAC's last steps on correspondences src -> dst (B, M, 3) with weights w (B, M): each candidate
    (B, C, 4, 4) refit once on its inliers (residual < tau; kept with fewer than 3), the one with the lowest
    weighted truncated mean residual kept, then refit once at each of `limits` (absolute thresholds, in
    order). Returns the transforms (B, 4, 4) float64 and their inliers at tau (B, M)."""
    B, C, M = candidates.shape[0], candidates.shape[1], src.shape[1]
    out = np.empty((B, 4, 4))
    inliers = np.empty((B, M), dtype=np.bool_)
    mask, fitted, T = np.empty(M), np.empty((4, 4)), np.empty((4, 4))
    for b in range(B):
        total = max(w[b].sum(), 1e-9)
        best = np.inf
        for c in range(C):
            T[:] = candidates[b, c]
            _refit(T, src[b], dst[b], w[b], tau, mask, fitted)  # local optimisation
            score = 0.0
            for i in range(M):
                score += w[b, i] * min(_residual(T, src[b, i], dst[b, i]), tau)
            score /= total
            if score < best:
                best = score
                out[b] = T
        for limit in limits:
            _refit(out[b], src[b], dst[b], w[b], limit, mask, fitted)
        for i in range(M):
            inliers[b, i] = _residual(out[b], src[b, i], dst[b, i]) < tau
    return out, inliers


@njit(**_OPTIONS)
def cloud_mean(points: np.ndarray) -> np.ndarray:
    """(3,) mean of (M, 3) float64 points, summed in row order (zeros for no points): `plane_normals`'s centre."""
    centre = np.zeros(3)
    for i in range(points.shape[0]):
        for a in range(3):
            centre[a] += points[i, a]
    centre /= max(points.shape[0], 1)
    return centre


@njit(**_OPTIONS)
def plane_normals(points: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """`score.plane_normals`'s formulas, one pass per set: (m, 3) unit normals (zero without spread) of the sets
    points[neighbours] ((m, k) rows of (M, 3) float64 points), from moments about the cloud's mean."""
    return plane_normals_about(points, neighbours, cloud_mean(points))


@njit(**_OPTIONS)
def plane_normals_about(points: np.ndarray, neighbours: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """`plane_normals` with the cloud's mean given (`cloud_mean`: a large cloud's, worked out once, not on
    every call)."""
    m, k = neighbours.shape
    out = np.zeros((m, 3))
    for r in range(m):
        sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
        for j in range(k):
            n = neighbours[r, j]
            x, y, z = points[n, 0] - centre[0], points[n, 1] - centre[1], points[n, 2] - centre[2]
            sx += x
            sy += y
            sz += z
            sxx += x * x
            sxy += x * y
            sxz += x * z
            syy += y * y
            syz += y * z
            szz += z * z
        mx, my, mz = sx / k, sy / k, sz / k
        c00, c01, c02 = sxx / k - mx * mx, sxy / k - mx * my, sxz / k - mx * mz
        c11, c12, c22 = syy / k - my * my, syz / k - my * mz, szz / k - mz * mz
        top = max(abs(c00), abs(c01), abs(c02), abs(c11), abs(c12), abs(c22))
        if not top > 0:
            continue  # no spread: a zero normal
        c00, c01, c02, c11, c12, c22 = c00 / top, c01 / top, c02 / top, c11 / top, c12 / top, c22 / top
        q = (c00 + c11 + c22) / 3
        b00, b11, b22 = c00 - q, c11 - q, c22 - q
        p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2 * (c01 * c01 + c02 * c02 + c12 * c12)) / 6)
        p = p if p != 0 else 1.0  # isotropic: any direction will do
        det = b00 * (b11 * b22 - c12 * c12) - c01 * (c01 * b22 - c12 * c02) + c02 * (c01 * c12 - b11 * c02)
        smallest = q + 2 * p * math.cos(math.acos(min(max(det / (2 * p ** 3), -1.0), 1.0)) / 3 + 2 * math.pi / 3)
        v0, v1, v2, best = _longest_cross(c00 - smallest, c01, c02, c11 - smallest, c12, c22 - smallest)
        if best > 0:
            norm = math.sqrt(best)
            out[r, 0], out[r, 1], out[r, 2] = v0 / norm, v1 / norm, v2 / norm
    return out


@njit(**{**_OPTIONS, "fastmath": True})
def transform_rows(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """x' = R x + t for the rows of (N, 3) points (any real dtype, any strides) -> (N, 3) float32, one pass;
    T (4, 4) in the arithmetic's dtype (float32 for float32 points, float64 otherwise)."""
    out = np.empty((points.shape[0], 3), dtype=np.float32)
    r00, r01, r02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    r10, r11, r12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    r20, r21, r22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    for i in range(points.shape[0]):
        x, y, z = T.dtype.type(points[i, 0]), T.dtype.type(points[i, 1]), T.dtype.type(points[i, 2])
        out[i, 0] = r00 * x + r01 * y + r02 * z + t0
        out[i, 1] = r10 * x + r11 * y + r12 * z + t1
        out[i, 2] = r20 * x + r21 * y + r22 * z + t2
    return out


@njit(**_OPTIONS)
def weighted_sets(cdf: np.ndarray, w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """`pdsac.sample_weighted_sequential`'s mapping of uniform draws u (k, B, m) to (B, m, k) minimal sets,
    ascending: draw j is u_j times the mass not yet taken, moved past the taken points' intervals
    [cdf_i - w_i, cdf_i) (ascending), then found in the cumulative weights cdf (B, N) (float64, as given)."""
    k, B, m = u.shape
    N = cdf.shape[1]
    out = np.empty((B, m, k), dtype=np.int64)
    for b in range(B):
        for s in range(m):
            picks = out[b, s]
            left = cdf[b, N - 1]
            for j in range(k):
                x = u[j, b, s] * left
                for i in range(j):
                    t = picks[i]
                    if x >= cdf[b, t] - w[b, t]:
                        x = x + w[b, t]
                lo, hi = 0, N  # searchsorted, right: the first index whose cdf exceeds x
                while lo < hi:
                    mid = (lo + hi) // 2
                    if cdf[b, mid] <= x:
                        lo = mid + 1
                    else:
                        hi = mid
                r = min(lo, N - 1)
                left = left - w[b, r]
                slot = j  # keep the picks ascending
                while slot > 0 and picks[slot - 1] > r:
                    picks[slot] = picks[slot - 1]
                    slot -= 1
                picks[slot] = r
    return out


@njit(**_OPTIONS)
def copy_rows(view: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of an (N, 3) array of any strides (x, y, z inside a PointCloud2's records), one
    pass: numpy's strided copy of 300k points takes 1.4 ms, this 0.3."""
    out = np.empty((view.shape[0], 3), dtype=view.dtype)
    for i in range(view.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = view[i, 0], view[i, 1], view[i, 2]
    return out


@njit(**_OPTIONS)
def voxel_centroids(points: np.ndarray, voxel: np.ndarray) -> np.ndarray:
    """`preprocess.voxel_downsample` of finite (N, 3) points, bit for bit, in one pass. Each point's voxel,
    floor(p / voxel[0]) per axis (`voxel` in the points' dtype: numpy divides in that dtype), is looked up in
    an open-addressing hash table (linear probing, twice as many slots as points, rounded up to a power of
    two) that numbers the voxels in their first appearance; the sums run in input order (as `np.bincount`'s)
    and the centroids come out in that order, in the points' dtype."""
    n, size = points.shape[0], voxel[0]
    slots = 1
    while slots < 2 * n:
        slots *= 2
    mask = slots - 1
    table = np.full(slots, -1, dtype=np.int64)  # a slot's voxel number, -1: empty
    keys = np.empty((n, 3), dtype=np.int64)  # each voxel's key, in order of appearance
    sums = np.zeros((n, 3), dtype=np.float64)
    counts = np.zeros(n, dtype=np.int64)
    voxels = 0
    for i in range(n):
        kx = np.int64(math.floor(points[i, 0] / size))
        ky = np.int64(math.floor(points[i, 1] / size))
        kz = np.int64(math.floor(points[i, 2] / size))
        h = ((kx * 73856093) ^ (ky * 19349663) ^ (kz * 83492791)) & mask
        while True:
            v = table[h]
            if v < 0:
                v = voxels
                table[h] = v
                keys[v, 0], keys[v, 1], keys[v, 2] = kx, ky, kz
                voxels += 1
                break
            if keys[v, 0] == kx and keys[v, 1] == ky and keys[v, 2] == kz:
                break
            h = (h + 1) & mask
        sums[v, 0] += points[i, 0]
        sums[v, 1] += points[i, 1]
        sums[v, 2] += points[i, 2]
        counts[v] += 1
    out = np.empty((voxels, 3), dtype=points.dtype)
    for v in range(voxels):
        for j in range(3):
            out[v, j] = sums[v, j] / counts[v]
    return out


@njit(**_OPTIONS)
def cell_bounds(points: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and the highest cell (3,) int64 of finite (N >= 1, 3) points on a grid of edge `cell[0]`
    (in the points' dtype: numpy divides in that dtype): min and max of floor(p / cell) per axis, in one
    pass."""
    size = cell[0]
    low = np.empty(3, dtype=np.int64)
    high = np.empty(3, dtype=np.int64)
    for a in range(3):
        low[a] = high[a] = np.int64(math.floor(points[0, a] / size))
    for i in range(1, points.shape[0]):
        for a in range(3):
            c = np.int64(math.floor(points[i, a] / size))
            low[a] = min(low[a], c)
            high[a] = max(high[a], c)
    return low, high


@njit(**_OPTIONS)
def cell_keys(points: np.ndarray, cell: np.ndarray, low: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """One int64 key per point of its cell floor(p / cell[0]) (as `cell_bounds`) on the grid of `extent` cells
    from `low`, x-major (`score.cell_key`), in one pass."""
    size = cell[0]
    keys = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        key = np.int64(0)
        for a in range(3):
            key = key * extent[a] + (np.int64(math.floor(points[i, a] / size)) - low[a])
        keys[i] = key
    return keys


def compile_all() -> None:
    """Compile (or load from numba's cache) every kernel for the array types the pipeline passes, on tiny
    inputs: a cold compile takes about half a minute, a cached load about a second. `scripts/setup.sh` runs
    it once (`python -m genreg_core.kernels`) and the node at configure, so no registration waits for it."""
    f32, f64 = np.float32, np.float64
    rng = np.random.default_rng(0)
    cloud = rng.random((1, 32, 3)).astype(f32)
    graph = knn_self(cloud, 8)
    knn_self(cloud.astype(f64), 8)
    invariant_geometry(cloud, graph)
    neighbour_max(rng.random((1, 32, 4)).astype(f32), graph)
    rows = rng.random((1, 4, 8)).astype(f32)
    first_index(rows, rows.max(axis=-1))
    neighbour_mix(rng.random((1, 32, 32)).astype(f32), graph[:, :, 0], cloud, graph, 4)
    for dtype in (f32, f64):
        sets = rng.random((4, 3, 3)).astype(dtype)
        fit_rigid(sets, sets, np.ones((4, 3), dtype=dtype))
        transform_rows(np.eye(4, dtype=dtype), cloud[0].astype(dtype))
        transform_rows(np.eye(4, dtype=dtype), np.ones((32, 4), dtype=dtype)[:, :3])  # a strided view (x y z of more)
        copy_rows(np.ones((32, 4), dtype=dtype)[:, :3])
    hypotheses = np.tile(np.eye(4, dtype=f32), (1, 2, 1, 1))
    rows = np.ascontiguousarray(cloud.transpose(0, 2, 1))
    truncated_scores(hypotheses, rows, rows, np.ones((1, 32), dtype=f32), 0.1)
    consensus(hypotheses, cloud, cloud, np.ones((1, 32), dtype=f32), 0.1, np.array([0.1]))
    plane_normals(cloud[0].astype(f64), graph[0])  # with cloud_mean and plane_normals_about
    weights = np.ones((1, 32))
    weighted_sets(np.cumsum(weights, axis=1), weights, rng.random((3, 1, 4)))
    for dtype in (f32, f64):
        voxel_centroids(cloud[0].astype(dtype), np.array([0.1], dtype=dtype))
        low, high = cell_bounds(cloud[0].astype(dtype), np.array([0.1], dtype=dtype))
        cell_keys(cloud[0].astype(dtype), np.array([0.1], dtype=dtype), low, high - low + 1)


if __name__ == "__main__":
    compile_all()
