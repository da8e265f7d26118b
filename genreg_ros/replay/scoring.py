"""Scoring of a replay: per-pair results against the bag's ground truth, reasons for missing outputs, the
Open3D ICP reference and the summary figures.

A pair is (target = cloud k - gap, source = cloud k) of one bag; every transform is T_target_source (see
`genreg_core.geometry`); the ground truth is inv(T_world_target) @ T_world_source from the bag's poses.
RE is the isotropic rotation error in degrees, TE the translation error in metres (`genreg_core.metrics`).
Latency is the harness's wall time from publishing the source cloud to receiving the node's
TransformStamped for it.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from genreg_core.metrics import transform_errors
from genreg_core.refine import icp
from genreg_ros.bag.reader import BagData

# Node counters that mean "this pair produced no output", in the order they are assigned to missing pairs.
PAIR_REASONS = ("dropped.superseded", "failed.", "dropped.unmatched", "dropped.queue_full", "dropped.")
# The ICP reference: Open3D point-to-point from identity on the bag clouds (metres).
ICP_MAX_DISTANCE = 0.1  # m: correspondence cut-off (gap-10 motion in 7-Scenes is ~7 cm)
ICP_VOXEL = 0.02  # m: downsampling before ICP
ICP_ITERATIONS = 50
ICP_TEXT = (f"Open3D point-to-point, identity start, voxel {ICP_VOXEL:g} m, max distance {ICP_MAX_DISTANCE:g} m, "
            f"{ICP_ITERATIONS} iterations")


@dataclass
class PairResult:
    """One replayed pair and what became of it."""

    bag: str
    k: int  # index of the source cloud in the bag; the target is cloud k - gap
    source_frame: int
    target_frame: int
    source_stamp: int  # ns, the source's stamp in the bag
    target_stamp: int  # ns, the target's stamp in the bag
    source_frame_id: str
    target_frame_id: str
    source_points: int  # finite source points (what the aligned cloud must carry)
    T_gt: np.ndarray | None  # 4x4 T_target_source from the bag's poses
    out_stamp: int = 0  # ns, the stamp published with both clouds, which the node must put on its outputs
    published: float | None = None  # time.monotonic() just before the source was published
    malformed: str = ""  # "source: <reason>" / "target: <reason>" when the harness found the bag message bad
    T_est: np.ndarray | None = None  # the node's transform
    received: float | None = None  # arrival of the node's TransformStamped
    aligned_received: float | None = None
    header_problems: list[str] = field(default_factory=list)  # wrong stamps / frames / point counts
    reason: str = ""  # why there is no output
    icp_T: np.ndarray | None = None
    icp_seconds: float | None = None

    @property
    def registered(self) -> bool:
        return self.T_est is not None

    @property
    def latency(self) -> float | None:
        if self.received is None or self.published is None:
            return None
        return self.received - self.published

    def errors(self, T: np.ndarray | None) -> tuple[float, float]:
        """(RE deg, TE m) of T against the ground truth; NaN when either is missing."""
        if T is None or self.T_gt is None:
            return math.nan, math.nan
        return transform_errors(T, self.T_gt)


def make_pairs(bag: BagData, gap: int) -> list[PairResult]:
    """Pairs (target = cloud k - gap, source = cloud k) with their ground truth T_target_source."""
    if gap < 1 or gap >= len(bag.clouds):
        raise ValueError(f"gap {gap} needs a bag with more than {gap} clouds ({bag.path} has {len(bag.clouds)})")
    frames = bag.frame_numbers
    pairs = []
    for k in range(gap, len(bag.clouds)):
        src, tgt = bag.clouds[k], bag.clouds[k - gap]
        Tw_s, Tw_t = bag.pose_at(src.stamp_ns), bag.pose_at(tgt.stamp_ns)
        T_gt = None if Tw_s is None or Tw_t is None else np.linalg.inv(Tw_t) @ Tw_s
        finite = 0 if src.points is None else int(np.isfinite(src.points).all(axis=1).sum())
        bad = f"source: {src.error}" if src.error else f"target: {tgt.error}" if tgt.error else ""
        pairs.append(PairResult(str(bag.path), k, frames[k], frames[k - gap], src.stamp_ns, tgt.stamp_ns,
                                src.frame_id, tgt.frame_id, finite, T_gt, malformed=bad))
    return pairs


def assign_reasons(pairs: list[PairResult], deltas: dict[str, int]) -> None:
    """Give each pair without output a reason, consuming the node's counted drops and failures."""
    pool = Counter(deltas)
    for p in pairs:
        if p.registered:
            continue
        if p.malformed:
            role, reason = p.malformed.split(": ", 1)
            counted = pool[f"dropped.{reason}"] > 0
            pool[f"dropped.{reason}"] -= counted
            p.reason = f"malformed {role} ({reason})" + ("" if counted else ", not counted by the node")
            continue
        for prefix in PAIR_REASONS:
            key = next((k for k in sorted(pool) if k.startswith(prefix) and pool[k] > 0), None)
            if key is not None:
                pool[key] -= 1
                p.reason = f"node {key}"
                break
        else:
            p.reason = "lost (no output, not counted by the node)"


def malformed_clouds(bag: BagData) -> list[dict[str, Any]]:
    frames = bag.frame_numbers
    return [{"bag": str(bag.path), "index": i, "frame": frames[i], "stamp_ns": c.stamp_ns, "reason": c.error,
             "text": c.error_text} for i, c in enumerate(bag.clouds) if c.error]


def icp_reference(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """The ICP reference on one pair's finite points (`genreg_core.refine.icp`): (T_target_source, seconds)."""
    t0 = time.perf_counter()
    src, tgt = (np.asarray(p, dtype=np.float64) for p in (source, target))
    T = icp(src[np.isfinite(src).all(axis=1)], tgt[np.isfinite(tgt).all(axis=1)], method="point_to_point",
            max_distance=ICP_MAX_DISTANCE, max_iterations=ICP_ITERATIONS, voxel_size=ICP_VOXEL)
    return T, time.perf_counter() - t0


def run_icp(bag: BagData, pairs: list[PairResult]) -> None:
    """The ICP reference on each pair's bag clouds (source = cloud k, target = its target)."""
    by_stamp = {c.stamp_ns: c.points for c in bag.clouds}
    for p in pairs:
        src, tgt = by_stamp.get(p.source_stamp), by_stamp.get(p.target_stamp)
        if src is not None and tgt is not None and len(src) >= 3 and len(tgt) >= 3:
            p.icp_T, p.icp_seconds = icp_reference(src, tgt)


# ----------------------------------------------------------------------------- summary
def _stats(values: list[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"n": 0, "mean": math.nan, "median": math.nan, "p95": math.nan, "max": math.nan}
    return {"n": int(v.size), "mean": float(v.mean()), "median": float(np.median(v)),
            "p50": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}


def summarize(pairs: list[PairResult], node_counts: dict[str, int], malformed: list[dict[str, Any]]) -> dict[str, Any]:
    """Figures of a replay: counts, RE/TE (GenReg, and ICP on the same registered pairs and on all pairs),
    latency, drop reasons, header problems."""
    reg = [p for p in pairs if p.registered]
    genreg = [p.errors(p.T_est) for p in reg]
    icp_same = [p.errors(p.icp_T) for p in reg]
    icp_all = [p.errors(p.icp_T) for p in pairs]
    reasons: dict[str, int] = {}
    for p in pairs:
        if not p.registered:
            reasons[p.reason] = reasons.get(p.reason, 0) + 1
    return {
        "pairs": len(pairs),
        "registered": len(reg),
        "missing": len(pairs) - len(reg),
        "lost": sum(1 for p in pairs if not p.registered and p.reason.startswith("lost")),
        "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        "re": _stats([e[0] for e in genreg]),
        "te": _stats([e[1] for e in genreg]),
        "icp_re": _stats([e[0] for e in icp_same]),
        "icp_te": _stats([e[1] for e in icp_same]),
        "icp_all_re": _stats([e[0] for e in icp_all]),
        "icp_all_te": _stats([e[1] for e in icp_all]),
        "identity_re": _stats([p.errors(np.eye(4))[0] for p in reg]),
        "identity_te": _stats([p.errors(np.eye(4))[1] for p in reg]),
        "latency": _stats([p.latency for p in reg]),
        "icp_seconds": _stats([p.icp_seconds for p in pairs]),
        "header_problems": sum(1 for p in reg if p.header_problems),
        "node_counts": dict(node_counts),
        "malformed": malformed,
    }
